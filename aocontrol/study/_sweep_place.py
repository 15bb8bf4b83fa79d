"""Where the runs of a sweep go (private): the first run of each case to build on a worker of its
own (its other runs wait for it, then go to any worker: :func:`_after_builds`), the runs of
cases already calibrated on disk balanced over the workers by their expected work, preferring
the worker that holds the scene in memory (:func:`aocontrol.study.sweep.run_sweep`)."""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from typing import Any

from aocontrol.study._sweep_spec import SweepRun

__all__ = ["_after_builds", "_calibrated_cases", "_case_affinity", "_run_placement"]


def _case_affinity(client: Any, todo: Sequence[SweepRun]) -> dict[str, str]:
    """Worker address per case, balancing the run counts (greedy, largest case first).

    Workers cache the scenes and calibrations they build: runs of one case sent to one worker
    build its scene once. The restriction is loose (``allow_other_workers``: a lost worker never
    blocks a sweep); the local cluster runs without work stealing so that runs stay put, a
    remote scheduler may move them (then a worker builds a scene again). A case whose
    calibrations are already in the disk cache (:func:`_calibrated_cases`) gets no worker: any
    worker loads them in a moment, so its runs fill whichever worker is free (with whole cases
    per worker, five cases on two workers could not beat 5/3 of one process). The sweep sends
    only a case's first run there; the others follow it once it is done (:func:`_after_builds`).
    """
    try:
        workers = sorted(client.scheduler_info()["workers"])
    except Exception:  # an older or unusual scheduler: no affinity, plain scheduling
        return {}
    if len(workers) < 2:
        return {}
    counts: dict[str, int] = {}
    free = _calibrated_cases(todo)
    for r in todo:
        if r.settings["case"] not in free:
            counts[r.settings["case"]] = counts.get(r.settings["case"], 0) + 1
    load = dict.fromkeys(workers, 0)
    out = {}
    for case in sorted(counts, key=lambda c: (-counts[c], c)):
        w = min(workers, key=lambda a: (load[a], a))
        out[case] = w
        load[w] += counts[case]
    return out


#: Expected cost of a run in fast frames (:func:`_run_cost`): a fixed part (the quick
#: calibration run, the controller's design, writing the result) plus one per fast frame, and
#: the cost of loading a scene's calibrations from the disk cache. Measured (one process,
#: quick scenes, integrator, standalone): 0.24 ms of CPU per 3-kHz frame, 0.38 s fixed, a
#: scene loaded in 0.37 s; red5-best (300 Hz) 0.5 s per 2-s run, bright1-worst (3 kHz) 1.9 s.
_RUN_FIXED_FRAMES = 1600.0
_LOAD_FRAMES = 1500.0


def _run_cost(settings: Mapping) -> float | None:
    """Expected cost of a run [fast frames]: fixed part + (start-up + seconds) x the fastest
    stage rate of its case (with its overrides); None if not a case of the package."""
    from aocontrol.study.cases import apply_overrides, load_case

    try:
        c = apply_overrides(
            load_case(settings["case"]), dict(settings.get("overrides") or {}) or None
        )
        seconds = float(settings["seconds"]) + float(c.science.startup)
        return _RUN_FIXED_FRAMES + seconds * max(float(c.stage1.fs), float(c.stage2.fs))
    except (ValueError, OSError, KeyError, TypeError, AttributeError):
        return None


def _scenes_in_memory() -> list[str]:
    """Worker side: disk-cache keys of the calibrations this process holds in memory."""
    scene = sys.modules.get("aocontrol.study.scene")
    if scene is None:
        return []
    return ["scene geometry " + key for key in scene._GEOMETRY_CACHE]


def _scene_key(settings: Mapping) -> str | None:
    """The disk-cache key of a run's calibrations (None: not a case of the package)."""
    from aocontrol.study.cases import apply_overrides, load_case
    from aocontrol.study.scene import geometry_cache_key

    try:
        c = apply_overrides(
            load_case(settings["case"]), dict(settings.get("overrides") or {}) or None
        )
        return geometry_cache_key(c, bool(settings.get("quick", False)))
    except (ValueError, OSError, KeyError, TypeError):
        return None


