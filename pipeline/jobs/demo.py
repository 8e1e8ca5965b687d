"""The bundled demo: a realistic historian export of the boiler steam-pressure loop.

The plant is the shipped model ``configs/models/boiler_pressure.yaml`` (PI pressure
controller with steam-flow feedforward, 8 s fuel dead time, integrating drum) simulated
at 1 s, with the pressure setpoint the operators move.  The steam flow (the load) wanders like a real unit's: slow load moves plus
turbulence.  Measured: steam flow FI-101.PV, turbine pressure PI-102.PV and its setpoint
PIC-102.SP, fuel flow FI-103.PV, each with sensor noise, written as a PI-style long CSV with exception-reported
(irregular) timestamps in local time and a few digital states ("I/O Timeout",
"Bad Input"), as a historian export arrives in the drop folder.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from pipeline.models.model import Model, model_from_dict
from pipeline.simulated.synthetic import (
    DEMO_EFFECTS,
    TWO_EFFECT_DEMO_EFFECTS,
    boiler_demo_plant,
    boiler_demo_signals,
    make_discrepancy_demo,
)

# The shipped jobs and models: configs/ of the checkout, reached through the package's
# _shipped link, which the wheel carries as package data (so an installed plantdyn has them).
SHIPPED = Path(__file__).parents[1] / "_shipped"
DEMO_JOB = SHIPPED / "demo_boiler.yaml"
BOILER_MODEL = SHIPPED / "models" / "boiler_pressure.yaml"

# operating point the deviations of the model are added to
STEAM0, PRESSURE0, FUEL0 = 50.0, 120.0, 30.0


def boiler_model() -> Model:
    """The shipped boiler pressure model (``configs/models/boiler_pressure.yaml``)."""
    from pipeline.adapters.config import load_yaml_file

    return model_from_dict(load_yaml_file(BOILER_MODEL, what="model file"))


def make_demo_signals(*, hours: float = 12.0, dt_s: float = 1.0, seed: int = 7) -> dict:
    """The demo plant's signals (:func:`pipeline.simulated.synthetic.boiler_demo_signals` of the
    shipped boiler model with a moving pressure setpoint,
    :func:`pipeline.simulated.synthetic.boiler_demo_plant`, at the demo's operating point).

    Parameters
    ----------
    hours : float
        Length of the record, h.
    dt_s : float
        Sample period of the simulation, s.
    seed : int
        Seeds the load, the setpoint moves and the sensor noise.
    """
    from pipeline.adapters.config import load_yaml_file

    shipped = load_yaml_file(BOILER_MODEL, what="model file")
    plant = model_from_dict({"model": boiler_demo_plant(shipped["model"])})
    op = {"steam_flow": STEAM0, "turbine_pressure": PRESSURE0, "fuel_flow": FUEL0}
    return boiler_demo_signals(plant, op, hours=hours, dt_s=dt_s, seed=seed)


def write_demo_export(folder: Path, *, hours: float = 12.0, seed: int = 7) -> Path:
    """Write the demo export CSV into ``folder`` and return its path.

    Parameters
    ----------
    folder : Path
        Destination folder (created if missing); the file is ``boiler_export.csv``.
    hours : float
        Length of the record, h.
    seed : int
        Seeds the signals (:func:`make_demo_signals`); ``seed + 1`` the irregular
        timestamps and the digital states.
    """
    from pipeline.adapters.historian_writer import write_long_csv

    sig = make_demo_signals(hours=hours, seed=seed)
    folder.mkdir(parents=True, exist_ok=True)
    # UTC; 18:00 local (CET) to 07:00 local (CEST): spans the spring DST change at 01:00Z
    start = np.datetime64("2026-03-28T17:00:00", "us")
    times = start + (sig["t_s"] * 1e6).astype("timedelta64[us]")
    rng = np.random.default_rng(seed + 1)
    n = times.size
    states = {
        "FI-101.PV": [(int(i), "I/O Timeout") for i in rng.integers(100, n - 100, 3)],
        "PI-102.PV": [(int(i), "Bad Input") for i in rng.integers(100, n - 100, 3)],
        "FI-103.PV": [(int(i), "Shutdown") for i in rng.integers(100, n - 100, 2)],
    }
    path = folder / "boiler_export.csv"
    write_long_csv(path, times, {"FI-101.PV": sig["steam_flow"],
                                 "PI-102.PV": sig["turbine_pressure"],
                                 "PIC-102.SP": sig["pressure_sp"],
                                 "FI-103.PV": sig["fuel_flow"]},
                   timezone="Europe/Berlin", irregular=rng, states=states)
    return path


# ------------------------------------------------------------------ discrepancy demo
DISCREPANCY_JOB = SHIPPED / "demo_discrepancy.yaml"
TWO_EFFECT_JOB = SHIPPED / "demo_discrepancy_two.yaml"
AUX0 = 20.0  # operating point of the unrelated auxiliary flow


def write_discrepancy_export(folder: Path, *, hours: float = 8.0, seed: int = 11,
                             two_effects: bool = False) -> Path:
    """Historian export of a plant whose pressure controller gain is 20 % above the model's
    (and, with `two_effects`, an auxiliary flow the model ignores acts on the pressure).

    The signals come from :func:`pipeline.simulated.synthetic.make_discrepancy_demo` (the shipped
    boiler model with ``controller.kp`` × 1.2, AR(1) sensor noise), moved to the demo's
    operating point and written as a PI-style long CSV at 1 s in local time with two
    isolated "Bad Input" states (bridged by the workflow).

    Parameters
    ----------
    folder : Path
        Destination folder (created if missing); the file is ``boiler_kp_export.csv``.
    hours : float
        Length of the record, h.
    seed : int
        Seeds the simulated signals; ``seed + 1`` places the digital states.
    two_effects : bool
        The plant of the two-effect demo (:data:`pipeline.simulated.synthetic.TWO_EFFECT_DEMO_EFFECTS`);
        the file is then ``boiler_two_effects_export.csv``.
    """
    from pipeline.adapters.historian_writer import write_long_csv
    effects = TWO_EFFECT_DEMO_EFFECTS if two_effects else DEMO_EFFECTS
    inputs, measured, dt_s = make_discrepancy_demo(boiler_model(), seed, hours=hours,
                                                   effects=effects)
    n = measured["turbine_pressure"].size
    folder.mkdir(parents=True, exist_ok=True)
    start = np.datetime64("2026-11-20T22:00:00", "us")
    times = start + (np.arange(n) * dt_s * 1e6).astype("timedelta64[us]")
    rng = np.random.default_rng(seed + 1)
    states = {"PI-102.PV": [(int(i), "Bad Input") for i in rng.integers(1000, n - 1000, 2)]}
    path = folder / ("boiler_two_effects_export.csv" if two_effects else "boiler_kp_export.csv")
    write_long_csv(path, times, {"FI-101.PV": STEAM0 + inputs["steam_flow"],
                                 "FI-110.PV": AUX0 + inputs["aux_flow"],
                                 "PI-102.PV": PRESSURE0 + measured["turbine_pressure"]},
                   timezone="Europe/Berlin", states=states)
    return path


def _write_own(path: Path, data: bytes) -> Path:
    """Write one of the demo's files in ``--dir`` (replaced each time, but never a FIFO,
    device node, folder or link: :mod:`pipeline.adapters.safe_write`)."""
    from pipeline.adapters.safe_write import safe_target, write_atomically

    return write_atomically(safe_target(path, force=True, option="--dir"), data,
                            option="--dir")


def _clear_exports(exports: Path) -> None:
    """Remove the demo's previous export folder — only a real folder, never a link."""
    if exports.is_symlink() or (exports.exists() and not exports.is_dir()):
        from pipeline.adapters.safe_write import file_kind
        from pipeline.errors import ConfigError

        raise ConfigError(f"--dir: {exports} is a {file_kind(exports.lstat().st_mode)}, not "
                          "the demo's export folder; move it away or give another --dir")
    if exports.exists():
        shutil.rmtree(exports)


