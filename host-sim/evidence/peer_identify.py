#!/usr/bin/env python3
"""The peer for `host-sim identify`: what a user would write in Python for seed 001's asymmetric
stage model (Case III) — scipy.optimize.differential_evolution over the project's search box with a
numba-jitted objective that uses the project's variable projection.

Model (f64, the reading of core/src/static_model.rs): A = 1, theta = (log10(H/U), r, n, d, p) with
H = (1/(beta+gamma))^(1/n), U the input span, r = (beta-gamma)/(beta+gamma), delta = d*H/(U*T_rec),
phi = p*T; per sample U[k] = u[k] - p*(u[k]-u[k-1]), the delta-term half before and half after the
Bouc-Wen increment (dh/du = 1 - (beta*s*sgn h + gamma)*|h|^n, RK4 in u with ceil(|dU|*J/0.1)
sub-steps, J = n*(beta+|gamma|)*H^(n-1)), h clamped at 1.25*H; y = k1*u + k2*h + y0 with
(k1, k2, y0) by least squares inside every evaluation.

Prints one JSON line: seconds to reach the target RMS (time to fitness: from the start of the
optimisation, after numba's compilation and the file read, to the first evaluation at or below the
target; the optimiser stops after that generation), the final RMS, evaluations.

With --sse-timing instead: the time of one objective evaluation on the whole record (after numba's
compilation) at the search box's midpoint, the point `cargo bench -p host-sim --bench identify`
times the project's evaluation at; prints one JSON line with the median of --repeats calls.

Usage: peer_identify.py DATA.csv --target-rms M [--seed S]
       peer_identify.py DATA.csv --sse-timing [--repeats R]
"""
import argparse
import json
import math
import time

import numpy as np
import numba
from scipy.optimize import differential_evolution

BOUNDS = [(-1.5, 1.0), (-1.0, 30.0), (1.0, 5.0), (-1.0, 1.0), (-1.0, 1.0)]


@numba.njit
def slope(h, s, beta, gamma, n):
    sigma = -1.0 if h < 0.0 else 1.0
    return 1.0 - (beta * s * sigma + gamma) * abs(h) ** n


@numba.njit
def advance(h, du, beta, gamma, n, per_volt):
    if du == 0.0:
        return h
    s = 1.0 if du > 0.0 else -1.0
    m = max(1.0, math.ceil(abs(du) * per_volt))
    dh = du / m
    for _ in range(int(m)):
        k1 = slope(h, s, beta, gamma, n)
        k2 = slope(h + 0.5 * dh * k1, s, beta, gamma, n)
        k3 = slope(h + 0.5 * dh * k2, s, beta, gamma, n)
        k4 = slope(h + dh * k3, s, beta, gamma, n)
        h += dh / 6.0 * (k1 + 2.0 * (k2 + k3) + k4)
    return h


@numba.njit
def sse(theta, u, y, span, period, duration):
    n = theta[2]
    H = span * 10.0 ** theta[0]
    b = H ** (-n)
    beta = b * (1.0 + theta[1]) / 2.0
    gamma = b * (1.0 - theta[1]) / 2.0
    delta = theta[3] * H / (span * duration)
    p = theta[4]
    half_step = 0.5 * delta * period
    per_volt = n * (beta + abs(gamma)) * H ** (n - 1.0) / 0.1
    limit = 1.25 * H
    g = np.zeros((3, 3))
    rhs = np.zeros(3)
    yy = 0.0
    h = 0.0
    prev = u[0]
    shifted_prev = u[0]
    for k in range(u.shape[0]):
        v = u[k]
        du = v - prev
        shifted = v - p * du
        half = 0.0
        if du > 0.0:
            half = half_step * 0.5 * (v + prev)
        elif du < 0.0:
            half = -half_step * 0.5 * (v + prev)
        h = advance(h + half, shifted - shifted_prev, beta, gamma, n, per_volt) + half
        h = min(max(h, -limit), limit)
        prev = v
        shifted_prev = shifted
        phi0, phi1, phi2 = v, h, 1.0
        g[0, 0] += phi0 * phi0
        g[0, 1] += phi0 * phi1
        g[0, 2] += phi0
        g[1, 1] += phi1 * phi1
        g[1, 2] += phi1
        g[2, 2] += 1.0
        rhs[0] += phi0 * y[k]
        rhs[1] += phi1 * y[k]
        rhs[2] += y[k]
        yy += y[k] * y[k]
    if not math.isfinite(h):
        return 1e300
    g[1, 0] = g[0, 1]
    g[2, 0] = g[0, 2]
    g[2, 1] = g[1, 2]
    for i in range(3):
        g[i, i] += 1e-12 * g[i, i]
    lin = np.linalg.solve(g, rhs)
    return max(yy - (lin[0] * rhs[0] + lin[1] * rhs[1] + lin[2] * rhs[2]), 0.0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("--target-rms", type=float)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sse-timing", action="store_true")
    ap.add_argument("--repeats", type=int, default=200)
    a = ap.parse_args()
    if not a.sse_timing and a.target_rms is None:
        ap.error("--target-rms is required (or --sse-timing)")
    d = np.loadtxt(a.data, delimiter=",", skiprows=1)
    t, u, y = d[:, 0], d[:, 1].copy(), d[:, 2] - d[:, 2].mean()
    period = (t[-1] - t[0]) / (len(t) - 1)
    span = u.max() - u.min()
    duration = period * len(u)
    sse(np.array([-0.5, 8.0, 3.0, 0.5, 0.0]), u, y, span, period, duration)  # compile
    if a.sse_timing:
        midpoint = np.array([0.5 * (lo + hi) for lo, hi in BOUNDS])
        times = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            sse(midpoint, u, y, span, period, duration)
            times.append(time.perf_counter() - t0)
        times.sort()
        print(json.dumps({
            "sse_seconds_median": times[len(times) // 2],
            "sse_seconds_min": times[0],
            "samples": len(u),
            "theta": midpoint.tolist(),
            "repeats": a.repeats,
            "numba": numba.__version__,
        }))
        return
    target_sse = a.target_rms ** 2 * len(u)
    evaluations = [0]
    reached = [None]
    start = time.perf_counter()

    def objective(theta):
        evaluations[0] += 1
        f = sse(theta, u, y, span, period, duration)
        if reached[0] is None and f <= target_sse:
            reached[0] = time.perf_counter() - start
        return f

    def stop_at_target(intermediate_result):
        return reached[0] is not None

    result = differential_evolution(
        objective, BOUNDS, seed=a.seed, tol=1e-10, maxiter=1000, polish=True, callback=stop_at_target
    )
    total = time.perf_counter() - start
    print(json.dumps({
        "seconds_to_target": reached[0],
        "seconds_total": total,
        "final_rms": math.sqrt(result.fun / len(u)),
        "target_rms": a.target_rms,
        "evaluations": evaluations[0],
        "numba": numba.__version__,
    }))


if __name__ == "__main__":
    main()
