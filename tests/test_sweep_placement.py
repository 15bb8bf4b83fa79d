"""Where a sweep's runs go (aocontrol.study._sweep_place): a case to build on one worker, its
other runs held until its first is done, calibrated cases balanced by expected work.

No public call shows the placement: :func:`aocontrol.study.sweep.run_sweep` hands it to a Dask
client, and a real cluster would build real calibrations. So these tests give the placement a
stub client (the workers it lists and the scenes each holds in memory) and put stand-in entries
in the disk cache under a case's real key (the public ``geometry_cache_key``), the one thing
the placement reads from the disk.
"""

from __future__ import annotations

import itertools

import pytest

from aocontrol.study._cache import cached
from aocontrol.study._sweep_place import (
    _LOAD_FRAMES,
    _after_builds,
    _calibrated_cases,
    _case_affinity,
    _run_cost,
    _run_placement,
)
from aocontrol.study.cases import load_case
from aocontrol.study.scene import geometry_cache_key
from aocontrol.study.sweep import SweepSpec


@pytest.fixture
def on_disk(tmp_path, monkeypatch):
    """``on_disk(name, quick)``: the case's calibrations in a fresh disk cache (a stand-in
    entry under its real key)."""
    monkeypatch.setenv("AOCONTROL_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("AOCONTROL_CACHE_MAX_GB", raising=False)
    monkeypatch.delenv("AOCONTROL_CACHE_MAX_DAYS", raising=False)

    def put(name: str, quick: bool) -> str:
        key = geometry_cache_key(load_case(name), quick)
        cached(key, lambda: {"stand-in": True})
        return key

    return put


class _Workers:
    """A stub Dask client: two workers, ``held`` the scene keys each has in memory."""

    def __init__(self, held: dict | None = None):
        self.held = held or {"tcp://a": [], "tcp://b": []}

    def scheduler_info(self):
        return {"workers": dict.fromkeys(self.held, {})}

    def run(self, func):
        return {w: list(keys) for w, keys in self.held.items()}


def test_sweep_pins_only_cases_whose_calibrations_are_not_on_disk(on_disk):
    # Affinity keeps the runs of a case to build its calibrations once; a case already on
    # disk is free (any worker loads it), so the runs balance over the workers.
    spec = SweepSpec(
        cases=("bright1-best", "red1-fast", "red3-medium"),
        controllers=("reference",),
        schemes=("standalone",),
        seeds=(0, 1),
        seconds=0.1,
        quick=True,
    )
    runs = spec.runs()
    assert _calibrated_cases(runs) == set()
    assert set(_case_affinity(_Workers(), runs)) == {"bright1-best", "red1-fast", "red3-medium"}
    on_disk("red1-fast", True)
    assert _calibrated_cases(runs) == {"red1-fast"}
    pinned = _case_affinity(_Workers(), runs)
    assert set(pinned) == {"bright1-best", "red3-medium"}
    assert set(pinned.values()) == {"tcp://a", "tcp://b"}  # one each: balanced


def test_other_runs_of_a_case_to_build_are_held_until_its_first_is_done(on_disk):
    spec = SweepSpec(
        cases=("bright1-best", "red1-fast", "red3-medium"),
        controllers=("reference",),
        schemes=("standalone",),
        seeds=(0, 1, 2),
        seconds=0.1,
        quick=True,
    )
    runs = spec.runs()
    on_disk("red1-fast", True)
    later = _after_builds(runs)
    by_case: dict = {}
    for r in runs:
        by_case.setdefault(r.settings["case"], []).append(r)
    # the cases to build: their first run builds, the others wait for it; red1-fast is on disk
    assert later == {by_case[c][0].hash: by_case[c][1:] for c in ("bright1-best", "red3-medium")}


def test_sweep_places_calibrated_runs_where_their_scene_is_in_memory(on_disk):
    # Cases on disk: their runs are balanced over the workers by expected work, each
    # preferably where its scene is in memory (a worker without it loads it from disk); a case
    # still to build keeps one worker.
    names = ("bright1-best", "bright1-worst", "red1-fast", "red3-medium", "red5-best")
    spec = SweepSpec(cases=names, controllers=("reference",), schemes=("standalone",), seeds=(0, 1))
    runs = spec.runs()
    keys = {name: geometry_cache_key(load_case(name), spec.quick) for name in names}
    for name in names[:4]:
        on_disk(name, spec.quick)  # red5-best is not
    held = {"tcp://a": names[0::2], "tcp://b": names[1::2]}  # the cold sweep's cases
    client = _Workers({w: [keys[n] for n in cases] for w, cases in held.items()})

    # a case not on disk: all its runs on one worker (built once)
    where = _run_placement(client, runs)
    assert len({where[r.hash] for r in runs if r.settings["case"] == "red5-best"}) == 1
    on_disk("red5-best", spec.quick)
    where = _run_placement(client, runs)
    assert set(where) == {r.hash for r in runs}
    loads = {(where[r.hash], r.settings["case"]) for r in runs} - {
        (w, n) for w, cases in held.items() for n in cases
    }
    assert len(loads) <= 3  # the balance costs at most three loads (free placement: about five)
    # Balanced by expected work, not by run count: a 300-Hz case's run costs about a fifth of
    # a 3-kHz case's (measured 0.5 s vs 1.9 s of CPU). Oracle: every assignment of the ten
    # runs to the two workers, tried; the placement's busiest worker (runs + loads of scenes
    # it does not hold) within 5 % of the best possible.
    cost = {r.hash: _run_cost(r.settings) for r in runs}
    assert cost[runs[-1].hash] < 0.5 * cost[runs[0].hash]  # red5-best vs bright1-best

    def makespan(assign):
        work = []
        for w, cases in held.items():
            mine = [r for r, a in zip(runs, assign, strict=True) if a == w]
            new = {r.settings["case"] for r in mine} - set(cases)
            work.append(sum(cost[r.hash] for r in mine) + _LOAD_FRAMES * len(new))
        return max(work)

    best = min(makespan(a) for a in itertools.product(list(held), repeat=len(runs)))
    assert makespan([where[r.hash] for r in runs]) <= 1.05 * best

    class _Blind(_Workers):
        def run(self, func):
            raise OSError("no answer")

    assert _run_placement(_Blind(client.held), runs) == {}  # cannot ask: plain scheduling
