"""Run every benchmark the README quotes, with the README's settings (``make bench``).

Each entry of :data:`BENCHMARKS` is the command line the README gives next to its figure; the
scripts run one after the other (never in parallel: they time themselves) and each prints its
ratios. Benchmarks present in this folder but not in the table run with ``--quick``, so none is
forgotten. ``--quick`` runs every benchmark in its quick (smoke) mode instead; ``--only NAME``
selects scripts. The OOPAO side of the pyramid benchmark needs a virtualenv with OOPAO
(``OOPAO_PYTHON=/path/to/venv/bin/python``; skipped with a message otherwise). A summary with
each script's exit code and wall time closes the run; the exit code is non-zero if any failed.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent

#: script -> arguments of the README's figure (the quick mode only adds ``--quick``).
BENCHMARKS: dict[str, list[str]] = {
    "bench_synthesis.py": [],
    "bench_loop.py": [],
    "bench_atmosphere.py": [],
    "bench_pyramid.py": ["--repeats", "3"],
    "bench_sweep.py": ["--seconds", "2"],
    "bench_lqg.py": [],
    "bench_mpc.py": [],
    "bench_paper_tables.py": [],
}


def _command(script: pathlib.Path, quick: bool) -> list[str]:
    args = ["--quick"] if quick or script.name not in BENCHMARKS else list(BENCHMARKS[script.name])
    if script.name == "bench_pyramid.py" and os.environ.get("OOPAO_PYTHON"):
        args += ["--oopao-python", os.environ["OOPAO_PYTHON"]]
    return [sys.executable, str(script), *args]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="every benchmark in quick mode")
    parser.add_argument("--only", nargs="+", default=None, help="script names (bench_x.py)")
    args = parser.parse_args(argv)
    present = {p.name: p for p in sorted(HERE.glob("bench_*.py"))}
    order = [n for n in BENCHMARKS if n in present] + sorted(set(present) - set(BENCHMARKS))
    if args.only:
        unknown = sorted(set(args.only) - set(present))
        if unknown:
            parser.error(f"--only: unknown {unknown}; valid: {', '.join(order)}")
        order = [n for n in order if n in args.only]
    results = []
    for name in order:
        cmd = _command(present[name], args.quick)
        print(f"=== {' '.join([pathlib.Path(cmd[1]).name, *cmd[2:]])}", flush=True)
        t0 = time.perf_counter()
        code = subprocess.call(cmd)
        results.append((name, code, time.perf_counter() - t0))
    print("=== summary")
    for name, code, wall in results:
        print(f"{name:24s} exit {code:3d}  {wall:8.1f} s")
    return 0 if all(code == 0 for _, code, _ in results) else 1


if __name__ == "__main__":
    sys.exit(main())
