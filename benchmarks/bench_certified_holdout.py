"""Held-out check of the certified data-driven designs by an independent program. A script.

    python benchmarks/bench_certified_holdout.py [--n-modes 108] [--quick] [--seed 0]

Generates held-out modes (turbulence with slow or fast knees, 0 to 3 vibrations, white
noise; fs 1 and 3 kHz; latencies 0.83, 1.5 and 2 frames), designs them with
:func:`aocontrol.synthesis.datadriven` (order 5 and ``order="auto"``, default margin 0.5 and
pole radius) and checks every returned figure WITHOUT aocontrol's certificate, grids or
residual code: only ``scipy.signal.freqz`` and ``numpy.roots`` on the coefficients.

* True modulus margin: ``min |1 + G K|`` by brute force on 2,000,001 points of [0, fs/2],
  then refined (dense local grid and a bounded scalar minimisation) around the brute-force
  minimum and around every controller and closed-loop pole of modulus above 0.9, where a
  lightly damped pole can hide a dip narrower than the brute-force spacing.
* Free controller poles outside ``max_pole_radius`` (a pole at exactly z = 1 is the
  integrator's fixed factor, allowed), unstable closed loops.
* Residual on 20,000 linear points of [0, fs/2] with the exact PSD (the analytic formula, not
  the input grid), plus 2,001 points over +-20 widths of every vibration line (which 20,000
  linear points do not resolve at 3 kHz): designed vs starting controller, and reported /
  measured residual.

Prints counts (reported margin above the true one, true margin below the requested one,
poles outside the radius, unstable loops, worse than the start) and the reported / measured
residual ratio. Everything is seeded.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.signal import freqz
from scipy.special import gamma

from aocontrol import loop_plant
from aocontrol.synthesis import datadriven

MARGIN = 0.5
RADIUS = 0.9999  # datadriven's default max_pole_radius
N_BRUTE = 2_000_001
N_RESIDUAL = 20_000
N_LINE = 2001
NEAR_CIRCLE = 0.9  # poles above this modulus get a local refinement
REL_TOL = 1e-6  # a reported margin may exceed the true one by this (relative) only


@dataclass
class Mode:
    """One held-out mode: analytic disturbance PSD and white noise."""

    fc: float  # turbulence knee [Hz]
    c: float  # turbulence level [nm^2/Hz]
    lines: list  # (f0 [Hz], zeta, level [nm^2/Hz at the peak])
    noise: float  # white noise PSD [nm^2/Hz]

    def psd(self, f: np.ndarray) -> np.ndarray:
        out = self.c / (1 + (f / self.fc) ** 2) ** (11 / 6)
        for f0, zeta, level in self.lines:
            out = out + level * (2 * zeta) ** 2 / (
                (1 - (f / f0) ** 2) ** 2 + (2 * zeta * f / f0) ** 2
            )
        return out


def make_modes(rng: np.random.Generator, n: int, fs: float) -> list[Mode]:
    modes = []
    for i in range(n):
        fc = rng.uniform(0.3, 3.0) if i % 2 == 0 else rng.uniform(5.0, 30.0)
        rms = rng.uniform(5.0, 30.0)  # turbulence rms [nm]
        # int_0^inf (1 + (f/fc)^2)^(-11/6) df = fc * sqrt(pi) Gamma(4/3) / (2 Gamma(11/6))
        c = rms**2 / (fc * np.sqrt(np.pi) * gamma(4 / 3) / (2 * gamma(11 / 6)))
        lines = []
        for _ in range(int(rng.integers(0, 4))):
            f0, zeta = (
                rng.uniform(10.0, 0.1 * fs),
                10 ** rng.uniform(np.log10(0.002), np.log10(0.05)),
            )
            vib_rms = rng.uniform(1.0, 10.0)
            # variance of the line ~ level * pi * zeta * f0 (Lorentzian approximation)
            lines.append((f0, zeta, vib_rms**2 / (np.pi * zeta * f0)))
        sigma = rng.uniform(1.0, 8.0)  # noise rms per frame [nm]
        modes.append(Mode(fc, c, lines, 2 * sigma**2 / fs))
    return modes


def input_grid(fs: float, modes: list[Mode]) -> np.ndarray:
    """The user's grid: 0, 600 log points to 0.9999 fs/2, 41 points over +-10 widths per line."""
    parts = [[0.0], np.geomspace(0.01, 0.9999 * fs / 2, 600)]
    for m in modes:
        for f0, zeta, _ in m.lines:
            parts.append(f0 + 2 * zeta * f0 * np.linspace(-10, 10, 41))
    f = np.unique(np.concatenate(parts))
    return f[(f >= 0) & (f <= fs / 2)]


