"""Identification: from a record to the orders and checks a step response is judged by —
spikes, the α_T sample period (method.md §3), conditioning (§4), the N_p/N_d search (§5),
truncation and feedback tests, window agreement, settledness (§11), grades and verdicts.

Numeric and pure (numpy/scipy only); uses :mod:`pipeline.estimation`.
"""
