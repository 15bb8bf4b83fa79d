"""Benchmark of the LQG baseline (optimality and real-time cost). A script, not a test.

    python benchmarks/bench_lqg.py [--quick] [--n-modes 540]

(a) Optimality with the true model: LQG residual / Wiener bound for AR(2) turbulence (double
    pole, corner 8 Hz at fs = 1 kHz) with 0, 1 or 2 AR(2) vibrations, without and with white
    measurement noise, at latencies 0, 0.3, 0.83, 1, 1.83 and 2 frames beyond the WFS frame
    (total loop delays 1 to 3 frames, fractional ones included). Goal <= 1.02.
(b) Model fitted from 10 s of closed-loop telemetry (integrator, gain 0.3, plant difference
    equation, disturbance and noise from a seeded Generator): telemetry -> pseudo open loop ->
    Welch PSD -> AR model -> LQG, scored with the true PSDs. Goal <= 1.10.
(c) A spectrum that is not AR(2): the von Karman-like modal PSDs of
    :func:`aocontrol.disturbance.synthetic_turbulence_psd` (3 kHz, latency 0.83), model fitted
    from the PSD: the cost of the AR(2) model's mismatch, for information.
(d) Real-time cost per frame for ``n_modes`` modes at 3 kHz: integrator, order-5 IIR bank
    (random stable coefficients), LQG (two resonances per mode, latency 0.83: 8 states per
    mode) on its structured path and on the dense batched product. Best of several repeats;
    ratios to the integrator measured in the same run (goal <= 50 us each).

Timings are wall-clock on a shared machine: compare the ratios measured in one run.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from aocontrol.analysis import margins, residual_variance, wiener_bound
from aocontrol.controllers import IIRBank, Integrator, LQGBank
from aocontrol.disturbance import synthetic_turbulence_psd
from aocontrol.plant import loop_plant, split_latency
from aocontrol.synthesis import DisturbanceModel, lqg, lqg_from_telemetry, lqg_state_space

FS = 1000.0
POLE = 0.95  # turbulence double pole: corner 2 pi f_c / fs = -ln(0.95) -> 8.2 Hz at 1 kHz
NOISE_VAR = 1e-2  # per-frame noise variance (turbulence variance 1)
LATENCIES = (0.0, 0.3, 0.83, 1.0, 1.83, 2.0)


def model(n_vib: int, n_modes: int = 1, fs: float = FS) -> DisturbanceModel:
    """AR(2) turbulence (variance 1) plus the first ``n_vib`` of two resonances."""
    f0 = np.array([60.0, 170.0])[:n_vib]
    xi = np.array([0.02, 0.005])[:n_vib]
    var = np.array([0.5, 0.1])[:n_vib]
    rep = lambda x: np.tile(x, (n_modes, 1))  # noqa: E731
    return DisturbanceModel(
        rep([2 * POLE, -(POLE**2)]), np.ones(n_modes), rep(f0), rep(xi), rep(var), fs=fs
    )


def closed_loop_telemetry(d, latency, noise_var, n_frames, rng):
    """Telemetry (m, u) of an integrator loop (plant difference equation in numpy)."""
    k0, f = split_latency(latency)
    dist = d.simulate(n_frames + 1, rng)
    noise = rng.normal(scale=np.sqrt(noise_var), size=(n_frames, d.n_modes))
    ctrl = Integrator(0.3, fs=d.fs, n_modes=d.n_modes)
    u = np.zeros((n_frames + k0 + 2, d.n_modes))
    m = np.zeros((n_frames, d.n_modes))
    y_prev = np.zeros(d.n_modes)
    for k in range(n_frames):
        m[k] = dist[k] - y_prev + noise[k]
        u[k + k0 + 2] = ctrl.step(m[k])
        y_prev = (1 - f) * u[k + 2] + f * u[k + 1]
    return m, u[k0 + 2 :]


def part_a(freqs: np.ndarray, quick: bool) -> None:
    print("(a) LQG with the true model: residual / Wiener bound (goal <= 1.02)")
    lats = (0.0, 0.83, 2.0) if quick else LATENCIES
    print(f"{'vibrations':>10} {'noise var':>9} " + " ".join(f"lat={x:<5}" for x in lats))
    worst = 0.0
    mm = []
    for n_vib in (0, 1, 2):
        d = model(n_vib)
        psd = d.psd(freqs)
        for nv in (0.0, NOISE_VAR):
            npsd = 2 * nv / FS
            row = []
            for lat in lats:
                G = loop_plant(FS, lat)
                bank = lqg(G, freqs, psd, noise_psd=npsd, model=d)
                r = residual_variance(G, bank, freqs, psd, npsd)[0] / wiener_bound(
                    G, freqs, psd, npsd
                )
                r = float(np.squeeze(r))
                row.append(r)
                worst = max(worst, r)
                mm.append(margins(G, bank).modulus_margin)
            print(f"{n_vib:>10} {nv:>9.0e} " + " ".join(f"{x:9.5f}" for x in row))
    print(f"    worst ratio {worst:.5f}")
    print(
        f"    LQG promises no margin: modulus margins {min(mm):.3f} .. {max(mm):.3f} "
        "(the data-driven design enforces 0.5)"
    )


def part_b(freqs: np.ndarray, quick: bool) -> None:
    print(
        "(b) LQG fitted from 10 s of closed-loop telemetry: residual / Wiener bound (goal <= 1.10)"
    )
    seeds = (1,) if quick else (1, 2, 3)
    cases = [(1, 0.83), (2, 1.0)] if quick else [(0, 0.83), (1, 0.83), (1, 2.0), (2, 1.0)]
    n_modes = 2
    worst = 0.0
    for n_vib, lat in cases:
        d = model(n_vib, n_modes)
        psd = d.psd(freqs)
        npsd = 2 * NOISE_VAR / FS
        G = loop_plant(FS, lat)
        bound = wiener_bound(G, freqs, psd, npsd)
        ratios = []
        for seed in seeds:
            m, u = closed_loop_telemetry(d, lat, NOISE_VAR, 10_000, np.random.default_rng(seed))
            bank = lqg_from_telemetry(m, u, G, n_vibrations=max(n_vib, 1))
            ratios.append(residual_variance(G, bank, freqs, psd, npsd) / bound)
        ratios = np.concatenate(ratios)
        worst = max(worst, float(ratios.max()))
        print(
            f"    vibrations {n_vib}, latency {lat}: median {np.median(ratios):.4f}, "
            f"worst {ratios.max():.4f} ({ratios.size} mode fits)"
        )
    print(f"    worst ratio {worst:.4f}")


def part_c(quick: bool) -> None:
    fs, lat = 3000.0, 0.83
    n_modes = 20 if quick else 100
    freqs = np.geomspace(1e-3, fs / 2, 8000)
    psd = synthetic_turbulence_psd(freqs, n_modes, fs=fs)
    npsd = 2 * 4.0 / fs  # 4 nm^2 per frame
    G = loop_plant(fs, lat)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bound = wiener_bound(G, freqs, psd, npsd)
    t0 = time.perf_counter()
    bank = lqg(G, freqs, psd, noise_psd=npsd, n_vibrations=1)
    design = time.perf_counter() - t0
    r = residual_variance(G, bank, freqs, psd, npsd) / bound
    print(
        f"(c) non-AR turbulence PSDs ({n_modes} modes, 3 kHz, latency {lat}), AR(2) + 1 "
        f"resonance fitted from the PSD ({freqs.size} points): residual / Wiener median "
        f"{np.median(r):.3f}, worst {r.max():.3f} (mode {int(np.argmax(r))}); fit + design "
        f"{design / n_modes * 1e3:.0f} ms per mode (one process, 2-core shared machine)"
    )


def time_per_frame(ctrl, n_modes: int, n_frames: int, repeats: int) -> tuple[float, float]:
    """Best (wall, CPU) time per ``step()`` [us] over ``repeats`` runs of ``n_frames``."""
    rng = np.random.default_rng(0)
    m = rng.normal(size=(n_frames, n_modes))
    wall = cpu = np.inf
    for _ in range(repeats):
        ctrl.reset()
        t0, c0 = time.perf_counter(), time.process_time()
        for k in range(n_frames):
            ctrl.step(m[k])
        wall = min(wall, (time.perf_counter() - t0) / n_frames)
        cpu = min(cpu, (time.process_time() - c0) / n_frames)
    return wall * 1e6, cpu * 1e6


def part_d(n_modes: int, quick: bool) -> None:
    fs = 3000.0
    n_frames, repeats = (1000, 3) if quick else (3000, 5)
    rng = np.random.default_rng(0)
    poles = rng.uniform(-0.9, 0.9, size=(n_modes, 5))
    a = np.array([np.poly(p) for p in poles])
    b = rng.normal(size=(n_modes, 6))
    t0 = time.perf_counter()
    ss = lqg_state_space(model(2, n_modes, fs=fs), 0.83, NOISE_VAR)
    design = time.perf_counter() - t0
    ctrls = {
        "integrator": Integrator(0.4, fs=fs, n_modes=n_modes),
        "IIR order 5": IIRBank(b, a, fs=fs),
        "LQG (structured)": LQGBank(ss),
        "LQG (dense matmul)": LQGBank(ss, dense=True),
    }
    # Interleave the repeats of the controllers so that machine load hits all alike.
    wall = {k: np.inf for k in ctrls}
    cpu = {k: np.inf for k in ctrls}
    for _ in range(3):
        for name, c in ctrls.items():
            w, p = time_per_frame(c, n_modes, n_frames, repeats)
            wall[name], cpu[name] = min(wall[name], w), min(cpu[name], p)
    print(
        f"(d) real-time cost of step(), {n_modes} modes at 3 kHz (budget 333 us), best of "
        f"{3 * repeats} x {n_frames} frames; 2-core shared machine (wall and process CPU time)"
    )
    for name in ctrls:
        print(
            f"    {name:<20} wall {wall[name]:7.1f} us  cpu {cpu[name]:7.1f} us   ratio to "
            f"integrator: wall {wall[name] / wall['integrator']:5.2f}  "
            f"cpu {cpu[name] / cpu['integrator']:5.2f}"
        )
    print(
        f"    LQG design of {n_modes} modes (2 DAREs + 1 Stein equation per mode): {design:.2f} s"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--n-modes", type=int, default=540)
    args = parser.parse_args()
    freqs = np.geomspace(1e-3, FS / 2, 12_000)
    part_a(freqs, args.quick)
    part_b(freqs, args.quick)
    part_c(args.quick)
    part_d(args.n_modes, args.quick)


if __name__ == "__main__":
    main()