def _say(progress, message: str) -> None:
    if progress:
        progress("demo", message)


def prepare_demo(folder: Path, *, progress=None) -> Path:
    """Write the demo export into ``folder/exports`` and a copy of the shipped demo job
    pointing at it (results go to ``../storage`` beside the folder); returns the job.

    Parameters
    ----------
    folder : Path
        Where the job file and ``exports/`` are written (``exports/`` is replaced).
    progress : callable (stage, message), optional
        Told what is being written (stage ``"demo"``); ``None`` says nothing.
    """
    folder = folder.resolve()
    exports = folder / "exports"
    text = DEMO_JOB.read_text().replace("../demo/exports/*.csv", "exports/*.csv")
    folder.mkdir(parents=True, exist_ok=True)
    job = _write_own(folder / "demo_boiler.yaml", text.encode("utf-8"))
    _clear_exports(exports)
    _say(progress, f"writing a 12 h historian export of the boiler loop to {exports}")
    path = write_demo_export(exports)
    _say(progress, f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB); running {job}")
    return job


def prepare_discrepancy_demo(folder: Path, *, progress=None, two_effects: bool = False) -> Path:
    """Write the discrepancy demo export, the shipped boiler model and a copy of
    ``configs/demo_discrepancy.yaml`` (``demo_discrepancy_two.yaml`` with `two_effects`)
    into ``folder``; returns the job.

    Parameters
    ----------
    folder : Path
        Where the job file, ``models/`` and ``discrepancy/`` are written
        (``discrepancy/`` is replaced).
    progress : callable (stage, message), optional
        Told what is being written (stage ``"demo"``); ``None`` says nothing.
    two_effects : bool
        The two-effect demo (controller gain and an unmodelled auxiliary flow).
    """
    folder = folder.resolve()
    name = "discrepancy_two" if two_effects else "discrepancy"
    shipped = TWO_EFFECT_JOB if two_effects else DISCREPANCY_JOB
    exports = folder / name
    text = shipped.read_text().replace(f"../demo/{name}/*.csv", f"{name}/*.csv")
    (folder / "models").mkdir(parents=True, exist_ok=True)
    _write_own(folder / "models" / BOILER_MODEL.name, BOILER_MODEL.read_bytes())
    job = _write_own(folder / shipped.name, text.encode("utf-8"))
    _clear_exports(exports)
    what = ("and an auxiliary flow it ignores acts on the pressure" if two_effects else "")
    _say(progress, f"writing an 8 h export of a boiler whose controller gain is 20 % above "
                   f"the model's {what + ' ' if what else ''}to {exports}")
    path = write_discrepancy_export(exports, two_effects=two_effects)
    _say(progress, f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB); running {job}")
    return job
