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
  U(0.95, 0.98) quantile of the nominal record's output, kept beyond its 10-min moving
  average (:func:`_saturation_limits`): transients hit the stop and the controller winds
  up against it, steady demands stay inside;
* ``deadband``/``backlash``: ``width ~ U(ranges[...])`` % OP;
* ``sensor_bias_drift``: bias 0 (not identifiable against the ``mean`` operating point),
  a total drift over the record of ``U(ranges["drift"])`` times the output's scale,
  random sign;
* ``unmodelled_input``: the family's :meth:`~tests.zoo.sim.Family.unmodelled`, and a
  delay of a whole number of samples in ``ranges["unmodelled_delay"]``.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tests.zoo.sim import (
    WARMUP_S,
    ZOO_EFFECTS,
    Family,
    PlantRecord,
    TrueEffect,
    simulate_plant,
)

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
    """

    family: Family
    seed: int
    effect: TrueEffect | None
    record: PlantRecord
    inputs: dict[str, np.ndarray]
    rel_noise: float

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


def _saturation_limits(free: np.ndarray, dt_s: float, rng: np.random.Generator
                       ) -> dict[str, float]:
    """One limit of the valve output: at the U(0.95, 0.98) quantile of the nominal
    record's output (or the mirrored low one), but at least a tenth of the way from the
    extreme of its 10-min moving average to its raw extreme -- steady demands stay
    inside, so the loop always recovers and the OP never winds into its 0/100 % clamp;
    transients hit the stop for a few per cent of the record."""
    width = max(1, round(600.0 / dt_s))
    smooth = np.convolve(free, np.ones(width) / width, mode="valid")
    q = float(rng.uniform(0.95, 0.98))
    if rng.random() < 0.5:
        sm, raw = smooth.max(), free.max()
        return {"low": -np.inf, "high": float(max(sm + 0.1 * (raw - sm), np.quantile(free, q)))}
    sm, raw = smooth.min(), free.min()
    return {"low": float(min(sm + 0.1 * (raw - sm), np.quantile(free, 1.0 - q))),
            "high": np.inf}


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
        lim = _saturation_limits(nominal.valve_free, family.dt_s, rng)
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

    def run(eff: TrueEffect | None, physical: dict, updates: dict) -> PlantRecord:
        pp = {**p, **updates}
        shift = round(pp.get("extra_delay_s", 0.0) / h)
        table = {**exo, "extra_in": _delayed_deviation(extra, warm, shift)}
        return simulate_plant(family, table, p=pp, effect=eff, physical=physical,
                              rel_noise=rel_noise, rng=np.random.default_rng(sim_seed))

    truth_effect = None
    if effect is None:
        record = run(None, {}, {})
    else:
        nominal = run(None, {}, {}) if effect == "saturation" else None
        truth_effect, physical, updates = draw_effect(
            family, effect, rng, nominal=nominal, hours=hours, extra_std=extra_std)
        record = run(truth_effect, physical, updates)
        if effect == "sensor_bias_drift":
            loc = truth_effect.location
            drift = truth_effect.parameters["drift_per_h"] * record.t_s / 3600.0
            record.measured[loc] = record.measured[loc] + drift
    n = record.t_s.size
    idx = warm + np.arange(n) * round(family.dt_s / h)
    inputs = {}
    for name in (*family.setpoints, *family.loads, family.extra[0]):
        v = np.asarray(exo[name], dtype=float)[idx]
        if name not in family.setpoints:
            v = v + rel_noise * float(np.std(v)) * rng.standard_normal(n)
        inputs[name] = v
    return ZooTrial(family=family, seed=seed, effect=truth_effect, record=record,
                    inputs=inputs, rel_noise=rel_noise)


def job_dict(trial: ZooTrial, *, discrepancy: dict[str, Any] | None = None) -> dict[str, Any]:
    """The discrepancy job YAML mapping of `trial` (paths relative to the job file).

    Parameters
    ----------
    trial : ZooTrial
    discrepancy : dict, optional
        Extra keys of the job's ``discrepancy:`` section (default: only ``seed``).
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
        "discrepancy": {"seed": int(trial.seed), **(discrepancy or {})},
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
