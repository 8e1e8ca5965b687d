"""Plants for the noise-model, closed-loop and integrating-output tests (issue 9).

Every record here is simulated independently of the code under test: python-control's
exact zero-order-hold discretisation (``control.sample_system``) or scipy's
``cont2discrete`` at a fine step, explicit loops for controllers — never
``pipeline.models.simulate`` and never the estimator's own model structure.  Noise is seeded.
The true step responses come from the same independent discretisations.
"""

from __future__ import annotations

import control as ct
import numpy as np
import scipy.signal as ss


def ar1(n: int, r: float, rng) -> np.ndarray:
    """Unit-variance AR(1) sequence with pole ``r``."""
    return ss.lfilter([np.sqrt(1 - r * r)], [1, -r], rng.standard_normal(n))


def zoh_response(G, u: np.ndarray, dt: float, delay: int = 0) -> np.ndarray:
    """Response of continuous ``G`` to a held input, exact at the samples, delayed by
    ``delay`` whole samples."""
    Gd = ct.sample_system(G, dt, method="zoh")
    y = ct.forced_response(Gd, T=np.arange(len(u)) * dt, U=u).outputs
    return np.concatenate([np.zeros(delay), y[: len(u) - delay]])


def zoh_step(G, dt: float, n: int, delay: int = 0) -> np.ndarray:
    """Discrete step response ``s[m]`` of the ZOH-discretised ``G`` (``m`` samples after the
    step), which is what ``step[m]`` of the estimator means for held inputs."""
    Gd = ct.sample_system(G, dt, method="zoh")
    s = ct.step_response(Gd, T=np.arange(n) * dt).outputs
    return np.concatenate([np.zeros(delay), s[: n - delay]])


# ------------------------------------------------------------------------- open loop
OPEN_LOOP_G = ct.tf([2.0], [30.0, 13.0, 1.0])  # 2 / ((10 s + 1)(3 s + 1))
OPEN_LOOP_DELAY = 3  # samples at T = 1 s; 98 % settled after ~45 s


