"""An independent "true plant" for the discrepancy tests: a block-diagram model simulated
in continuous time, with nuisances a real plant has and the model does not.

Test truths must not come from the code under test, so nothing here imports or copies
``pipeline.models.simulate``, ``pipeline.discrepancy.effects.predict_outputs`` or the pipeline's
discretisation: :mod:`pipeline.models.model` / :mod:`pipeline.models.blocks` are only *read* (a model's
inputs and blocks, each block's ``TYPE``, terms and parameter fields).  Each block's
transfer function is rebuilt here from its parameters.

Method
------
The whole diagram is integrated at the fine step ``h = dt_s / substeps`` by **Heun's
method** (explicit trapezoidal RK2), where the pipeline uses the exact zero-order-hold
discretisation at ``dt_s``:

* inputs (and disturbances) are linearly interpolated between the sample instants, as a
  continuous process variable would be, and evaluated at the fine grid points;
* Heun evaluates the right-hand side only at the ends of a step (``t`` and ``t + h``),
  i.e. only at fine grid points: the piecewise-linear inputs are exact there, the kinks
  of the inputs fall on step boundaries (no loss of order), dead-time buffers are read at
  stored points (no interpolation when ``delay_s / h`` is an integer) and a DCS hold
  switches only at step boundaries.  RK4 would need mid-step values of every delayed
  signal, which a buffer only gives by interpolation -- second order again, at twice
  the cost;
* the global error is second order, ``O((h w)^2)`` relative for the fastest block mode
  ``w``; the trapezoid rule is exact for an integrator of a piecewise-linear signal.
  Heun is explicit, so each block's poles must satisfy ``h |p| <= 0.25`` (checked, a
  ValueError names the block); loop modes are not checked.  Heun slightly amplifies
  undamped oscillation (by ``(h wn)^4 / 8`` per step), so a ``second_order`` block with
  ``zeta`` near 0 grows slowly over very long records.

Every linear block is realised in controllable canonical form (states ``z``; the
highest state is driven by ``u``), ``y = C z + D u``.  Dead time is a ring buffer of
the undelayed output at the fine grid points, linearly interpolated between slots when
``delay_s / h`` is not an integer; the plant is at rest before ``t = 0`` (every state
and buffer 0).  Dead times shorter than ``h`` are refused.

For speed the diagram is compiled once per call into a straight-line Python function
(generated here, with Python floats in the inner loop; the generated code names blocks
and inputs by index only, never by their names): about 0.1-0.15 s for 1e5 fine steps of
the 7-9 block shipped loops (``tests/project/test_plant_sim.py`` prints it).

Nuisances
---------
* ``dcs_scan_s``: ``pi``/``pid`` blocks are digital controllers in a DCS: they run once
  per scan ``T`` at ``t_j = j T``, act on the input sampled at the PREVIOUS scan
  ``e_j = u(t_{j-1})`` (``e_0 = 0``), integrate by rectangles
  ``I_j = I_{j-1} + T e_j`` and hold ``y_j = kp (e_j + I_j / ti_s) + d_j`` until the next
  scan; the pid derivative is ``tf = td_s / n_filter`` filtered by backward Euler,
  ``d_j = tf/(tf+T) d_{j-1} + kp td_s/(tf+T) (e_j - e_{j-1})``.  At a sample instant the
  historian sees the output of the scan at that instant.
* ``quanta``: a block's output is rounded to the nearest multiple of its quantum where
  it is computed (at every evaluation, after the dead time; for a DCS controller at each
  scan -- its integral is not rounded).  Inside the integration this makes the
  right-hand side discontinuous, so near a rounding step Heun is first order.
* ``disturbances``: an unmeasured signal added to a block's input ``u``.
"""

from __future__ import annotations

import graphlib
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

#: Largest ``h |pole|`` accepted for a block (Heun: relative error ~(h|p|)^3/6 per step,
#: and a margin from the growth of lightly damped modes, |1 + i x - x^2/2| > 1).
MAX_STEP_POLE = 0.25

