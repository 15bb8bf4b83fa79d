"""Benchmark of the data-driven synthesis (speed, quality, convergence). A script, not a test.

    python benchmarks/bench_synthesis.py [--n-modes 540] [--quick] [--n-jobs N]
        [--old-checkout PATH]

Case: ``n_modes`` turbulence-like modal PSDs
(:func:`aocontrol.disturbance.synthetic_turbulence_psd`,
D = 8 m, V = 10 m/s, r0 = 0.15 m) plus white measurement noise, order-5 controllers,
fs = 3000 Hz, latency 0.83 frame (SAXO+ stage 2).

(a) Speed: wall time for the whole bank (all cores), and the per-mode time of a straightforward
    implementation (cvxpy problem rebuilt from numpy constants at every iteration, same cones,
    no extrapolation, no dense-check refinement) against ours, both serial on a subset of modes
    in the same run; the straightforward total is extrapolated from that subset. Serial CPU
    per mode (process time, one worker) on 32 neighbouring modes (the bank's warm-start
    chain) and on 24 modes spread over the bank; with ``--old-checkout PATH`` (or
    ``AOCONTROL_OLD_CHECKOUT``) the same designs by the aocontrol of that checkout (e.g. a
    worktree of an older commit) in a subprocess, and the CPU ratio new / old.
(b) Quality: residual variance / Wiener bound of the data-driven controllers, of the optimal
    modal-gain integrators and of one hand-tuned gain for all modes (minimising the total).
(c) Convergence: final objective vs a tightly converged reference (many iterations, tight
    tolerance) on a few modes.
(e) Certificates: modes whose design the certificates changed (cutting planes at certified
    minima of |1 + G K|, |S| peaks added, damped steps) and the free-pole radius: the bank with
    ``max_pole_radius=None`` (poles unconstrained) beside the default, residual ratio.
(f) Resonant spectra (turbulence plus 1 to 3 sharp vibrations): data-driven with
    ``order="auto"`` and order 5 against :func:`aocontrol.analysis.constrained_bound`, with the
    reduced-bound start (``bound_start``: None, the default, on modes with a line in the
    disturbance PSD, under the noise too, or in disturbance plus noise; True on every mode)
    and without it (False, the design before the start existed), in the
    same run; wall time and the CPU of this process (``n_jobs=1``).
    Without the bound start the convex-concave iterations stop in a local optimum (1.24
    median, 1.56 worst at order 5): a 300-point design grid, no design-grid margin safety, or
    ``max_pole_radius=None`` left that unchanged; a mode designed alone ends better than in the
    bank (1.20 vs 1.56: there the previous mode's design is the start, another basin). The
    bound's FIR-Youla controllers (degree 257) have 8 to 14 poles outside the unit circle; the
    reduced start (the bound's sensitivity fitted at the design's order, its free poles
    reflected inside the radius, see ``aocontrol/synthesis/_dd_starts.py``) is stable and
    certified. The iterations barely move from it: the first convex step raises the true
    objective (the start's poles crowd near z = 1, where the coefficient parametrisation is
    ill-conditioned), so the result is the start.
    Measured (one run, n_jobs=1, one BLAS thread, loaded machine): order 5 median 1.244 /
    worst 1.563 without, 1.045 / 1.058 on every mode; auto 1.149 / 1.302 without, 1.045 /
    1.058 on every mode. CPU: order 5 6.5 s -> 36 s (the bound: about 5 s per mode);
    auto 41 s -> 48 s. The default selects every mode here (6 of 6: auto 1.045 / 1.058,
    58.5 s CPU at load 18-20); the former default, lines in disturbance plus noise only,
    selected 5 (1.056 / 1.072: the sixth's only line is 100x below the noise; the bound
    start takes it from 1.07 to 1.03, with or without the line: the gain is the start's).
    Seeds 2 and 3 of this generator, auto: 1.035 / 1.058 and 1.034 / 1.038 with the bound
    start on every mode (the default: 6 of 6 each), 1.12 / 1.34 and 1.09 / 1.38 without;
    the former default selected 4 and 2 of 6. Fits that keep unstable controller poles
    reach 1.007-1.017 (order 5 to 16): the rest of the gap is the price of stable poles in
    this reduction.
(d) Estimated PSDs (what a design from telemetry sees): each PSD as a Welch estimate of
    disturbance + noise with ``WELCH_SEGMENTS`` averaged segments (chi-square scatter with
    ``2 WELCH_SEGMENTS`` degrees of freedom) on a 513-bin Welch grid, minus the noise level,
    clipped to a floor -- the estimate :func:`aocontrol.synthesis.disturbance_from_telemetry`
    (pre-whitened by default) forms. Design-grid size and serial time per mode against the
    exact PSDs on the same grid and modes, in the same run.

Timings are wall-clock on a shared machine: compare the ratios measured in one run.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import cvxpy as cp
import numpy as np

from aocontrol import loop_plant
from aocontrol.analysis import residual_psd, white_noise_psd
from aocontrol.analysis._wiener import wiener_bound
from aocontrol.controllers import Integrator
from aocontrol.disturbance import synthetic_turbulence_psd
from aocontrol.synthesis import _ccp, _socp
from aocontrol.synthesis import _datadriven as dd
from aocontrol.synthesis._dd_certify import _ModeCertifier, _p_of
from aocontrol.synthesis._dd_grids import _interp_matrix
from aocontrol.synthesis._dd_mode import _design_chunk
from aocontrol.synthesis._modal_gain import integrator_gain_limit, optimal_modal_gain

FS = 3000.0
LATENCY = 0.83
ORDER = 5
NOISE_VAR = 4.0  # per-frame noise variance [nm^2] on every mode
WELCH_SEGMENTS = 12  # averaged segments of the simulated Welch estimates in (d)


def naive_mode(setup: dd._Setup, item: tuple) -> tuple[float, int, bool]:
    """Straightforward CCP: a new cvxpy problem from numpy constants at every iteration.

    Same design grid, cones, winding constraints, scaling and stopping rule as datadriven;
    no Parameters, no extrapolation, no dense-grid refinement. Returns (objective, solves,
    verified: stable and modulus margin met on the dense grid).
    """
    psd_row, noise_row, b0, a0, fixed = item.psd, item.noise, item.b0, item.a0, item.fixed_factor
    ctx = setup.ctx.with_structure(fixed, setup.ctx.free_order + setup.ctx.fixed_factor.size - 1)
    H = _interp_matrix(ctx.h2_freqs, ctx.input_freqs)
    pos = np.searchsorted(ctx.design_freqs, ctx.h2_freqs)
    q1 = np.zeros(ctx.design_freqs.size)
    qn = np.zeros(ctx.design_freqs.size)
    q1[pos] = (psd_row * ctx.input_weights) @ H.T
    qn[pos] = (noise_row * ctx.input_weights) @ H.T
    mu_d = ctx.design_margin
    grid = ctx.grid_data(ctx.design_freqs, ctx.design_response, mu_d)
    wind = ctx.grid_data(ctx.dense_freqs, ctx.dense_response, ctx.modulus_margin).take(
        ctx.winding_index
    )
    total = q1 + qn
    _, P0 = _p_of(ctx, ctx.design_freqs, ctx.design_response, b0, a0)
    Y0 = P0 - ctx.design_response * np.polyval(
        b0[::-1], np.exp(-2j * np.pi * ctx.design_freqs / FS)
    )
    v_ref = float(np.sum((q1 * np.abs(Y0) ** 2 + qn * np.abs(P0 - Y0) ** 2) / np.abs(P0) ** 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        r1 = np.where(total > 0, np.sqrt(q1 / total), 0.0)
        rn = np.where(total > 0, np.sqrt(qn / total), 0.0)
    h = total / v_ref
    vc = ctx.to_v(b0, a0)
    J, Pc = _socp.true_objective(grid, vc, r1, rn, h)
    history = [J]
    solves = 0
    for _ in range(ctx.max_iter):
        Pw = wind.A @ vc + wind.F
        s = _socp._g_scale(grid, Pc, vc, r1, rn)
        v = cp.Variable(vc.size)
        u = cp.Variable(grid.F.size)
        M = 2.0 * (Pc.real[:, None] * grid.A.real + Pc.imag[:, None] * grid.A.imag)
        c = 2.0 * (grid.F.real * Pc.real + grid.F.imag * Pc.imag) - np.abs(Pc) ** 2
        phi = M @ v + c
        Y = grid.AY @ v + grid.F
        GX = grid.AX @ v
        g = cp.multiply(s, u)
        rows = [
            2 * cp.multiply(r1, cp.real(Y)),
            2 * cp.multiply(r1, cp.imag(Y)),
            2 * cp.multiply(rn, cp.real(GX)),
            2 * cp.multiply(rn, cp.imag(GX)),
            g - phi,
        ]
        cons = [
            cp.SOC(g + phi, cp.vstack(rows), axis=0),
            cp.SOC(
                1 + phi, cp.vstack([2 * mu_d * cp.real(Y), 2 * mu_d * cp.imag(Y), 1 - phi]), axis=0
            ),
        ]
        objective = (h * s) @ u
        if ctx.hinf_weight > 0:
            gamma = cp.Variable()
            sw = 2 * np.sqrt(ctx.hinf_weight)
            cons.append(
                cp.SOC(
                    gamma + phi,
                    cp.vstack([sw * cp.real(GX), sw * cp.imag(GX), gamma - phi]),
                    axis=0,
                )
            )
            objective = objective + gamma
        scale = 1.0 / np.abs(Pw)
        Wa = (Pw.real[:, None] * wind.A.real + Pw.imag[:, None] * wind.A.imag) * scale[:, None]
        floor = np.maximum(_socp._WIND_MIN * np.abs(Pw), np.minimum(_socp._P_FLOOR, np.abs(Pw)))
        Wb = (Pw.real * wind.F.real + Pw.imag * wind.F.imag) * scale - floor
        cons.append(Wa @ v + Wb >= 0)
        prob = cp.Problem(cp.Minimize(objective), cons)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                prob.solve(solver=cp.CLARABEL, **_socp._SOLVER_OPTS)
        except cp.error.SolverError:
            break
        solves += 1
        if v.value is None:
            break
        Jn, Pn = _socp.true_objective(grid, v.value, r1, rn, h)
        if not Jn <= J:
            break
        vc, J, Pc = np.array(v.value), Jn, Pn
        history.append(J)
        if len(history) > _ccp.PATIENCE:
            past = history[-1 - _ccp.PATIENCE]
            if past - J <= ctx.tol * past:
                break
    dense = ctx.grid_data(ctx.dense_freqs, ctx.dense_response, ctx.modulus_margin)
    cert = _ModeCertifier(ctx, psd_row, noise_row, v_ref, b0, a0, dense, mu_d)
    return J, solves, cert.check_final(vc) is not None


# Serial CPU measurement (a): the bank's block of this many neighbouring modes, in this process
# and, with --old-checkout PATH (or the AOCONTROL_OLD_CHECKOUT environment variable), with the
# aocontrol of another checkout (e.g. a git worktree of an older commit) in a subprocess.
CPU_BLOCK = 32
_CPU_SCRIPT = """
import json, sys, time
import numpy as np
from aocontrol import loop_plant
from aocontrol.synthesis import datadriven
d = np.load(sys.argv[1])
plant = loop_plant(float(d["fs"]), float(d["latency"]))
t0 = time.process_time()
r = datadriven(plant, d["freqs"], d["psd"], order=int(d["order"]), noise_psd=float(d["noise"]),
               n_jobs=1, progress=False)
