"""Benchmark: a data-driven bank of an ELT-class instrument, one process vs a local Dask cluster.

Measured in one run, on the same machine and the same inputs:

1. A synthetic 5,000-mode bank (:func:`synthetic_bank`: per-mode temporal PSDs of a von
   Karman-like model, a white noise floor, vibration lines on the six lowest modes; seeded).
   ``--modes N`` designs ``N`` of its modes: whole chunks of 32 neighbouring modes (the unit
   of work of :func:`aocontrol.synthesis.datadriven`) spread evenly over the bank, the first
   chunk (the vibrating modes) always in; every mode when ``N = 5000``.
2. The design in this process (``n_jobs=1``), then on a local cluster of ``--workers``
   processes (:func:`aocontrol.study.sweep.local_cluster`: one thread and one BLAS thread
   each) through ``datadriven(..., client=...)``. Printed: both wall times, the cluster's
   start-up, the ratio one process / cluster with and without the start-up (issue 34's goal:
   1.8x on 2 workers), each worker's peak resident memory against the estimate the design
   refuses beyond (:func:`aocontrol.synthesis._dd_dask.task_memory`), the workers' CPU time
   (its total against the one process's: the machinery's cost; over the wall time: the cores
   the workers got on a shared machine), and whether the two banks are identical bit for bit
   (they must be).
3. With ``N < 5000``: the extrapolation to the 5,000 modes: the first chunk timed alone, the
   other chunks' time scaled by the modes (the sampled chunks span the bank's mix of modes;
   the design grid, chosen from every designed mode's PSD peaks, may differ slightly from the
   full bank's), the cluster at the measured ratio.

``--quick``: two chunks away from the vibrating modes (40 modes: the bank's last chunk has 8),
a smoke test of the same path (its ratio means little with two tasks and cold workers).

With ``N < 5000`` the extrapolation times the first chunk (the vibrating modes, whose bound
starts make it the dearest) alone and scales the others' time.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time

import numpy as np

BANK_MODES = 5000
CHUNK = 32  # aocontrol.synthesis._dd_mode._CHUNK: the chunks sampled are the design's own
FS = 1000.0
LATENCY = 1.0
GOAL = 1.8


def synthetic_bank(
    n_modes: int = BANK_MODES, *, fs: float = FS, n_freqs: int = 513, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Disturbance and noise PSDs of a 39-m telescope's KL modes from a cheap model.

    Mode ``j`` (from 0, tip and tilt first) has radial order ``n ~ sqrt(2 (j + 1))``; its
    temporal PSD is flat below ``f_c = 0.3 (n + 1) v / D`` (``v`` = 10 m/s, ``D`` = 39 m,
    times a random factor in [0.8, 1.25]) and falls as ``f^(-17/3)`` above it, with the
    variance ``1e4 n^(-11/3)`` nm^2 (times a factor in [0.7, 1.4]). The six lowest modes carry
    one to three vibration lines (Lorentzians at 10 to 120 Hz, 1 % wide, 5 to 30 % of the
    mode's variance each). The noise is white, one level per mode. One-sided PSDs
    [nm^2/Hz] on ``n_freqs`` frequencies: 0 and log-spaced from 0.01 Hz to ``fs/2``.

    Parameters
    ----------
    n_modes : int
        Modes of the bank.
    fs : float
        Loop rate [Hz].
    n_freqs : int
        Frequencies of the PSDs.
    seed : int
        Seed of the generator (same seed, same bank, bit for bit).

    Returns
    -------
    freqs : ndarray, shape (n_freqs,)
    psd : ndarray, shape (n_modes, n_freqs)
    noise : ndarray, shape (n_modes,)
    """
    rng = np.random.default_rng(seed)
    f = np.concatenate([[0.0], np.geomspace(0.01, fs / 2, n_freqs - 1)])
    j = np.arange(1, n_modes + 1)
    n = np.maximum(np.floor((np.sqrt(8 * j + 1) - 1) / 2), 1.0)
    fc = 0.3 * (n + 1) * 10.0 / 39.0 * rng.uniform(0.8, 1.25, n_modes)
    var = 1e4 * n ** (-11 / 3) * rng.uniform(0.7, 1.4, n_modes)
    shape = (1.0 + (f[None, :] / fc[:, None]) ** 2) ** (-17 / 12)
    psd = var[:, None] * shape / np.trapezoid(shape, f, axis=1)[:, None]
    for i in range(min(6, n_modes)):
        for _ in range(int(rng.integers(1, 4))):
            f0 = rng.uniform(10.0, 120.0)
            w = 0.01 * f0
            psd[i] += var[i] * rng.uniform(0.05, 0.3) * (w / np.pi) / ((f - f0) ** 2 + w**2)
    noise = 1e-3 * var.mean() / fs * rng.uniform(0.5, 2.0, n_modes)
    return f, psd, noise


