"""Benchmark of the optimality yardsticks: every controller as a ratio to both bounds.

    python benchmarks/bench_bounds.py [--quick] [--n-taps 256]

Case: the synthesis benchmark's (benchmarks/bench_synthesis.py): 540 turbulence-like modal
PSDs (:func:`aocontrol.disturbance.synthetic_turbulence_psd`, D = 8 m, V = 10 m/s,
r0 = 0.15 m) on the same log-spaced grid, white noise 4 nm^2 per frame, fs = 3000 Hz, latency
0.83 frame, modulus margin 0.5, order-5 data-driven controllers. A log-spaced subset of the
modes keeps it to a few minutes: the low orders 0, 1, 5, 14, 35 (the hardest: deep rejection
needed) and 12 modes evenly spaced in index (6 with --quick), whose median stands for the
median over the 540 modes; plus three "resonant" modes (a mode of the subset with a strong
vibration added) where the margin binds.

For each mode: the Wiener bound (no robustness requirement), the margin-constrained bound
(:func:`aocontrol.analysis.constrained_bound`, FIR Youla parameter of ``n_taps`` taps, and
``n_taps / 2`` to show convergence), and the residual of the data-driven controller, of the
optimal modal-gain integrator (the margin imposed) and of the LQG (fitted model; no margin
promised), and of one integrator gain for every mode (the best total over the turbulence
modes among gains meeting the margin), each as a ratio to both bounds. Goal: data-driven /
constrained bound median <= 1.05.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from aocontrol import loop_plant
from aocontrol.analysis import (
    constrained_bound,
    margins,
    residual_variance,
    white_noise_psd,
    wiener_bound,
)
from aocontrol.controllers import Integrator
from aocontrol.disturbance import synthetic_turbulence_psd, vibration_psd
from aocontrol.synthesis import datadriven, integrator_gain_limit, lqg, optimal_modal_gain

FS = 3000.0
LATENCY = 0.83
ORDER = 5
NOISE_VAR = 4.0  # per-frame noise variance [nm^2], as bench_synthesis
MARGIN = 0.5
# Resonant extras: (mode of the subset, vibration frequency [Hz], variance [nm^2], damping).
VIBRATIONS = [(1, 300.0, 2000.0, 0.01), (4, 150.0, 300.0, 0.02), (-1, 500.0, 200.0, 0.01)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="8 modes, shorter FIR")
    parser.add_argument("--n-taps", type=int, default=None, help="FIR length (default 256)")
    args = parser.parse_args()
    n_taps = args.n_taps or (128 if args.quick else 256)
    n_even = 6 if args.quick else 12

    plant = loop_plant(FS, LATENCY)
    freqs = np.concatenate([[0.0], np.geomspace(1e-3, FS / 2, 2048)])
    all_psd = synthetic_turbulence_psd(freqs, 540, fs=FS)
    even = np.linspace(0, 539, n_even).round().astype(int)
    modes = np.unique(np.concatenate([[0, 1, 5, 14, 35], even]))
    is_even = np.isin(modes, even)
    psd = all_psd[modes]
    labels = [f"{m}" for m in modes]
    extra = [(i % modes.size, f0, v, z) for i, f0, v, z in VIBRATIONS]
    if extra:
        psd = np.vstack(
            [psd] + [psd[i] + vibration_psd(freqs, f0, v, z, fs=FS) for i, f0, v, z in extra]
        )
        labels += [f"{modes[i]}+vib{f0:g}Hz" for i, f0, v, z in extra]
    noise = float(white_noise_psd(NOISE_VAR, FS))
    print(
        f"modes {modes.tolist()} of the synthesis benchmark (+{len(extra)} resonant), "
        f"fs = {FS:g} Hz, latency {LATENCY}, noise {NOISE_VAR:g} nm^2/frame, margin {MARGIN}"
    )

    t0 = time.perf_counter()
    wiener = wiener_bound(plant, freqs, psd, noise)
    t_w = time.perf_counter() - t0
    t0 = time.perf_counter()
    cb = constrained_bound(plant, freqs, psd, noise, MARGIN, n_taps=n_taps)
    t_cb = time.perf_counter() - t0
    cb_half = constrained_bound(plant, freqs, psd, noise, MARGIN, n_taps=n_taps // 2)
    t0 = time.perf_counter()
    dd = datadriven(
        plant, freqs, psd, order=ORDER, noise_psd=noise, modulus_margin=MARGIN, progress=False
    )
    t_dd = time.perf_counter() - t0
    # One gain for every mode, the best among gains meeting the margin (hand tuning).
    gains = np.linspace(0.05, 1.0, 20) * integrator_gain_limit(plant, modulus_margin=MARGIN)
    v_gain = [
        residual_variance(plant, Integrator(g, fs=FS, n_modes=psd.shape[0]), freqs, psd, noise)
        for g in gains
    ]
    # (Total over the turbulence modes: a resonant mode's total would pick a tiny gain.)
    i_best = int(np.argmin([v[: modes.size].sum() for v in v_gain]))
    v_int, g_int = v_gain[i_best], gains[i_best]
    omg = optimal_modal_gain(plant, freqs, psd, noise, modulus_margin=MARGIN)
    v_omg = residual_variance(plant, omg, freqs, psd, noise)
    mm_lqg = np.full(psd.shape[0], np.nan)
    try:
        bank = lqg(plant, freqs, psd, noise_psd=noise)
        v_lqg = residual_variance(plant, bank, freqs, psd, noise)
        mm_lqg = np.array([margins(plant, bank, mode=k).modulus_margin for k in range(len(v_lqg))])
    except ValueError as exc:  # report, do not hide
        print(f"LQG design failed: {exc}")
        v_lqg = np.full(psd.shape[0], np.nan)
    v_dd = dd.residual_variance

    print(
        f"\ntimes [s] (2-core shared machine): wiener {t_w:.1f}, constrained_bound "
        f"({n_taps} taps) {t_cb:.1f} ({cb.solves.sum()} SOCP solves), datadriven {t_dd:.1f}"
    )
    print("\nper mode: ratios to the constrained bound (C) and to the Wiener bound (W)")
    print("  mode            C/W     C(n/2)/C  verified  dd/C   dd/W   omgi/C omgi/W  lqg/C  lqg/W")
    for k, lab in enumerate(labels):
        c = cb.variance[k]
        print(
            f"  {lab:<14s} {c / wiener[k]:6.3f}  {cb_half.variance[k] / c:8.4f}  "
            f"{cb.verified_margin[k]:7.3f}  {v_dd[k] / c:6.3f} {v_dd[k] / wiener[k]:6.3f} "
            f"{v_omg[k] / c:6.3f} {v_omg[k] / wiener[k]:6.3f} {v_lqg[k] / c:6.3f} "
            f"{v_lqg[k] / wiener[k]:6.3f}  {mm_lqg[k]:6.3f}"
        )

    def summary(name: str, v: np.ndarray, rows: slice) -> None:
        rc, rw = v[rows] / cb.variance[rows], v[rows] / wiener[rows]
        print(
            f"  {name:<18s} median {np.median(rc):6.3f}  worst {np.max(rc):6.3f}   |   "
            f"median {np.median(rw):6.3f}  worst {np.max(rw):6.3f}"
        )

    n_turb = modes.size
    even_rows = np.flatnonzero(is_even)
    for title, rows in (
        (f"evenly spaced modes {modes[even_rows].tolist()}", even_rows),
        ("turbulence modes (low orders included)", slice(0, n_turb)),
        ("all modes (resonant included)", slice(None)),
    ):
        print(f"\nsummary, {title}:   / constrained bound      |   / Wiener bound")
        summary("data-driven", v_dd, rows)
        summary(f"integrator g={g_int:.2f}", v_int, rows)
        summary("optimal modal gain", v_omg, rows)
        summary("LQG (no margin)", v_lqg, rows)
    print(
        f"  (goal: data-driven / constrained bound median <= 1.05; modes below the "
        f"constrained bound: {int(np.sum(v_dd < cb.variance * (1 - 1e-3)))}, verified margin "
        f"of the bound's controllers min {np.nanmin(cb.verified_margin):.4f})"
    )
    print(
        f"  FIR convergence: bound({n_taps // 2} taps) / bound({n_taps} taps) max "
        f"{np.max(cb_half.variance / cb.variance):.4f}"
    )


if __name__ == "__main__":
    main()
