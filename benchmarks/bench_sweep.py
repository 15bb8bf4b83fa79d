"""Benchmark: a sweep of the five science cases on a local Dask cluster vs one process.

Measured in one run, on the same machine:

1. The five cases (``bright1-best``, ``bright1-worst``, ``red1-fast``, ``red3-medium``,
   ``red5-best``) x ``--controllers`` x ``--schemes`` x ``--seeds`` with short, quick runs
   (``--seconds``), first one after the other in this process (the runner called directly,
   writing the same results files), then through :func:`aocontrol.study.sweep.run_sweep` on a
   ``LocalCluster`` (``--workers`` processes, 1 thread each). Printed: both wall times, the
   cluster's start-up, and the ratio serial / cluster with and without the start-up (on a
   2-core machine at most about 2x).
2. Scheduler overhead per run: ``--trivial`` runs that only write a tiny file, through the
   same cluster (``run_sweep``: validation, submission, worker-side atomic write, summary
   table) vs called directly, after a warm-up sweep (the workers' first task imports
   aocontrol, timed apart); the difference per run is the price of the machinery.

Scene calibrations are cached on disk (:mod:`aocontrol.study._cache`), shared by the workers
and later runs. Cold: each side starts with an empty cache folder of its own (the cluster's
workers share one, the one process has another) and nothing in memory, so each side builds
every calibration once; the cluster's workers build different cases' calibrations in parallel
(one BLAS thread each), the one process builds them one after the other (BLAS on every core).
Warm: a second sweep with new seeds, every calibration on disk and in the processes' memory:
the ratio of the runs themselves. Cases already on disk are not pinned to a worker
(:func:`aocontrol.study.sweep.run_sweep`), so the runs fill both workers. The cluster's
results are checked equal to the one process's (same settings, same numbers).

``--quick`` runs two cases, one seed, and fewer trivial runs (smoke test).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time

CASES = ("bright1-best", "bright1-worst", "red1-fast", "red3-medium", "red5-best")


def trivial_run(settings: dict, path: pathlib.Path) -> None:
    """A run that costs nothing: one small HDF5 file with the settings."""
    import json

    import h5py

    with h5py.File(path, "w") as f:
        f.attrs["settings"] = json.dumps(settings)


def trivial_read(path: pathlib.Path) -> dict:
    """Summary row of a trivial run."""
    import json

    import h5py

    with h5py.File(path, "r") as f:
        return {"settings": json.loads(f.attrs["settings"])}


def _spec(cases, controllers, schemes, seeds, seconds, quick):
    from aocontrol.study.sweep import SweepSpec

    return SweepSpec(
        cases=tuple(cases),
        controllers=tuple(controllers),
        schemes=tuple(schemes),
        seeds=tuple(seeds),
        seconds=seconds,
        quick=quick,
        source="bench_sweep",
    )


def _serial(
    runner, runs, out: pathlib.Path, cpu: list | None = None, parts: list | None = None
) -> float:
    """Every run one after the other in this process [s]; each run's CPU [s] into ``cpu``,
    its parts (cache, kernel counts: ``aocontrol.study._cache.process_usage``) into ``parts``."""
    from aocontrol.study._cache import process_usage as _usage

    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for r in runs:
        c0, u0 = time.process_time(), _usage()
        runner.run(dict(r.settings), out / f"{r.hash}.h5")
        if cpu is not None:
            cpu.append(time.process_time() - c0)
        if parts is not None:
            parts.append({k: v - u0[k] for k, v in _usage().items()})
    return time.perf_counter() - t0


def _cpu_outside() -> tuple[float, float]:
    """CPU [s] so far of this process (client, scheduler and nannies: the local cluster runs
    them in this process) and of its children (the worker processes)."""
    import psutil

    me = psutil.Process()
    workers = 0.0
    for child in me.children():
        try:
            t = child.cpu_times()
            workers += t.user + t.system
        except psutil.Error:
            pass
    return time.process_time(), workers


def _sweep(spec, out, cluster, runner):
    """``run_sweep`` on ``cluster``; prints the CPU this process and the workers used."""
    from aocontrol.study.sweep import run_sweep

    a = _cpu_outside()
    rep = run_sweep(spec, out=out, scheduler=cluster.scheduler_address, runner=runner)
    b = _cpu_outside()
    print(
        f"  during the sweep: this process (client, scheduler, nannies) {b[0] - a[0]:.2f} s "
        f"CPU, the worker processes {b[1] - a[1]:.2f} s CPU",
        flush=True,
    )
    return rep


def _parts_line(parts: list) -> str:
    """Sums of the runs' parts: cache lock waits, loads, builds, writes; kernel counts."""
    tot: dict = {}
    for p in parts:
        for k, v in (p or {}).items():
            tot[k] = tot.get(k, 0.0) + v
    g = tot.get
    return (
        f"lock wait {g('lock_wait_s', 0):.2f} s; loads {g('load_n', 0):.0f} "
        f"({g('load_s', 0):.2f} s, {g('load_cpu_s', 0):.2f} s CPU); builds "
        f"{g('build_n', 0):.0f} ({g('build_s', 0):.1f} s, {g('build_cpu_s', 0):.1f} s CPU); "
        f"writes {g('write_n', 0):.0f} ({g('write_s', 0):.2f} s, {g('write_cpu_s', 0):.2f} s "
        f"CPU); user {g('user_s', 0):.1f} s, sys {g('sys_s', 0):.1f} s, page faults "
        f"{g('minflt', 0) / 1e3:.0f}k, preempted {g('nivcsw', 0):.0f}x, "
        f"blocked {g('nvcsw', 0):.0f}x"
    )


