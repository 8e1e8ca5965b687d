"""Readouts: what engineers read off an estimated step response — characteristic
quantities (method.md §6), frequency responses and transfer-function fits (§7), the
nightly monitoring comparison with a baseline, min/max envelopes for plots.

Numeric and pure (numpy/scipy only).
"""