_LINEAR_TYPES = ("gain", "sum", "first_order", "second_order", "transfer", "integrator",
                 "pi", "pid")
_SUPPORTED = (*_LINEAR_TYPES, "deadband", "saturation", "operating_point_gain")


@dataclass
class _Node:
    """One block as the code generator sees it (``i`` indexes the generated names)."""

    i: int
    name: str
    kind: str  # "linear", "dcs", "deadband", "saturation" or "operating_point_gain"
    terms: tuple[tuple[str, float], ...]
    d: float = 0.0  # feedthrough D
    c: tuple[float, ...] = ()  # output row C; len(c) = number of states
    a: tuple[float, ...] = ()  # monic denominator without the leading 1
    delay: tuple[int, float] | None = None  # (m, f): delay_s = (m + f) h
    quantum: float | None = None
    disturbed: bool = False
    params: tuple[float, ...] = ()  # nonlinear or DCS parameters
    schedule: str | None = None  # the signal of an operating_point_gain

    @property
    def refs(self) -> set[str]:
        return {s for s, _ in self.terms} | ({self.schedule} if self.schedule else set())

    @property
    def n(self) -> int:
        return len(self.a)

    @property
    def early(self) -> bool:
        """Output known from the states, the buffer or the hold before any input is."""
        if self.delay is not None or self.kind == "dcs":
            return True
        return self.kind == "linear" and self.d == 0.0


def _tf(block) -> tuple[list[float], list[float]]:
    """Continuous (num, den) of a linear block, descending powers, from its parameters."""
    t = block.TYPE
    if t == "gain":
        return [block.k], [1.0]
    if t == "sum":
        return [1.0], [1.0]
    if t == "first_order":
        return [block.k], [block.tau_s, 1.0]
    if t == "second_order":
        w2 = block.wn * block.wn
        return [block.k * w2], [1.0, 2.0 * block.zeta * block.wn, w2]
    if t == "transfer":
        return list(block.num), list(block.den)
    if t == "integrator":
        return [block.k], [1.0, 0.0]
    # pi / pid: kp (1 + 1/(ti s) + td s/(tf s + 1)) over the common denominator
    # ti s (tf s + 1); td = 0 is the pi.
    kp, ti = block.kp, block.ti_s
    td = getattr(block, "td_s", 0.0)
    if td == 0.0:
        return [kp * ti, kp], [ti, 0.0]
    tf = td / block.n_filter
    return [kp * (ti * tf + ti * td), kp * (ti + tf), kp], [ti * tf, ti, 0.0]


def _realise(name: str, num: list[float], den: list[float], h: float
             ) -> tuple[float, tuple[float, ...], tuple[float, ...]]:
    """(D, C, a) of the controllable canonical form of ``num/den``; checks ``h |pole|``."""
    while len(den) > 1 and den[0] == 0.0:
        den = den[1:]
    while len(num) > 1 and num[0] == 0.0:
        num = num[1:]
    n = len(den) - 1
    if len(num) > n + 1:
        raise ValueError(f"block {name!r}: improper transfer function; cannot simulate")
    lead = den[0]
    a = [x / lead for x in den[1:]]
    num_p = [0.0] * (n + 1 - len(num)) + [x / lead for x in num]
    d = num_p[0]
    b = [num_p[j + 1] - d * a[j] for j in range(n)]  # s^(n-1) .. s^0
    if n:
        fastest = float(np.max(np.abs(np.roots([1.0, *a]))))
        if h * fastest > MAX_STEP_POLE:
            raise ValueError(
                f"block {name!r}: pole of {fastest:.4g} rad/s is too fast for the fine "
                f"step h={h:g} s (h*|pole|={h * fastest:.3g} > {MAX_STEP_POLE}); multiply "
                f"substeps by at least {math.ceil(h * fastest / MAX_STEP_POLE)}"
            )
    c = tuple(b[n - 1 - j] for j in range(n))  # coefficient of z_j
    return d, c, tuple(a)


