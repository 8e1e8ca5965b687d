"""Hidden-effect trials whose plant is NOT the model: nuisance mismatch (issue 12).

The clean hidden-effect trials (:func:`pipeline.simulated.effect_trials.make_hidden_effects_trial`)
simulate the plant with the same simulator and block structure as the nominal model, so
the only difference between plant and model is the hidden effect.  Here the same trial
(same seed: same inputs, same hidden effects, same sensor-noise kind and size) is
re-simulated as a real plant differs from its model:

* **another simulator**: :func:`tests.plant_sim.simulate_plant` -- continuous time, Heun
  at ``dt_s / 10``, inputs linearly interpolated between samples, outputs snapshotted at
  the sample instants as a historian does -- not ``pipeline.models.simulate`` (exact ZOH at
  ``dt_s``);
* **a DCS**: every ``pi``/``pid`` block scans every :data:`DCS_SCAN_S` s and acts on the
  previous scan's measurement (a one-scan controller delay);
* **actuator resolution**: every controller's output quantised to :data:`QUANTUM_FRAC`
  of its nominal std;
* **a slow unmeasured disturbance** on every integrator's balance: AR(1), correlation
  time :data:`DISTURBANCE_TAU_S`, std :data:`DISTURBANCE_FRAC` of the first model
  input's std (the boiler: 0.1 kg/s on a 3-4 kg/s load wander);
* **noise on the measured inputs** (:data:`INPUT_NOISE_FRAC` of each signal's std, white)
  besides the sensor noise of the outputs (the clean trial's kind and relative size).

The plant's blocks are the nominal model with the hidden effects added by the
catalogue's :func:`pipeline.discrepancy.effects.apply_effect` -- that is the *definition* of each
effect -- so what is independent of the code under test is the simulation, the
nuisances and the noise.

A hidden effect can drown in the nuisances: the trial is kept only when the effect,
added to the model with its true parameters, still shrinks the held-out gap of the
nuisance record by :data:`pipeline.simulated.effect_trials.TRIAL_GAP_REDUCTION` (each effect on
top of the others); otherwise the next derived seed is drawn (``redraws`` counts them).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from pipeline.simulated.effect_trials import (
    TRIAL_GAP_REDUCTION,
    HiddenEffectTrial,
    holdout_start,
    make_hidden_effects_trial,
    unit_ar1,
)
from pipeline.discrepancy.effects import Effect, apply_effect, output_offsets
from pipeline.errors import ConfigError
from pipeline.models.model import Model
from pipeline.models.simulate import simulate
from tests.plant_sim import simulate_plant

DCS_SCAN_S = 1.0
QUANTUM_FRAC = 1e-3
DISTURBANCE_TAU_S = 1800.0
DISTURBANCE_FRAC = 0.03
INPUT_NOISE_FRAC = 0.02
SUBSTEPS = 10
#: Derived seeds: attempt ``a`` of trial seed ``s`` uses ``s + SEED_STRIDE * a``.
SEED_STRIDE = 7_919_000


def _with_effects(model: Model, effects: Sequence[Effect], dt_s: float) -> Model:
    for effect in effects:
        model = apply_effect(model, effect, dt_s=dt_s)
    return model


def nuisance_plant(model: Model, effects: Sequence[Effect], inputs: dict[str, np.ndarray],
                   dt_s: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Noise-free outputs (measurement offsets included) of the nuisance plant.

    Parameters
    ----------
    model : Model
        The nominal model.
    effects : sequence of Effect
        Hidden effects (catalogue locations of the nominal model).
    inputs : dict of str -> ndarray (N,)
        TRUE signals at the sample instants (every one the plant reads).
    dt_s : float
        Sample period, s.
    rng : numpy.random.Generator
        Draws the unmeasured disturbance.
    """
    plant = _with_effects(model, effects, dt_s)
    n = next(iter(inputs.values())).size
    nominal = simulate(model, {k: inputs[k] for k in model.inputs}, dt_s=dt_s)
    controllers = [b.name for b in plant.blocks if b.TYPE in ("pi", "pid")]
    quanta = {c: QUANTUM_FRAC * float(np.std(nominal.signals[c])) for c in controllers
              if c in nominal.signals and np.std(nominal.signals[c]) > 0}
    scale = DISTURBANCE_FRAC * float(np.std(inputs[model.inputs[0]]))
    disturbances = {b.name: scale * unit_ar1(rng, n, math.exp(-dt_s / DISTURBANCE_TAU_S))
                    for b in plant.blocks if b.TYPE == "integrator"}
    out = simulate_plant(plant, {k: inputs[k] for k in plant.inputs}, dt_s=dt_s,
                         substeps=SUBSTEPS, dcs_scan_s=DCS_SCAN_S, quanta=quanta,
                         disturbances=disturbances)
    truth = {o: out[o] for o in model.outputs}
    for effect in effects:
        offsets = output_offsets(effect, n=n, dt_s=dt_s, outputs=model.outputs)
        truth = {o: truth[o] + offsets[o] for o in model.outputs}
    return truth


