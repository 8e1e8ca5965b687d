"""Estimation core: step responses by least squares from the lag Gram (method.md §2),
with noise models (§10), instruments and the kernel-regularised FIR (§11).

Numeric and pure (numpy/scipy only): arrays in, frozen results out.  The fixed entry
point is :func:`pipeline.estimation.estimate.estimate_step_responses`, also importable
as ``pipeline.estimate.estimate_step_responses`` (design.md).
"""