def _delay(name: str, delay_s: float, h: float) -> tuple[int, float] | None:
    if delay_s == 0.0:
        return None
    steps = delay_s / h
    m = math.floor(steps + 1e-9)
    f = steps - m
    if f < 1e-9:
        f = 0.0
    if m < 1:
        raise ValueError(
            f"block {name!r}: delay_s={delay_s:g} is shorter than the fine step h={h:g} s; "
            "raise substeps (the fine-step buffer cannot hold a sub-step dead time)"
        )
    return m, f


def _nodes(model, h: float, dcs: bool, quanta: Mapping[str, float],
           disturbed: set[str]) -> list[_Node]:
    nodes = []
    for i, block in enumerate(model.blocks):
        t = block.TYPE
        if t not in _SUPPORTED:
            raise ValueError(
                f"block {block.name!r}: type {t!r} is not supported by the plant simulator; "
                f"supported: {', '.join(_SUPPORTED)}"
            )
        node = _Node(i=i, name=block.name, kind=t if t not in _LINEAR_TYPES else "linear",
                     terms=tuple((term.signal, term.k) for term in block.inputs),
                     quantum=quanta.get(block.name), disturbed=block.name in disturbed)
        if t in _LINEAR_TYPES:
            node.delay = _delay(block.name, float(getattr(block, "delay_s", 0.0)), h)
        if t in ("pi", "pid") and dcs:
            td = getattr(block, "td_s", 0.0)
            node.kind = "dcs"
            node.params = (block.kp, block.ti_s, td, td / block.n_filter if td else 0.0)
        elif t in _LINEAR_TYPES:
            node.d, node.c, node.a = _realise(block.name, *_tf(block), h)
        elif t == "deadband":
            node.params = (block.width / 2.0,)
        elif t == "saturation":
            node.params = (block.low, block.high)
        else:
            node.params = (block.slope,)
            node.schedule = block.signal
        nodes.append(node)
    return nodes


def _late_order(nodes: list[_Node]) -> list[_Node]:
    """Feedthrough blocks in an order where each block's inputs are known before it."""
    late = {node.name: node for node in nodes if not node.early}
    graph = {name: node.refs & set(late) for name, node in late.items()}
    try:
        order = list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        raise ValueError(
            f"algebraic loop through blocks {' -> '.join(map(repr, exc.args[1]))}: the plant "
            "simulator needs a dead time, lag, integrator or DCS controller in every loop"
        ) from None
    return [late[name] for name in order]


def _num(x: float) -> str:
    return repr(float(x))


