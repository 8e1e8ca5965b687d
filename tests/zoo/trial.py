"""Zoo trials: draw an effect, simulate the plant, write what a user would have.

A trial is one family (:data:`tests.zoo.FAMILIES`), one seed and either nothing (a null:
the plant is the nominal model's structure with its parameters; only the DCS, the
quantisation, the unmeasured disturbance and the noise differ) or one injected effect of
:data:`tests.zoo.sim.ZOO_EFFECTS` at the family's site for it (``Family.sites``) with
parameters drawn from ``Family.ranges``.  :func:`write_trial` writes

* ``export/<family>.csv``: a PI-style long historian export
  (:func:`pipeline.adapters.historian_writer.write_long_csv`), absolute values;
* ``model.yaml``: the family's nominal model;
* ``job.yaml``: the discrepancy job (every measured signal, ``sampling.dt_s`` the
  export's period, Rerun off), run as ``plantdyn discrepancy job.yaml --no-prefect``;
* ``truth.json``: the known answer (effect, location, parameters) and the noise.

Draws (``rng = default_rng([seed, crc32(family)])``):

* ``gain``: factor ``1 ± U(ranges["gain"])`` (random sign);
* ``dead_time``: a whole number of samples in ``ranges["dead_time"]`` (s);
* ``extra_lag``: ``tau_s ~ U(ranges["extra_lag"])``;
* ``saturation``: one limit (high or low, random) of the valve output at the
  U(0.90, 0.97) quantile of the nominal record's output on the part the workflow fits
  on (the first two thirds; :func:`_saturation_limits`): transients hit the stop and
  the controller winds up against it; redrawn if an OP winds into its 0/100 % clamp
  (the loop could not recover, and the nominal models have no clamp);
* ``deadband``/``backlash``: ``width ~ U(ranges[...])`` % OP;
* ``sensor_bias_drift``: bias 0 (not identifiable against the ``mean`` operating point),
  a total drift over the record of ``U(ranges["drift"])`` times the output's scale,
  random sign;
* ``unmodelled_input``: the family's :meth:`~tests.zoo.sim.Family.unmodelled`, and a
  delay of a whole number of samples in ``ranges["unmodelled_delay"]``.

Visible effects only, by the workflow's own definition of a finding: a drawn effect is
redrawn (up to :data:`MAX_REDRAWS` times, the trial's ``redraws``) until a model that had
it exactly would shrink the gap of the nominal model, on the held-out part where the
workflow judges and on the part it fits on alike, by at least
:data:`~pipeline.simulated.effect_trials.TRIAL_GAP_REDUCTION` (1.5 times the 5 % practical bar,
as the boiler trials).  Measured from the zoo's own records, not from the workflow:
the gap before is the measured record against the nominal plant (the same simulation
without the effect, the unmeasured disturbance and the noise -- what a perfect nominal
model predicts), the gap after is the same with the effect's footprint (the record with
the effect less the record without it, same disturbance and noise) added to the
prediction; both pooled over outputs as the workflow's ``gap`` (each output's held-out
RMS over its held-out std).  A saturation hit by 2 % of the record changes the
temperature loop's outputs by far less than its slow unmeasured disturbance does, and
the workflow then must by definition call it minor.  A trial still below the bar after
the redraws is kept with ``visible`` False; the suite counts it apart.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from pipeline.simulated.effect_trials import TRIAL_GAP_REDUCTION, holdout_start
from tests.zoo.sim import (
    WARMUP_S,
    ZOO_EFFECTS,
    Family,
    PlantRecord,
    TrueEffect,
    simulate_plant,
)

#: Redraws of an effect that is not visible (module docstring) before it is kept as it is.
MAX_REDRAWS = 20

#: Start of every export (UTC).
START = np.datetime64("2026-06-01T00:00:00", "us")


@dataclass(frozen=True)
class ZooTrial:
    """One simulated trial and its known answer.

    Attributes
    ----------
    family : Family
    seed : int
    effect : TrueEffect or None
        None for a null trial.
    record : PlantRecord
        Plant outputs and OPs as measured and noise-free.
    inputs : dict of str -> ndarray (N,)
        Setpoints, loads and the extra signal as exported (loads and extra with noise).
    rel_noise : float
        Sensor and input noise std as a fraction of each signal's scale.
    gap_reduction : float
        Held-out gap reduction of a model with the effect exactly (module docstring;
        NaN for a null trial).
    redraws : int
        Effects drawn and found not visible before this one.
    clamped : bool
        An OP of the record reached its 0/100 % clamp (the nominal models have none).
    """

    family: Family
    seed: int
    effect: TrueEffect | None
    record: PlantRecord
    inputs: dict[str, np.ndarray]
    rel_noise: float
    gap_reduction: float = float("nan")
    redraws: int = 0
    clamped: bool = False

    @property
    def visible(self) -> bool:
        """Whether the effect clears the visibility bar and no OP reached its clamp
        (a null trial: True)."""
        return self.effect is None or (self.gap_reduction >= TRIAL_GAP_REDUCTION
                                       and not self.clamped)

    @property
    def tags(self) -> dict[str, str]:
        """Signal name -> historian tag, every exported signal."""
        f = self.family
        return {**f.setpoints, **f.loads, f.extra[0]: f.extra[1], **f.outputs}

    def export_values(self) -> dict[str, np.ndarray]:
        """Tag -> exported values."""
        values = {**self.inputs, **self.record.measured}
        return {tag: values[name] for name, tag in self.tags.items()}


def _rng(family: Family, seed: int) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(family.name.encode())])


def _delayed_deviation(signal: np.ndarray, warm: int, n_shift: int) -> np.ndarray:
    dev = signal - signal[warm:].mean()
    if n_shift == 0:
        return dev
    return np.concatenate([np.full(n_shift, dev[0]), dev[:-n_shift]])


def _samples_in(rng: np.random.Generator, bounds: tuple[float, float], dt_s: float) -> float:
    lo, hi = (max(1, round(b / dt_s)) for b in bounds)
    return float(rng.integers(lo, hi + 1)) * dt_s


def _saturation_limits(free: np.ndarray, rng: np.random.Generator) -> dict[str, float]:
    """One limit of the valve output: at the U(0.90, 0.97) quantile of the nominal
    record's output on the part the workflow fits on (a limit met only in the held-out
    third cannot be estimated; the boiler trials do the same), or the mirrored low one:
    transients hit the stop and the controller winds up against it.  A draw whose OP
    winds into its 0/100 % clamp anywhere (a steady demand beyond the limit: the loop
    cannot recover) is redrawn (:func:`make_trial`): the nominal models have no OP
    clamp."""
    free = free[:holdout_start(free.size)]
    q = float(rng.uniform(0.90, 0.97))
    if rng.random() < 0.5:
        return {"low": -np.inf, "high": float(np.quantile(free, q))}
    return {"low": float(np.quantile(free, 1.0 - q)), "high": np.inf}


def ideal_gap_reduction(measured: dict[str, np.ndarray], without: dict[str, np.ndarray],
                        nominal: dict[str, np.ndarray]) -> float:
    """Gap reduction of a model that has the effect exactly (module docstring): the
    smaller of the held-out part's and the fit part's.

    Parameters
    ----------
    measured : dict of str -> ndarray (N,)
        The outputs as measured, with the effect.
    without : dict of str -> ndarray (N,)
        The same record without the effect (same disturbance and noise): measured less
        the effect's footprint.
    nominal : dict of str -> ndarray (N,)
        The nominal plant's outputs (no effect, disturbance or noise).
    """
    n = next(iter(measured.values())).size
    return min(_part_gap_reduction(measured, without, nominal, part)
               for part in (slice(holdout_start(n), n), slice(0, holdout_start(n))))


def _part_gap_reduction(measured: dict[str, np.ndarray], without: dict[str, np.ndarray],
                        nominal: dict[str, np.ndarray], part: slice) -> float:
    before, after = [], []
    for name, y in measured.items():
        std = float(np.std(y[part])) or 1.0
        before.append(float(np.sqrt(np.mean((y[part] - nominal[name][part]) ** 2))) / std)
        after.append(float(np.sqrt(np.mean((without[name][part] - nominal[name][part]) ** 2))) / std)
    if len(before) == 1:
        b, a = before[0], after[0]
    else:
        b, a = float(np.sqrt(np.mean(np.square(before)))), float(np.sqrt(np.mean(np.square(after))))
    return 1.0 - a / b if b > 0 else 0.0


def _clamped(family: Family, record: PlantRecord) -> bool:
    """Whether an OP of `record` reached its 0/100 % clamp (the zoo's DCS clamps; the
    nominal models do not)."""
    return any(float(np.min(record.truth[lp.op])) <= 0.0 or float(np.max(record.truth[lp.op])) >= 100.0
               for lp in family.loops)


def draw_effect(family: Family, name: str, rng: np.random.Generator, *,
                nominal: PlantRecord | None, hours: float, extra_std: float
                ) -> tuple[TrueEffect, dict[str, float], dict[str, float]]:
    """Draw effect `name` for `family` (module docstring).

    Parameters
    ----------
    family : Family
    name : str
        One of :data:`ZOO_EFFECTS`.
    rng : numpy.random.Generator
    nominal : PlantRecord or None
        The nominal record of the same exogenous signals (needed for ``saturation``).
    hours : float
        Record length, h.
    extra_std : float
        Std of the extra signal (``unmodelled_input``).

    Returns
    -------
    (TrueEffect, dict, dict)
        The known answer, the actuator effect in plant units for
        :func:`~tests.zoo.sim.simulate_plant`, plant-parameter updates.
    """
    if name not in ZOO_EFFECTS:
        raise ValueError(f"effect {name!r} is not in the zoo; allowed: {', '.join(ZOO_EFFECTS)}")
    r, loc = family.ranges, family.sites[name]
    if name == "gain":
        factor = 1.0 + rng.choice([-1.0, 1.0]) * rng.uniform(*r["gain"])
        return TrueEffect(name, loc, {"factor": factor}), {"factor": factor}, {}
    if name == "dead_time":
        delay = _samples_in(rng, r["dead_time"], family.dt_s)
        return TrueEffect(name, loc, {"delay_s": delay}), {"delay_s": delay}, {}
    if name == "extra_lag":
        tau = float(rng.uniform(*r["extra_lag"]))
        return TrueEffect(name, loc, {"tau_s": tau}), {"tau_s": tau}, {}
    if name in ("deadband", "backlash"):
        width = float(rng.uniform(*r[name]))
        return TrueEffect(name, loc, {"width": width}), {"width": width}, {}
    if name == "saturation":
        if nominal is None:
            raise ValueError("saturation needs the nominal record to place its limit")
        lim = _saturation_limits(nominal.valve_free, rng)
        return TrueEffect(name, loc, lim), lim, {}
    if name == "sensor_bias_drift":
        total = rng.choice([-1.0, 1.0]) * rng.uniform(*r["drift"]) * family.scales[loc]
        return TrueEffect(name, loc, {"bias": 0.0, "drift_per_h": total / hours}), {}, {}
    updates, answer = family.unmodelled(rng, extra_std)
    delay = _samples_in(rng, r["unmodelled_delay"], family.dt_s)
    return (TrueEffect(name, loc, {"k": answer["k"], "tau_s": answer["tau_s"],
                                   "delay_s": delay}), {}, {**updates, "extra_delay_s": delay})


def make_trial(family: Family, effect: str | None, seed: int, *,
               hours: float | None = None, rel_noise: float | None = None) -> ZooTrial:
    """Simulate one trial of `family` with `effect` (None: a null trial).

    Parameters
    ----------
    family : Family
    effect : str or None
        One of :data:`ZOO_EFFECTS`, or None.
    seed : int
    hours : float, optional
        Record length (default ``family.hours``).
    rel_noise : float, optional
        Sensor and input noise as a fraction of each signal's scale (default: drawn
        from U(0.01, 0.03); the draw is made either way, so the rest of the trial is
        the same).

    Returns
    -------
    ZooTrial
    """
    hours = family.hours if hours is None else float(hours)
    rng = _rng(family, seed)
    h = family.fine_s
    warm = round(WARMUP_S / h)
    n_fine = warm + round(hours * 3600.0 / h) + round(family.dt_s / h)
    exo = family.exogenous(rng, n_fine)
    extra = exo[family.extra[0]]
    extra_std = float(np.std(extra[warm:]))
    drawn = float(rng.uniform(0.01, 0.03))
    rel_noise = drawn if rel_noise is None else float(rel_noise)
    p = family.calibrate(family.params, [
        float(np.mean(exo[k][warm:])) if k in exo else 0.0 for k in family.exo_names])
    sim_seed = int(rng.integers(2**32))

    def run(eff: TrueEffect | None, physical: dict, updates: dict, *,
            clean: bool = False) -> PlantRecord:
        pp = {**p, **updates}
        shift = round(pp.get("extra_delay_s", 0.0) / h)
        table = {**exo, "extra_in": _delayed_deviation(extra, warm, shift)}
        if clean:  # the nominal plant: no unmeasured disturbance, no noise
            table["disturbance"] = np.zeros_like(np.asarray(exo["disturbance"], dtype=float))
        return simulate_plant(family, table, p=pp, effect=eff, physical=physical,
                              rel_noise=0.0 if clean else rel_noise,
                              rng=np.random.default_rng(sim_seed))

    truth_effect, reduction, redraws, clamped = None, float("nan"), 0, False
    if effect is None:
        record = run(None, {}, {})
    else:
        null, nominal = run(None, {}, {}), run(None, {}, {}, clean=True)
        while True:
            truth_effect, physical, updates = draw_effect(
                family, effect, rng, nominal=null, hours=hours, extra_std=extra_std)
            record = run(truth_effect, physical, updates)
            if effect == "sensor_bias_drift":
                loc = truth_effect.location
                drift = truth_effect.parameters["drift_per_h"] * record.t_s / 3600.0
                record.measured[loc] = record.measured[loc] + drift
            reduction = ideal_gap_reduction(
                {o: record.measured[o] for o in family.outputs},
                {o: null.measured[o] for o in family.outputs},
                {o: nominal.truth[o] for o in family.outputs})
            clamped = _clamped(family, record)
            if (reduction >= TRIAL_GAP_REDUCTION and not clamped) or redraws == MAX_REDRAWS:
                break
            redraws += 1
    n = record.t_s.size
    idx = warm + np.arange(n) * round(family.dt_s / h)
    inputs = {}
    for name in (*family.setpoints, *family.loads, family.extra[0]):
        v = np.asarray(exo[name], dtype=float)[idx]
        if name not in family.setpoints:
            v = v + rel_noise * float(np.std(v)) * rng.standard_normal(n)
        inputs[name] = v
    return ZooTrial(family=family, seed=seed, effect=truth_effect, record=record,
                    inputs=inputs, rel_noise=rel_noise, gap_reduction=reduction,
                    redraws=redraws, clamped=clamped)


def job_dict(trial: ZooTrial, *, discrepancy: dict[str, Any] | None = None) -> dict[str, Any]:
    """The discrepancy job YAML mapping of `trial` (paths relative to the job file).

    Parameters
    ----------
    trial : ZooTrial
    discrepancy : dict, optional
        Extra keys of the job's ``discrepancy:`` section (default: only ``seed``, and
        the family's ``operating_point`` where it states one).
    """
    f = trial.family
    inputs = {**f.setpoints, **f.loads, f.extra[0]: f.extra[1]}
    return {
        "job": f"zoo_{f.name}",
        "source": {"path": f"export/{f.name}.csv", "timezone": "UTC"},
        "signals": {"inputs": {k: {"tag": t} for k, t in inputs.items()},
                    "outputs": {k: {"tag": t} for k, t in f.outputs.items()}},
        "storage": "storage",
        "sampling": {"dt_s": f.dt_s},
        "rerun": {"enabled": False},
        "model": "model.yaml",
        "discrepancy": {"seed": int(trial.seed),
                        **({"operating_point": dict(f.operating_point)}
                           if f.operating_point else {}),
                        **(discrepancy or {})},
    }


def write_trial(trial: ZooTrial, directory: Path, *,
                discrepancy: dict[str, Any] | None = None) -> Path:
    """Write the export, the model, the job and the known answer; return the job path.

    Parameters
    ----------
    trial : ZooTrial
    directory : Path
        Created if missing.
    discrepancy : dict, optional
        Extra keys of the job's ``discrepancy:`` section.
    """
    from pipeline.adapters.historian_writer import write_long_csv

    directory = Path(directory)
    (directory / "export").mkdir(parents=True, exist_ok=True)
    times = START + (trial.record.t_s * 1e6).astype(np.int64).astype("timedelta64[us]")
    write_long_csv(directory / "export" / f"{trial.family.name}.csv", times,
                   trial.export_values())
    (directory / "model.yaml").write_text(yaml.safe_dump(trial.family.model(), sort_keys=False))
    job = directory / "job.yaml"
    job.write_text(yaml.safe_dump(job_dict(trial, discrepancy=discrepancy), sort_keys=False))
    (directory / "truth.json").write_text(json.dumps({
        "family": trial.family.name, "seed": trial.seed,
        "effect": None if trial.effect is None else trial.effect.to_dict(),
        "rel_noise": trial.rel_noise, "dt_s": trial.family.dt_s,
        "op_ref": trial.record.op_ref, "valve_ref": trial.record.a_ref}, indent=2))
    return job