cpu = time.process_time() - t0
import aocontrol
print(json.dumps({"cpu": cpu, "residual": np.asarray(r.residual_variance).tolist(),
                  "package": aocontrol.__file__,
                  "solves": np.asarray(r.solves).tolist()}))
"""


def serial_cpu(freqs, psd, noise, checkout: str | None = None) -> dict:
    """CPU time [s] of ``datadriven`` on ``psd`` (one process, ``n_jobs=1``), its residuals.

    With ``checkout`` the aocontrol found there runs the same design in a subprocess (same
    inputs through a temporary ``.npz``): a same-run comparison with another version.
    """
    import json
    import os
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "inputs.npz")
        np.savez(path, freqs=freqs, psd=psd, noise=noise, fs=FS, latency=LATENCY, order=ORDER)
        env = dict(os.environ)
        if checkout is not None:
            env["PYTHONPATH"] = os.path.abspath(checkout)
        else:
            import aocontrol

            env["PYTHONPATH"] = os.path.dirname(
                os.path.dirname(os.path.abspath(aocontrol.__file__))
            )
        out = subprocess.run(
            [sys.executable, "-c", _CPU_SCRIPT, path],
            env=env,
            cwd=tmp,  # not the caller's folder: its aocontrol would come first on sys.path
            capture_output=True,
            text=True,
            check=True,
        )
    return json.loads(out.stdout.strip().splitlines()[-1])


def _setup(plant, freqs, psd, noise, hinf_weight: float) -> dd._Setup:
    """The synthesis set-up of ``datadriven``'s defaults (order ORDER), for per-mode timing."""
    return dd._prepare(plant, freqs, psd, order=ORDER, noise_psd=noise, hinf_weight=hinf_weight)