class _Generator:
    """Writes the straight-line Python function that simulates one diagram."""

    def __init__(self, model, nodes: list[_Node], h: float, substeps: int,
                 scan_steps: int) -> None:
        self.nodes, self.h, self.substeps, self.scan_steps = nodes, h, substeps, scan_steps
        self.late = _late_order(nodes)
        self.early = [node for node in nodes if node.early]
        self.dcs = [node for node in nodes if node.kind == "dcs"]
        self.stateful = [node for node in nodes if node.n]
        self.n_inputs = len(model.inputs)
        self.signal = {name: f"v{j}" for j, name in enumerate(model.inputs)}
        self.signal.update({node.name: f"y{node.i}" for node in nodes})

    def u_expr(self, node: _Node) -> str:
        parts = []
        for signal, k in node.terms:
            var = self.signal[signal]
            parts.append(var if k == 1.0 else f"-{var}" if k == -1.0 else f"{_num(k)}*{var}")
        if node.disturbed:
            parts.append(f"w{node.i}")
        return " + ".join(parts)

    def linear_output(self, node: _Node, states: str, feedthrough: bool) -> str:
        parts = [f"{_num(c)}*{states}{node.i}_{j}" for j, c in enumerate(node.c) if c]
        if feedthrough and node.d:
            parts.append(f"{_num(node.d)}*u{node.i}")
        return " + ".join(parts) or "0.0"

    def output(self, node: _Node, states: str) -> str:
        """Expression of a feedthrough block's output (its input ``u{i}`` is known)."""
        u = f"u{node.i}"
        if node.kind == "linear":
            return self.linear_output(node, states, feedthrough=True)
        if node.kind == "deadband":
            w = _num(node.params[0])
            return f"({u} - {w} if {u} > {w} else ({u} + {w} if {u} < -{w} else 0.0))"
        if node.kind == "saturation":
            low, high = node.params
            expr = u
            if math.isfinite(high):
                expr = f"({_num(high)} if {u} > {_num(high)} else {expr})"
            if math.isfinite(low):
                expr = f"({_num(low)} if {u} < {_num(low)} else {expr})"
            return expr
        return f"{u} * (1.0 + {_num(node.params[0])}*{self.signal[node.schedule]})"

    def quantise(self, node: _Node, var: str) -> list[str]:
        if node.quantum is None:
            return []
        q = _num(node.quantum)
        return [f"{var} = _round({var} / {q}) * {q}"]

    def delayed(self, node: _Node, g: str) -> str:
        m, f = node.delay
        size = m + 2  # times g-m-1 .. g+1 are live during a step
        now = f"B{node.i}[({g} - {m}) % {size}]"
        if f == 0.0:
            return now
        before = f"B{node.i}[({g} - {m + 1}) % {size}]"
        return f"{_num(1.0 - f)}*{now} + {_num(f)}*{before}"

    def dcs_update(self, node: _Node, scan_s: float) -> list[str]:
        """One scan of a DCS controller: previous scan's sample, rectangles, hold."""
        kp, ti, td, tf = node.params
        i = node.i
        lines = [f"e{i} = E{i}", f"I{i} = I{i} + {_num(scan_s)}*e{i}"]
        out = f"{_num(kp)}*e{i} + {_num(kp / ti)}*I{i}"
        if td:
            lines += [f"DF{i} = {_num(tf / (tf + scan_s))}*DF{i} + "
                      f"{_num(kp * td / (tf + scan_s))}*(e{i} - EP{i})", f"EP{i} = e{i}"]
            out += f" + DF{i}"
        return [*lines, f"H{i} = {out}", *self.quantise(node, f"H{i}")]

    def stage(self, g: str, states: str, first: bool) -> list[str]:
        """Every block output (and input) at grid point ``g`` from the states ``states``.

        The first stage of a step also runs the DCS scans, fills the dead-time buffers
        and samples the DCS inputs (the second stage is only a predictor).
        """
        lines = [f"v{j} = U{j}[{g}]" for j in range(self.n_inputs)]
        lines += [f"w{n.i} = W{n.i}[{g}]" for n in self.nodes if n.disturbed]
        if first and self.dcs:
            scan_s = self.scan_steps * self.h
            lines += ["if scan:"] + [f"    {x}" for n in self.dcs
                                     for x in self.dcs_update(n, scan_s)]
        for node in self.early:
            if node.delay is not None:
                lines.append(f"y{node.i} = {self.delayed(node, g)}")
            elif node.kind == "dcs":
                lines.append(f"y{node.i} = H{node.i}")
                continue  # quantised at the scan
            else:
                lines.append(f"y{node.i} = {self.linear_output(node, states, False)}")
            lines += self.quantise(node, f"y{node.i}")
        for node in self.late:
            lines += [f"u{node.i} = {self.u_expr(node)}",
                      f"y{node.i} = {self.output(node, states)}",
                      *self.quantise(node, f"y{node.i}")]
        for node in self.early:
            if node.n or (first and (node.delay is not None or node.kind == "dcs")):
                lines.append(f"u{node.i} = {self.u_expr(node)}")
        if first:
            for node in self.early:
                if node.delay is not None:
                    y0 = (f"H{node.i}" if node.kind == "dcs"
                          else self.linear_output(node, states, True))
                    lines.append(f"B{node.i}[{g} % {node.delay[0] + 2}] = {y0}")
            if self.dcs:
                lines += ["if scan:"] + [f"    E{n.i} = u{n.i}" for n in self.dcs]
        return lines

    def derivatives(self, node: _Node, states: str) -> list[str]:
        """Right-hand sides of the controllable canonical form of ``node``."""
        i, n = node.i, node.n
        top = [f"u{i}"] + [f"{_num(-a)}*{states}{i}_{n - 1 - m}"
                           for m, a in enumerate(node.a) if a]
        return [f"{states}{i}_{j + 1}" for j in range(n - 1)] + [" + ".join(top)]

    def heun(self) -> list[str]:
        """Body of one fine step (grid point ``g`` to ``g + 1``)."""
        lines = self.stage("g", "x", first=True)
        lines += ["if s == 0:"] + [f"    R{n.i}[k] = y{n.i}" for n in self.nodes]
        predict = []
        for node in self.stateful:
            for j, rhs in enumerate(self.derivatives(node, "x")):
                lines.append(f"a{node.i}_{j} = {rhs}")
                predict.append(f"p{node.i}_{j} = x{node.i}_{j} + {_num(self.h)}*a{node.i}_{j}")
        lines += predict + ["g1 = g + 1"] + self.stage("g1", "p", first=False)
        for node in self.stateful:
            for j, rhs in enumerate(self.derivatives(node, "p")):
                lines.append(f"x{node.i}_{j} = x{node.i}_{j} + "
                             f"{_num(self.h / 2.0)}*(a{node.i}_{j} + {rhs})")
        return lines

    def source(self) -> str:
        head = [f"U{j} = U[{j}]" for j in range(self.n_inputs)]
        head += [f"W{n.i} = W[{n.i}]" for n in self.nodes if n.disturbed]
        head += [f"R{n.i} = R[{n.i}]" for n in self.nodes]
        head += [f"B{n.i} = [0.0] * {n.delay[0] + 2}" for n in self.nodes if n.delay]
        head += [f"x{n.i}_{j} = 0.0" for n in self.stateful for j in range(n.n)]
        head += [f"{v}{n.i} = 0.0" for n in self.dcs for v in ("H", "E", "I", "DF", "EP")]
        head += ["_round = round"]
        loop = ["for k in range(n_samples - 1):", f"    base = k * {self.substeps}",
                f"    for s in range({self.substeps}):", "        g = base + s"]
        if self.dcs:
            loop.append(f"        scan = s % {self.scan_steps} == 0")
        loop += [f"        {x}" for x in self.heun()]
        tail = ["k = n_samples - 1", f"g = k * {self.substeps}", "scan = True", "s = 0"]
        tail += self.stage("g", "x", first=True)
        tail += [f"R{n.i}[k] = y{n.i}" for n in self.nodes]
        body = "\n".join(f"    {x}" for x in head + loop + tail)
        return f"def run(U, W, R, n_samples):\n{body}\n"


