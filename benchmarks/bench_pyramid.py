"""Benchmark: diffractive pyramid closed loop, aocontrol vs OOPAO, side by side in one run.

Set-up (SAXO+ second stage, 40x40-class): VLT pupil (8 m, obstruction 0.14) sampled on
``n_pix = 80`` points, pyramid with 40 pixels across each pupil image, 2 pixels between images
(FFT 168 x 168), circular modulation 3 lambda/D with 40 points, slopes-maps, ~500 KL modes of a
28x28-actuator DM, push-pull interaction matrix, pseudo-inverse reconstructor, a plain
integrator (gain 0.4, one frame of delay), one frozen-flow layer (r0 = 0.15 m at 500 nm,
10 m/s), 3 kHz. The same geometry and the same number of modulation points on both sides.

Measured for each code, in separate processes (so peak memory is each code's own):
frames/s of the closed loop (atmosphere + DM + pyramid + reconstruction + integrator),
frames/s of the pyramid alone, calibration time (modal basis + interaction matrix) and peak
resident memory. Ratios are printed from this one run (the machine is shared: absolute times
are noisy, ratios less so). Rates are given from wall-clock time and from the process's CPU
time (``time.process_time``, which does not count time spent waiting for a core on a busy
machine). Both codes run with the same number of threads (``--threads``, also applied to BLAS
through ``OMP/OPENBLAS/MKL_NUM_THREADS``).

OOPAO (PyPI ``oopao``) is an optional benchmark dependency, never imported by aocontrol.
Install it in a separate virtualenv and point ``--oopao-python`` at its interpreter::

    python3 -m venv /work/oopao-venv && /work/oopao-venv/bin/pip install oopao
    .venv/bin/python benchmarks/bench_pyramid.py --oopao-python /work/oopao-venv/bin/python

Without ``--oopao-python`` the OOPAO half is skipped with a message. ``--quick`` runs a small
configuration (smoke test). OOPAO runs in double precision by default (its default);
``--oopao-precision 32`` selects its single-precision mode.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

RESULT_TAG = "BENCH_RESULT_JSON:"


def _time_per_call(fn, n_calls: int) -> tuple[float, float]:
    """Wall-clock and CPU seconds per call of ``fn()``, over ``n_calls`` calls."""
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(n_calls):
        fn()
    return (time.perf_counter() - t0) / n_calls, (time.process_time() - c0) / n_calls


def _peak_rss_mb() -> float:
    """Peak resident set size of this process [MB] (Linux ru_maxrss is in kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _config(args: argparse.Namespace) -> dict:
    if args.quick:
        return dict(
            n_pix=32, n_subap=16, n_act=12, n_modes=60, modulation=2.0, frames=30, n_points=None
        )
    return dict(
        n_pix=args.n_pix,
        n_subap=args.n_subap,
        n_act=args.n_actuators,
        n_modes=args.n_modes,
        modulation=args.modulation,
        frames=args.frames,
        n_points=None,
    )


# --------------------------------------------------------------------------------- ours
def run_ours(args: argparse.Namespace) -> dict:
    import numpy as np

    from aocontrol.sim.atmosphere import Atmosphere, Layer
    from aocontrol.sim.dm import DeformableMirror
    from aocontrol.sim.modes import kl_basis
    from aocontrol.sim.pupil import vlt_pupil
    from aocontrol.sim.wfs import PyramidWFS, interaction_matrix, reconstructor

    c = _config(args)
    fs, gain, wavelength = 3000.0, 0.4, 1.215e-6  # OOPAO's J band wavelength
    pupil = vlt_pupil(c["n_pix"])
    t0 = time.perf_counter()
    wfs = PyramidWFS(
        pupil,
        wavelength,
        n_subapertures=c["n_subap"],
        modulation=c["modulation"],
        workers=args.threads,
    )
    _ = wfs.reference_signals
    t_wfs = time.perf_counter() - t0
    t0 = time.perf_counter()
    dm = DeformableMirror(pupil, n_actuators=c["n_act"])
    basis = kl_basis(dm, c["n_modes"])
    t_modes = time.perf_counter() - t0
    t0 = time.perf_counter()
    imat = interaction_matrix(wfs, basis, amplitude=10.0)
    recon = reconstructor(imat)
    t_imat = time.perf_counter() - t0
    mem_cal = _peak_rss_mb()
    # information only: the exact-derivative interaction matrix (one propagation per mode)
    t0 = time.perf_counter()
    imat_lin = interaction_matrix(wfs, basis, method="derivative")
    t_imat_derivative = time.perf_counter() - t0
    imat_rel_diff = float(np.linalg.norm(imat_lin - imat) / np.linalg.norm(imat))

    atm = Atmosphere(pupil, r0=0.15, layers=[Layer(0.0, 1.0, 10.0, 0.0)], fs=fs, rng=1)
    modes = basis.modes
    coeffs = np.zeros(basis.n_modes)
    meas = np.zeros(basis.n_modes)
    res_rms = []
    n_frames, warm = c["frames"], args.warmup
    t_loop = c_loop = 0.0
    for k in range(n_frames + warm):
        t0, c0 = time.perf_counter(), time.process_time()
        turb = atm.phase_vectors(1)[0]
        res = turb - coeffs @ modes
        coeffs += gain * meas  # command from the previous frame's measurement
        s = wfs.signals(pupil.to_map(res))
        meas = recon @ s
        if k >= warm:
            t_loop += time.perf_counter() - t0
            c_loop += time.process_time() - c0
            res_rms.append(float(np.std(res)))
    opd = pupil.to_map(res)
    t_wfs_only, c_wfs_only = _time_per_call(lambda: wfs.signals(opd), n_frames)
    return dict(
        code="aocontrol",
        loop_fps=n_frames / t_loop,
        wfs_fps=1.0 / t_wfs_only,
        loop_fps_cpu=n_frames / c_loop,
        wfs_fps_cpu=1.0 / c_wfs_only,
        t_setup_wfs=t_wfs,
        t_modes=t_modes,
        t_imat=t_imat,
        t_imat_derivative=t_imat_derivative,
        imat_derivative_rel_diff=imat_rel_diff,
        t_calibration=t_modes + t_imat,
        peak_mb_calibration=mem_cal,
        peak_mb=_peak_rss_mb(),
        residual_nm=float(np.mean(res_rms[-10:])),
        turbulence_nm=float(np.std(turb)),
        n_modes=int(basis.n_modes),
        n_signals=int(wfs.n_signals),
        n_fft=wfs.n_fft,
        n_points=wfs.n_points,
        push_pull=True,
    )


# --------------------------------------------------------------------------------- OOPAO
def run_oopao(args: argparse.Namespace) -> dict:
    os.environ.setdefault("OOPAO_PRECISION", str(args.oopao_precision))
    os.environ.setdefault("OOPAO_BACKEND", "cpu")
    import numpy as np
    from OOPAO.Atmosphere import Atmosphere
    from OOPAO.calibration.compute_KL_modal_basis import compute_KL_basis
    from OOPAO.calibration.InteractionMatrix import InteractionMatrix
    from OOPAO.DeformableMirror import DeformableMirror
    from OOPAO.Pyramid import Pyramid
    from OOPAO.Source import Source
    from OOPAO.Telescope import Telescope

    # Same threads as aocontrol: OOPAO's single-block CPU path calls scipy.fft with workers=-1
    # (all cores); pin it to --threads (its joblib blocks are set through wfs.nJobs below).
    _oopao_pyramid = sys.modules["OOPAO.Pyramid"]
    _oopao_pyramid._fft_kwargs = lambda workers: {"workers": args.threads}

    c = _config(args)
    fs, gain = 3000.0, 0.4
    tel = Telescope(
        resolution=c["n_pix"], diameter=8.0, samplingTime=1 / fs, centralObstruction=0.14
    )
    ngs = Source(optBand="J", magnitude=8, display_properties=False)
    ngs * tel
    atm = Atmosphere(
        telescope=tel,
        r0=0.15,
        L0=25,
        windSpeed=[10],
        fractionalR0=[1],
        windDirection=[0],
        altitude=[0],
    )
    atm.initializeAtmosphere(tel)
    tel.resetOPD()
    n_points = 4 * int(np.ceil(np.pi * c["modulation"]))  # same as aocontrol's default
    t0 = time.perf_counter()
    wfs = Pyramid(
        nSubap=c["n_subap"],
        telescope=tel,
        modulation=c["modulation"],
        lightRatio=0.5,
        n_pix_separation=2,
        postProcessing="slopesMaps",
        nTheta_user_defined=n_points,
    )
    wfs.nJobs = args.threads
    t_wfs = time.perf_counter() - t0
    t0 = time.perf_counter()
    dm = DeformableMirror(
        telescope=tel, nSubap=c["n_act"] - 1, mechCoupling=0.3, print_dm_properties=False
    )
    m2c = compute_KL_basis(tel, atm, dm)[:, : c["n_modes"]]
    t_modes = time.perf_counter() - t0
    tel.resetOPD()
    ngs * tel
    t0 = time.perf_counter()
    calib = InteractionMatrix(
        ngs,
        tel,
        dm,
        wfs,
        m2c,
        stroke=1e-9,
        nMeasurements=8,
        single_pass=False,
        invert=True,
        display=False,
    )
    t_imat = time.perf_counter() - t0
    mem_cal = _peak_rss_mb()
    recon = calib.M

    tel.resetOPD()
    ngs * tel
    tel + atm
    dm.coefs = 0
    meas = np.zeros(m2c.shape[1])
    res_rms = []
    n_frames, warm = c["frames"], args.warmup
    t_loop = c_loop = 0.0
    pupil = tel.pupil > 0
    for k in range(n_frames + warm):
        t0, c0 = time.perf_counter(), time.process_time()
        atm.update()
        turb = tel.OPD[pupil].copy()
        tel * dm * wfs
        dm.coefs = dm.coefs - gain * (m2c @ meas)
        meas = recon @ wfs.signal
        if k >= warm:
            t_loop += time.perf_counter() - t0
            c_loop += time.process_time() - c0
            res_rms.append(float(np.std(tel.OPD[pupil]) * 1e9))
    phase = tel.src.phase.copy()
    t_wfs_only, c_wfs_only = _time_per_call(lambda: wfs.wfs_measure(phase_in=phase), n_frames)
    return dict(
        code="OOPAO",
        loop_fps=n_frames / t_loop,
        wfs_fps=1.0 / t_wfs_only,
        loop_fps_cpu=n_frames / c_loop,
        wfs_fps_cpu=1.0 / c_wfs_only,
        t_setup_wfs=t_wfs,
        t_modes=t_modes,
        t_imat=t_imat,
        t_calibration=t_modes + t_imat,
        peak_mb_calibration=mem_cal,
        peak_mb=_peak_rss_mb(),
        residual_nm=float(np.mean(res_rms[-10:])),
        turbulence_nm=float(np.std(turb) * 1e9),
        n_modes=int(m2c.shape[1]),
        n_signals=int(wfs.nSignal),
        n_fft=int(wfs.resolution),
        n_points=int(wfs.nTheta),
        push_pull=True,
        precision=int(os.environ["OOPAO_PRECISION"]),
    )


# --------------------------------------------------------------------------------- driver
def _run_part(python: str, part: str, argv: list[str]) -> dict | str:
    env = dict(os.environ)
    threads = argv[argv.index("--threads") + 1] if "--threads" in argv else "1"
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[var] = threads
    cmd = [python, os.path.abspath(__file__), "--part", part, *argv]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    for line in proc.stdout.splitlines()[::-1]:
        if line.startswith(RESULT_TAG):
            return json.loads(line[len(RESULT_TAG) :])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-15:]
    return f"{part} part failed (exit {proc.returncode}):\n" + "\n".join(tail)


