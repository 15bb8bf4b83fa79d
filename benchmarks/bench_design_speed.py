"""Benchmark: a certified data-driven bank from telemetry in seconds (issue 34). A script.

    python benchmarks/bench_design_speed.py [--reference REV | --reference-checkout PATH]
        [--quick] [--telemetry FILE] [--parts abc]

Each part runs every command in a fresh process, once with this checkout and once with the
reference (``--reference REV``, checked out in a temporary git worktree, or
``--reference-checkout PATH``; the ratio new / reference is measured in the same run, the
reference first), and prints
wall and CPU time (the process and its workers: the process tree polled with psutil),
peak memory and the load average before and after.

(a) ``aocontrol design`` on the stage-2 telemetry of a 5-s run of ``bright1-worst``
    (540 modes at 3 kHz, 15,300 frames; written by ``aocontrol run ... --telemetry`` with
    the reference integrator, seed 1000) with the defaults (every core, both bounds, the
    report): estimation, design, certificates, bounds, report, export. Goal: at most 20 s
    wall on 2 cores. The banks of the two checkouts are compared (coefficients, predicted
    residual, certified margins).
(b) Per mode, one ``datadriven`` call per mode (order 5, one process, after a warm-up
    mode): the 12 first modes of the ``vibration`` case's stage-2 telemetry (4,000 frames,
    the tilt with four lines) and six synthetic resonant modes (turbulence plus one to three
    lines 300 times the turbulence, damping 0.002-0.05: one of them needs the bound start's
    cutting planes). Goals: the median at least 4x shorter than dd4ao's 1.80 s per mode
    (issue 34's figure, measured by the issue's author; dd4ao is not run here) and no mode
    above 3 s.
(c) A warm redesign of (a)'s bank from the telemetry of the next 5 s (seed 1001):
    :func:`aocontrol.adaptive.redesign` of every mode, 32 points, one convex iteration (the
    adaptive loop's default warm design), every switched mode certified. Goal: at most 5 s.

``--quick``: 0.5-s quick scenes (smoke run of the same code). Timings on a shared machine:
read the ratios and the loads printed beside them.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _run(cmd: list[str], checkout: str, cwd: str) -> dict:
    """Run ``cmd`` with ``checkout`` first on the path; wall, CPU of its process tree, peak RSS."""
    import psutil

    env = dict(
        os.environ, PYTHONPATH=checkout, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "")
    )
    if not env["OMP_NUM_THREADS"]:
        del env["OMP_NUM_THREADS"]
    load0 = _load()
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, env=env, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    root = psutil.Process(proc.pid)
    cpu: dict[int, float] = {}
    rss: dict[int, float] = {}
    while proc.poll() is None:
        try:
            tree = [root, *root.children(recursive=True)]
        except psutil.Error:
            tree = []
        for p in tree:
            try:
                t = p.cpu_times()
                cpu[p.pid] = t.user + t.system
                rss[p.pid] = max(rss.get(p.pid, 0.0), p.memory_info().rss / 1e6)
            except psutil.Error:
                pass
        time.sleep(0.05)
    wall = time.perf_counter() - t0
    out = proc.stdout.read()
    if proc.returncode:
        print(out)
        raise RuntimeError(f"{cmd} failed with exit code {proc.returncode}")
    return {
        "wall": wall,
        "cpu": sum(cpu.values()),
        "rss": max(rss.values(), default=0.0),
        "out": out,
        "load": (load0, _load()),
    }


def _checkouts(args) -> list[tuple[str, str]]:
    ref = (
        [("reference", os.path.abspath(args.reference_checkout))] if args.reference_checkout else []
    )
    return [*ref, ("this", ROOT)]


def _reference_worktree(rev: str, folder: str) -> str:
    """A detached git worktree of ``rev`` in ``folder`` (removed by :func:`main` at the end),
    its bytecode compiled first (a fresh checkout would otherwise pay the compilation of
    every module, in the command and in each of its workers, inside the timed run)."""
    path = os.path.join(folder, "reference-checkout")
    subprocess.run(
        ["git", "-C", ROOT, "worktree", "add", "--detach", path, rev],
        check=True,
        capture_output=True,
    )
    subprocess.run(
        [sys.executable, "-m", "compileall", "-q", os.path.join(path, "aocontrol")],
        check=True,
        capture_output=True,
    )
    return path


def _telemetry(args, folder: str, seed: int) -> str:
    """The stage-2 telemetry file of ``bright1-worst`` (results file, HDF5)."""
    case = "bright1-worst"
    seconds = "0.5" if args.quick else "5"
    cmd = [sys.executable, "-m", "aocontrol.study.cli", "run", case, "--controller", "reference",
           "--scheme", "standalone", "--seconds", seconds, "--seed", str(seed), "--telemetry",
           "--out", folder, "--no-progress", *(["--quick"] if args.quick else [])]  # fmt: skip
    subprocess.run(cmd, env=dict(os.environ, PYTHONPATH=ROOT), check=True, capture_output=True)
    name = [f for f in os.listdir(folder) if f.endswith(".h5") and f"seed{seed}" in f]
    return os.path.join(folder, name[0])


def part_a(args, folder: str, path: str) -> dict:
    print(
        f"(a) aocontrol design {os.path.basename(path)} --stage stage2 (defaults: every "
        "core, both bounds, report)"
    )
    print(f"{'checkout':10}{'wall[s]':>9}{'CPU[s]':>8}{'peak MB':>9}  load before / after")
    runs = {}
    for label, checkout in _checkouts(args):
        out = os.path.join(folder, label, "controller.h5")
        r = _run([sys.executable, "-m", "aocontrol.study.cli", "design", path, "--stage", "stage2",
                  "--out", out, "--no-progress"], checkout, folder)  # fmt: skip
        r["bank"] = out
        runs[label] = r
        print(
            f"{label:10}{r['wall']:>9.1f}{r['cpu']:>8.1f}{r['rss']:>9.0f}  "
            f"{r['load'][0]} / {r['load'][1]}"
        )
        for line in r["out"].splitlines():
            if line.startswith(("predicted residual", "min ", "median ", "wall time:")):
                print("    " + line[:200])
    if "reference" in runs:
        new, old = runs["this"], runs["reference"]
        print(
            f"  this / reference: wall {new['wall'] / old['wall']:.3f}x, CPU "
            f"{new['cpu'] / old['cpu']:.3f}x; goal: wall <= 20 s on 2 idle cores: "
            f"{'met' if new['wall'] <= 20 else 'not met'} ({new['wall']:.1f} s)"
        )
        _compare_banks(old["bank"], new["bank"], path)
    return runs


def _compare_banks(old: str, new: str, telemetry: str) -> None:
    """Coefficients, predicted residual and certified margin of two banks (this process)."""
    from aocontrol.analysis import margins, residual_variance
    from aocontrol.controllers import load_controller
    from aocontrol.plant import loop_plant
    from aocontrol.study._cli_design import read_telemetry
    from aocontrol.synthesis import disturbance_from_telemetry

    a, b = load_controller(old), load_controller(new)
    m, u, info = read_telemetry(telemetry, "stage2")
    plant = loop_plant(info["fs"], info["latency_frames"])
    est = disturbance_from_telemetry(m, u, plant)
    va = residual_variance(plant, a, est.freqs, est.psd, est.noise_psd)
    vb = residual_variance(plant, b, est.freqs, est.psd, est.noise_psd)
    same = np.all((a.b == b.b) & (a.a == b.a), axis=1)
    diff = np.flatnonzero(~same)
    ratio = vb / va
    print(
        f"  banks: {same.sum()}/{same.size} modes bit-identical; residual new/old per mode: "
        f"median {np.median(ratio):.6f}, min {ratio.min():.6f}, max {ratio.max():.6f}; "
        f"total {np.sqrt(vb.sum()):.4f} / {np.sqrt(va.sum()):.4f} nm"
    )
    if diff.size:
        mm = np.array([margins(plant, b, mode=int(i)).modulus_margin for i in diff])
        print(
            f"  the {diff.size} modes that differ (first {diff[:12].tolist()}): certified "
            f"modulus margin min {mm.min():.4f} (required 0.5)"
        )


_MODES_SCRIPT = textwrap.dedent(
    """
    import json, sys, time
    import numpy as np
    from aocontrol.analysis import white_noise_psd
    from aocontrol.disturbance import synthetic_turbulence_psd
    from aocontrol.plant import loop_plant
    from aocontrol.study._cli_design import read_telemetry
    from aocontrol.synthesis import datadriven, disturbance_from_telemetry

    FS = 3000.0
    plant = loop_plant(FS, 0.828)
    m, u, info = read_telemetry(sys.argv[1], "stage2")
    m, u = m[-4000:, :12], u[-4000:, :12]
    est = disturbance_from_telemetry(m, u, plant)
    f = np.concatenate([[0.0], np.geomspace(1e-2, FS / 2, 1200)])
    base = synthetic_turbulence_psd(f, 60, fs=FS)[[3, 10, 20, 30, 40, 50]]
    lines = [[(60.0, 0.004)], [(98.0, 0.004), (47.0, 0.01)], [(150.0, 0.003)],
             [(200.0, 0.002), (60.0, 0.006)], [(17.5, 0.05), (47.0, 0.01), (98.0, 0.004)],
             [(120.0, 0.002)]]
    psd = base.copy()
    for i, ls in enumerate(lines):
        for f0, z in ls:
            peak = 300.0 * np.max(base[i] * (f > f0 / 2))
            psd[i] += peak / (1 + ((f**2 - f0**2) / (2 * z * f0 * np.maximum(f, 1e-9))) ** 2)
    noise = float(white_noise_psd(0.01, FS))
    cases = [("vibration", k, est.freqs, est.psd[k], est.noise_psd[k]) for k in range(est.n_modes)]
    cases += [("resonant", k, f, psd[k], noise) for k in range(6)]
    datadriven(plant, est.freqs, est.psd[-1], noise_psd=est.noise_psd[-1], n_jobs=1, progress=False)
    out = []
    for name, k, freqs, p, n in cases:
        t0, c0 = time.perf_counter(), time.process_time()
        r = datadriven(plant, freqs, p, noise_psd=n, n_jobs=1, progress=False)
        out.append({"set": name, "mode": k, "wall": time.perf_counter() - t0,
                    "cpu": time.process_time() - c0, "resid": float(r.residual_variance[0]),
                    "mm": float(r.reports[0].modulus_margin), "start": r.reports[0].start})
    print(json.dumps(out))
    """
)


def part_b(args, folder: str, vib: str) -> None:
    print(
        "\n(b) per mode: one datadriven call each (order 5, one process), 12 vibration-case "
        "modes + 6 resonant"
    )
    res = {}
    for label, checkout in _checkouts(args):
        r = _run([sys.executable, "-c", _MODES_SCRIPT, vib], checkout, folder)
        res[label] = json.loads(r["out"].strip().splitlines()[-1])
        w = np.array([x["wall"] for x in res[label]])
        worst = res[label][int(np.argmax(w))]
        print(
            f"  {label:10} median {np.median(w):.3f} s, max {w.max():.2f} s ({worst['set']} "
            f"mode {worst['mode']}, start {worst['start']!r}), load {r['load'][0]} / "
            f"{r['load'][1]}"
        )
    new = res["this"]
    w = np.array([x["wall"] for x in new])
    print(
        f"  goals: median <= 1.80 / 4 = 0.45 s (dd4ao's median, quoted from issue 34): "
        f"{'met' if np.median(w) <= 0.45 else 'not met'}; no mode above 3 s: "
        f"{'met' if w.max() <= 3 else 'not met'}"
    )
    print(
        f"  {'set':10}{'mode':>5}"
        + "".join(f"{label + ' [s]':>16}" for label in res)
        + f"{'resid new/old':>15}{'MM new':>9}{'start':>18}"
    )
    for i, x in enumerate(new):
        old = res.get("reference", new)[i]
        print(
            f"  {x['set']:10}{x['mode']:>5}"
            + "".join(f"{res[label][i]['wall']:>16.3f}" for label in res)
            + f"{x['resid'] / old['resid']:>15.9f}{x['mm']:>9.4f}{x['start']:>18}"
        )


_WARM_SCRIPT = textwrap.dedent(
    """
    import json, sys, time
    import numpy as np
    from aocontrol.adaptive import datadriven_designer, redesign
    from aocontrol.controllers import load_controller
    from aocontrol.plant import loop_plant
    from aocontrol.study._cli_design import read_telemetry
    from aocontrol.synthesis import disturbance_from_telemetry

    bank = load_controller(sys.argv[1])
    m, u, info = read_telemetry(sys.argv[2], "stage2")
    plant = loop_plant(info["fs"], info["latency_frames"])
    t0 = time.perf_counter()
    est = disturbance_from_telemetry(m, u, plant)
    t_est = time.perf_counter() - t0
    design = datadriven_designer(order=5, n_jobs=None, warm_n_grid=32, warm_max_iter=1)
    t0 = time.perf_counter()
    up = redesign(plant, bank, est, design, modulus_margin=0.5)
    t_first = time.perf_counter() - t0
    # the same update again in this process: the workers and the compiled problems warm, as
    # an adaptive loop's next update finds them
    t0 = time.perf_counter()
    again = redesign(plant, bank, est, design, modulus_margin=0.5)
    t_again = time.perf_counter() - t0
    same = bool(
        np.array_equal(up.bank.b, again.bank.b)
        and np.array_equal(up.bank.a, again.bank.a)
    )
    print(json.dumps({"estimate": t_est, "redesign": t_first, "again": t_again, "same": same}))
    """
)


def part_c(args, folder: str, runs: dict, path2: str) -> None:
    print(
        "\n(c) warm redesign of (a)'s bank from the next 5 s (adaptive.redesign, every mode, "
        "32 points, 1 iteration)"
    )
    for label, checkout in _checkouts(args):
        r = _run([sys.executable, "-c", _WARM_SCRIPT, runs[label]["bank"], path2], checkout, folder)
        t = json.loads(r["out"].strip().splitlines()[-1])
        print(
            f"  {label:10} redesign {t['redesign']:.2f} s wall (estimate {t['estimate']:.2f} s), "
            f"process {r['wall']:.1f} s wall {r['cpu']:.1f} s CPU, load {r['load'][0]} / "
            f"{r['load'][1]}; goal <= 5 s: {'met' if t['redesign'] <= 5 else 'not met'}"
        )
        if "again" in t:  # a reference checkout's script may predate it
            print(
                f"  {'':10} the same redesign again in that process (workers warm): "
                f"{t['again']:.2f} s wall, the same bank: {t['same']}"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--reference-checkout", default=None, help="a checkout of the code to compare with"
    )
    parser.add_argument(
        "--reference",
        default=None,
        metavar="REV",
        help="a git revision to compare with (checked out in a temporary worktree)",
    )
    parser.add_argument("--quick", action="store_true", help="0.5-s quick scenes (smoke run)")
    parser.add_argument("--telemetry", default=None, help="(a)'s results file instead of a new run")
    parser.add_argument("--parts", default="abc")
    args = parser.parse_args()
    import platform

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"load {_load()}"
    )
    folder = tempfile.mkdtemp(prefix="aocontrol-bench34-")
    if args.reference and not args.reference_checkout:
        args.reference_checkout = _reference_worktree(args.reference, folder)
        print(f"reference: {args.reference} in {args.reference_checkout}")
    try:
        _parts(args, folder)
    finally:
        if args.reference and args.reference_checkout.startswith(folder):
            subprocess.run(
                ["git", "-C", ROOT, "worktree", "remove", "--force", args.reference_checkout],
                check=False,
                capture_output=True,
            )


def _parts(args, folder: str) -> None:
    path = args.telemetry or _telemetry(args, folder, 1000)
    runs = {}
    if "a" in args.parts or "c" in args.parts:
        runs = part_a(args, folder, path)
    if "b" in args.parts:
        cmd = [sys.executable, "-m", "aocontrol.study.cli", "run", "vibration", "--controller",
               "reference", "--scheme", "standalone", "--seconds", "1.5", "--seed", "1000",
               "--telemetry", "--out", os.path.join(folder, "vib"), "--no-progress",
               *(["--quick"] if args.quick else [])]  # fmt: skip
        subprocess.run(cmd, env=dict(os.environ, PYTHONPATH=ROOT), check=True, capture_output=True)
        vib = os.path.join(
            folder,
            "vib",
            [f for f in os.listdir(os.path.join(folder, "vib")) if f.endswith(".h5")][0],
        )
        part_b(args, folder, vib)
    if "c" in args.parts:
        part_c(args, folder, runs, _telemetry(args, os.path.join(folder, "next"), 1001))


if __name__ == "__main__":
    main()