def sampled_modes(n: int, bank: int = BANK_MODES, first: bool = True) -> np.ndarray:
    """About ``n`` modes of the bank as whole chunks of :data:`CHUNK` spread evenly over it,
    the first chunk (the vibrating modes) in unless ``first`` is False."""
    n_chunks = -(-bank // CHUNK)
    take = min(n_chunks, max(1, -(-n // CHUNK)) + (0 if first else 1))
    starts = np.unique(np.linspace(0, n_chunks - 1, take).round().astype(int)) * CHUNK
    starts = starts if first else starts[1:]
    return np.concatenate([np.arange(s, min(s + CHUNK, bank)) for s in starts])


def _load() -> str:
    return "load " + " / ".join(f"{x:.1f}" for x in os.getloadavg())


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _peak_rss_mb() -> float:
    """This process's own peak resident memory [MB]: ``VmHWM`` (Linux), not ``ru_maxrss``,
    which a process started by fork and exec inherits from its parent (a Dask worker would
    report the peak of the process that started the cluster)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--modes", type=int, default=BANK_MODES, help="modes designed (default all)")
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--order", type=int, default=5, help="controller order (default 5)")
    p.add_argument("--freqs", type=int, default=513, help="PSD frequencies (default 513)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="96 modes: a smoke test")
    args = p.parse_args(argv)
    modes = sampled_modes(2 * CHUNK if args.quick else args.modes, first=not args.quick)

    import warnings

    from distributed import Client

    from aocontrol import loop_plant
    from aocontrol.study.sweep import local_cluster
    from aocontrol.synthesis import GridResolutionWarning, datadriven

    warnings.simplefilter("ignore", GridResolutionWarning)  # the same for both sides
    f, psd_all, noise_all = synthetic_bank(fs=FS, n_freqs=args.freqs, seed=args.seed)
    psd, noise = psd_all[modes], noise_all[modes]
    plant = loop_plant(FS, LATENCY)
    kw = dict(order=args.order, noise_psd=noise, progress=False)
    print(f"machine: {_cpu_model()}, {os.cpu_count()} cores; Python {platform.python_version()}")
    print(
        f"bank: {BANK_MODES} synthetic modes (von Karman-like, noise floor, vibrations on modes "
        f"0-5; seed {args.seed}), {args.freqs} frequencies, fs {FS:g} Hz, latency "
        f"{LATENCY:g} frame, order {args.order}; designing {modes.size} modes "
        f"({-(-modes.size // CHUNK)} chunks of up to {CHUNK}, spread over the bank"
        f"{'' if modes[0] == 0 else ', not the vibrating modes'})"
    )

    print(f"one process: designing ... ({_load()})", flush=True)
    t0, c0 = time.perf_counter(), time.process_time()
    serial = datadriven(plant, f, psd, n_jobs=1, **kw)
    t_serial, c_serial = time.perf_counter() - t0, time.process_time() - c0
    print(
        f"one process: {t_serial:.1f} s wall, {c_serial:.1f} s CPU, "
        f"{1e3 * t_serial / modes.size:.0f} ms per mode; peak memory {_peak_rss_mb():.0f} MB "
        f"({_load()})",
        flush=True,
    )

    from aocontrol.synthesis._datadriven import _prepare
    from aocontrol.synthesis._dd_dask import task_memory  # the estimate the design refuses by

    setup = _prepare(plant, f, psd, noise_psd=noise, order=args.order)
    parts = [setup.items[i : i + CHUNK] for i in range(0, len(setup.items), CHUNK)]
    estimate = max(task_memory(setup.ctx, len(c), any(i.bound_start for i in c)) for c in parts)

    t0 = time.perf_counter()
    with local_cluster(args.workers) as cluster, Client(cluster) as client:
        startup = time.perf_counter() - t0
        limit = min(w["memory_limit"] for w in client.scheduler_info()["workers"].values())
        print(f"cluster: {args.workers} workers up in {startup:.1f} s ({_load()})", flush=True)
        cpu0 = client.run(time.process_time)
        t1 = time.perf_counter()
        dask = datadriven(plant, f, psd, client=client, **kw)
        t_dask = time.perf_counter() - t1
        cpu = {w: c - cpu0.get(w, 0.0) for w, c in client.run(time.process_time).items()}
        peaks = client.run(_peak_rss_mb)
    same = all(
        np.array_equal(x, y)
        for x, y in (
            (serial.controller.b, dask.controller.b),
            (serial.controller.a, dask.controller.a),
            (serial.residual_variance, dask.residual_variance),
            (serial.residual_variance_fine, dask.residual_variance_fine),
        )
    )
    ratio, ratio_up = t_serial / t_dask, t_serial / (t_dask + startup)
    print(
        f"cluster: {t_dask:.1f} s wall ({1e3 * t_dask / modes.size:.0f} ms per mode); one "
        f"process / cluster {ratio:.2f}x ({ratio_up:.2f}x with the start-up); goal {GOAL}x: "
        f"{'met' if ratio >= GOAL else 'not met'} ({_load()})"
    )
    total = sum(cpu.values())
    print(
        f"cluster CPU: {total:.1f} s in all, {100 * (total / c_serial - 1):+.1f} % on one "
        "process's; per worker "
        + ", ".join(f"{c:.1f}" for c in sorted(cpu.values()))
        + f" s; the workers had {total / t_dask:.2f} cores of {os.cpu_count()}; with a free "
        f"core per worker and the chunks perfectly shared, one process / cluster would be at "
        f"most {c_serial * len(cpu) / total:.2f}x"
    )
    print(
        "memory per worker: peak "
        + ", ".join(f"{v:.0f}" for v in sorted(peaks.values()))
        + f" MB; estimate (refused beyond) {estimate / 1e6:.0f} MB; worker limit "
        f"{limit / 1e9:.1f} GB"
    )
    print(f"banks identical bit for bit: {same}")
    if modes.size < BANK_MODES and modes[0] == 0 and modes.size > CHUNK:
        # The first chunk (six modes with lines: the bound starts) costs far more than the
        # others: timed alone (its own call, its own design grid) and counted once.
        t0 = time.perf_counter()
        datadriven(plant, f, psd[:CHUNK], n_jobs=1, **{**kw, "noise_psd": noise[:CHUNK]})
        t_first = time.perf_counter() - t0
        k = (BANK_MODES - CHUNK) / (modes.size - CHUNK)
        est_serial = t_first + k * max(t_serial - t_first, 0.0)
        est_dask = est_serial / ratio
        print(
            f"extrapolated to {BANK_MODES} modes: the first chunk {t_first:.1f} s alone in one "
            f"process, the other {modes.size - CHUNK} modes x{k:.1f}: one process "
            f"{est_serial / 60:.1f} min, cluster {est_dask / 60:.1f} min at the measured "
            f"ratio ({_load()})"
        )
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
