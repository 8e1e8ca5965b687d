"""Simulated plant records: the demo's plants (:mod:`pipeline.simulated.synthetic`) and
the hidden-effect trials of the discrepancy benchmarks and tests
(:mod:`pipeline.simulated.effect_trials`).

Numeric and pure (models in, arrays out).  Only the demo reads them in production; the
estimation and discrepancy code never does.
"""
