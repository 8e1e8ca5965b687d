"""Kernel-regularised FIR vs least squares with the noise model, at the same n_p.

Run:  .venv/bin/python -m tests.benchmarks.bench_kernel [--repeat R]

Times, side by side in one run, ``estimate_step_responses(x, y, n_p=P, dt=1,
noise="auto")`` (prediction-error least squares: lag Gram, AR order by BIC, GLS +
Gauss-Newton per output) and ``estimate_kernel(x, y, n_p=P, dt=1, noise="auto")`` (the
same noise-model fit, then the TC posterior with hyperparameters by marginal likelihood)
on two plant-sized problems:

(a) 6 inputs x 3 outputs, n_p = 180, N = 5,800 (the fractionator's size: 4 days at 1 min);
(b) 4 inputs x 4 outputs, n_p = 170, N = 6,400 (the steam generator's fit part).

Each output is a sum of first-order responses (gains in ±2, time constants 5-40
samples, dead times 0-7) of correlated AR(1) inputs, plus AR(1) 0.9 noise.  Prints the
best-of-R wall-clock seconds of each, the ratio kernel / least squares (target <= 3),
the kernel's Fisher-scoring iterations per output and both estimates' RMS step errors.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.signal as ss

from pipeline.estimation.estimate import estimate_step_responses
from pipeline.estimation.kernel_fir import estimate_kernel
from tests.benchmarks.bench_estimate import best_of


def make_plant(n: int, n_x: int, n_y: int, P: int, seed: int = 0):
    """Inputs, outputs and the true step responses (n_y, n_x, P)."""
    rng = np.random.default_rng(seed)
    mix = np.eye(n_x) + 0.3 * rng.standard_normal((n_x, n_x))
    x = ss.lfilter([1.0], [1, -0.7], rng.standard_normal((n, n_x)) @ mix.T, axis=0)
    y = np.zeros((n, n_y))
    steps = np.zeros((n_y, n_x, P))
    for i in range(n_y):
        for j in range(n_x):
            gain, tau, dead = rng.uniform(-2, 2), rng.uniform(5, 40), int(rng.integers(0, 8))
            a = np.exp(-1 / tau)
            imp = ss.lfilter([gain * (1 - a)], [1, -a], np.r_[np.zeros(dead), 1.0,
                                                              np.zeros(P - 1)])[:P]
            y[:, i] += ss.lfilter(imp, [1.0], x[:, j])
            steps[i, j] = np.cumsum(imp)
    y += 0.3 * ss.lfilter([1.0], [1, -0.9], rng.standard_normal((n, n_y)), axis=0)
    return x, y, steps


def case(name: str, n_x: int, n_y: int, P: int, N: int, repeat: int) -> float:
    x, y, steps = make_plant(N, n_x, n_y, P)
    t_ls, ls = best_of(lambda: estimate_step_responses(x, y, n_p=P, dt=1.0, noise="auto"),
                       repeat)
    t_k, ke = best_of(lambda: estimate_kernel(x, y, n_p=P, dt=1.0, noise="auto",
                                              clock=time.perf_counter), repeat)
    rms = lambda e: float(np.sqrt(np.mean((e.step - steps) ** 2)))  # noqa: E731
    its = [h["iterations"] for h in ke.extra["hyperparameters"]]
    print(f"({name}) {n_x} inputs x {n_y} outputs, n_p {P}, N {N}: "
          f"least squares + noise model {t_ls:.2f} s, kernel {t_k:.2f} s, "
          f"ratio kernel/LS {t_k / t_ls:.2f} (target <= 3)")
    print(f"    kernel iterations per output {its}; RMS step error LS {rms(ls):.4f}, "
          f"kernel {rms(ke):.4f}")
    return t_k / t_ls


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="best of R runs (default 2)")
    args = ap.parse_args(argv)
    case("a", 6, 3, 180, 5_800, args.repeat)
    case("b", 4, 4, 170, 6_400, args.repeat)


if __name__ == "__main__":
    main()