def _table(ours: dict, ref: dict | None) -> str:
    rows = [
        ("closed loop [frames/s, wall]", "loop_fps", True),
        ("closed loop [frames/s, CPU time]", "loop_fps_cpu", True),
        ("pyramid alone [frames/s, wall]", "wfs_fps", True),
        ("pyramid alone [frames/s, CPU time]", "wfs_fps_cpu", True),
        ("modal basis [s]", "t_modes", False),
        ("interaction matrix [s]", "t_imat", False),
        ("calibration total [s]", "t_calibration", False),
        ("peak memory, calibration [MB]", "peak_mb_calibration", False),
        ("peak memory, whole run [MB]", "peak_mb", False),
        ("closed-loop residual [nm RMS]", "residual_nm", None),
    ]
    out = [f"{'':34s}{'aocontrol':>12s}{'OOPAO':>12s}{'ratio':>10s}"]
    for label, key, higher_better in rows:
        a = ours[key]
        if ref is None:
            out.append(f"{label:34s}{a:12.3g}{'-':>12s}{'-':>10s}")
            continue
        b = ref[key]
        if higher_better is None:
            ratio = "-"
        elif higher_better:
            ratio = f"{a / b:9.2f}x"
        else:
            ratio = f"{b / a:9.2f}x"
        out.append(f"{label:34s}{a:12.3g}{b:12.3g}{ratio:>10s}")
    out.append(
        f"aocontrol interaction matrix by exact derivative (one propagation per mode): "
        f"{ours['t_imat_derivative']:.3g} s, relative difference from push-pull "
        f"{ours['imat_derivative_rel_diff']:.1e}"
    )
    out.append(
        "ratio: how many times faster / smaller aocontrol is (OOPAO / aocontrol for "
        "times and memory, aocontrol / OOPAO for rates)"
    )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["all", "ours", "oopao"], default="all")
    parser.add_argument(
        "--oopao-python", default=None, help="interpreter of a virtualenv with OOPAO installed"
    )
    parser.add_argument("--oopao-precision", type=int, choices=[32, 64], default=64)
    parser.add_argument("--n-pix", type=int, default=80)
    parser.add_argument("--n-subap", type=int, default=40)
    parser.add_argument("--n-actuators", type=int, default=28)
    parser.add_argument("--n-modes", type=int, default=500)
    parser.add_argument("--modulation", type=float, default=3.0)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    raw = sys.argv[1:] if argv is None else list(argv)

    if args.part in ("ours", "oopao"):
        result = run_ours(args) if args.part == "ours" else run_oopao(args)
        print(RESULT_TAG + json.dumps(result))
        return 0

    passthrough = [a for a in raw if a not in ("--part", "all")]
    if "--oopao-python" in passthrough:
        i = passthrough.index("--oopao-python")
        del passthrough[i : i + 2]
    print(f"configuration: {_config(args)}, threads={args.threads}", flush=True)
    ours = _run_part(sys.executable, "ours", passthrough)
    if isinstance(ours, str):
        print(ours)
        return 1
    ref = None
    if args.oopao_python is None:
        print(
            "OOPAO part skipped: pass --oopao-python /path/to/venv/bin/python (a virtualenv "
            "with `pip install oopao`) to measure it side by side."
        )
    elif not os.path.exists(args.oopao_python):
        print(f"OOPAO part skipped: {args.oopao_python} does not exist.")
    else:
        ref = _run_part(args.oopao_python, "oopao", passthrough)
        if isinstance(ref, str):
            print("OOPAO part skipped:", ref)
            ref = None
    print(json.dumps({"aocontrol": ours, "OOPAO": ref}, indent=1))
    print(_table(ours, ref))
    return 0


if __name__ == "__main__":
    sys.exit(main())