def _held_gap_reduction(model: Model, effects: Sequence[Effect], others: Sequence[Effect],
                        inputs: dict[str, np.ndarray], measured: dict[str, np.ndarray],
                        dt_s: float) -> float:
    """Held-out gap reduction (pooled as the workflow pools outputs) when `effects` are
    in the model, against the model with only `others`, on the measured record."""
    n = next(iter(measured.values())).size
    held = slice(holdout_start(n), n)

    def rms(effs: Sequence[Effect]) -> float:
        m = _with_effects(model, effs, dt_s)
        sim = simulate(m, {k: inputs[k] for k in m.inputs}, dt_s=dt_s)
        total = 0.0
        for o in model.outputs:
            pred = sim.signals[o]
            for effect in effs:
                pred = pred + output_offsets(effect, n=n, dt_s=dt_s, outputs=[o])[o]
            e = measured[o][held] - pred[held]
            total += float(np.mean(e ** 2)) / float(np.var(measured[o][held]))
        return math.sqrt(total)

    return 1.0 - rms(effects) / rms(others)


def make_nuisance_trial(model: Model, effect_names: Sequence[str], *, seed: int,
                        n: int = 10_000, dt_s: float = 2.0, max_redraws: int = 20
                        ) -> HiddenEffectTrial:
    """A hidden-effect trial re-simulated with nuisance mismatch (module docstring).

    Parameters
    ----------
    model : Model
        A shipped model (``boiler_pressure`` or ``drum_level``).
    effect_names : sequence of str
        Effects to hide (empty: a null trial).
    seed : int
        Seeds the clean trial (inputs, effects, noise) and the nuisances.
    n, dt_s : int, float
        Samples and sample period, s.
    max_redraws : int
        Derived seeds tried when the nuisances hide an effect.

    Returns
    -------
    HiddenEffectTrial
        ``inputs`` are the MEASURED signals (with input noise), ``truth`` the nuisance
        plant's noise-free outputs, ``noise`` adds ``"nuisance": True``; ``redraws``
        counts the clean generator's and the nuisance redraws.
    """
    redraws = 0
    for attempt in range(max_redraws):
        trial_seed = seed + SEED_STRIDE * attempt
        try:
            clean = make_hidden_effects_trial(model, tuple(effect_names), seed=trial_seed,
                                              n=n, dt_s=dt_s)
        except ConfigError:  # no visible effect at this draw's noise level
            redraws += 1
            continue
        rng = np.random.default_rng([trial_seed, 1])
        truth = nuisance_plant(model, clean.effects, clean.inputs, dt_s, rng)
        rel, phi = clean.noise["relative_std"], clean.noise["phi"]
        measured = {o: truth[o] + rel * float(np.std(truth[o])) * unit_ar1(rng, n, phi)
                    for o in model.outputs}
        inputs = {k: v + INPUT_NOISE_FRAC * float(np.std(v)) * rng.standard_normal(n)
                  for k, v in clean.inputs.items()}
        effects = clean.effects
        visible = all(
            _held_gap_reduction(model, effects, effects[:k] + effects[k + 1:], inputs,
                                measured, dt_s) >= TRIAL_GAP_REDUCTION
            for k in range(len(effects)))
        redraws += clean.redraws
        if visible:
            return dataclasses.replace(
                clean, inputs=inputs, measured=measured, truth=truth,
                noise={**clean.noise, "nuisance": True, "dcs_scan_s": DCS_SCAN_S},
                redraws=redraws, seed=seed)
        redraws += 1
    raise RuntimeError(f"no nuisance trial with visible {list(effect_names)} in "
                       f"{max_redraws} derived seeds of {seed} ({model.name})")