def plant_coefficients(plant) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of the plant in powers of z^-1 (for freqz)."""
    num, den = np.asarray(plant.num[0][0], float), np.asarray(plant.den[0][0], float)
    num = np.concatenate([np.zeros(den.size - num.size), num])
    return num / den[0], den / den[0]


def response(b, a, f, fs):
    return freqz(b, a, worN=f, fs=fs)[1]


def true_margin(bg, ag, bk, ak, fs) -> tuple[float, int]:
    """min |1 + G K| on [0, fs/2] (brute force plus local refinements), closed loop unstable."""
    # 1 + G K = (ag ak + bg bk) / (ag ak): the closed-loop characteristic polynomial on top
    # (coefficients in ascending powers of z^-1: pad at the end).
    p1, p2 = np.convolve(ag, ak), np.convolve(bg, bk)
    n = max(p1.size, p2.size)
    char = np.pad(p1, (0, n - p1.size)) + np.pad(p2, (0, n - p2.size))
    den = np.convolve(ag, ak)

    def mag(f):
        return np.abs(response(char, den, np.atleast_1d(f), fs))

    f = np.linspace(0.0, fs / 2, N_BRUTE)
    m = mag(f)
    k = int(np.argmin(m))
    best = float(m[k])
    step = f[1] - f[0]
    centres = [(f[k], step)]
    cl = np.roots(char)
    for p in np.concatenate([np.roots(ak), cl]):
        r = abs(p)
        if r > NEAR_CIRCLE:
            centres.append(
                (abs(np.angle(p)) * fs / (2 * np.pi), max(abs(1 - r), 1e-10) * fs / (2 * np.pi))
            )
    for fc, width in centres:
        lo, hi = max(0.0, fc - 50 * width), min(fs / 2, fc + 50 * width)
        loc = np.linspace(lo, hi, 4001)
        ml = mag(loc)
        j = int(np.argmin(ml))
        a_, b_ = loc[max(j - 1, 0)], loc[min(j + 1, loc.size - 1)]
        best = min(best, float(ml[j]))
        if b_ > a_:
            opt = minimize_scalar(
                lambda x: mag(x)[0],
                bounds=(a_, b_),
                method="bounded",
                options={"xatol": 1e-12 * fs},
            )
            best = min(best, float(opt.fun))
    return best, int(np.max(np.abs(cl)) >= 1.0) if cl.size else 0


def measured_residual(bg, ag, bk, ak, fs, mode: Mode) -> float:
    """int (|S|^2 psd + |T|^2 noise) df on 20,000 linear points plus points around each line."""
    parts = [np.linspace(0.0, fs / 2, N_RESIDUAL)]
    for f0, zeta, _ in mode.lines:
        parts.append(np.clip(f0 + 2 * zeta * f0 * np.linspace(-20, 20, N_LINE), 0.0, fs / 2))
    f = np.unique(np.concatenate(parts))
    # S = Ag Ak / (Ag Ak + Bg Bk) and T = Bg Bk / (...) from the polynomials: finite where
    # the controller has its integrator's pole (z = 1 at 0 Hz, where G K is infinite).
    d, n = np.convolve(ag, ak), np.convolve(bg, bk)
    size = max(d.size, n.size)
    c = np.pad(d, (0, size - d.size)) + np.pad(n, (0, size - n.size))
    s2 = np.abs(response(d, c, f, fs)) ** 2
    t2 = np.abs(response(n, c, f, fs)) ** 2
    return float(np.trapezoid(s2 * mode.psd(f) + t2 * mode.noise, f))


def free_poles_outside(ak: np.ndarray) -> int:
    p = np.roots(np.trim_zeros(ak, "b"))
    p = p[np.abs(p - 1.0) > 1e-9]  # the integrator's fixed pole is allowed
    return int(p.size and np.max(np.abs(p)) > RADIUS * (1 + 1e-12))


def _order(text: str) -> int | str:
    return text if text == "auto" else int(text)


def _summary(order, r: list) -> None:
    """Counts over the designs so far."""
    rep = np.array([x["reported_margin"] for x in r])
    tru = np.array([x["margin"] for x in r])
    ratio = np.array([x["ratio"] for x in r])
    gain = np.array([x["gain"] for x in r])
    print(f"  order {order}: {len(r)} designs so far")
    print(
        f"    reported margin > true (rel. {REL_TOL:g}): {int(np.sum(rep > tru * (1 + REL_TOL)))}"
        f"  (max reported/true {np.max(rep / tru):.8f})"
    )
    print(
        f"    true margin < requested {MARGIN}: {int(np.sum(tru < MARGIN * (1 - REL_TOL)))}"
        f"  (min true {tru.min():.6f})"
    )
    print(f"    free poles outside {RADIUS}: {sum(x['outside'] for x in r)}")
    print(f"    closed loop unstable: {sum(x['unstable'] for x in r)}")
    print(
        f"    worse than the start (measured): {sum(x['worse'] for x in r)}"
        f"  (design/start median {np.median(gain):.3f}, max {gain.max():.4f})"
    )
    print(
        f"    reported/measured residual: median {np.median(ratio):.4f}, "
        f"min {ratio.min():.4f}, max {ratio.max():.4f}"
    )
    if order == "auto":
        o, c = np.unique([x["order"] for x in r], return_counts=True)
        print(f"    orders chosen: {dict(zip(o.tolist(), c.tolist(), strict=True))}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--n-modes", type=int, default=108, help="held-out modes (>= 100 for the check)"
    )
    ap.add_argument(
        "--quick", action="store_true", help="smoke run: 6 modes (one per rate and latency)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-jobs", type=int, default=1)
    ap.add_argument("--out", help="also write the per-design rows to this JSON file")
    ap.add_argument("--orders", default="both", help="'both' (5 then auto), '5' or 'auto'")
    args = ap.parse_args()
    n_modes = 6 if args.quick else args.n_modes
    combos = [(fs, lat) for fs in (1000.0, 3000.0) for lat in (0.83, 1.5, 2.0)]
    per = np.full(len(combos), n_modes // len(combos))
    per[: n_modes % len(combos)] += 1
    rows = {5: [], "auto": []} if args.orders == "both" else {_order(args.orders): []}
    t_all = time.perf_counter()
    # Order 5 over every set first, then "auto" (slower): counts are printed after each set.
    for order in rows:
        for k, ((fs, lat), n) in enumerate(zip(combos, per, strict=True)):
            if n == 0:
                continue
            modes = make_modes(np.random.default_rng([args.seed, k]), int(n), fs)
            plant = loop_plant(fs, lat)
            bg, ag = plant_coefficients(plant)
            f = input_grid(fs, modes)
            psd = np.array([m.psd(f) for m in modes])
            noise = np.array([m.noise for m in modes])
            res = datadriven(
                plant,
                f,
                psd,
                order=order,
                noise_psd=noise,
                modulus_margin=MARGIN,
                n_jobs=args.n_jobs,
                progress=False,
            )
            for i, m in enumerate(modes):
                bk, ak = res.controller.b[i], res.controller.a[i]
                b0, a0 = res.initial.b[i], res.initial.a[i]
                margin, unstable = true_margin(bg, ag, bk, ak, fs)
                v = measured_residual(bg, ag, bk, ak, fs, m)
                v0 = measured_residual(bg, ag, b0, a0, fs, m)
                rows[order].append(
                    dict(
                        reported_margin=float(res.modulus_margin[i]),
                        margin=margin,
                        unstable=unstable,
                        outside=free_poles_outside(ak),
                        worse=bool(v > v0 * (1 + 1e-9)),
                        ratio=float(res.residual_variance[i] / v),
                        gain=v / v0,
                        order=int(res.order[i]),
                        fs=fs,
                        latency=lat,
                        n_lines=len(m.lines),
                    )
                )
            print(
                f"order {order}, fs {fs:.0f} Hz, latency {lat}: {n} modes done "
                f"({time.perf_counter() - t_all:.0f} s)",
                flush=True,
            )
            _summary(order, rows[order])
            if args.out:
                with open(args.out, "w") as fh:
                    json.dump({str(o): r for o, r in rows.items()}, fh)
    print(f"\ntotal {time.perf_counter() - t_all:.0f} s (machine shared with other jobs)")


if __name__ == "__main__":
    main()