def _series(name: str, what: str, values, n: int | None) -> np.ndarray:
    """`values` as a finite float array of shape (n,)."""
    arr = np.asarray(values, dtype=float)
    if arr.ndim != 1 or arr.size == 0 or (n is not None and arr.size != n):
        want = f"({n},)" if n is not None else "(N,) with N >= 1"
        raise ValueError(f"{what} {name!r}: shape {arr.shape}, expected {want}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} {name!r}: non-finite value at sample "
                         f"{int(np.flatnonzero(~np.isfinite(arr))[0])}")
    return arr


def _positive(value) -> bool:
    return (isinstance(value, numbers.Real) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0)


def _check_names(given, allowed, what: str) -> None:
    unknown = sorted(set(given) - set(allowed))
    if unknown:
        raise ValueError(f"{what}: {unknown} not in the model; allowed: {list(allowed)}")


def _scan_steps(dcs_scan_s: float | None, h: float, substeps: int) -> int:
    """The DCS scan period in fine steps (it must divide the sample period)."""
    if dcs_scan_s is None:
        return substeps
    if not _positive(dcs_scan_s):
        raise ValueError(f"dcs_scan_s={dcs_scan_s!r} must be a finite number > 0")
    steps = round(dcs_scan_s / h)
    if steps < 1 or abs(steps * h - dcs_scan_s) > 1e-9 * dcs_scan_s or substeps % steps:
        raise ValueError(
            f"dcs_scan_s={dcs_scan_s:g} must be a whole number of fine steps h={h:g} s "
            f"that divides dt_s={h * substeps:g} s (dt_s/scan an integer); e.g. "
            f"dcs_scan_s={h * substeps:g} or {h:g}"
        )
    return steps


