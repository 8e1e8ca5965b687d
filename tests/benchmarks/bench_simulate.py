"""Simulation benchmark: the two paths of :func:`pipeline.models.simulate.simulate`, one run.

Run:  .venv/bin/python -m tests.benchmarks.bench_simulate [--samples N]

Prints, for 1e5 samples (default) of random inputs at dt_s = 1 s:
1. boiler_pressure and drum_level: the lifted linear path, the per-sample path and
   scipy.signal.dlsim on the same assembled system (the library reference), with the
   largest difference between the paths and the ratio per-sample / linear.
2. boiler_pressure with a saturation after the controller and a deadband before the
   fuel (nonlinear: per-sample path only).
Timings are best-of-5 wall clock (dlsim: one run) including discretisation (what a caller pays).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.signal
import yaml

from pipeline.models.blocks import Deadband, Saturation, Term
from pipeline.models.model import Model, insert_after, insert_before, model_from_dict
from pipeline.models.simulate import discrete_state_space, simulate

MODELS = Path(__file__).resolve().parents[2] / "configs" / "models"


def _load(name: str) -> Model:
    with (MODELS / f"{name}.yaml").open(encoding="utf-8") as fh:
        return model_from_dict(yaml.safe_load(fh))


def _best_of(fn: Callable[[], object], repeats: int = 5) -> tuple[float, object]:
    best, value = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        value = fn()
        best = min(best, time.perf_counter() - start)
    return best, value


def _nonlinear_boiler() -> Model:
    model = insert_before(_load("boiler_pressure"), "fuel",
                          block=Deadband(name="fuel_db", width=0.001))
    return insert_after(
        model, "controller", upstream_name="controller_raw",
        block=Saturation(name="controller", inputs=(Term("controller_raw"),),
                         low=-0.05, high=0.05),
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=100_000)
    args = parser.parse_args(argv)
    n, dt_s = args.samples, 1.0
    rng = np.random.default_rng(0)
    print(f"samples: {n}, dt_s: {dt_s}")
    for name in ("boiler_pressure", "drum_level"):
        model = _load(name)
        u = rng.standard_normal((n, len(model.inputs)))
        t_lin, lin = _best_of(lambda m=model, u=u: simulate(m, u, dt_s=dt_s, method="linear"))
        t_ps, ps = _best_of(lambda m=model, u=u: simulate(m, u, dt_s=dt_s, method="per_sample"))
        system = discrete_state_space(model, dt_s=dt_s)
        t_dl, dl = _best_of(lambda s=system, u=u: scipy.signal.dlsim(
            (s.a, s.b, s.c, s.d, dt_s), u), repeats=1)
        y_dl = dl[1]
        scale = np.abs(lin.outputs).max()
        out_index = [system.signal_names.index(o) for o in model.outputs]
        print(
            f"{name:16s} states {len(system.state_names):3d} | linear {t_lin * 1e3:7.1f} ms"
            f" | per-sample {t_ps * 1e3:7.1f} ms | dlsim {t_dl * 1e3:7.1f} ms"
            f" | per-sample/linear {t_ps / t_lin:5.1f}x | dlsim/linear {t_dl / t_lin:5.1f}x"
            f" | max |linear - per-sample| / max|y| "
            f"{np.abs(lin.outputs - ps.outputs).max() / scale:.1e}"
            f" | vs dlsim {np.abs(lin.outputs - y_dl[:, out_index]).max() / scale:.1e}"
        )
    model = _nonlinear_boiler()
    u = rng.standard_normal((n, 1))
    t_nl, _ = _best_of(lambda: simulate(model, u, dt_s=dt_s))
    print(f"{'boiler+sat+db':16s} nonlinear, per-sample path {t_nl * 1e3:7.1f} ms")
    # the test suite's independent plant (tests/plant_sim.py: continuous time, Heun at
    # dt/10, DCS controllers) on the same record, beside the pipeline's simulator
    from tests.plant_sim import simulate_plant

    for name in ("boiler_pressure", "drum_level"):
        model = _load(name)
        u = {k: np.cumsum(rng.standard_normal(n)) * 0.01 for k in model.inputs}
        t_sim, _ = _best_of(lambda m=model, u=u: simulate(m, u, dt_s=dt_s), repeats=3)
        t_ind, _ = _best_of(lambda m=model, u=u: simulate_plant(
            m, u, dt_s=dt_s, substeps=10, dcs_scan_s=0.5), repeats=1)
        print(f"{name:16s} independent plant (10 substeps, DCS) {t_ind * 1e3:7.1f} ms "
              f"= {t_ind / t_sim:5.1f}x pipeline.models.simulate")


if __name__ == "__main__":
    main()
