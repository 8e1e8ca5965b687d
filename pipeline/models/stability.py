"""Bounds a model must meet before it is simulated over a record: dead times shorter than
the record, and no part of the model that grows without bound (issue 33, build 4).

A model that passes :class:`~pipeline.models.model.Model`'s checks may still be unusable on a
given record:

* a ``delay_s`` longer than the record makes the block's output zero throughout and
  asks for one state per delayed sample (``delay_s: 1e12`` at 1 s asked for 7 TiB);
* an unstable part -- a block with a pole in the right half plane (``transfer`` with
  ``den: [-20, 1]``, a negative time constant) or a loop whose closed-loop poles lie
  outside the unit circle (positive feedback with a loop gain above 1) -- grows
  e-fold every ``1 / Re(s)`` seconds; over a day at 1 s that is ``e^180`` or an
  overflow to ``inf``, which later steps would blame on the data.

The model is decomposed into its strongly connected parts (every block reading itself
through other blocks is one loop).  The poles of the whole model are the union of the
parts' poles (the parts are connected in cascade), so each part is judged on its own:
a single block by the roots of its ``den`` (continuous time, exact), a loop of linear
blocks by the eigenvalues of its zero-order-hold discretisation with its dead times as
shift registers (exact at the sample period; loops with more than
:data:`MAX_LOOP_STATES` states, or with nonlinear blocks, whose saturations may bound
the growth, are left to :func:`divergence_message` after the simulation).

A part is called unstable when its fastest mode grows more than :data:`GROWTH_LIMIT`
times over the record; a slower growth is indistinguishable from a drift over that
record and is left to the discrepancy analysis (``sensor_bias_drift``, the offsets).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from pipeline.errors import ModelError
from pipeline.models.blocks import CONTROLLER_TYPES
from pipeline.models.model import Model

__all__ = ["GROWTH_LIMIT", "MAX_LOOP_STATES", "UnstablePart", "check_delays",
           "check_simulable", "divergence_message", "unstable_parts"]

GROWTH_LIMIT = 10.0
"""A mode that grows more than this factor over the record makes the model unstable."""
MAX_LOOP_STATES = 1500
"""Largest loop (states incl. dead-time samples) whose poles are computed densely
(1500: about a second for the eigenvalues on a loaded core)."""


@dataclass(frozen=True)
class UnstablePart:
    """One block or loop of a model that grows without bound.

    Attributes
    ----------
    blocks : tuple of str
        The block, or the blocks of the loop in model order.
    is_loop : bool
        True for a loop (the blocks read each other).
    growth_per_s : float
        Growth rate of the fastest mode, 1/s (``Re(s)`` of its continuous pole).
    pole : complex
        That pole: ``s`` (1/s) for a block, ``z`` (discrete, at ``dt_s``) for a loop.
    loop_gain : float or None
        Steady-state gain around a loop that is one simple cycle (product of its blocks'
        static gains and term weights; above +1 is an unstable positive feedback); None
        otherwise.
    """

    blocks: tuple[str, ...]
    is_loop: bool
    growth_per_s: float
    pole: complex
    loop_gain: float | None = None

    def describe(self, record_s: float | None = None) -> str:
        """The part, its pole and its growth, in words.

        Parameters
        ----------
        record_s : float, optional
            Length of the record, s; adds the growth over it.
        """
        efold = 1.0 / self.growth_per_s
        over = ""
        if record_s is not None:
            exponent = self.growth_per_s * record_s
            over = (f", x{math.exp(exponent):.3g}" if exponent < 700
                    else f", x10^{exponent / math.log(10):.0f}") + f" over the {record_s:g} s record"
        if self.is_loop:
            path = " -> ".join(repr(b) for b in (*self.blocks, self.blocks[0]))
            gain = "" if self.loop_gain is None else \
                f" (steady-state loop gain {self.loop_gain:+.4g})"
            return (f"the loop {path}{gain} is unstable: its closed-loop pole at z = "
                    f"{_num(self.pole)} (|z| = {abs(self.pole):.6g}) grows e-fold every "
                    f"{efold:.3g} s{over} -- a positive feedback or a loop gain too high; "
                    "check the signs and gains of the loop's blocks")
        return (f"block {self.blocks[0]!r} is unstable: its pole at s = {_num(self.pole)} 1/s "
                f"grows e-fold every {efold:.3g} s{over} -- a negative time constant or a "
                "'den' with coefficients of mixed sign; check its parameters")


def _num(value: complex) -> str:
    if abs(value.imag) < 1e-12 * max(1.0, abs(value.real)):
        return f"{value.real:+.6g}"
    return f"{value.real:+.6g}{value.imag:+.6g}j"


def check_delays(model: Model, *, record_s: float, where: str = "the record") -> None:
    """Refuse a dead time that is not shorter than the record.

    Parameters
    ----------
    model : Model
        The model.
    record_s : float
        Length of the record the model will be simulated over, s.
    where : str
        What the record is, for the message.

    Raises
    ------
    ModelError
        Names the block, its delay, the record length and the fix.
    """
    for i, block in enumerate(model.blocks):
        delay = block.dead_time_s
        if delay >= record_s:
            raise ModelError(
                f"model {model.name!r}, block {block.name!r} (model.blocks[{i}]): delay "
                f"{delay:g} s is longer than {where}, {record_s:g} s; set delay_s below "
                f"{record_s:g} s in the model (a dead time that long leaves the block's "
                "output zero over the whole record)")


def _parts(model: Model) -> list[list[int]]:
    """Strongly connected parts (block indices, model order), each a block or a loop."""
    index = {name: i for i, name in enumerate(model.block_names)}
    rows, cols = [], []
    for i, block in enumerate(model.blocks):
        for ref in block.references():
            if ref in index:
                rows.append(index[ref])
                cols.append(i)
    n = len(model.blocks)
    graph = scipy.sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, labels = scipy.sparse.csgraph.connected_components(graph, directed=True,
                                                          connection="strong")
    parts: dict[int, list[int]] = {}
    for i, label in enumerate(labels):
        parts.setdefault(int(label), []).append(i)
    self_loops = {i for i, c in zip(rows, cols, strict=True) if i == c}
    return [p for p in parts.values() if len(p) > 1 or p[0] in self_loops] + \
        [[p[0]] for p in parts.values() if len(p) == 1 and p[0] not in self_loops]


def _block_part(model: Model, i: int) -> UnstablePart | None:
    block = model.blocks[i]
    if not block.LINEAR:
        return None
    _, den = block.transfer_function()
    if len(den) < 2:
        return None
    poles = np.roots(den)
    k = int(np.argmax(poles.real))
    return UnstablePart((block.name,), False, float(poles[k].real), complex(poles[k]))


def _loop_part(model: Model, members: Sequence[int], dt_s: float) -> UnstablePart | None:
    from pipeline.models.simulate import loop_state_matrix

    blocks = [model.blocks[i] for i in members]
    if not all(b.LINEAR for b in blocks):
        return None  # saturations may bound it: the simulation will tell
    a = loop_state_matrix(model, [b.name for b in blocks], dt_s=dt_s,
                          max_states=MAX_LOOP_STATES)
    if a is None:
        return None
    z = np.linalg.eigvals(a)
    k = int(np.argmax(np.abs(z)))
    rate = math.log(max(abs(z[k]), 1e-300)) / dt_s
    local = {b.name: j for j, b in enumerate(blocks)}
    m = np.zeros((len(blocks), len(blocks)))
    for j, block in enumerate(blocks):
        for term in block.inputs:
            if term.signal in local:
                m[j, local[term.signal]] += term.k
    return UnstablePart(tuple(b.name for b in blocks), True, rate, complex(z[k]),
                        _cycle_gain(blocks, m))


def _cycle_gain(blocks: Sequence, m: np.ndarray) -> float | None:
    """Static gain around a loop that is one simple cycle (None otherwise)."""
    if np.count_nonzero(m) != len(blocks) or np.any(np.count_nonzero(m, axis=1) != 1):
        return None
    gain = 1.0
    for j, block in enumerate(blocks):
        num, den = block.transfer_function()
        if den[-1] == 0.0:
            return None  # an integrator: no static gain
        gain *= float(m[j].sum()) * float(num[-1] / den[-1])
    return gain


def unstable_parts(model: Model, *, dt_s: float, record_s: float | None = None,
                   growth_limit: float = 1.0) -> list[UnstablePart]:
    """The blocks and loops of ``model`` whose fastest mode grows.

    Parameters
    ----------
    model : Model
        The model.
    dt_s : float
        Sample period, s (loops are judged on their discretisation, dead times included).
    record_s : float, optional
        Record length, s; with it a part counts only when it grows more than
        ``growth_limit`` times over the record.
    growth_limit : float
        See `record_s`; without a record, any growth rate above zero (beyond rounding)
        counts.  Below 1 it asks for the parts that do not *decay* enough over the
        record: ``exp(-4)`` finds every part whose slowest mode has not settled to 2 %
        (an integrator, or a time constant above a quarter of `record_s`).

    Returns
    -------
    list of UnstablePart
        Fastest-growing first.
    """
    found = []
    for members in _parts(model):
        part = (_block_part(model, members[0]) if len(members) == 1 and
                model.blocks[members[0]].name not in model.blocks[members[0]].references()
                else _loop_part(model, members, dt_s))
        if part is None:
            continue
        if record_s is None and part.growth_per_s <= 1e-9 / dt_s:
            continue
        if record_s is not None and part.growth_per_s * record_s <= math.log(growth_limit):
            continue
        found.append(part)
    return sorted(found, key=lambda p: -p.growth_per_s)


def check_simulable(model: Model, *, dt_s: float, n_samples: int) -> None:
    """Refuse a model that cannot be simulated meaningfully over ``n_samples``: a dead
    time not shorter than the record, or a block or loop that grows more than
    :data:`GROWTH_LIMIT` times over it.

    Parameters
    ----------
    model : Model
        The model.
    dt_s : float
        Sample period, s.
    n_samples : int
        Record length, samples.

    Raises
    ------
    ModelError
        Names the block or loop, the numbers and what to check.
    """
    record_s = n_samples * dt_s
    check_delays(model, record_s=record_s)
    found = unstable_parts(model, dt_s=dt_s, record_s=record_s, growth_limit=GROWTH_LIMIT)
    if found:
        raise ModelError(
            f"model {model.name!r} is unstable: {found[0].describe(record_s)}"
            + (f" (and {len(found) - 1} more unstable part(s): "
               f"{', '.join(repr(p.blocks[0]) for p in found[1:4])})" if len(found) > 1
               else "")
            + "; simulated over the record it would grow without bound, so no comparison "
            "with the measurements is possible")


def divergence_message(model: Model, y: np.ndarray, *, dt_s: float) -> str:
    """Why a simulation from finite inputs produced non-finite signals, in words.

    Parameters
    ----------
    model : Model
        The simulated model.
    y : ndarray, shape (N, n_blocks)
        Every block's output (model block order), some of them non-finite.
    dt_s : float
        Sample period, s.
    """
    bad = ~np.isfinite(y)
    first = np.where(bad.any(axis=0), bad.argmax(axis=0), y.shape[0])
    j = int(np.argmin(first))
    head = (f"model {model.name!r} diverged: block {model.block_names[j]!r} overflowed to "
            f"{y[first[j], j]} at sample {int(first[j])} (t = {first[j] * dt_s:g} s) although "
            "every input is finite")
    try:
        found = unstable_parts(model, dt_s=dt_s)
    except (ModelError, ValueError, np.linalg.LinAlgError):
        found = []
    if found:
        return f"{head}; {found[0].describe(y.shape[0] * dt_s)}"
    parts = [p for p in _parts(model) if len(p) > 1]
    loops = [[model.block_names[i] for i in p] for p in parts]
    where = (f"; look at the loop(s) {', '.join(str(p) for p in loops[:3])} (with nonlinear "
             "or long-delayed blocks, whose poles are not computed)" if loops
             else "; check the blocks' gains for values far outside the plant's")
    return head + where + next((h for p in parts if (h := _unlimited_controller_hint(model, p))),
                               "")


def _unlimited_controller_hint(model: Model, part: Sequence[int]) -> str:
    """For a loop through a controller without limits and a nonlinear block that is not
    a saturation: the likely cause and its fix in model-YAML terms (a valve-cooler
    record of the plant zoo whose OP sat at 0 %: the model's PI wound on and the
    operating-point gain ``v (1 + slope * controller)`` turned the feedback positive)."""
    blocks = [model.blocks[i] for i in part]
    controllers = [b.name for b in blocks if b.TYPE in CONTROLLER_TYPES]
    curved = [f"{b.name!r} ({b.TYPE})" for b in blocks
              if not b.LINEAR and b.TYPE != "saturation"]
    if not controllers or not curved or any(b.TYPE == "saturation" for b in blocks):
        return ""
    return (f"; the loop's controller {controllers[0]!r} has no output limits in the model, "
            f"so where the plant's controller output stops at a limit (e.g. 0 or 100 %) the "
            f"model's winds on, and {', '.join(curved)} can turn the feedback positive "
            f"there: add a block {{name: {controllers[0]}_limited, type: saturation, "
            f"input: {controllers[0]}, low: ..., high: ...}} (the limits in the model's "
            f"units) and let the blocks that read {controllers[0]!r} read it")
