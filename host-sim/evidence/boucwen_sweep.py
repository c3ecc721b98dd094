#!/usr/bin/env python3
"""Sine-sweep checks of an identified Bouc-Wen benchmark oscillator.

1. Our own sweep of the benchmark's published system (SOURCE.md of the data: m = 2, c = 10, k = 5e4,
   alpha = 5e4, beta = 1e3, gamma = 0.8, delta = -1.1, nu = 1), simulated independently of the
   project: f64 classical RK4 at 200 steps per 750 Hz sample (150 kHz) on the analytic input
   u(t) = 40 sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T))), f0 = 15 Hz, f1 = 60 Hz, T = 120 s, through the
   35.6 Hz resonance; the same at 100 steps per sample shows the reference's own error.
2. The benchmark's official sine sweep (uval/yval_sinesweep of the EHH file in ../shared/data, read in
   place): the published system simulated at 15 kHz on its samples (band-limited interpolation),
   read at the 750 Hz instants and, alternatively, decimated as MATLAB's decimate(y, r, 'fir') does
   (fir1(30, 1/r), Hamming, zero phase) by 20 in one stage and by 2, 2, 5 (the benchmark generator's
   chain for its multisines): which processing the file carries.
Writes OUT/sweep_reference.csv and OUT/sweep_official.csv (t_s,u_N,y_m) for `host-sim predict`, and
prints the reference's convergence and the published system's distance to the official file.

Usage: boucwen_sweep.py OUT_DIR [DATA_DIR]
"""
import math
import os
import sys

import numba
import numpy as np
import scipy.io
import scipy.signal

TRUE = (2.0, 10.0, 5e4, 5e4, 1e3 * 0.8, 1e3 * -1.1)
FS = 750.0


@numba.njit
def rhs(y, v, z, u, p):
    m, c, k, alpha, bg, bd = p
    return v, (u - c * v - k * y - z) / m, alpha * v - (bg * abs(v) * z + bd * v * abs(z))


@numba.njit
def step(y, v, z, ua, um, ub, h, p):
    a1 = rhs(y, v, z, ua, p)
    a2 = rhs(y + 0.5 * h * a1[0], v + 0.5 * h * a1[1], z + 0.5 * h * a1[2], um, p)
    a3 = rhs(y + 0.5 * h * a2[0], v + 0.5 * h * a2[1], z + 0.5 * h * a2[2], um, p)
    a4 = rhs(y + h * a3[0], v + h * a3[1], z + h * a3[2], ub, p)
    return (y + h / 6 * (a1[0] + 2 * a2[0] + 2 * a3[0] + a4[0]),
            v + h / 6 * (a1[1] + 2 * a2[1] + 2 * a3[1] + a4[1]),
            z + h / 6 * (a1[2] + 2 * a2[2] + 2 * a3[2] + a4[2]))


@numba.njit
def sweep_analytic(samples, sub, p, amp, f0, f1, duration):
    h = 1.0 / (FS * sub)
    out = np.zeros(samples)
    y = v = z = 0.0
    for i in range(1, samples):
        for j in range(sub):
            t = ((i - 1) * sub + j) * h
            ua = amp * math.sin(2 * math.pi * (f0 * t + (f1 - f0) * t * t / (2 * duration)))
            tm = t + 0.5 * h
            um = amp * math.sin(2 * math.pi * (f0 * tm + (f1 - f0) * tm * tm / (2 * duration)))
            tb = t + h
            ub = amp * math.sin(2 * math.pi * (f0 * tb + (f1 - f0) * tb * tb / (2 * duration)))
            y, v, z = step(y, v, z, ua, um, ub, h, p)
        out[i] = y
    return out


@numba.njit
def simulate_fine(fine, factor, p):
    h = 1.0 / (FS * factor)
    out = np.zeros(len(fine))
    y = v = z = 0.0
    for i in range(1, len(fine)):
        y, v, z = step(y, v, z, fine[i - 1], 0.5 * (fine[i - 1] + fine[i]), fine[i], h, p)
        out[i] = y
    return out


def decimate_fir(x, factors):
    """MATLAB's decimate(x, r, 'fir') per factor: fir1(30, 1/r) (Hamming, unit DC gain), zero phase."""
    for r in factors:
        x = np.convolve(x, scipy.signal.firwin(31, 1.0 / r), mode="same")[::r]
    return x


def upsample_even(u, factor):
    e = np.concatenate([u, u[::-1]])
    n, m = len(e), len(e) * factor
    spec = np.fft.rfft(e)
    wide = np.zeros(m // 2 + 1, complex)
    wide[: len(spec)] = spec
    wide[n // 2] *= 0.5
    return np.fft.irfft(wide, m)[: len(u) * factor] * factor


def write(path, u, y):
    t = np.arange(len(u)) / FS
    np.savetxt(path, np.stack([t, u, y], 1), delimiter=",", header="t_s,u_N,y_m", comments="", fmt="%.10e")


def main():
    out = sys.argv[1]
    data = sys.argv[2] if len(sys.argv) > 2 else "../shared/data"
    os.makedirs(out, exist_ok=True)
    p = np.array(TRUE)
    amp, f0, f1, duration = 40.0, 15.0, 60.0, 120.0
    samples = int(duration * FS)
    t = np.arange(samples) / FS
    u = amp * np.sin(2 * np.pi * (f0 * t + (f1 - f0) * t * t / (2 * duration)))
    fine = sweep_analytic(samples, 200, p, amp, f0, f1, duration)
    coarse = sweep_analytic(samples, 100, p, amp, f0, f1, duration)
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))
    print(f"reference sweep: rms y {rms(fine):.4e} m; 100 vs 200 steps per sample: {rms(fine - coarse):.2e} m")
    write(f"{out}/sweep_reference.csv", u, fine)
    mat = scipy.io.loadmat(f"{data}/boucwen_benchmark/original/bouc-wen_preston1000_EHH.mat")
    us, ys = mat["uval_sinesweep"].ravel(), mat["yval_sinesweep"].ravel()
    write(f"{out}/sweep_official.csv", us, ys)
    fine_official = simulate_fine(upsample_even(us, 20), 20, p)
    print(f"official sweep: rms y {rms(ys):.4e} m; the published system (RK4 at 15 kHz) against it:")
    for name, y in (("read at the 750 Hz instants", fine_official[::20]),
                    ("decimated 20 in one stage", decimate_fir(fine_official, [20])),
                    ("decimated 2, 2, 5", decimate_fir(fine_official, [2, 2, 5]))):
        print(f"  {name:28s} {rms(y[:len(ys)] - ys):.3e} m")


if __name__ == "__main__":
    main()