def _run_placement(client: Any, todo: Sequence[SweepRun]) -> dict[str, str]:
    """Worker address per run hash: whole cases to build (:func:`_case_affinity`), the others
    run by run, balancing the expected work and preferring the worker that holds the scene.

    Work is counted in fast frames (:func:`_run_cost`: the runs of a 300-Hz case cost a
    fifth of a 3-kHz case's), a scene not in a worker's memory adding :data:`_LOAD_FRAMES`
    (it is loaded from disk); runs another runner describes count one unit each and a load
    half of one. Runs whose calibrations are on disk go, scene by scene, costliest first, to
    the worker with the least work after them; then, while moving one run from the busiest
    worker to another, or swapping one of its runs with another worker's, lowers the larger
    of the two workers' work below the busiest's (loads included), the best such change is
    made. A worker that cannot be asked what it holds counts as holding nothing.
    """
    pinned = _case_affinity(client, todo)
    out = {r.hash: pinned[r.settings["case"]] for r in todo if r.settings["case"] in pinned}
    rest = [r for r in todo if r.settings["case"] not in pinned]
    try:
        held = {w: set(keys) for w, keys in client.run(_scenes_in_memory).items()}
    except Exception:  # an older or unusual scheduler: no placement, plain scheduling
        return out
    if len(held) < 2 or not rest:
        return out
    costs = {r.hash: _run_cost(r.settings) for r in todo}
    if any(c is None for c in costs.values()):  # not all ours: count runs
        costs, load_cost = dict.fromkeys(costs, 1.0), 0.5
    else:
        load_cost = _LOAD_FRAMES
    load = dict.fromkeys(held, 0.0)
    for h, w in out.items():
        if w in load:
            load[w] += costs[h]
    keys = {r.hash: _scene_key(r.settings) or r.settings["case"] for r in rest}
    groups: dict[Any, list[SweepRun]] = {}
    for r in rest:
        groups.setdefault(keys[r.hash], []).append(r)
    placed: dict[str, list[str]] = {w: [] for w in held}

    def after(w: str, key: Any, work: float) -> float:
        return load[w] + work + (0.0 if key in held[w] else load_cost)

    def total(runs: list[SweepRun]) -> float:
        return sum(costs[r.hash] for r in runs)

    for key, runs in sorted(groups.items(), key=lambda kv: (-total(kv[1]), str(kv[0]))):
        w = min(held, key=lambda a: (after(a, key, total(runs)), key not in held[a], a))
        load[w] = after(w, key, total(runs))
        held[w].add(key)
        placed[w] += [r.hash for r in runs]
    while True:  # local search: a move or a swap that lowers the busiest worker's work
        busy = max(load, key=lambda a: (load[a], a))
        best = (load[busy] * (1 - 1e-9), None)
        for h in placed[busy]:
            for w in held:
                if w == busy:
                    continue
                # move h to w (the busy worker keeps the scene it loaded)
                cand = max(load[busy] - costs[h], after(w, keys[h], costs[h]))
                if cand < best[0]:
                    best = (cand, (h, w, None))
                for g in placed[w]:  # swap h and g
                    b_new = after(busy, keys[g], costs[g]) - costs[h]
                    w_new = after(w, keys[h], costs[h]) - costs[g]
                    if max(b_new, w_new) < best[0]:
                        best = (max(b_new, w_new), (h, w, g))
        if best[1] is None:
            break
        h, w, g = best[1]
        load[w] = after(w, keys[h], costs[h]) - (costs[g] if g else 0.0)
        load[busy] -= costs[h]
        placed[busy].remove(h)
        placed[w].append(h)
        held[w].add(keys[h])
        if g is not None:
            load[busy] = after(busy, keys[g], costs[g])
            placed[w].remove(g)
            placed[busy].append(g)
            held[busy].add(keys[g])
    for w, hashes in placed.items():
        out.update(dict.fromkeys(hashes, w))
    return out


def _calibrated_cases(todo: Sequence[SweepRun]) -> set[str]:
    """Cases every run of which finds its scene's calibrations in the disk cache.

    A run whose settings are not a case of the package (another runner's) counts as not
    calibrated (its case keeps its worker).
    """
    from aocontrol.study._cache import is_cached

    out: dict[str, bool] = {}
    for r in todo:
        case = r.settings["case"]
        if out.get(case, True):
            key = _scene_key(r.settings)
            out[case] = key is not None and is_cached(key)
    return {case for case, ok in out.items() if ok}


def _after_builds(todo: Sequence[SweepRun]) -> dict[str, list[SweepRun]]:
    """The runs to submit once their case's first run is done, by that first run's hash.

    A case whose calibrations are not on disk (:func:`_calibrated_cases`) is built by its
    first run, on the worker :func:`_case_affinity` gives it. Its other runs are held back
    until that run is done, then go to any worker (a free one loads the calibrations from
    disk): submitted with the first, they would all wait for the same worker while the other
    sits idle once its own cases are built, and a run moved to another worker would block
    on the lock of the entry being built.
    """
    free = _calibrated_cases(todo)
    first: dict[str, str] = {}
    out: dict[str, list[SweepRun]] = {}
    for r in todo:
        case = r.settings["case"]
        if case in free:
            continue
        if case in first:
            out[first[case]].append(r)
        else:
            first[case] = r.hash
            out[r.hash] = []
    return {h: runs for h, runs in out.items() if runs}