def open_loop_record(n: int, phi: float, seed: int, *, noise_frac: float = 0.3,
                     gain_change: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Open loop, AR(1) noise (pole ``phi``) at ``noise_frac`` of the output's s.d.

    The input moves like normal operation (AR(1), pole 0.9).  With ``gain_change`` the
    plant's gain is multiplied by it for the second half of the record.
    """
    rng = np.random.default_rng(seed)
    u = ar1(n, 0.9, rng)
    if gain_change is None:
        y0 = zoh_response(OPEN_LOOP_G, u, 1.0, OPEN_LOOP_DELAY)
    else:
        # one continuous simulation whose gain changes mid-record (a time-varying plant)
        y0 = zoh_response(OPEN_LOOP_G, u, 1.0, OPEN_LOOP_DELAY)
        y1 = zoh_response(gain_change * OPEN_LOOP_G, u, 1.0, OPEN_LOOP_DELAY)
        y0 = np.concatenate([y0[: n // 2], y1[n // 2:]])
    v = ss.lfilter([1.0], [1.0, -phi], rng.standard_normal(n))
    v *= noise_frac * y0.std() / v.std()
    return u - u.mean(), (y0 + v) - (y0 + v).mean()


def open_loop_truth(n: int) -> np.ndarray:
    return zoh_step(OPEN_LOOP_G, 1.0, n, OPEN_LOOP_DELAY)


def arx_bic_step(u: np.ndarray, y: np.ndarray, max_order: int, n: int) -> tuple[int, np.ndarray]:
    """The peer tools' estimate: an ARX(o, o) model
    ``y(k) + a_1 y(k-1) + .. + a_o y(k-o) = b_0 u(k) + .. + b_{o-1} u(k-o+1) + e(k)``
    with the order chosen by BIC from 1..``max_order`` (as MATLAB's arxstruc/selstruc
    does), fitted by explicit least squares (numpy QR of the regressor matrix: with the
    columns interleaved, order ``o`` is the first ``2 o`` columns, so one factorisation
    gives every order's residual).  Returns ``(order, step response at lags 0..n-1)``.
    """
    k0 = max_order
    idx = np.arange(k0, y.size)
    cols = []
    for a in range(1, max_order + 1):
        cols += [-y[idx - a], u[idx - a + 1]]
    Phi = np.column_stack(cols)
    Q, R = np.linalg.qr(Phi)
    z = Q.T @ y[idx]
    yy = float(y[idx] @ y[idx])
    n_obs = idx.size
    orders = np.arange(1, max_order + 1)
    rss = yy - np.cumsum(z**2)[1::2]
    bic = n_obs * np.log(rss / n_obs) + 2 * orders * np.log(n_obs)
    o = int(orders[np.argmin(bic)])
    th = np.linalg.solve(R[: 2 * o, : 2 * o], z[: 2 * o])
    a = np.concatenate([[1.0], th[0::2]])
    b = th[1::2]
    return o, np.cumsum(ss.lfilter(b, a, np.r_[1.0, np.zeros(n - 1)]))


# ----------------------------------------------------------------- closed PI loop
def pi_loop_record(n: int, phi: float, seed: int, *, noise_sd: float = 1.0,
                   kp: float = 0.5, ki: float = 0.1, step_every: int = 200
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The loop of the issue: plant ``y(k) = 0.9 y(k-1) + 0.1 u(k-1) + v(k)`` (gain 1,
    one sample delay), AR(1) output noise ``v`` (pole ``phi``, s.d. ``noise_sd``), a PI
    controller acting on the same sample's measurement, setpoint steps of unit s.d.
    every ``step_every`` samples.  Returns ``(u, y, r)``, each mean-removed.
    """
    rng = np.random.default_rng(seed)
    r = np.repeat(rng.standard_normal(n // step_every + 1), step_every)[:n]
    v = ss.lfilter([1.0], [1.0, -phi], rng.standard_normal(n))
    v *= noise_sd / v.std()
    y = np.zeros(n)
    u = np.zeros(n)
    yp = 0.0
    integral = 0.0
    for k in range(n):
        if k:
            yp = 0.9 * yp + 0.1 * u[k - 1]
        y[k] = yp + v[k]
        e = r[k] - y[k]
        integral += ki * e
        u[k] = kp * e + integral
    return u - u.mean(), y - y.mean(), r - r.mean()


def pi_loop_truth(n: int) -> np.ndarray:
    """Step response of ``0.1 q^-1 / (1 - 0.9 q^-1)`` at lags 0..n-1 (gain 1)."""
    return np.concatenate([[0.0], 1.0 - 0.9 ** np.arange(1, n)])


# ------------------------------------------------------ historian loop (SP, OP, PV)
LOOP_GAIN = 2.0
LOOP_TAU_S = 20.0
LOOP_DELAY_S = 3.0


def historian_loop_signals(hours: float, seed: int, *, fine_dt: float = 0.05,
                           scan_s: float = 0.5) -> dict:
    """A flow/level-style loop as a DCS runs it and a historian records it.

    Plant ``2 e^{-3 s} / (20 s + 1)`` integrated at ``fine_dt`` (scipy ``cont2discrete``,
    zero-order hold); a PI controller scanned every ``scan_s`` acting on the previous
    scan's PV (the DCS delay), its output quantised to 0.01 %; PV = plant + a slow
    unmeasured disturbance (AR(1), time constant 200 s, s.d. 1.5 %) + sensor noise
    (s.d. 0.3 %); the operator moves the setpoint every 3–10 minutes.  Returns 1 s
    snapshots ``{"t_s", "SP", "OP", "PV"}``.
    """
    rng = np.random.default_rng(seed)
    n_fine = int(hours * 3600 / fine_dt)
    # x' = -x/tau + K u/tau, PV = x: exact zero-order-hold step of the first-order lag
    A, B, C, _, _ = ss.cont2discrete((np.array([[-1.0 / LOOP_TAU_S]]),
                                      np.array([[LOOP_GAIN / LOOP_TAU_S]]),
                                      np.array([[1.0]]), np.array([[0.0]])), fine_dt,
                                     method="zoh")
    a, b = float(A[0, 0]), float(B[0, 0])
    c = float(C[0, 0])
    delay = int(round(LOOP_DELAY_S / fine_dt))
    per_scan = int(round(scan_s / fine_dt))
    per_s = int(round(1.0 / fine_dt))
    n_s = n_fine // per_s
    # setpoint: steps every 5-15 min, in 0.5 % increments around 50 %
    sp_s = np.empty(n_s)
    k = 0
    level = 50.0
    while k < n_s:
        dur = int(rng.uniform(180, 600))
        sp_s[k:k + dur] = level
        level = float(np.clip(level + rng.normal(0, 4.0), 30, 70))
        level = round(level * 2) / 2
        k += dur
    dist = ss.lfilter([1.0], [1.0, -np.exp(-1.0 / 200.0)], rng.standard_normal(n_s))
    dist *= 1.5 / dist.std()
    sensor = 0.3 * rng.standard_normal(n_s)
    kp, ti = 0.6, 30.0
    x = 0.0
    u_hist = np.full(delay + 1, 25.0)  # ring buffer of actuator values for the dead time
    pos = 0
    op = 25.0
    integral = 25.0
    pv_prev = 50.0
    out = {"SP": np.empty(n_s), "OP": np.empty(n_s), "PV": np.empty(n_s)}
    for kf in range(n_fine):
        ks = kf // per_s
        if kf % per_scan == 0:
            e = sp_s[ks] - pv_prev  # the previous scan's PV
            integral += kp * scan_s / ti * e
            op = float(np.clip(kp * e + integral, 0.0, 100.0))
            op = round(op * 1e4) / 1e4  # actuator/DCS quantisation
        u_hist[pos] = op
        pos = (pos + 1) % (delay + 1)
        x = a * x + b * (u_hist[pos] - 25.0)  # the value written delay steps ago
        pv = 50.0 + c * x + dist[ks] + sensor[ks]
        if kf % per_scan == per_scan - 1:
            pv_prev = pv
        if kf % per_s == per_s - 1:
            out["SP"][ks], out["OP"][ks], out["PV"][ks] = sp_s[ks], op, pv
    return {"t_s": np.arange(n_s, dtype=float), **out}


# ----------------------------------------------------------------------- drum level
def drum_plant():
    """Drum level (integrating, two inputs): steam flow ``-0.01/s + 0.59/(10 s + 1)`` —
    shrink and swell: after a steam-flow increase the level first rises (wrong-way peak
    0.312 at 18 s), then falls at 0.01 per unit per s — and feedwater
    ``0.008 / (s (3 s + 1))`` with 2 s dead time."""
    s = ct.tf("s")
    return (-0.01 / s + 0.59 / (10 * s + 1)), 0.008 / (s * (3 * s + 1)), 2


DRUM_RATES = (-0.01, 0.008)


def drum_record(n: int, seed: int, *, sensor_noise: float = 1.0, dt: float = 1.0):
    """Steam and feedwater flows (AR(1), pole 0.95) and the drum level with white
    level-sensor noise.  Returns ``(x (n, 2), level (n,))``."""
    rng = np.random.default_rng(seed)
    Gs, Gf, dly = drum_plant()
    us, uf = ar1(n, 0.95, rng), ar1(n, 0.95, rng)
    level = zoh_response(Gs, us, dt) + zoh_response(Gf, uf, dt, dly)
    return np.column_stack([us, uf]), level + sensor_noise * rng.standard_normal(n)


def drum_truth(n: int, dt: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    Gs, Gf, dly = drum_plant()
    return zoh_step(Gs, dt, n), zoh_step(Gf, dt, n, dly)


# --------------------------------------------------------------- historian exports
EXPORT_START = np.datetime64("2026-05-04T00:00:00", "us")


def write_export(path, signals: dict, *, seed: int, timezone: str = "UTC"):
    """Write ``{tag: 1 s samples}`` as a PI-style long CSV with exception reporting
    (irregular, jittered timestamps) through the project's historian writer — the I/O
    path a real export takes, not a model of the plant."""
    from pipeline.adapters.historian_writer import write_long_csv

    n = len(next(iter(signals.values())))
    times = EXPORT_START + (np.arange(n) * 1_000_000).astype("timedelta64[us]")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_long_csv(path, times, signals, timezone=timezone,
                   irregular=np.random.default_rng(seed))
    return path


DRUM_TAGS = {"steam_flow": "FI-201.PV", "feedwater": "FI-202.PV", "drum_level": "LI-203.PV"}


def write_drum_export(path, *, hours: float, seed: int):
    """Drum-level export: steam flow around 60 kg/s, feedwater around 60 kg/s, level in
    cm around 0 with 1 cm of white sensor noise (tests/plants.drum_record)."""
    x, level = drum_record(int(hours * 3600), seed)
    return write_export(path, {DRUM_TAGS["steam_flow"]: 60.0 + x[:, 0],
                               DRUM_TAGS["feedwater"]: 60.0 + x[:, 1],
                               DRUM_TAGS["drum_level"]: level}, seed=seed)


LOOP_TAGS = {"SP": "FIC-301.SP", "OP": "FIC-301.OP", "PV": "FIC-301.PV"}


def write_loop_export(path, *, hours: float, seed: int):
    """The historian loop's SP, OP and PV as an exception-reported PI-style CSV."""
    sig = historian_loop_signals(hours, seed)
    return write_export(path, {LOOP_TAGS[k]: sig[k] for k in ("SP", "OP", "PV")}, seed=seed)


# ------------------------------------------------------- boiler with nuisance mismatch
#: The boiler pressure loop of ../shared/design.md ("Model YAML"), written out here as
#: equations: feedforward 0.019 on steam flow, PI (kp -0.554, ti 60 s) on the measured
#: pressure, fuel 65 x demand after 8 s, drum integrator 0.000883 (fuel - steam), pressure
#: drum - 0.045 steam.
BOILER = {"k_ff": 0.019, "kp": -0.554, "ti_s": 60.0, "k_fuel": 65.0, "delay_s": 8.0,
          "k_drum": 0.000883, "k_direct": -0.045}


def _boiler_loop(steam_fine, dist_fine, sensor_s, fine_dt, per_s, *, kp, delay_s, lag_s,
                 quantum):
    """Euler/exact-lag integration at ``fine_dt`` with a DCS that scans once per second
    and acts on the previous scan's measured pressure (true + ``sensor_s``)."""
    b = BOILER
    n_fine = steam_fine.size
    n_s = n_fine // per_s
    delay = int(round(delay_s / fine_dt))
    buf = np.zeros(delay + 1)
    pos = 0
    a_lag = np.exp(-fine_dt / lag_s) if lag_s > 0 else 0.0
    lagged = 0.0
    drum = 0.0
    integral = 0.0
    demand = 0.0
    p_meas_prev = 0.0
    pressure = np.empty(n_s)
    for kf in range(n_fine):
        ks = kf // per_s
        if kf % per_s == 0:  # DCS scan: the previous scan's measurement
            integral += p_meas_prev * 1.0
            u_c = kp * (p_meas_prev + integral / b["ti_s"])
            demand = u_c + b["k_ff"] * steam_fine[kf]
            demand = round(demand / quantum) * quantum  # actuator resolution
        buf[pos] = b["k_fuel"] * demand
        pos = (pos + 1) % (delay + 1)
        fuel = buf[pos]  # written `delay` fine steps ago
        if lag_s > 0:
            lagged = a_lag * lagged + (1.0 - a_lag) * fuel
            fuel = lagged
        drum += fine_dt * b["k_drum"] * (fuel - steam_fine[kf] + dist_fine[kf])
        if kf % per_s == per_s - 1:
            p = drum + b["k_direct"] * steam_fine[kf]
            pressure[ks] = p
            p_meas_prev = p + sensor_s[ks]
    return pressure


def boiler_nuisance_record(hours: float, seed: int, *, kp_factor: float = 1.0,
                           extra_fuel_delay_s: float = 0.0, extra_fuel_lag_s: float = 0.0,
                           sensor_frac: float = 0.05, input_frac: float = 0.02,
                           fine_dt: float = 0.05) -> tuple[dict, dict]:
    """The boiler loop as a plant, not as the model: independent of ``pipeline.models.simulate``.

    Nuisances a real plant has and the nominal model does not: Euler integration of the
    drum at ``fine_dt`` with the fuel path's dead time and lag in continuous time; a DCS
    that scans once per second and acts on the *previous* scan's measurement (a
    one-sample controller delay); fuel demand quantised to 1e-4; a slow unmeasured
    disturbance on the drum's energy balance (AR, time constant 30 min, 0.15 kg/s);
    white sensor noise of ``sensor_frac`` of the pressure's std; noise of ``input_frac``
    of its std on the *measured* steam flow.  Hidden effects: the controller's gain
    times ``kp_factor``, an extra fuel dead time, an extra first-order lag on the fuel
    path.  Returns ``(inputs, measured)`` as deviations at 1 s snapshots:
    ``{"steam_flow"}``, ``{"turbine_pressure"}``.
    """
    rng = np.random.default_rng(seed)
    n_s = int(hours * 3600)
    per_s = int(round(1.0 / fine_dt))
    slow = ss.lfilter([1.0], [1.0, -np.exp(-1 / 1200.0)], rng.standard_normal(n_s))
    fast = ss.lfilter([1.0], [1.0, -np.exp(-1 / 40.0)], rng.standard_normal(n_s))
    steps = np.zeros(n_s)
    k = int(rng.uniform(600, 1800))
    while k < n_s:
        steps[k:] += rng.choice([-1, 1]) * rng.uniform(1.0, 3.0)
        k += int(rng.uniform(900, 2400))
    steam = 3.0 * slow / slow.std() + 0.5 * fast / fast.std() + steps - steps.mean()
    dist = ss.lfilter([1.0], [1.0, -np.exp(-1 / 1800.0)], rng.standard_normal(n_s))
    dist *= 0.15 / dist.std()
    t = np.arange(n_s, dtype=float)
    t_fine = np.arange(n_s * per_s) * fine_dt
    steam_fine = np.interp(t_fine, t, steam)
    dist_fine = np.interp(t_fine, t, dist)
    unit_sensor = rng.standard_normal(n_s)
    kw = {"kp": BOILER["kp"] * kp_factor, "delay_s": BOILER["delay_s"] + extra_fuel_delay_s,
          "lag_s": extra_fuel_lag_s, "quantum": 1e-4}
    # the sensor noise is a fraction of the pressure's own std: one noise-free pass sets it
    scale = float(np.std(_boiler_loop(steam_fine, dist_fine, np.zeros(n_s), fine_dt, per_s,
                                      **kw)))
    pressure = _boiler_loop(steam_fine, dist_fine, sensor_frac * scale * unit_sensor,
                            fine_dt, per_s, **kw)
    measured_p = pressure + sensor_frac * scale * unit_sensor
    measured_steam = steam + input_frac * steam.std() * rng.standard_normal(n_s)
    return ({"steam_flow": measured_steam - measured_steam.mean()},
            {"turbine_pressure": measured_p - measured_p.mean()})


# ------------------------------------- feedback test on integrating outputs (issue 36)
LEVEL_NOISES = ("white", "ar", "walk", "walk_ar")
"""Disturbances of :func:`open_level_record`: white level-sensor noise alone, plus an
AR(1) on the level, a random walk (an integrated white flow imbalance) or an integrated
AR(1) flow imbalance."""


def held_moves(rng, n: int, lo: int = 20, hi: int = 200) -> np.ndarray:
    """Normal operation of a manipulated input: a random level (unit s.d.) held for
    ``lo..hi`` samples, then the next."""
    u = np.empty(n)
    t = 0
    while t < n:
        hold = int(rng.integers(lo, hi + 1))
        u[t:t + hold] = rng.normal()
        t += hold
    return u


def lag_delay(u: np.ndarray, tau: float, dead: int) -> np.ndarray:
    """Unit-gain first-order lag (time constant ``tau`` samples, exact ZOH: one sample of
    hold delay) followed by ``dead`` more samples of delay."""
    a = np.exp(-1.0 / tau)
    v = ss.lfilter([0.0, 1.0 - a], [1.0, -a], u)
    return np.r_[np.zeros(dead), v[: v.size - dead]] if dead else v


def level_noise(n: int, kind: str, rng) -> tuple[np.ndarray, dict]:
    """A level disturbance of one of :data:`LEVEL_NOISES` (white sensor noise of s.d.
    0.05-0.5 in every kind); returns it and its parameters."""
    if kind not in LEVEL_NOISES:
        raise ValueError(f"kind={kind!r}; use one of {LEVEL_NOISES}")
    sensor = float(rng.uniform(0.05, 0.5))
    e = sensor * rng.standard_normal(n)
    par: dict = {"sensor_sd": sensor}
    if kind == "ar":
        par.update(phi=float(rng.choice([0.9, 0.97])), sd=float(rng.uniform(0.1, 0.4)))
        return e + ss.lfilter([par["sd"]], [1, -par["phi"]], rng.standard_normal(n)), par
    if kind == "walk":
        par["sd"] = float(rng.uniform(0.005, 0.05))
        return e + np.cumsum(par["sd"] * rng.standard_normal(n)), par
    if kind == "walk_ar":
        par.update(phi=float(rng.choice([0.7, 0.9])), sd=float(rng.uniform(0.002, 0.02)))
        return e + np.cumsum(ss.lfilter([par["sd"]], [1, -par["phi"]],
                                        rng.standard_normal(n))), par
    return e, par


def open_level_record(n: int, noise: str, seed: int, *, n_x: int | None = None):
    """An open-loop level (nothing controls it): ``y(k) = y(k-1) + sum_j K_j v_j(k)``,
    ``v_j`` input ``j`` through a first-order lag (2-30 samples) and 0-4 samples of dead
    time, rates ``|K_j|`` 0.005-0.03 per sample of either sign, plus a
    :func:`level_noise`; 1-2 inputs (``n_x``; default drawn) of :func:`held_moves` with a
    little white noise.  Returns ``(inputs (n, n_x), level (n,), info)``."""
    rng = np.random.default_rng(seed)
    n_x = int(rng.integers(1, 3)) if n_x is None else n_x
    us, rate, plant = [], np.zeros(n), []
    for _ in range(n_x):
        u = held_moves(rng, n) + 0.05 * rng.standard_normal(n)
        k = float(rng.choice([-1, 1]) * rng.uniform(0.005, 0.03))
        tau, dead = float(rng.uniform(2, 30)), int(rng.integers(0, 5))
        rate += k * lag_delay(u, tau, dead)
        us.append(u)
        plant.append({"rate": k, "tau": tau, "dead": dead})
    v, par = level_noise(n, noise, rng)
    return np.column_stack(us), np.cumsum(rate) + v, {"plant": plant, "noise": par}


def pi_controlled_record(n: int, integrating: bool, seed: int):
    """A PI loop whose controller output ``u`` is the pair's input: ``u`` moves a level
    (``integrating``: an inflow valve, rate 0.02-0.05 per sample per unit ``u``) or a
    self-regulating output (gain 1), through a first-order lag (3-20 samples) and 1-3
    samples of delay; the controller acts on the same sample's measurement (tuned to a
    closed-loop time constant of about ``40 + 2 tau`` samples on the level, integral time =
    ``tau`` on the self-regulating output).  Setpoint moves held 100-600 samples (unit
    s.d.), an unmeasured disturbance (an AR(1) flow imbalance integrated by the level, or
    an AR(1) of s.d. 0.3-1 on the output; pole 0.9 or 0.97) and white sensor noise of s.d.
    0.02-0.2.  Returns ``(u (n, 1), y (n,), info)``."""
    rng = np.random.default_rng(seed)
    sp = held_moves(rng, n, 100, 600)
    e = rng.uniform(0.02, 0.2) * rng.standard_normal(n)
    phi = float(rng.choice([0.9, 0.97]))
    w = ss.lfilter([np.sqrt(1 - phi**2)], [1, -phi], rng.standard_normal(n))
    tau, dead = float(rng.uniform(3, 20)), int(rng.integers(0, 3))
    a = np.exp(-1.0 / tau)
    if integrating:
        k_r = float(rng.uniform(0.02, 0.05))
        w *= 0.02
        kc, ti = 1.0 / (k_r * (40 + 2 * tau)), 4 * (40 + 2 * tau)
    else:
        k_r = 1.0
        w *= float(rng.uniform(0.3, 1.0))
        kc, ti = 0.5, tau
    u, y = np.zeros(n), np.zeros(n)
    line = np.zeros(dead + 1)  # u(k-1) .. u(k-1-dead)
    state = level = integral = 0.0
    for k in range(n):
        state = a * state + (1 - a) * line[-1]
        if integrating:
            level += k_r * state + w[k]
            y[k] = level + e[k]
        else:
            y[k] = state + w[k] + e[k]
        err = sp[k] - y[k]
        integral += err / ti
        u[k] = kc * (err + integral)
        line = np.r_[u[k], line[:-1]]
    return u[:, None], y, {"plant": {"gain_or_rate": k_r, "tau": tau, "delay": dead + 1},
                           "noise": {"phi": phi}}
