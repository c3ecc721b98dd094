#!/usr/bin/env python3
"""The peer for the core's static model: the same records and parameter sets as the `core/static_*`
benches of host-sim/benches/throughput.rs (1 M samples of a triangle, 5000-sample period), the Bouc-Wen
step written as a user would in numba (f64): n = 1 by its exact exponential increment, general n by RK4
in u with ceil(|du|*J/0.1) sub-steps, J = n*(beta+|gamma|)*H^(n-1). Prints samples per second (best
of 5 runs, after compilation) as JSON.
"""
import json
import math
import time

import numba
import numpy as np

N = 1_000_000


def triangle(n, low, high, period):
    p = (np.arange(n) % period) / period
    return low + (high - low) * np.where(p < 0.5, 2 * p, 2 - 2 * p)


@numba.njit
def run_n1(u, a, beta, gamma, k1, k2):
    h = 0.0
    prev = u[0]
    acc = 0.0
    for v in u:
        du = v - prev
        if du != 0.0:
            s = 1.0 if du > 0 else -1.0
            sig = 1.0 if (h > 0 or (h == 0 and a * du > 0)) else -1.0
            kappa = beta * s + gamma * sig
            z = kappa * du
            g = 1.0 if z == 0.0 else -math.expm1(-z) / z
            h1 = h + (a - kappa * h) * du * g
            if h1 * sig < 0.0:
                x = -kappa * h / a
                du0 = -(h / a) * (math.log1p(x) / x if x != 0.0 else 1.0)
                rest = du - du0
                ka = beta * s - gamma * sig
                z = ka * rest
                h1 = a * rest * (1.0 if z == 0.0 else -math.expm1(-z) / z)
            h = h1
        prev = v
        acc += k1 * v + k2 * h
    return acc


@numba.njit
def slope(h, s, a, beta, gamma, n):
    sig = -1.0 if h < 0 else 1.0
    return a - (beta * s * sig + gamma) * abs(h) ** n


@numba.njit
def run_general(u, a, beta, gamma, n, k1, k2):
    H = (abs(a) / (beta + gamma * np.sign(a))) ** (1.0 / n)
    per_volt = n * (beta + abs(gamma)) * H ** (n - 1.0) / 0.1
    h = 0.0
    prev = u[0]
    acc = 0.0
    for v in u:
        du = v - prev
        if du != 0.0:
            s = 1.0 if du > 0 else -1.0
            m = max(1.0, math.ceil(abs(du) * per_volt))
            dh = du / m
            for _ in range(int(m)):
                q1 = slope(h, s, a, beta, gamma, n)
                q2 = slope(h + 0.5 * dh * q1, s, a, beta, gamma, n)
                q3 = slope(h + 0.5 * dh * q2, s, a, beta, gamma, n)
                q4 = slope(h + dh * q3, s, a, beta, gamma, n)
                h += dh / 6.0 * (q1 + 2.0 * (q2 + q3) + q4)
        prev = v
        acc += k1 * v + k2 * h
    return acc


def rate(f, *args):
    f(*args)
    best = math.inf
    for _ in range(5):
        t = time.perf_counter()
        f(*args)
        best = min(best, time.perf_counter() - t)
    return N / best


u100 = triangle(N, 0.0, 100.0, 5000)
u20 = triangle(N, 0.0, 20.0, 5000)
print(json.dumps({
    "static_n1": rate(run_n1, u100, 0.18522, 0.029586, -0.020710, 6.0e-7, -6.0e-7),
    "static_general_n1.5": rate(run_general, u20, 0.8, 0.5, 0.2, 1.5, 4.0e-7, -4.0e-7),
    "static_general_n3.06": rate(run_general, u20, -7.02182e-2, 4.45753, 3.49259, 3.05869, -3.51711e-7, -1.94566e-6),
    "numba": numba.__version__,
}))
