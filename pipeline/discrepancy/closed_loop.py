"""Opened loops checked closed: a candidate fitted with a loop opened must not widen the
gap the loop leaves when it is closed again and driven by the setpoints and loads alone
(method §10(c): the external signals are the instruments).

Why: opened (:func:`pipeline.discrepancy.problem.opened_view`), the measured OP drives the
blocks after the controller, and that OP carries the controller's answer to the
unmeasured disturbance.  A candidate that shrinks the path the OP drives (a smaller
vessel gain, a wide deadband on the vessel, a backlash on the controlled sensor) cancels
part of that answer and so part of the disturbance in the opened output error -- and
the whitened criteria do not stop it: on unseen valve-cooler nulls (zoo seeds
8 678 000-029) nine of thirty were named such effects through the whitened tests.
Closed, the same model sees only the instruments: under the nominal model the closed
loop's output error is its answer to the disturbance, which the instruments do not move,
so a wrong candidate can only add to it in expectation (the candidate's own
instrument-driven difference); a right one removes the part of the error the
instruments drive.  On those nulls the named effects widened the closed gap by 7-133 %;
on the zoo's true gains, delays and lags (spent seeds 8 670 000-002) the right
candidate narrowed it by 2-75 % (output errors; what is compared is below).

The comparison is on the hold-out only.  On the fit part the candidate's parameters
already took whatever the instruments and the disturbance happened to share there (the
opened fit exploited it), so the closed loop sees the same luck: over the whole record
the valve-cooler null's vessel gain 0.65 (seed 8 678 005) narrowed the closed gap, on
the hold-out it widened it by 29 %.

It compares one-step prediction errors, not output errors
(:meth:`ClosedLoop.prediction_error_reduction`): each output's closed residual is
whitened by the AR noise model of the nominal closed residual on the fit part -- the
prediction-error criterion with the noise model fixed (method §10).  With a wrong
candidate's instrument-driven change ``δ`` and the disturbance ``d``, the change of the
held-out sum of squares is ``|δ|^2 + 2<d, δ>``; a slow ``d`` has few independent values
over a hold-out, so the cross term's spread is of the order of ``|δ|^2`` itself and the
sign of the output-error change was a coin for small changes -- and the same for a
right candidate, whose change is ``-|δ|^2 - 2<d, δ>``: the zoo's true steam-valve lags
widened a heat exchanger's closed output-error gap by 5 % and 10 % and were lost (spent
seeds 8 682 000 and 8 682 004).  Whitened, ``d``'s innovations are white and the cross
term's spread shrinks to the innovation std times ``|Aδ|``.  On the simulated PI loop of
``tests/discrepancy/test_closed_loop.py`` (20 records): wrong gains of 0.6, 1.5 and 2.0
narrowed the whitened error in 0 records each (2, 5 and 1 on output errors), 0.8 and
1.25 in 1 and 4 (5 and 6); the true gain in 20 of 20 (17).  Tried and left out as
well: judging the held-out narrowing of the output errors against surrogates of the
closed residual's AR noise model (:func:`pipeline.discrepancy.select.holdout_rms_noise_test`):
it passed 8 of 100 wrong gains at p <= 0.01 and the true one in only 6 of 20 (a
low-order AR model does not describe a loop's output error well enough to calibrate
that).  The criterion is a point criterion, no test at a stated level: a filter behind
the whitened opened tests, which a wrong candidate has passed already.

Which candidates (:meth:`ClosedLoop.applies`): the argument is exact for an effect that
keeps the model linear (:attr:`pipeline.discrepancy.effects.Effect.keeps_linear`) and
leaves its loops settling within the hold-out.  A linear effect that makes an opened
loop ring past the hold-out where the model without it settles (its slowest closed-loop
mode above 2 % at the hold-out's end, the test :func:`pipeline.discrepancy.problem.loops_to_open`
asks of an opened path), and still decays, is judged like a nonlinearity, below: the closed free run then
compares the ring's phase, which the instruments do not set -- the plant's own ring is
excited by the disturbance and held by its stops.  A heat exchanger's true 16 s steam
delay leaves the linear loop a mode decaying over 1.6 h (|z| 0.99967 at 2 s) against a
4 800 s hold-out, and widened the closed error by 0.4 % where its opened fit closed
72 % of the gap, the steam meter's share measured outside the loop (spent zoo seed
8 711 000); delays up to 14 s settle and stay checked, and a candidate whose closed
loop grows stays checked (and fails): a plant held bounded by nothing the candidate
adds is not what it describes.  With
a deadband, a backlash or a limit in the loop, the closed response also depends on where
the disturbance has pushed the OP (the side of the play, whether the limit is reached),
so even the true effect does not reproduce the plant from the instruments alone: on the
spent zoo seeds the right deadbands and backlashes at the blend's and the heat
exchanger's valves changed the closed gap by -3 % to +2 %, and a true steam stop widened
it 49 % (the model's controller winds up where the plant's clamps at 0-100 %); checked,
six correct findings were lost.  Such a candidate is judged opened, where its evidence
is sound when it moves a measured signal outside the loop's controlled variable (the
valve's flow meter shows the play with sensor noise only), and checked closed when all
it moves is a controlled variable of an opened loop -- whose opened error is the
disturbance the controller answered, so the opened criteria have nothing unbiased to go
on (a backlash at the valve cooler's temperature sensor, a deadband at its vessel, named
on nulls).  A sensor correction (``sensor_bias_drift``) changes what a sensor reports,
never the loop's simulation (:attr:`pipeline.discrepancy.effects.Effect.is_sensor_correction`):
it is not checked.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import scipy.signal

from pipeline.discrepancy.chain import build, predict_with_effects
from pipeline.discrepancy.effects import Effect, original_location
from pipeline.discrepancy.problem import downstream
from pipeline.estimation.noise_model import fit_ar
from pipeline.errors import PipelineError
from pipeline.models.model import Model
from pipeline.models.stability import unstable_parts


@dataclasses.dataclass
class ClosedLoop:
    """The user's model with its loops closed and the record as measured: what a
    candidate of an opened analysis is checked on (module docstring).

    Parameters
    ----------
    model : Model
        The user's model, loops closed (before :func:`~pipeline.discrepancy.problem.opened_view`).
    inputs : mapping of str -> ndarray (N,)
        The model's inputs (setpoints and loads; deviations).
    measured : mapping of str -> ndarray (N,)
        Every measured output, the opened loops' OPs included (deviations).
    dt_s : float
        Sample period, s.
    fit_start, holdout_start : int
        The fit part's first sample and the hold-out's (``Problem``'s).
    free : tuple of str
        Outputs whose constant is profiled out on the fit part (``free_offsets``).
    initial : str
        ``DiscrepancyConfig.initial``.
    prior : tuple of Effect
        The chain's effects already in the model (nominal names).
    opened : tuple of str
        The opened loops' controllers (``Problem.opened_loops``).
    ar_order_max : int
        Highest order of the closed residual's AR noise model
        (``DiscrepancyConfig.ar_order_max``).
    """

    model: Model
    inputs: Mapping[str, np.ndarray]
    measured: Mapping[str, np.ndarray]
    dt_s: float
    fit_start: int
    holdout_start: int
    free: tuple[str, ...]
    initial: str
    prior: tuple[Effect, ...] = ()
    opened: tuple[str, ...] = ()
    ar_order_max: int = 4
    _nominal: np.ndarray | None = dataclasses.field(default=None, init=False, repr=False)
    _whitening: list[tuple[np.ndarray, float]] = dataclasses.field(default_factory=list,
                                                                  init=False, repr=False)
    _prior_loops: str | None = dataclasses.field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.inputs = {k: np.asarray(v, dtype=float) for k, v in self.inputs.items()}
        self.measured = {k: np.asarray(v, dtype=float) for k, v in self.measured.items()}

    def controlled(self) -> set[str]:
        """The opened loops' controlled variables: the measured outputs each opened
        controller reads, directly or through blocks that are not measured (its error
        sum), not beyond them."""
        blocks, found = set(self.model.block_names), set()
        frontier = set(self.opened)
        seen = set(frontier)
        while frontier:
            refs = {r for f in frontier for r in self.model.block(f).references()} - seen
            seen |= refs
            found |= refs & set(self.measured)
            frontier = {r for r in refs if r in blocks and r not in self.measured}
        return found

    def applies(self, effect: Effect, searched: Model) -> bool:
        """Whether `effect` is checked closed (module docstring): a linear effect
        whose closed loops settle within the hold-out (or did not without it) always,
        a sensor correction never, any other when every output it moves in the
        opened model `searched` is a controlled variable of an opened loop.

        Parameters
        ----------
        effect : Effect
            A candidate, located in `searched`'s names.
        searched : Model
            The opened model the candidate was fitted on.
        """
        if effect.is_sensor_correction:
            return False
        if effect.keeps_linear and self._settles(effect):
            return True
        names = set(self.measured)
        moved = ({effect.location} | downstream(searched, effect.location)) & names
        return moved <= self.controlled()

    def _loops(self, effects: Sequence[Effect]) -> str | None:
        """How the closed model with `effects` ends the hold-out in its loops through an
        opened controller (:func:`pipeline.models.stability.unstable_parts`, growth
        ``exp(-4)``, as :func:`~pipeline.discrepancy.problem.loops_to_open` asks of an
        opened path): ``"settles"`` (to 2 %), ``"slow"`` (decays, but slower),
        ``"grows"``; None when the model cannot be built."""
        try:
            model = build(self.model, effects, self.dt_s)
        except PipelineError:
            return None
        n = min(np.size(v) for v in self.measured.values())
        slow = [part for part in unstable_parts(
                    model, dt_s=self.dt_s, record_s=(n - self.holdout_start) * self.dt_s,
                    growth_limit=math.exp(-4.0))
                if part.is_loop and set(part.blocks) & set(self.opened)]
        if not slow:
            return "settles"
        return "grows" if any(part.growth_per_s > 0.0 for part in slow) else "slow"

    def _settles(self, effect: Effect) -> bool:
        """False when `effect` makes a loop of the closed model ring past the hold-out
        (decaying) where the model without it settles (module docstring, "Which
        candidates")."""
        loc = original_location(effect.location, (*self.model.block_names, *self.model.outputs))
        if loc is None:
            return True
        if self._prior_loops is None:
            self._prior_loops = self._loops(self.prior)
        moved = dataclasses.replace(effect, location=loc, equivalent_locations=())
        return not (self._prior_loops == "settles"
                    and self._loops((*self.prior, moved)) == "slow")

    def check(self, effect: Effect, searched: Model) -> float:
        """:meth:`prediction_error_reduction` of `effect` where :meth:`applies` says it is checked,
        else NaN.

        Parameters
        ----------
        effect : Effect
            A candidate, located in `searched`'s names.
        searched : Model
            The opened model the candidate was fitted on.
        """
        return (self.prediction_error_reduction(effect) if self.applies(effect, searched)
                else math.nan)

    def residuals(self, effects: Sequence[Effect]) -> np.ndarray | None:
        """Measured minus simulated outputs (N, n_y; columns in :attr:`measured`'s
        order, free outputs' constants profiled on the fit part) of the closed model
        with `effects` added; None when its simulation fails or diverges.

        Parameters
        ----------
        effects : sequence of Effect
            In nominal names, applied in order.
        """
        try:
            with np.errstate(all="ignore"), warnings.catch_warnings():
                # as in pipeline.discrepancy.fit.predict_with
                warnings.simplefilter("ignore", scipy.signal.BadCoefficients)
                pred = predict_with_effects(self.model, effects, self.inputs, dt_s=self.dt_s,
                                            initial=self.initial, outputs=list(self.measured))
        except PipelineError:
            return None
        fit = slice(self.fit_start, self.holdout_start)
        columns = []
        for o in self.measured:
            e = self.measured[o] - pred[o]
            if not np.all(np.isfinite(e)) or np.max(np.abs(e)) > 1e12:
                return None
            columns.append(e - float(np.mean(e[fit])) if o in self.free else e)
        return np.column_stack(columns)

    def prediction_error_reduction(self, effect: Effect) -> float:
        """The share of the closed loop's held-out one-step prediction error (with
        :attr:`prior`) that `effect` added removes (module docstring): each output's
        closed residual whitened by the AR noise model of the nominal closed residual on
        the fit part, pooled in units of its innovation std.  Negative when it widens
        it, ``-inf`` when the closed loop with it diverges; NaN when the closed loop
        without it cannot be simulated (nothing to check against), for a sensor
        correction and for a block of the effects' own (not checked).

        Parameters
        ----------
        effect : Effect
            A candidate (its location in the searched model's names: a block an
            earlier effect wrapped maps back, :func:`~pipeline.discrepancy.effects.original_location`).
        """
        loc = original_location(effect.location, (*self.model.block_names, *self.model.outputs))
        if self._nominal is None:
            self._nominal = self.residuals(self.prior)
            if self._nominal is not None:
                fit = slice(self.fit_start, self.holdout_start)
                self._whitening = [fit_ar(e[fit], self.ar_order_max)[:2]
                                   for e in self._nominal.T]
        e0 = self._nominal
        if effect.is_sensor_correction or loc is None or e0 is None:
            return math.nan
        e1 = self.residuals((*self.prior, dataclasses.replace(
            effect, location=loc, equivalent_locations=())))
        if e1 is None:
            return -math.inf
        # filtered from the fit part's start, so the hold-out's first errors are
        # predicted from the samples before them, as everywhere else in the record
        skip = self.holdout_start - self.fit_start
        t0 = t1 = 0.0
        for i, (d, s) in enumerate(self._whitening):
            w0, w1 = (scipy.signal.lfilter(d, [1.0], e[self.fit_start:, i])[skip:]
                      for e in (e0, e1))
            t0 += float(np.sum(w0 ** 2)) / (s * s or 1.0)
            t1 += float(np.sum(w1 ** 2)) / (s * s or 1.0)
        return 1.0 - math.sqrt(t1 / t0) if t0 > 0 else math.nan
