"""Run every benchmark the README quotes, with the README's settings (``make bench``).

Each entry of :data:`BENCHMARKS` is one command of the README's benchmark table (the
figure's own settings) and the smoke settings that exercise the same code quickly; the
scripts run one after the other (never in parallel: they time themselves) and each prints its
ratios. ``--quick`` runs the smoke settings instead; ``--only NAME ...`` selects entries (by
entry name or script name); ``--list`` prints the commands without running them. The OOPAO
side of the pyramid benchmark needs a virtualenv with OOPAO
(``OOPAO_PYTHON=/path/to/venv/bin/python``; skipped with a message otherwise). A summary
with each command's exit code and wall time closes the run; the exit code is non-zero if any
failed. The run opens with the machine (CPU model, cores, memory, Python, the commit) and
every command's line closes with the load average before and after it and the CPU time of
its processes, so each figure is printed with the machine and the load it was measured on.
The full run takes hours on a 2-core machine (the held-out certificate check, the paper's
tables and the adaptive study dominate).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import resource
import subprocess
import sys
import time
from typing import NamedTuple

HERE = pathlib.Path(__file__).resolve().parent


class Entry(NamedTuple):
    """One README command: the script, the figure's arguments, the smoke arguments.

    ``covers``: other README commands whose figures the full run also prints (a part run
    alone, e.g. ``--resonant-only``).
    """

    script: str
    full: tuple[str, ...]
    quick: tuple[str, ...] = ("--quick",)
    covers: tuple[str, ...] = ()


#: name -> the README's command and its smoke version, in the README table's order.
BENCHMARKS: dict[str, Entry] = {
    "pyramid": Entry("bench_pyramid.py", ("--repeats", "3")),
    "pyramid-flops": Entry("bench_pyramid.py", ("--flops",), ("--flops", "--quick")),
    "sweep": Entry("bench_sweep.py", ("--seconds", "2")),
    "design-scaleout": Entry("bench_design_scaleout.py", ("--modes", "1024")),
    # Issue 34: against the code before it (fd45857), in the same run.
    "design-speed": Entry("bench_design_speed.py", ("--reference", "fd45857")),
    "synthesis": Entry("bench_synthesis.py", (), covers=("--resonant-only",)),
    "holdout": Entry("bench_certified_holdout.py", ()),
    "loop": Entry("bench_loop.py", ()),
    "cascade": Entry("bench_cascade.py", ("--repeat", "2")),
    "cascade-diffractive": Entry(
        "bench_cascade.py",
        ("--sensor", "diffractive", "--n-pix", "80", "--modes2", "400", "--repeat", "1"),
        ("--quick", "--sensor", "diffractive", "--repeat", "1"),
    ),
    # Issue 34 part 3 (the pyramid with fewer operations): against the code before it
    # (1802ad0), in the same run, fresh processes, alternating.
    "cascade-diffractive-speed": Entry(
        "bench_cascade.py",
        ("--reference", "1802ad0", "--rounds", "2", "--sensor", "diffractive")
        + ("--n-pix", "80", "--modes2", "400", "--repeat", "1"),
        ("--reference", "1802ad0", "--quick", "--sensor", "diffractive", "--repeat", "1"),
    ),
    "lqg": Entry("bench_lqg.py", ()),
    "mpc": Entry("bench_mpc.py", ()),
    "bounds": Entry("bench_bounds.py", ()),
    "paper-tables": Entry("bench_paper_tables.py", ()),
    "telemetry-aot": Entry(
        "bench_telemetry_design.py",
        ("aot",),
        ("aot", "--seconds", "0.5", "--exposure", "0.2", "--controllers", "integrator", "omgi"),
    ),
    "telemetry-estimators": Entry(
        "bench_telemetry_design.py",
        ("estimators",),
        ("estimators", "--cases", "bright1-best", "--controllers", "omgi", "--exposure", "0.2"),
    ),
    "telemetry-own": Entry(
        "bench_telemetry_design.py",
        ("own",),
        ("own", "--cases", "bright1-best", "--schemes", "standalone"),
    ),
    "telemetry-own-diffractive": Entry(
        "bench_telemetry_design.py",
        ("own", "--sensor", "diffractive"),
        ("own", "--sensor", "diffractive", "--cases", "red5-best", "--schemes", "standalone"),
    ),
    "fidelity": Entry(
        "bench_fidelity.py",
        ("--quick", "--seconds", "1", "--cases", "red5-best"),
        ("--quick", "--seconds", "0.2", "--cases", "red5-best"),
    ),
    "fidelity-full": Entry(
        "bench_fidelity.py",
        tuple(
            "--cases red5-best --overrides paper-text --seconds 5 "
            "--settings diffractive/calibrated".split()
        ),
        tuple(
            "--quick --seconds 0.2 --cases red5-best --overrides paper-text "
            "--settings diffractive/calibrated".split()
        ),
    ),
    "fidelity-limits": Entry(
        "bench_fidelity.py",
        tuple(
            "--limits --cases red5-best --overrides paper-text "
            "--alphas 0.001,0.03,0.1,0.3,1".split()
        ),
        tuple(
            "--limits --quick --cases red5-best --overrides paper-text --schemes dcao "
            "--n-taps 64 --n-bound 6".split()
        ),
    ),
    "fidelity-bright": Entry(
        "bench_fidelity.py",
        tuple(
            "--cases bright1-best,bright1-worst --seconds 5 "
            "--settings linear/calibrated,diffractive/calibrated".split()
        ),
        tuple(
            "--quick --seconds 0.2 --cases bright1-best "
            "--settings linear/calibrated,diffractive/calibrated".split()
        ),
    ),
    "adaptive-study": Entry(
        "bench_adaptive.py",
        ("--study", "--quick", "--select", "0.9", "--jobs", "1"),
        # Parts (a)-(c) on 6 s of drift: 72 s on 2 cores (the 60-s default took 597 s).
        ("--quick", "--seconds", "6"),
    ),
    "adaptive-seeds": Entry(
        "bench_adaptive.py",
        tuple(
            "--study --quick --jobs 1 --scenarios wind-doubles --strategies "
            "fixed,adaptive,oracle --measure-from 6 --seeds 0,1,2 --periods 2 "
            "--windows 1,T".split()
        ),
        tuple(
            "--study --quick --jobs 1 --scenarios wind-doubles --strategies fixed,adaptive "
            "--seconds 6 --periods 2".split()
        ),
    ),
    "adaptive-seeing": Entry(
        "bench_adaptive.py",
        tuple(
            "--study --quick --jobs 1 --scenarios seeing-worsens --strategies "
            "fixed,adaptive,oracle --measure-from 6 --seeds 0,1,2 --periods 2".split()
        ),
        tuple(
            "--study --quick --jobs 1 --scenarios seeing-worsens --strategies fixed,adaptive "
            "--seconds 6 --periods 2".split()
        ),
    ),
    "adaptive-transients": Entry(
        "bench_adaptive.py",
        tuple("--parts b --quick --scenarios seeing-worsens --seeds 0,1,2".split()),
        tuple("--parts b --quick --scenarios seeing-worsens --seeds 0 --seconds 6".split()),
    ),
    "adaptive-cascade": Entry(
        "bench_adaptive.py",
        tuple(
            "--cascade --strategies fixed,adaptive,oracle --periods 2 --window 1 "
            "--seconds 60 --jobs 2".split()
        ),
        tuple(
            "--cascade --quick --strategies fixed,adaptive,oracle --periods 1 --seconds 4 "
            "--jobs 1".split()
        ),
    ),
    "warm-redesign": Entry(
        "bench_adaptive.py",
        ("--parts", "c", "--sweep", "--start-stride", "10", "--jobs", "2"),
        ("--quick", "--parts", "c"),
    ),
    "atmosphere": Entry("bench_atmosphere.py", ()),
    "eof": Entry("bench_eof.py", ()),
    "paper-tables-predictors": Entry(
        "bench_paper_tables.py",
        ("--extra-controllers", "eof,lqg"),
        ("--quick", "--cases", "bright1-best", "--extra-controllers", "eof,lqg"),
    ),
    "cascade-eof": Entry(
        "bench_cascade.py",
        ("--repeat", "2", "--stage2-controllers", "iir5,eof"),
        ("--quick", "--repeat", "1", "--stage2-controllers", "iir5,eof"),
    ),
    "robustness": Entry(
        "bench_robustness.py",
        ("--cases", "bright1-best,red1-fast", "--seconds", "2"),
        ("--smoke", "--seconds", "0.2", "--cases", "bright1-best"),
    ),
    "robustness-diffractive": Entry(
        "bench_robustness.py",
        ("--cases", "bright1-best,red1-fast", "--seconds", "1", "--sensor", "diffractive"),
        ("--smoke", "--seconds", "0.2", "--cases", "bright1-best", "--sensor", "diffractive"),
    ),
}


def machine() -> str:
    """One line naming the machine the figures are measured on, and the code's commit."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next(
                (ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), model
            )
    except OSError:
        pass
    try:
        with open("/proc/meminfo") as f:
            memory = f"{int(f.readline().split()[1]) / 2**20:.1f} GiB"
    except (OSError, ValueError, IndexError):
        memory = "memory unknown"
    try:
        commit = subprocess.run(
            ["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return (
        f"machine: {model}, {os.cpu_count()} cores, {memory}; Python {platform.python_version()};"
        f" commit {commit}"
    )


def _children_cpu() -> float:
    """User + system CPU time of the finished child processes so far [s]."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def load() -> str:
    """The 1-minute load average (other jobs on the machine), or "n/a" where there is none."""
    try:
        return f"{os.getloadavg()[0]:.1f}"
    except OSError:
        return "n/a"


def command(name: str, quick: bool) -> list[str]:
    """The command line of entry ``name`` (``quick``: its smoke settings)."""
    entry = BENCHMARKS[name]
    args = list(entry.quick if quick else entry.full)
    if entry.script == "bench_pyramid.py" and os.environ.get("OOPAO_PYTHON"):
        args += ["--oopao-python", os.environ["OOPAO_PYTHON"]]
    return [sys.executable, str(HERE / entry.script), *args]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="every benchmark's smoke settings")
    parser.add_argument("--only", nargs="+", default=None, help="entry or script names")
    parser.add_argument("--list", action="store_true", help="print the commands, run nothing")
    args = parser.parse_args(argv)
    missing = sorted({e.script for e in BENCHMARKS.values()} - {p.name for p in HERE.iterdir()})
    if missing:
        parser.error(f"benchmark scripts missing from {HERE}: {missing}")
    order = list(BENCHMARKS)
    if args.only:
        scripts = {e.script for e in BENCHMARKS.values()}
        unknown = sorted(set(args.only) - set(order) - scripts)
        if unknown:
            parser.error(f"--only: unknown {unknown}; valid: {', '.join(order)} (or a script name)")
        order = [n for n in order if n in args.only or BENCHMARKS[n].script in args.only]
    print(machine(), flush=True)
    results = []
    for name in order:
        cmd = command(name, args.quick)
        print(f"=== {name}: {' '.join([pathlib.Path(cmd[1]).name, *cmd[2:]])}", flush=True)
        if args.list:
            continue
        before, cpu0 = load(), _children_cpu()
        t0 = time.perf_counter()
        code = subprocess.call(cmd)
        wall, cpu = time.perf_counter() - t0, _children_cpu() - cpu0
        results.append((name, code, wall, cpu, before, load()))
    if args.list:
        return 0
    print("=== summary (load: the 1-minute load average before -> after the command)")
    for name, code, wall, cpu, before, after in results:
        print(
            f"{name:28s} exit {code:3d}  {wall:8.1f} s wall  {cpu:8.1f} s CPU"
            f"  load {before} -> {after}"
        )
    return 0 if all(r[1] == 0 for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
