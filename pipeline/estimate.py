"""The fixed core API's import path (design.md): ``pipeline.estimate.estimate_step_responses``.

The estimate lives in :mod:`pipeline.estimation.estimate`; this module re-exports it so
that code written against the fixed path keeps working (scipy keeps old module paths the
same way).
"""

from pipeline.estimation.estimate import (
    estimate_from_normal_equations,
    estimate_merged,
    estimate_step_responses,
)

__all__ = ["estimate_step_responses", "estimate_from_normal_equations", "estimate_merged"]