def resonant_part(plant, noise: float, n_modes: int = 6) -> None:
    """(f): turbulence plus 1 to 3 sharp vibrations, data-driven vs constrained_bound."""
    from aocontrol.analysis import constrained_bound

    rng = np.random.default_rng(1)
    freqs = np.concatenate([[0.0], np.geomspace(1e-2, FS / 2, 1200)])
    base = synthetic_turbulence_psd(freqs, 60, fs=FS)[rng.choice(np.arange(5, 60), n_modes)]
    psd = base.copy()
    for i in range(n_modes):
        for _ in range(1 + i % 3):
            f0, zeta = rng.uniform(10.0, 200.0), rng.uniform(0.002, 0.05)
            peak = rng.uniform(3.0, 30.0) * np.max(base[i] * (freqs > f0 / 2))
            psd[i] += peak / (
                1 + ((freqs**2 - f0**2) / (2 * zeta * f0 * np.maximum(freqs, 1e-9))) ** 2
            )
    t0 = time.perf_counter()
    bound = constrained_bound(plant, freqs, psd, noise, 0.5, n_taps=256).variance
    t_bound = time.perf_counter() - t0
    print(f"\n(f) resonant spectra, {n_modes} modes: constrained_bound (256 taps) {t_bound:.1f} s")
    for order in (ORDER, "auto"):
        for bound_start in (False, None, True):
            t0, c0 = time.perf_counter(), time.process_time()
            r = dd.datadriven(
                plant,
                freqs,
                psd,
                order=order,
                noise_psd=noise,
                bound_start=bound_start,
                n_jobs=1,
                progress=False,
            )
            t, c = time.perf_counter() - t0, time.process_time() - c0
            ratio = r.residual_variance / bound
            starts = sum(rep.start == "bound reduction" for rep in r.reports)
            print(
                f"  order {order!s:>4}, bound_start={bound_start!s:5}: data-driven / bound "
                f"median {np.median(ratio):.3f}, worst {ratio.max():.3f} (goal with auto: "
                f"<= 1.05, <= 1.15); reduced-bound starts {starts}/{n_modes}; orders "
                f"{r.order.tolist()}; {t:.1f} s wall, {c:.1f} s CPU"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-modes", type=int, default=540)
    parser.add_argument("--quick", action="store_true", help="60 modes, small subsets")
    parser.add_argument("--n-jobs", type=int, default=None, help="worker processes (all)")
    parser.add_argument(
        "--old-checkout",
        default=os.environ.get("AOCONTROL_OLD_CHECKOUT"),
        help="another checkout (its aocontrol) for a same-run CPU comparison in (a)",
    )
    parser.add_argument("--resonant-only", action="store_true", help="part (f) only")
    args = parser.parse_args()
    if args.resonant_only:
        resonant_part(loop_plant(FS, LATENCY), float(white_noise_psd(NOISE_VAR, FS)))
        return
    n_modes = 60 if args.quick and args.n_modes == 540 else args.n_modes
    n_subset = 2 if args.quick else 4
    n_conv = 2 if args.quick else 4

    plant = loop_plant(FS, LATENCY)
    # Log-spaced at low frequency: low-order modes span decades below 1 Hz, which a linear
    # grid does not resolve (the Wiener bound would then be unreliable and warns).
    freqs = np.concatenate([[0.0], np.geomspace(1e-3, FS / 2, 2048)])
    psd = synthetic_turbulence_psd(freqs, n_modes, fs=FS)
    noise = float(white_noise_psd(NOISE_VAR, FS))
    print(
        f"{n_modes} modes, order {ORDER}, fs = {FS:g} Hz, latency {LATENCY} frame, "
        f"noise {NOISE_VAR:g} nm^2/frame; input grid {freqs.size} points"
    )

    # (a) Speed: the whole bank on all cores.
    t0 = time.perf_counter()
    res = dd.datadriven(
        plant, freqs, psd, order=ORDER, noise_psd=noise, n_jobs=args.n_jobs, progress=True
    )
    t_bank = time.perf_counter() - t0
    subset = np.unique(np.linspace(0, n_modes - 1, n_subset).round().astype(int))
    setup = _setup(plant, freqs, psd[subset], noise, 1e-3)
    t0 = time.perf_counter()
    ours = [_design_chunk(setup.ctx, [item])[0] for item in setup.items]
    t_ours = (time.perf_counter() - t0) / len(subset)
    t0 = time.perf_counter()
    naive = [naive_mode(setup, item) for item in setup.items]
    t_naive = (time.perf_counter() - t0) / len(subset)
    # Serial CPU per mode on a block of neighbouring modes (the bank's warm-start chain) and
    # on modes spread over the bank, here and (optionally) with an older checkout.
    blocks = {
        "contiguous": np.arange(n_modes // 3, min(n_modes // 3 + CPU_BLOCK, n_modes)),
        "spread": np.unique(np.linspace(0, n_modes - 1, min(24, n_modes)).round().astype(int)),
    }
    cpu = {}
    for name, idx in blocks.items():
        cpu[name] = [serial_cpu(freqs, psd[idx], noise)]
        if args.old_checkout:
            cpu[name].append(serial_cpu(freqs, psd[idx], noise, args.old_checkout))

    # (b) Quality against the Wiener bound.
    bound = wiener_bound(plant, freqs, psd, noise, fs=FS)
    omg = optimal_modal_gain(plant, freqs, psd, noise)
    v_omg = np.trapezoid(residual_psd(plant, omg, freqs, psd, noise), freqs, axis=-1)
    g_max = integrator_gain_limit(plant)
    gains = np.linspace(0.02, 0.98, 49) * g_max
    totals = [
        np.trapezoid(
            residual_psd(plant, Integrator(g, fs=FS, n_modes=n_modes), freqs, psd, noise),
            freqs,
            axis=-1,
        ).sum()
        for g in gains
    ]
    g_hand = gains[int(np.argmin(totals))]
    v_hand = np.trapezoid(
        residual_psd(plant, Integrator(g_hand, fs=FS, n_modes=n_modes), freqs, psd, noise),
        freqs,
        axis=-1,
    )

    # (d) Estimated PSDs on a Welch grid: grid size and serial cost per mode vs exact PSDs.
    f_w = np.linspace(0.0, FS / 2, 513)
    exact = synthetic_turbulence_psd(f_w, n_modes, fs=FS)
    rng = np.random.default_rng(0)
    scatter = rng.chisquare(2 * WELCH_SEGMENTS, exact.shape) / (2 * WELCH_SEGMENTS)
    estimated = np.maximum((exact + noise) * scatter - noise, 1e-6 * noise)
    est = {}
    for name, p_in in (("exact", exact), ("estimated", estimated)):
        st = _setup(plant, f_w, p_in[subset], noise, 0.0)
        t0 = time.perf_counter()
        for item in st.items:
            _design_chunk(st.ctx, [item])
        est[name] = (st.ctx.design_freqs.size, (time.perf_counter() - t0) / len(subset))

    # (c) Convergence against a tightly converged reference, each mode alone (same start: the
    # optimal-gain integrator), and the bank's value (which may come from a continuation start).
    conv = np.unique(np.linspace(0, n_modes - 1, n_conv + 2)[1:-1].round().astype(int))
    j_alone, j_ref, ref_solves = [], [], []
    for i in conv:
        alone = dd.datadriven(
            plant, freqs, psd[[i]], order=ORDER, noise_psd=noise, n_jobs=1, progress=False
        )
        ref = dd.datadriven(
            plant,
            freqs,
            psd[[i]],
            order=ORDER,
            noise_psd=noise,
            max_iter=400,
            tol=1e-9,
            n_jobs=1,
            progress=False,
        )
        j_alone.append(alone.reports[0].objective_history[-1])
        j_ref.append(ref.reports[0].objective_history[-1])
        ref_solves.append(ref.reports[0].solves)
    j_bank = np.array([res.reports[i].objective_history[-1] for i in conv])

    print("\n(a) speed                                   value")
    print(f"  bank wall time, {n_modes} modes [s]        {t_bank:8.1f}   (goal <= 30 s for 540)")
    print(f"  median convex solves per mode              {np.median(res.solves):8.0f}")
    for name, idx in blocks.items():
        b_idx = bound[idx]
        runs = cpu[name]
        ms = runs[0]["cpu"] / idx.size * 1e3
        line = (
            f"  serial CPU per mode, {name} ({idx.size} modes) [ms] {ms:6.0f}"
            f"   median x Wiener {np.median(np.array(runs[0]['residual']) / b_idx):.4f}"
        )
        if len(runs) > 1:
            line += (
                f"; old checkout {runs[1]['cpu'] / idx.size * 1e3:.0f} ms, median x Wiener "
                f"{np.median(np.array(runs[1]['residual']) / b_idx):.4f}; "
                f"CPU new / old {runs[0]['cpu'] / runs[1]['cpu']:.2f}"
            )
        print(line)
    print(f"  serial per mode, ours [s]                  {t_ours:8.2f}   (modes {subset.tolist()})")
    print(f"  serial per mode, straightforward [s]       {t_naive:8.2f}")
    print(f"  straightforward / ours (per mode)          {t_naive / t_ours:8.1f}x")
    print(
        f"  straightforward, extrapolated to {n_modes} modes serial [s] "
        f"{t_naive * n_modes:8.0f}  vs our bank {t_bank:.1f} s "
        f"({t_naive * n_modes / t_bank:.0f}x)"
    )
    print(
        "  objective on the design grid, ours / straightforward, per mode "
        + " ".join(f"{o['history'][-1] / n[0]:.3f}" for o, n in zip(ours, naive, strict=True))
    )
    print(
        "  (a lower straightforward value is not better: it exploits the gaps of the design "
        "grid, see the next line)"
    )
    print(
        f"  straightforward results verified (stable, margin on the dense grid): "
        f"{sum(n[2] for n in naive)}/{len(naive)}; ours: all (or the mode fails)"
    )

    print("\n(b) quality: residual variance / Wiener bound   median    p90   total")
    for name, v in [
        ("data-driven", res.residual_variance),
        ("optimal modal gain", v_omg),
        (f"hand-tuned gain {g_hand:.3f}", v_hand),
    ]:
        r = v / bound
        print(
            f"  {name:<28s} {np.median(r):8.3f} {np.percentile(r, 90):7.3f} "
            f"{v.sum() / bound.sum():7.3f}"
        )
    print(
        f"  (goal: data-driven median <= 1.15; {np.sum(res.residual_variance < bound)} "
        "modes below the bound)"
    )
    print(
        f"  certified modulus margin min {res.modulus_margin.min():.4f} (required 0.5); all "
        f"stable: {bool(res.stable.all())}; free poles max radius {res.pole_radius.max():.5f} "
        f"(max_pole_radius {dd.DEFAULT_POLE_RADIUS})"
    )
    print(f"  verification: {res.verification}")

    # (e) What the certificates and the pole radius changed.
    t0 = time.perf_counter()
    free = dd.datadriven(
        plant,
        freqs,
        psd,
        order=ORDER,
        noise_psd=noise,
        max_pole_radius=None,
        n_jobs=args.n_jobs,
        progress=False,
    )
    t_free = time.perf_counter() - t0
    refined = np.array([r.refinements > 0 for r in res.reports])
    print("\n(e) certificates and pole radius")
    print(
        f"  modes whose design grid took cutting planes or peaks: {refined.sum()} of {n_modes}; "
        f"designs kept at their start (worse): "
        f"{sum(r.start.startswith('initial (design rejected') for r in res.reports)}"
    )
    r_free = res.residual_variance / free.residual_variance
    print(
        f"  default / poles unconstrained (max_pole_radius=None), residual: median "
        f"{np.median(r_free):.4f}, max {r_free.max():.4f}; unconstrained free poles up to "
        f"{free.pole_radius.max():.5f} ({np.sum(free.pole_radius > 1.0)} modes with an "
        f"unstable controller); bank time default / unconstrained {t_bank / t_free:.2f}x"
    )

    # (f) Resonant spectra against the margin-constrained bound.
    resonant_part(plant, noise)

    print("\n(c) convergence: objective / tightly converged reference (400 solves max, tol 1e-9)")
    for i, a, b, r, n in zip(conv, j_alone, j_bank, j_ref, ref_solves, strict=True):
        print(
            f"  mode {i:4d}: alone {a / r - 1:+.2%}, in the bank {b / r - 1:+.2%}   "
            f"(reference {n} solves)"
        )
    print(
        "  (goal: within 1 %; 'in the bank' may start from the previous mode's design, a "
        "different local optimum)"
    )

    print(
        f"\n(d) estimated PSDs ({WELCH_SEGMENTS}-segment Welch scatter, noise subtracted, "
        "513-bin grid), serial, same modes"
    )
    for name, (n_pts, t) in est.items():
        print(f"  {name:<10s} design grid {n_pts:4d} points, {t:6.2f} s per mode")
    ratio = est["estimated"][1] / est["exact"][1]
    print(
        f"  estimated / exact time per mode {ratio:.2f}x "
        "(goal: about 1; the peaks add at most 2 n_grid points)"
    )


if __name__ == "__main__":
    main()
