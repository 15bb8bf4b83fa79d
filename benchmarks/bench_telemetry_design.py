"""Benchmark: telemetry in, controller out (issue 16). A script, not a test.

    python benchmarks/bench_telemetry_design.py aot [--seconds 5] [--controllers ...]
    python benchmarks/bench_telemetry_design.py estimators [--cases ...] [--full]
    python benchmarks/bench_telemetry_design.py own [--cases ...] [--schemes ...] [--full]

``aot``: the case ``bright1-best`` (stage 2: 400 modes at 3 kHz, latency 0.828 frame,
standalone cascade). A calibration exposure of ``--seconds`` with the case's reference
integrator is written as an AOT file (:func:`aocontrol.study.aot.write_run_aot`, both stages),
read back (:func:`aocontrol.io.read_aot`, loop ``stage 2``) and designed from
(:func:`aocontrol.synthesis.design_from_telemetry`, Wiener bound per mode); each design then
runs in the simulator on an independent exposure (another seed) and its measured stage-2
modal residual is compared with the prediction. Prints the time of each step and
predicted / measured per controller.

``estimators``: per case, one calibration run with the reference integrator; its telemetry
estimated with the plain and with the pre-whitened Welch PSD
(:func:`aocontrol.synthesis.disturbance_from_telemetry`, ``method``); each controller
designed from each estimate and run on the same independent exposure; predicted / measured
stage-2 residual per (case, controller, estimator). Quick scenes unless ``--full``.

``own``: the estimator alone, no design (issue 15): per case and scheme, one run of the
reference integrator; the residual it should have, predicted from its own telemetry with each
estimator (``residual_variance`` on the estimated disturbance and noise PSDs), over the one it
had. The pseudo-open loop of a linear stage is exactly ``z^-1 d + n``, so the ratio shows the
estimator's bias (and the Welch scatter), nothing of the calibration/exposure difference.
``--sensor diffractive`` (with ``--optical-gain``) adds four columns that split the gap of
the pyramid in the loop: the pseudo-open loop divided by the uncompensated optical gains,
and predictions from the true disturbance (rebuilt from the recorded residuals) with the
sensor's error beyond ``og e`` as white noise, then with its own (low-frequency) PSD; and
the comparison's prediction (:class:`aocontrol.study.compare.ResidualModel`): the
telemetry's pseudo-open loop with that error's PSD moved from the disturbance to a coloured
noise through ``T`` (:func:`aocontrol.synthesis.split_sensor_error`).

Timings are wall-clock on a shared machine (2 cores, other jobs running): read the ratios.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from aocontrol.analysis import residual_variance
from aocontrol.study.aot import write_run_aot
from aocontrol.study.compare import (
    CONTROLLERS,
    ControllerSpec,
    DesignInputs,
    ResidualModel,
    calibration_seconds,
    design_inputs,
    register_controller,
    run_configuration,
)
from aocontrol.study.scene import build_scene
from aocontrol.synthesis import design_from_telemetry

SCHEME = "standalone"


def _run_bank(case: str, bank, design: DesignInputs, seconds: float, seed: int, quick: bool):
    """Run a given bank on stage 2 through a throw-away registry entry (public API only)."""
    name = f"bench-fixed-{id(bank)}"
    register_controller(ControllerSpec(name, lambda inp: bank))
    try:
        out = run_configuration(
            case, controller=name, scheme=SCHEME, seconds=seconds, seed=seed, quick=quick,
            design=design,
        )  # fmt: skip
    finally:
        del CONTROLLERS[name]
    return out.summary["residual_rms_nm"]


def bench_aot(args: argparse.Namespace) -> None:
    case = "bright1-best"
    t0 = time.perf_counter()
    cal = run_configuration(
        case, controller="reference", scheme=SCHEME, seconds=args.seconds, seed=1000
    )
    t_cal = time.perf_counter() - t0
    folder = args.out or tempfile.mkdtemp(prefix="aocontrol-aot-")
    path = os.path.join(folder, "bright1-best-calibration.fits")
    t0 = time.perf_counter()
    write_run_aot(cal.result, path)
    t_write = time.perf_counter() - t0
    size = os.path.getsize(path) / 1e6
    from aocontrol.io import read_aot

    t0 = time.perf_counter()
    k = cal.result.stages[1].settle_frames
    tel = read_aot(path, "stage 2", skip_frames=k)
    t_read = time.perf_counter() - t0
    print(
        f"calibration: {case} {SCHEME}, {args.seconds:g} s, stage 2 {tel.n_frames} frames x "
        f"{tel.n_modes} modes at {tel.fs:g} Hz, latency {tel.latency_frames:.3f} frame"
    )
    print(
        f"  simulate {t_cal:.1f} s; write AOT {t_write:.1f} s ({size:.0f} MB, both stages); "
        f"read loop 'stage 2' {t_read:.1f} s"
    )
    print(
        f"{'controller':12}{'design[s]':>10}{'margins[s]':>11}{'Wiener[s]':>10}"
        f"{'pred[nm]':>10}{'meas[nm]':>10}{'pred/meas':>10}{'Wiener[nm]':>11}{'MM ok':>7}"
    )
    for name in args.controllers:
        opts = {"progress": False} if name == "datadriven" else None
        rep = design_from_telemetry(
            tel, name, reference_gain=cal.settings["reference_gain"], bounds=("wiener",),
            options=opts,
        )  # fmt: skip
        est = rep.estimate
        design = DesignInputs(
            rep.plant, est.freqs, est.psd, est.noise_psd, rep.fs, rep.n_modes,
            cal.settings["reference_gain"], est,
        )  # fmt: skip
        measured = _run_bank(case, rep.controller, design, args.exposure, 7, False)
        t = rep.timings
        print(
            f"{name:12}{t['design']:>10.1f}{t['margins']:>11.1f}{t['bounds']:>10.1f}"
            f"{rep.residual_rms:>10.2f}{measured:>10.2f}{rep.residual_rms / measured:>10.3f}"
            f"{rep.wiener_rms:>11.2f}{int(rep.meets_margin.sum()):>4}/{rep.n_modes}"
        )


def bench_estimators(args: argparse.Namespace) -> None:
    quick = not args.full
    print(
        f"{'case':14}{'controller':12}{'estimator':13}{'pred[nm]':>10}{'meas[nm]':>10}"
        f"{'pred/meas':>10}"
    )
    for case in args.cases:
        scene = build_scene(case, quick=quick)
        gain = scene.case.stage2.gain
        cal_s = calibration_seconds(scene, quick)
        for estimator in ("welch", "prewhitened"):
            design = design_inputs(
                scene, SCHEME, gain, seconds=cal_s, seed=1000, estimator=estimator
            )
            for name in args.controllers:
                bank = CONTROLLERS[name].design(design)
                pred = residual_variance(
                    design.plant, bank, design.freqs, design.psd, design.noise_psd
                )
                pred_rms = float(np.sqrt(np.sum(pred)))
                measured = _run_bank(case, bank, design, args.exposure, 7, quick)
                print(
                    f"{case:14}{name:12}{estimator:13}{pred_rms:>10.2f}{measured:>10.2f}"
                    f"{pred_rms / measured:>10.3f}"
                )


def _diffractive_diagnosis(m, u, e, st, gain, og):
    """Predicted / measured of a diffractive stage 2, three ways (issue 15, section 3).

    ``og``: the optical gains the measurements carry uncompensated (the calibrated ones for
    the setting "none", 1 for "calibrated", which assumes the true gains are the calibrated
    ones). Returns the ratios of: the pre-whitened estimate of ``m / og + G u`` with the
    loop's gain ``og g``; the true disturbance (``z^-1 d = z^-1 e + G u`` from the recorded
    residuals) with a white noise at the level of ``v = m - og z^-1 e``; the same with ``v``'s
    own PSD as the noise (what the sensor adds beyond ``og e``: aliasing of the residual
    outside the basis, nonlinearity, photon and read noise), which the loop injects through
    ``T``, not ``S``; the comparison's prediction, the telemetry with ``v``'s PSD apart
    (:class:`aocontrol.study.compare.ResidualModel`).
    """
    from scipy import signal

    from aocontrol.analysis import welch_psd
    from aocontrol.controllers import Integrator
    from aocontrol.plant import z_inverse_coefficients
    from aocontrol.synthesis import disturbance_from_telemetry

    n = st.n_modes
    seen = Integrator(gain * og, fs=st.fs, n_modes=n)
    meas = float(np.sqrt(e[1:].var(axis=0).sum()))
    b, a = z_inverse_coefficients(st.plant, "plant")
    d_del = e[:-1] + signal.lfilter(b, a, u, axis=0)[1:]
    v = m[1:] - og * e[:-1]
    tel = disturbance_from_telemetry(m, u, st.plant, fs=st.fs, optical_gain=og)
    pred_og = residual_variance(st.plant, seen, tel.freqs, tel.psd, tel.noise_psd).sum()
    true = disturbance_from_telemetry(d_del, np.zeros_like(d_del), st.plant, fs=st.fs)
    f, pv = welch_psd(v / og, st.fs, 512)
    white = np.median(pv[:, f > 0.8 * st.fs / 2], axis=1)
    colored = np.array([np.interp(true.freqs, f, row) for row in pv])
    # The true disturbance whole: no white floor removed (the tracked setting's dither is a
    # white disturbance; removing it as "noise" left bright1-best tracked at 0.83).
    p_true = true.psd + true.noise_psd[:, None]
    pred_white = residual_variance(st.plant, seen, true.freqs, p_true, white).sum()
    pred_v = residual_variance(st.plant, seen, true.freqs, p_true, colored).sum()
    model = ResidualModel.from_calibration(
        m, u, e, st.plant, st.fs, optical_gain=None if np.all(og == 1) else og
    )
    pred_model = model.predicted_rms(st.plant, Integrator(gain, fs=st.fs, n_modes=n)) ** 2
    return [float(np.sqrt(x)) / meas for x in (pred_og, pred_white, pred_v, pred_model)]


def bench_own(args: argparse.Namespace) -> None:
    from aocontrol.controllers import Integrator
    from aocontrol.synthesis import disturbance_from_telemetry

    quick = not args.full
    diffractive = args.sensor == "diffractive"
    extra = ("pw m/og", "true d+white", "true d+v", "v apart") if diffractive else ()
    print(f"stage-2 sensor {args.sensor}, optical gain {args.optical_gain or 'case default'}")
    print(f"{'case':14}{'scheme':12}{'frames':>8}{'meas[nm]':>10}" + "".join(
        f"{m + ' p/m':>18}" for m in ("welch", "prewhitened", *extra)
    ))  # fmt: skip
    for case in args.cases:
        scene = build_scene(case, quick=quick)
        st = scene.stage2
        cal_s = calibration_seconds(scene, quick)
        for scheme in args.schemes:
            out = run_configuration(
                case, controller="reference", scheme=scheme, seconds=cal_s, seed=1000,
                quick=quick, sensor=args.sensor, optical_gain=args.optical_gain,
            )  # fmt: skip
            r2 = out.result.stages[1] if scheme != "single" else out.result
            k = r2.settle_frames
            m = np.asarray(r2.telemetry["measurements"][k:], dtype=float)
            u = np.asarray(r2.telemetry["commands"][k:], dtype=float)
            gain = out.settings["reference_gain"]
            ref = Integrator(gain, fs=st.fs, n_modes=st.n_modes)
            meas = out.summary["residual_rms_nm"]
            cells = []
            for method in ("welch", "prewhitened"):
                tel = disturbance_from_telemetry(m, u, st.plant, fs=st.fs, method=method)
                pred = residual_variance(st.plant, ref, tel.freqs, tel.psd, tel.noise_psd)
                cells.append(f"{float(np.sqrt(np.sum(pred))) / meas:>18.3f}")
            if diffractive:
                e = np.asarray(r2.telemetry["residuals"][k:], dtype=float)
                raw = (args.optical_gain or scene.case.stage2.optical_gain) == "none"
                og = np.asarray(st.calibrated_gains) if raw else np.ones(st.n_modes)
                cells += [f"{r:>18.3f}" for r in _diffractive_diagnosis(m, u, e, st, gain, og)]
            print(f"{case:14}{scheme:12}{m.shape[0]:>8}{meas:>10.2f}" + "".join(cells))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="part", required=True)
    a = sub.add_parser("aot")
    a.add_argument("--seconds", type=float, default=5.0, help="calibration exposure [s]")
    a.add_argument("--exposure", type=float, default=2.0, help="scoring exposure [s]")
    a.add_argument("--controllers", nargs="+", default=["integrator", "omgi", "lqg", "datadriven"])
    a.add_argument("--out", default=None, help="folder of the AOT file (default: a temp dir)")
    e = sub.add_parser("estimators")
    e.add_argument("--cases", nargs="+", default=["bright1-best", "red1-fast", "red3-medium"])
    e.add_argument("--controllers", nargs="+", default=["omgi", "lqg", "datadriven"])
    e.add_argument("--exposure", type=float, default=1.0, help="scoring exposure [s]")
    e.add_argument("--full", action="store_true", help="full scenes instead of quick ones")
    o = sub.add_parser("own")
    o.add_argument(
        "--cases", nargs="+",
        default=["bright1-best", "bright1-worst", "red1-fast", "red3-medium", "red5-best"],
    )  # fmt: skip
    o.add_argument("--schemes", nargs="+", default=["standalone", "dcao"])
    o.add_argument("--full", action="store_true", help="full scenes instead of quick ones")
    o.add_argument("--sensor", choices=["linear", "diffractive"], default="linear")
    o.add_argument(
        "--optical-gain", default=None, choices=["none", "calibrated", "tracked", "two-pass"],
        help="stage 2's optical-gain setting (default the case's)",
    )  # fmt: skip
    args = p.parse_args()
    t0 = time.perf_counter()
    {"aot": bench_aot, "estimators": bench_estimators, "own": bench_own}[args.part](args)
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