def _breakdown(
    label: str,
    report,
    wall: float,
    serial_cpu: list,
    serial_parts: list | None = None,
    serial_by_hash: dict | None = None,
) -> None:
    """Per worker: runs, busy wall and CPU, its parts; against the one process's."""
    per: dict = {}
    for t in report.timings:
        w = per.setdefault(t["worker"], {"runs": 0, "wall": 0.0, "cpu": 0.0, "parts": []})
        w["runs"] += 1
        w["wall"] += t["seconds"]
        w["cpu"] += t["cpu_s"]
        w["thread"] = w.get("thread", 0.0) + (t.get("thread_cpu_s") or 0.0)
        w["parts"].append(t.get("parts"))
    for i, (_, w) in enumerate(sorted(per.items())):
        print(
            f"  {label} worker {i}: {w['runs']} runs, busy {w['wall']:.1f} s wall, "
            f"{w['cpu']:.1f} s CPU ({w['cpu'] / max(w['runs'], 1):.2f} s CPU/run); "
            f"idle {wall - w['wall']:.1f} s of the sweep's {wall:.1f} s; the runs' own "
            f"thread {w['thread']:.1f} s CPU\n"
            f"    {_parts_line(w['parts'])}",
            flush=True,
        )
    if serial_parts:
        print(f"  {label} one process: {_parts_line(serial_parts)}", flush=True)
    if serial_by_hash:
        # the same runs' CPU in a worker and in the one process, runs that loaded nothing
        same = [
            (t["cpu_s"], serial_by_hash[t["hash"]])
            for t in report.timings
            if t["hash"] in serial_by_hash and not (t.get("parts") or {}).get("load_n")
        ]
        if same:
            print(
                f"  {label}: {len(same)} runs that loaded no calibration: CPU in the workers "
                f"{sum(a for a, _ in same):.2f} s, the same runs in the one process "
                f"{sum(b for _, b in same):.2f} s",
                flush=True,
            )
    cpu_cluster = sum(w["cpu"] for w in per.values())
    if serial_cpu:
        print(
            f"  {label}: CPU per run, cluster {cpu_cluster / max(len(report.timings), 1):.2f} s,"
            f" one process {sum(serial_cpu) / len(serial_cpu):.2f} s; slowest worker "
            f"{max((w['wall'] for w in per.values()), default=0.0):.1f} s busy of "
            f"{wall:.1f} s wall",
            flush=True,
        )