def simulate_plant(model, inputs: Mapping[str, np.ndarray], *, dt_s: float,
                   substeps: int = 10, dcs_scan_s: float | None = None,
                   quanta: Mapping[str, float] | None = None,
                   disturbances: Mapping[str, np.ndarray] | None = None
                   ) -> dict[str, np.ndarray]:
    """Simulate `model` as a continuous-time plant; every block output at the samples.

    Parameters
    ----------
    model : pipeline.models.model.Model
        Read only (inputs, blocks and their parameters).
    inputs : mapping of str to array, shape (N,)
        The true value of every model input at ``t_k = k dt_s``; linearly interpolated
        in between.
    dt_s : float
        Sample period, s.
    substeps : int
        Fine integration steps per sample (``h = dt_s / substeps``).
    dcs_scan_s : float, optional
        Run every ``pi``/``pid`` block as a DCS controller with this scan period, s (a
        whole number of fine steps dividing ``dt_s``); continuous when None.
    quanta : mapping of str to float, optional
        Block name -> output resolution (the output is rounded to a multiple of it).
    disturbances : mapping of str to array, shape (N,), optional
        Block name -> unmeasured signal at the samples (interpolated like the inputs),
        added to that block's input.

    Returns
    -------
    dict of str to ndarray, shape (N,)
        Every block's output at the sample instants, plant at rest before ``t = 0``.

    Raises
    ------
    ValueError
        Bad arguments, an unsupported block, a dead time shorter than the fine step, a
        block pole too fast for the fine step, or an algebraic loop (each names it).
    """
    if not _positive(dt_s):
        raise ValueError(f"dt_s={dt_s!r} must be a finite number > 0")
    if (isinstance(substeps, bool) or not isinstance(substeps, numbers.Integral)
            or substeps < 1):
        raise ValueError(f"substeps={substeps!r} must be an integer >= 1")
    quanta, disturbances = dict(quanta or {}), dict(disturbances or {})
    missing = [name for name in model.inputs if name not in inputs]
    if missing:
        raise ValueError(f"inputs: missing model inputs {missing}; the model reads "
                         f"{list(model.inputs)}")
    _check_names(inputs, model.inputs, "inputs")
    names = [block.name for block in model.blocks]
    _check_names(quanta, names, "quanta")
    _check_names(disturbances, names, "disturbances")
    for name, q in quanta.items():
        if not _positive(q):
            raise ValueError(f"quanta[{name!r}]={q!r} must be a finite number > 0")
    series = [_series(name, "input", inputs[name], None) for name in model.inputs]
    n = series[0].size if series else None
    series = [_series(name, "input", u, n) for name, u in zip(model.inputs, series)]
    dist = {name: _series(name, "disturbance", w, n) for name, w in disturbances.items()}
    if n is None:  # a model without inputs: the disturbances set the length
        n = next(iter(dist.values())).size if dist else 1
    substeps, h = int(substeps), dt_s / substeps
    scan = _scan_steps(dcs_scan_s, h, substeps)
    nodes = _nodes(model, h, dcs_scan_s is not None, quanta, set(dist))
    namespace: dict = {}
    exec(_Generator(model, nodes, h, substeps, scan).source(), namespace)  # noqa: S102
    fine = np.arange((n - 1) * substeps + 1) / substeps  # fine grid in samples
    coarse = np.arange(n)
    U = [np.interp(fine, coarse, u).tolist() for u in series]
    W = {nodes[names.index(name)].i: np.interp(fine, coarse, w).tolist()
         for name, w in dist.items()}
    R = [[0.0] * n for _ in nodes]
    namespace["run"](U, W, R, n)
    return {node.name: np.asarray(R[node.i]) for node in nodes}
