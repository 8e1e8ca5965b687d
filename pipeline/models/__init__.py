"""Block-diagram models: the blocks, the model (design.md's model format), their
simulation (a compiled per-sample kernel for nonlinear blocks) and the bounds a model
must meet before it is simulated.

Numeric and pure (numpy/scipy/numba only).
"""