def _warm_only(args, cases, seeds) -> int:
    """Warm sweeps only: cluster vs one process on calibrations already in memory."""
    import logging

    from aocontrol.study.scene import build_scene
    from aocontrol.study.sweep import default_runner, local_cluster, run_sweep, sweep_table

    logging.basicConfig(level=logging.WARNING)
    runner = default_runner()
    print(
        f"warm only: cases={list(cases)}, controllers={args.controllers}, "
        f"schemes={args.schemes}, seeds={seeds}, seconds={args.seconds}, quick=True, "
        f"workers={args.workers}; calibrations from {os.environ.get('AOCONTROL_CACHE')}",
        flush=True,
    )
    with (
        tempfile.TemporaryDirectory(prefix="bench-sweep-") as tmp,
        local_cluster(args.workers) as cluster,
    ):
        tmp = pathlib.Path(tmp)
        # untimed: every scene built (or read from disk) in some worker and in this process
        prime = _spec(cases, args.controllers, args.schemes, range(seeds), 0.05, True)
        run_sweep(prime, out=tmp / "prime", scheduler=cluster.scheduler_address, runner=runner)
        for case in cases:
            build_scene(case, quick=True)
        ratios = []
        for i in range(args.repeat):
            base = seeds * (i + 1)
            spec = _spec(
                cases, args.controllers, args.schemes, range(base, base + seeds), args.seconds, True
            )
            cpu: list = []
            parts = []
            for part in ("serial", "cluster") if i % 2 else ("cluster", "serial"):
                if part == "serial":
                    t_serial = _serial(runner, spec.runs(), tmp / f"serial{i}", cpu)
                    parts.append(f"one process {t_serial:.1f} s")
                else:
                    rep = _sweep(spec, tmp / f"cluster{i}", cluster, runner)
                    parts.append(f"cluster {rep.wall_s:.1f} s")
            serial_rows = {r["hash"]: r for r in sweep_table(tmp / f"serial{i}", runner=runner)}
            diff = max(
                abs(serial_rows[row["hash"]][k] - row[k]) / abs(row[k])
                for row in rep.table
                for k in ("strehl", "mean_contrast_4_6", "residual_rms_nm")
            )
            print(f"warm {i}: cluster vs one process, largest relative difference {diff:.1e}")
            ratios.append(t_serial / rep.wall_s)
            print(f"warm {i}: {', '.join(parts)}: {ratios[-1]:.2f}x", flush=True)
            _breakdown(
                f"warm {i}",
                rep,
                rep.wall_s,
                cpu,
                None,
                dict(zip([r.hash for r in spec.runs()], cpu, strict=True)),
            )
        print(f"warm ratios one process / cluster: {', '.join(f'{r:.2f}x' for r in ratios)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--controllers", nargs="+", default=["integrator"])
    parser.add_argument("--schemes", nargs="+", default=["standalone"])
    # Two seeds: ten runs fill two workers evenly (five equal runs on two workers cannot
    # beat 5/3 of one process, below the warm goal of 1.7x).
    parser.add_argument("--seeds", type=int, default=2, help="seeds per configuration")
    parser.add_argument("--seconds", type=float, default=0.2, help="simulated time per run [s]")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--trivial", type=int, default=40, help="trivial runs (overhead)")
    parser.add_argument("--skip-cases", action="store_true", help="only the overhead part")
    parser.add_argument(
        "--serial-first",
        action="store_true",
        help="time the one-process runs before the cluster's (default after): run both orders "
        "on a busy machine, whose load drifts between the two parts",
    )
    parser.add_argument(
        "--warm-only",
        action="store_true",
        help="only the warm comparison, on the calibrations in $AOCONTROL_CACHE (built by an "
        "untimed first sweep if missing), --repeat times, the two orders alternating",
    )
    parser.add_argument("--repeat", type=int, default=1, help="warm comparisons (--warm-only)")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        cases, seeds, n_trivial = CASES[:2], 1, min(args.trivial, 12)
    else:
        cases, seeds, n_trivial = CASES, args.seeds, args.trivial

    if args.warm_only:
        return _warm_only(args, cases, seeds)

    import logging

    from aocontrol.study.scene import clear_scene_cache
    from aocontrol.study.sweep import SweepRunner, local_cluster, run_sweep, sweep_table

    logging.basicConfig(level=logging.WARNING)
    print(
        f"configuration: cases={list(cases)}, controllers={args.controllers}, "
        f"schemes={args.schemes}, seeds={seeds}, seconds={args.seconds}, quick=True, "
        f"workers={args.workers} (1 thread each)",
        flush=True,
    )
    saved_cache = os.environ.get("AOCONTROL_CACHE")
    with tempfile.TemporaryDirectory(prefix="bench-sweep-") as tmp:
        tmp = pathlib.Path(tmp)
        # Empty calibration caches: one for the cluster's workers (they inherit it), one for
        # this process's runs (set before them).
        cache_cluster, cache_serial = tmp / "cache-cluster", tmp / "cache-serial"
        os.environ["AOCONTROL_CACHE"] = str(cache_cluster)
        t0 = time.perf_counter()
        # run_sweep's own local cluster (BLAS threads, no work stealing), kept for every part
        cluster_cm = local_cluster(args.workers)
        cluster = cluster_cm.__enter__()
        t_start = time.perf_counter() - t0
        os.environ["AOCONTROL_CACHE"] = str(cache_serial)
        clear_scene_cache()
        try:
            # ---- scheduler overhead: trivial runs through the cluster vs direct calls
            trivial = SweepRunner(run=trivial_run, read=trivial_read)
            # warm-up: the workers import aocontrol on their first task (counted apart)
            spec_w = _spec(["w"], ["c"], ["s"], range(2 * args.workers), 1.0, False)
            t_warm = run_sweep(
                spec_w, out=tmp / "warm-up", scheduler=cluster.scheduler_address, runner=trivial
            ).wall_s
            print(
                f"cluster start-up {t_start:.1f} s; first {2 * args.workers} trivial runs "
                f"(workers importing aocontrol) {t_warm:.1f} s",
                flush=True,
            )
            spec_t = _spec(["t"], ["c"], ["s"], range(n_trivial), 1.0, False)
            runs_t = spec_t.runs()
            t_direct = _serial(trivial, runs_t, tmp / "trivial-direct")
            report = run_sweep(
                spec_t,
                out=tmp / "trivial-cluster",
                scheduler=cluster.scheduler_address,
                runner=trivial,
            )
            assert len(report.ran) == n_trivial, report
            t_cluster_trivial = report.wall_s
            per_direct = t_direct / n_trivial
            per_cluster = t_cluster_trivial / n_trivial
            print(
                f"trivial runs: {n_trivial}; direct {1e3 * per_direct:.2f} ms/run, through the "
                f"cluster {1e3 * per_cluster:.1f} ms/run (wall / runs, {args.workers} workers); "
                f"scheduler overhead {1e3 * (per_cluster - per_direct):.1f} ms/run",
                flush=True,
            )
            if args.skip_cases:
                print(f"cluster start-up: {t_start:.1f} s")
                return 0
            # ---- the five cases
            from aocontrol.study.sweep import default_runner

            runner = default_runner()
            spec = _spec(cases, args.controllers, args.schemes, range(seeds), args.seconds, True)
            runs = spec.runs()
            hashes = [r.hash for r in runs]
            cpu_cold: list = []
            cpu_warm: list = []
            parts_cold: list = []
            parts_warm: list = []
            if args.serial_first:
                t_serial = _serial(runner, runs, tmp / "cases-serial", cpu_cold, parts_cold)
                print(f"one process: {len(runs)} runs in {t_serial:.1f} s", flush=True)
            t_par = _sweep(spec, tmp / "cases-cluster", cluster, runner)
            if t_par.failed:
                print("failed runs:", t_par.failed)
                return 1
            t_cluster = t_par.wall_s
            print(f"cluster: {len(runs)} runs in {t_cluster:.1f} s", flush=True)
            if not args.serial_first:
                t_serial = _serial(runner, runs, tmp / "cases-serial", cpu_cold, parts_cold)
                print(f"one process: {len(runs)} runs in {t_serial:.1f} s", flush=True)
            _breakdown(
                "cold",
                t_par,
                t_cluster,
                cpu_cold,
                parts_cold,
                dict(zip(hashes, cpu_cold, strict=True)),
            )
            # warm: new seeds, every calibration on disk and in the processes' memory
            spec_w = _spec(
                cases, args.controllers, args.schemes, range(seeds, 2 * seeds), args.seconds, True
            )
            warm = _sweep(spec_w, tmp / "warm-cluster", cluster, runner)
            t_cluster_warm = warm.wall_s
            t_serial_warm = _serial(
                runner, spec_w.runs(), tmp / "warm-serial", cpu_warm, parts_warm
            )
            print(
                f"warm caches: cluster {t_cluster_warm:.1f} s, one process {t_serial_warm:.1f} s",
                flush=True,
            )
            _breakdown(
                "warm",
                warm,
                t_cluster_warm,
                cpu_warm,
                parts_warm,
                {r.hash: c for r, c in zip(spec_w.runs(), cpu_warm, strict=True)},
            )
            # a scene's calibrations read from the disk cache (what a worker pays for a case
            # it does not hold in memory), against a warm run
            clear_scene_cache()
            from aocontrol.study.scene import build_scene

            c0 = time.process_time()
            build_scene(cases[0], quick=True)
            print(
                f"scene {cases[0]} loaded from the disk cache: "
                f"{time.process_time() - c0:.2f} s CPU (a warm run: "
                f"{sum(cpu_warm) / len(cpu_warm):.2f} s CPU)",
                flush=True,
            )
        finally:
            cluster_cm.__exit__(None, None, None)
            if saved_cache is None:
                os.environ.pop("AOCONTROL_CACHE", None)
            else:
                os.environ["AOCONTROL_CACHE"] = saved_cache
        # same settings, same numbers: the cluster's results equal the one process's, to
        # rounding (the workers' BLAS has one thread, this process's every core, which splits
        # some reductions differently)
        serial_rows = {r["hash"]: r for r in sweep_table(tmp / "cases-serial", runner=runner)}
        cluster_rows = {r["hash"]: r for r in t_par.table}
        worst = max(
            abs(serial_rows[h][k] - row[k]) / abs(row[k])
            for h, row in cluster_rows.items()
            for k in ("strehl", "mean_contrast_4_6", "residual_rms_nm")
        )
        same = all(
            serial_rows[h].get("strehl") == row.get("strehl") for h, row in cluster_rows.items()
        )
        print(
            f"cluster results vs the one process's (calibrations built separately, with 1 and "
            f"with every BLAS thread): largest relative difference {worst:.1e} (Strehl, "
            f"contrast, residual); Strehl bit for bit: {same}"
        )
        rows = {r["hash"]: r for r in t_par.table}
        print(
            f"{'case':16s}{'controller':12s}{'scheme':12s}{'seed':>5s}{'strehl':>9s}{'C(4-6)':>11s}"
        )
        for r in runs:
            row = rows[r.hash]
            s = r.settings
            strehl = row.get("strehl", float("nan"))
            contrast = row.get("mean_contrast_4_6", float("nan"))
            print(
                f"{s['case']:16s}{s['controller']:12s}{s['scheme']:12s}{s['seed']:5d}"
                f"{strehl:9.3f}{contrast:11.3g}"
            )
        print(
            f"\nwall time: one process {t_serial:.1f} s, local cluster {t_cluster:.1f} s "
            f"(+ {t_start:.1f} s start-up)\n"
            f"ratio one process / cluster: {t_serial / t_cluster:.2f}x without start-up, "
            f"{t_serial / (t_cluster + t_start):.2f}x with it ({args.workers} workers, "
            f"{os.cpu_count()} cores)\n"
            f"warm (calibrations cached; new seeds): {t_serial_warm / t_cluster_warm:.2f}x "
            f"(cluster {t_cluster_warm:.1f} s, one process {t_serial_warm:.1f} s)\n"
            f"scheduler overhead per run: {1e3 * (per_cluster - per_direct):.1f} ms "
            f"(trivial runs, {n_trivial} of them)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
