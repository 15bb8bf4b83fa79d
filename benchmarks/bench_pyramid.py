"""Benchmark: diffractive pyramid closed loop, aocontrol vs OOPAO, side by side in one run.

Set-up (SAXO+ second stage, 40x40-class): VLT pupil (8 m, obstruction 0.14) sampled on
``n_pix = 80`` points, pyramid with 40 pixels across each pupil image, 2 pixels between images
(FFT 168 x 168), circular modulation 3 lambda/D with 40 points, slopes-maps, ~500 KL modes of a
28x28-actuator DM, push-pull interaction matrix, pseudo-inverse reconstructor, a plain
integrator (gain 0.4, one frame of delay), one frozen-flow layer (r0 = 0.15 m at 500 nm,
10 m/s), 3 kHz. The same geometry and the same number of modulation points on both sides.

Measured for each code, in separate processes (so peak memory is each code's own):
frames/s of the closed loop (atmosphere + DM + pyramid + reconstruction + integrator),
each code's own way (``--loop engine``, the default: our engine's DM shape through the
mirror's separable influences, float32 (with ``--precision double``, the float64 product with
the modes), and its atmosphere generated in blocks of frames, the block's time counted in the
timed frames; ``--loop dense``: the loop measured before 6 Dec,
the phase frame by frame and the DM shape as one product with the float32 modes; OOPAO's
``atm.update()`` and its DM's influence-function product either way), frames/s of the
pyramid alone, calibration time (modal basis + interaction matrix) and peak
resident memory. Ratios are printed from this one run (the machine is shared: absolute times
are noisy, ratios less so). Rates are given from wall-clock time and from the process's CPU
time (``time.process_time``, which does not count time spent waiting for a core on a busy
machine). Both codes run with the same number of threads (``--threads``, also applied to BLAS
through ``OMP/OPENBLAS/MKL_NUM_THREADS``).

OOPAO (PyPI ``oopao``) is an optional benchmark dependency, never imported by aocontrol.
Install it in a separate virtualenv and point ``--oopao-python`` at its interpreter::

    python3 -m venv /work/oopao-venv && /work/oopao-venv/bin/pip install oopao
    .venv/bin/python benchmarks/bench_pyramid.py --oopao-python /work/oopao-venv/bin/python

Like for like: ``--precision single|double`` (default single) sets the precision of both codes'
pyramid propagation and DM shape (ours: ``PyramidWFS(precision=...)`` and the modes in
float32/float64; OOPAO: ``OOPAO_PRECISION=32|64``, which ``--oopao-precision`` overrides, and
which also puts its DM influence functions in float32); both reconstructors are float64. Our
pyramid propagates with matrix products (BLAS), OOPAO's with 2-D FFTs: ``--threads`` sets both
our BLAS threads and OOPAO's FFT/joblib threads. OOPAO's focal-plane image, unused in a closed
loop, is switched off (``wfs.compute_focal_plane = False``, as OOPAO recommends for closed
loops; it costs OOPAO 7-14 % per frame); ``--oopao-focal-plane`` turns it back on. ``--repeats
N`` runs each code N times in fresh processes, alternating (ours, OOPAO, ours, ...), so slow
phases of a shared machine hit both; the table gives each code's median with its spread
(min-max, in % of the median) and the ratio of the medians, then the median and range of the
per-repeat ratios.

Without ``--oopao-python`` the OOPAO half is skipped with a message. ``--quick`` runs a small
configuration (smoke test). ``--flops`` prints the propagation's floating-point operations per
frame, stage by stage, for the propagation before issue 15's pair products and for the current
one (:func:`propagation_flops`), and exits.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
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
def propagation_flops(wfs) -> dict:
    """Floating-point operations per frame of the pyramid's propagation, by stage [real flops;
    a complex multiply-add is 8, a real-by-complex one 4, a real one 2], for the propagation
    the library used before issue 15's pair products (complex line-operator products: step x
    per distinct x tilt, step y per modulation point) and for the current one (conjugate pairs
    of the two pupil images and mirror pairs of modulation points: real products, the y tilts
    in the columns); the textbook FFT model (per point: tilt, 2-D FFT, mask, inverse 2-D FFT,
    ``5 N log2 N`` per complex FFT of ``N`` samples) for scale. GEMM counts are exact from the
    shapes; element-wise passes (tilts, direct images, intensities) are counted as written.
    """
    import math

    import numpy as np

    n_pix, n, npts = wfs.pupil.n_pix, wfs.n_fft, wfs.n_points
    plan = wfs._plan
    nl = sum(k.lines.size for k in plan["classes"])  # detector lines (both images)
    n_half = n_pix / 2  # pupil samples of one parity (the dense part of a line)
    ax = np.round(wfs.modulation_offsets[:, 0] * wfs.samples_per_lambda_over_d, 12)
    n_xd = np.unique(ax).size  # distinct x tilts
    before = {
        "x tilts (field x tilt, per distinct x tilt)": 6 * n_pix * n_pix * n_xd,
        "step x (complex GEMM, per distinct x tilt)": 8 * n_pix * n_xd * n_half * nl,
        "y tilts (per point)": 6 * n_pix * nl * npts,
        "step y (complex GEMM, per point)": 8 * nl * n_half * nl * npts,
        "intensity |.|^2, summed over the points": 4 * nl * nl * npts,
    }
    n_m, n_x = plan["n_m"], plan["tx"][0].shape[0]
    n_g = sum((j1 - j0) * (2 if two else 1) for j0, j1, two in wfs._chunks)
    n_l = [p.first.size for p in plan["pairs"]]
    after = {
        "x tilts (field x tilt, per mirror pair)": 6 * n_pix * n_pix * n_x,
        "step x (complex GEMM, per mirror pair)": 8 * (2 * n_m * n_x) * n_half * nl,
        "y tilts (cos, sin of each pair) and constant rows": 6 * n_m * n_g * 2 * nl,
        "step y (real GEMM [u 1; v 0], all pairs at once)": sum(
            2 * (2 * k) * (n_m + 1) * (n_g * 2 * nl) for k in n_l
        ),
        "direct images (one value per face)": sum(2 * k * n_g * 2 * nl for k in n_l),
        "intensity (squares and cross terms of the products)": sum(
            2 * (2 * k * n_g * 2 * nl) + 4 * (k * n_g * nl) for k in n_l
        ),
    }
    n2 = n * n
    fft = {
        "tilt + mask (per point)": 2 * 6 * n2 * npts,
        "2-D FFT and inverse (per point)": 2 * 5 * n2 * math.log2(n2) * npts,
        "intensity": 3 * n2 * npts,
    }
    return {"before (main ccdd059)": before, "pairs (this code)": after, "textbook FFT": fft}


def print_flops(wfs) -> None:
    """Print :func:`propagation_flops` per stage [MFLOP per frame]."""
    for name, stages in propagation_flops(wfs).items():
        total = sum(stages.values())
        print(f"{name}: {total / 1e6:.1f} MFLOP per frame")
        for stage, v in stages.items():
            print(f"    {stage}: {v / 1e6:.2f}")


def run_ours(args: argparse.Namespace) -> dict:
    import numpy as np

    from aocontrol.sim._cascade import default_chunk
    from aocontrol.sim._phase_maps import shape_synthesizer
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
        precision=args.precision,
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
    coeffs = np.zeros(basis.n_modes)
    meas = np.zeros(basis.n_modes)
    res_rms = []
    n_frames, warm = c["frames"], args.warmup
    # the atmosphere: the engine's blocks of frames (the frames do not depend on the split;
    # a block's time counted in the timed frames) or, the former loop, frame by frame
    block = min(n_frames, default_chunk(pupil.n_valid)) if args.loop == "engine" else 1
    if args.loop == "engine" and args.precision == "single":
        # the DM shape as the engine synthesises it for a diffractive sensor: through the
        # mirror's separable influences, in float32 (sim._phase_maps)
        dm_shape = shape_synthesizer(basis)
    else:
        # the product with the modes in the FFT precision (like OOPAO's influence functions
        # under OOPAO_PRECISION); the engine's synthesiser is float32 only
        modes = basis.modes.astype(np.float32 if args.precision == "single" else np.float64)

        def dm_shape(x):
            return x.astype(modes.dtype) @ modes

    t_loop = c_loop = 0.0
    turbs, j = None, 0
    for k in range(n_frames + warm):
        t0, c0 = time.perf_counter(), time.process_time()
        if k < warm:  # the timed frames' blocks start at the first timed frame
            turbs, j = atm.phase_vectors(1), 0
        elif (j := (k - warm) % block) == 0:
            turbs = atm.phase_vectors(min(block, n_frames + warm - k))
        turb = turbs[j]
        res = turb - dm_shape(coeffs)
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
        precision=args.precision,
        loop=args.loop,
    )


# --------------------------------------------------------------------------------- OOPAO
def run_oopao(args: argparse.Namespace) -> dict:
    precision = args.oopao_precision or (32 if args.precision == "single" else 64)
    os.environ["OOPAO_PRECISION"] = str(precision)
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
    # the focal-plane image is not used by a closed loop (OOPAO's advice: switch it off)
    wfs.compute_focal_plane = bool(args.oopao_focal_plane)
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
        compute_focal_plane=bool(wfs.compute_focal_plane),
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


ROWS = [
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


def _median_spread(values: list[float]) -> tuple[float, float]:
    """Median and spread (max - min) in % of the median."""
    med = statistics.median(values)
    return med, (100.0 * (max(values) - min(values)) / med if med else 0.0)


def _cell(values: list[float]) -> str:
    med, spread = _median_spread(values)
    return f"{med:10.3g} ±{spread:3.0f}%" if len(values) > 1 else f"{med:10.3g}     "


def _table(ours: list[dict], ref: list[dict] | None) -> str:
    """Median (spread) per code, ratio of medians, and median [range] of per-repeat ratios."""
    out = [
        f"{'':34s}{'aocontrol':>16s}{'OOPAO':>16s}{'ratio':>9s}   per-repeat ratio",
    ]
    for label, key, higher_better in ROWS:
        a = [r[key] for r in ours]
        if ref is None:
            out.append(f"{label:34s}{_cell(a):>16s}{'-':>16s}{'-':>9s}")
            continue
        b = [r[key] for r in ref]
        if higher_better is None:
            out.append(f"{label:34s}{_cell(a):>16s}{_cell(b):>16s}{'-':>9s}")
            continue
        ma, mb = statistics.median(a), statistics.median(b)
        ratio = ma / mb if higher_better else mb / ma
        pairs = [x / y if higher_better else y / x for x, y in zip(a, b, strict=False)]
        per = (
            f"{statistics.median(pairs):.2f} [{min(pairs):.2f}, {max(pairs):.2f}]"
            if len(pairs) > 1
            else ""
        )
        out.append(f"{label:34s}{_cell(a):>16s}{_cell(b):>16s}{ratio:8.2f}x   {per}")
    last = ours[-1]
    out.append(
        f"aocontrol interaction matrix by exact derivative (one propagation per mode): "
        f"{last['t_imat_derivative']:.3g} s, relative difference from push-pull "
        f"{last['imat_derivative_rel_diff']:.1e}"
    )
    out.append(
        "ratio: how many times faster / smaller aocontrol is (OOPAO / aocontrol for times and "
        "memory, aocontrol / OOPAO for rates), from the medians over the repeats; ± is the "
        "spread (max - min) over the repeats in % of the median"
    )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["all", "ours", "oopao"], default="all")
    parser.add_argument(
        "--oopao-python", default=None, help="interpreter of a virtualenv with OOPAO installed"
    )
    parser.add_argument(
        "--precision",
        choices=["single", "double"],
        default="single",
        help="FFT precision of both codes (like for like)",
    )
    parser.add_argument(
        "--oopao-precision",
        type=int,
        choices=[32, 64],
        default=None,
        help="override OOPAO's precision (default: follows --precision)",
    )
    parser.add_argument(
        "--oopao-focal-plane",
        action="store_true",
        help="keep OOPAO's focal-plane image (off by default: unused in a closed loop)",
    )
    parser.add_argument("--repeats", type=int, default=None, help="alternating repeats (3)")
    parser.add_argument("--n-pix", type=int, default=80)
    parser.add_argument("--n-subap", type=int, default=40)
    parser.add_argument("--n-actuators", type=int, default=28)
    parser.add_argument("--n-modes", type=int, default=500)
    parser.add_argument("--modulation", type=float, default=3.0)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--loop",
        choices=["engine", "dense"],
        default="engine",
        help="our closed loop's DM shape and atmosphere: the engine's (separable influences, "
        "frames in blocks; default) or the former dense product and frame-by-frame phase",
    )
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--flops",
        action="store_true",
        help="print the propagation's FLOPs per frame by stage (former and current; this "
        "geometry and the cascade's 20 modulation points) and exit",
    )
    args = parser.parse_args(argv)
    if args.flops:
        from aocontrol.sim.pupil import vlt_pupil
        from aocontrol.sim.wfs import PyramidWFS

        c = _config(args)
        for points in (None, 20):
            wfs = PyramidWFS(
                vlt_pupil(c["n_pix"]),
                1.215e-6,
                n_subapertures=c["n_subap"],
                modulation=c["modulation"],
                n_modulation_points=points,
            )
            print(
                f"--- {c['n_pix']} px, {c['n_subap']}x{c['n_subap']}, {c['modulation']} "
                f"lambda/D, {wfs.n_points} points, n_fft {wfs.n_fft}"
            )
            print_flops(wfs)
        return 0
    raw = sys.argv[1:] if argv is None else list(argv)
    repeats = args.repeats if args.repeats is not None else (1 if args.quick else 3)
    if repeats < 1:
        parser.error(f"--repeats must be >= 1, got {repeats}")

    if args.part in ("ours", "oopao"):
        result = run_ours(args) if args.part == "ours" else run_oopao(args)
        print(RESULT_TAG + json.dumps(result))
        return 0

    passthrough = [a for a in raw if a not in ("--part", "all")]
    for opt in ("--oopao-python", "--repeats"):
        if opt in passthrough:
            i = passthrough.index(opt)
            del passthrough[i : i + 2]
    print(
        f"configuration: {_config(args)}, threads={args.threads}, precision={args.precision}, "
        f"OOPAO focal plane {'on' if args.oopao_focal_plane else 'off'}, repeats={repeats}",
        flush=True,
    )
    with_oopao = args.oopao_python is not None and os.path.exists(args.oopao_python)
    if args.oopao_python is None:
        print(
            "OOPAO part skipped: pass --oopao-python /path/to/venv/bin/python (a virtualenv "
            "with `pip install oopao`) to measure it side by side."
        )
    elif not with_oopao:
        print(f"OOPAO part skipped: {args.oopao_python} does not exist.")
    ours: list[dict] = []
    ref: list[dict] | None = [] if with_oopao else None
    for k in range(repeats):  # alternate, each in a fresh process
        mine = _run_part(sys.executable, "ours", passthrough)
        if isinstance(mine, str):
            print(mine)
            return 1
        ours.append(mine)
        print(
            f"repeat {k + 1}/{repeats}: aocontrol loop {mine['loop_fps']:.3g} frames/s", flush=True
        )
        if ref is not None:
            theirs = _run_part(args.oopao_python, "oopao", passthrough)
            if isinstance(theirs, str):
                print("OOPAO part skipped:", theirs)
                ref = None
                continue
            ref.append(theirs)
            print(
                f"repeat {k + 1}/{repeats}: OOPAO loop {theirs['loop_fps']:.3g} frames/s",
                flush=True,
            )
    print(json.dumps({"aocontrol": ours, "OOPAO": ref}, indent=1))
    print(_table(ours, ref))
    return 0


if __name__ == "__main__":
    sys.exit(main())
