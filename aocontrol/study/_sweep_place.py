"""Where the runs of a sweep go (private): whole cases to build on one worker each, the runs of
cases already calibrated on disk balanced over the workers, preferring the worker that holds the
scene in memory (:func:`aocontrol.study.sweep.run_sweep`)."""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from typing import Any

from aocontrol.study._sweep_spec import SweepRun

__all__ = ["_calibrated_cases", "_case_affinity", "_run_placement"]


def _case_affinity(client: Any, todo: Sequence[SweepRun]) -> dict[str, str]:
    """Worker address per case, balancing the run counts (greedy, largest case first).

    Workers cache the scenes and calibrations they build: runs of one case sent to one worker
    build its scene once. The restriction is loose (``allow_other_workers``: a lost worker never
    blocks a sweep); the local cluster runs without work stealing so that runs stay put, a
    remote scheduler may move them (then a worker builds a scene again). A case whose
    calibrations are already in the disk cache (:func:`_calibrated_cases`) gets no worker: any
    worker loads them in a moment, so its runs fill whichever worker is free (with whole cases
    per worker, five cases on two workers could not beat 5/3 of one process).
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


#: Cost of loading a scene's calibrations from the disk cache, in runs (placement weight: a
#: quick scene loads in about the CPU time of a 0.2-s quick run).
_LOAD_RUNS = 0.5


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


def _placement_cost(
    load: Mapping[str, float], held: Mapping[str, set], w: str, key: Any, n: int
) -> tuple[float, bool, str]:
    """Work of worker ``w`` after ``n`` more runs of scene ``key`` (then: a load, the name)."""
    miss = key not in held[w]
    return (load[w] + n + (_LOAD_RUNS if miss else 0.0), miss, w)


def _run_placement(client: Any, todo: Sequence[SweepRun]) -> dict[str, str]:
    """Worker address per run hash: whole cases to build (:func:`_case_affinity`), the others
    run by run, preferring the worker that holds the scene in memory.

    Runs whose calibrations are on disk go, case by case, largest first, to the worker with the
    least work counted in runs, a scene not in the worker's memory adding :data:`_LOAD_RUNS`
    (it is loaded from disk); while the busiest worker has more than one run (and a load) more
    than the idlest, one of its runs moves there. A worker that cannot be asked what it holds
    counts as holding nothing.
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
    load = dict.fromkeys(held, 0.0)
    for w in out.values():
        if w in load:
            load[w] += 1.0
    groups: dict[Any, list[SweepRun]] = {}
    for r in rest:
        groups.setdefault(_scene_key(r.settings) or r.settings["case"], []).append(r)
    placed: dict[str, list[str]] = {w: [] for w in held}
    for key, runs in sorted(groups.items(), key=lambda kv: (-len(kv[1]), str(kv[0]))):
        costs = {a: _placement_cost(load, held, a, key, len(runs)) for a in held}
        w = min(costs, key=costs.__getitem__)
        load[w] = costs[w][0]
        held[w].add(key)
        placed[w] += [r.hash for r in runs]
    by_hash = {r.hash: r for r in rest}
    while True:
        busy = max(load, key=lambda a: (load[a], a))
        idle = min(load, key=lambda a: (load[a], a))
        if not placed[busy] or load[busy] - load[idle] <= 1.0 + _LOAD_RUNS:
            break
        h = placed[busy].pop()
        key = _scene_key(by_hash[h].settings) or by_hash[h].settings["case"]
        load[busy] -= 1.0
        load[idle] += 1.0 + (0.0 if key in held[idle] else _LOAD_RUNS)
        held[idle].add(key)
        placed[idle].append(h)
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
