"""The on-disk calibration cache (aocontrol.study._cache): reuse, never a wrong entry, policy."""

from __future__ import annotations

import logging
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest

from aocontrol.study import _cache, scene
from aocontrol.study._cache import CacheWarning, cached, enforce_policy


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("AOCONTROL_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("AOCONTROL_CACHE_MAX_GB", raising=False)
    monkeypatch.delenv("AOCONTROL_CACHE_MAX_DAYS", raising=False)
    return tmp_path / "cache" / "calibrations"


class Counter:
    """A build function that counts its calls and returns a fresh array each time."""

    def __init__(self, value=None):
        self.calls = 0
        self.value = np.arange(1000.0) if value is None else value

    def __call__(self):
        self.calls += 1
        return {"basis": self.value.copy(), "gain": 0.5}


def _entries(directory: pathlib.Path) -> list[pathlib.Path]:
    return sorted(directory.glob("*.calib"))


def test_second_call_loads_the_entry_built_by_the_first(cache_dir):
    build = Counter()
    a = cached("key A", build)
    b = cached("key A", build)
    assert build.calls == 1  # built once, then read
    np.testing.assert_array_equal(a["basis"], b["basis"])  # bit for bit
    assert a["basis"] is not b["basis"]
    (entry,) = _entries(cache_dir)
    cached("key B", build)  # other settings: another entry
    assert build.calls == 2 and len(_entries(cache_dir)) == 2
    # The entry's name is the SHA-256 of its settings; no temporary file is left.
    assert not [p for p in cache_dir.iterdir() if p.name.startswith(".")]
    assert entry.stem == __import__("hashlib").sha256(b"key A").hexdigest()[:32]


def test_cache_stats_count_each_part(cache_dir):
    # cumulative per process: differences over a call are what it did
    before = _cache.cache_stats()
    cached("key stats", Counter())
    mid = _cache.cache_stats()
    cached("key stats", Counter())
    after = _cache.cache_stats()

    def diff(a, b):
        return {k: b[k] - a[k] for k in a if k.endswith("_n")}

    built = diff(before, mid)
    loaded = diff(mid, after)
    assert built == {"lock_wait_n": 1, "load_n": 1, "build_n": 1, "write_n": 1}
    assert loaded == {"lock_wait_n": 1, "load_n": 1, "build_n": 0, "write_n": 0}
    assert after["build_s"] - mid["build_s"] == 0.0 and mid["write_s"] > before["write_s"]


@pytest.mark.parametrize("damage", ["flip", "truncate", "header", "empty"])
def test_a_damaged_entry_is_rebuilt_never_trusted(cache_dir, caplog, damage):
    build = Counter()
    cached("key", build)
    (entry,) = _entries(cache_dir)
    data = bytearray(entry.read_bytes())
    if damage == "flip":  # one bit of the payload: its SHA-256 differs
        data[-100] ^= 0x01
    elif damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "header":
        data = b"not json\n" + data
    else:
        data = b""
    entry.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="aocontrol.study._cache"):
        value = cached("key", build)
    assert build.calls == 2
    np.testing.assert_array_equal(value["basis"], build.value)
    assert "rebuilt" in caplog.text
    # the rebuilt entry replaced the damaged one and is used from now on
    cached("key", build)
    assert build.calls == 2


def test_an_entry_of_another_code_version_is_reported_and_rebuilt(cache_dir, caplog, monkeypatch):
    monkeypatch.setattr(_cache, "_fingerprint", "an older version of the code")
    cached("key", Counter(np.zeros(10)))
    monkeypatch.setattr(_cache, "_fingerprint", None)  # this code's fingerprint again
    build = Counter()
    with caplog.at_level(logging.WARNING, logger="aocontrol.study._cache"):
        value = cached("key", build)
    assert build.calls == 1  # the other version's zeros were not used
    np.testing.assert_array_equal(value["basis"], build.value)
    assert "another version" in caplog.text


def test_unwritable_cache_folder_warns_once_and_is_bypassed(tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")  # a folder cannot be created below a file (even as root)
    monkeypatch.setenv("AOCONTROL_CACHE", str(blocker))
    monkeypatch.setattr(_cache, "_warned", set())
    build = Counter()
    with pytest.warns(CacheWarning, match="not usable"):
        cached("key", build)
    cached("key", build)  # reported once, still bypassed
    assert build.calls == 2


def test_cache_off_builds_every_time_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("AOCONTROL_CACHE", "off")
    assert _cache.cache_dir() is None
    build = Counter()
    cached("key", build)
    cached("key", build)
    assert build.calls == 2


def test_bad_policy_settings_name_the_variable(cache_dir, monkeypatch):
    monkeypatch.setenv("AOCONTROL_CACHE_MAX_GB", "-1")
    with pytest.raises(ValueError, match=r"\$AOCONTROL_CACHE_MAX_GB must be a number > 0"):
        cached("key", Counter())
    monkeypatch.setenv("AOCONTROL_CACHE_MAX_GB", "1")
    monkeypatch.setenv("AOCONTROL_CACHE_MAX_DAYS", "soon")
    with pytest.raises(ValueError, match="AOCONTROL_CACHE_MAX_DAYS.*'soon'"):
        cached("key", Counter())


def test_size_and_age_policy_delete_least_recently_used(cache_dir, monkeypatch):
    for key in ("a", "b", "c"):
        cached(key, Counter())
    a, b, c = (
        cache_dir / f"{__import__('hashlib').sha256(k.encode()).hexdigest()[:32]}.calib"
        for k in ("a", "b", "c")
    )
    now = time.time()
    os.utime(a, (now - 300, now - 300))
    os.utime(b, (now - 200, now - 200))
    cached("a", Counter())  # a use refreshes a's time: b is now the least recently used
    size = a.stat().st_size
    # room for two entries: the least recently used goes
    assert enforce_policy(cache_dir, max_bytes=int(2.5 * size), max_age_s=1e9) == 1
    assert a.exists() and not b.exists() and c.exists()
    # age: an entry unused for longer than the limit goes, whatever the size
    os.utime(c, (now - 10 * 86400, now - 10 * 86400))
    monkeypatch.setenv("AOCONTROL_CACHE_MAX_DAYS", "5")
    cached("d", Counter())  # the policy runs after each write
    assert a.exists() and not c.exists()


_CONCURRENT = """
import pathlib, sys, time
from aocontrol.study._cache import cached
def build():
    with open(sys.argv[1], "a") as fh:
        fh.write("built\\n")
    time.sleep(1.0)
    return list(range(100))
assert cached("shared key", build) == list(range(100))
"""


@pytest.mark.skipif(sys.platform == "win32", reason="fcntl lock")
def test_processes_needing_one_entry_build_it_once(cache_dir, tmp_path):
    # Two processes start together; the second waits for the first's lock and reads its entry.
    marker = tmp_path / "builds.txt"
    env = dict(os.environ, PYTHONPATH=str(pathlib.Path(__file__).resolve().parents[1]))
    procs = [
        subprocess.Popen([sys.executable, "-c", _CONCURRENT, str(marker)], env=env)
        for _ in range(2)
    ]
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    assert marker.read_text().count("built") == 1


def test_scene_geometry_goes_through_the_disk_cache(cache_dir, monkeypatch):
    # A fresh process (here: the memory cache cleared) reads the geometry that an earlier one
    # built; cache=False builds it anew. A cheap stand-in for the calibrations.
    build = Counter()
    monkeypatch.setattr(scene, "_build_geometry", lambda c, quick, rng, *progress: build())
    case = scene.load_case("bright1-best")
    scene.clear_scene_cache()
    try:
        first = scene._geometry(case, True, 0, True)
        scene.clear_scene_cache()
        again = scene._geometry(case, True, 0, True)
        assert build.calls == 1
        np.testing.assert_array_equal(first["basis"], again["basis"])
        # another seed of the optical-gain screens: another entry
        scene._geometry(case, True, 1, True)
        assert build.calls == 2 and len(_entries(cache_dir)) == 2
        scene._geometry(case, True, 0, False)
        assert build.calls == 3
    finally:
        scene.clear_scene_cache()


def test_quick_geometry_key_names_the_modes_built():
    # quick mode builds at most QUICK_MODES modes per stage: cases that differ only in n_modes
    # above that limit share their calibrations; in full mode they do not
    from aocontrol.study.cases import apply_overrides

    case = scene.load_case("bright1-best")
    more = apply_overrides(case, {"stage1.n_modes": case.stage1.n_modes - 1})
    assert case.stage1.n_modes - 1 > scene.QUICK_MODES[0]
    assert scene.geometry_cache_key(case, True) == scene.geometry_cache_key(more, True)
    assert scene.geometry_cache_key(case, False) != scene.geometry_cache_key(more, False)
    fewer = apply_overrides(case, {"stage1.n_modes": scene.QUICK_MODES[0] - 1})
    assert scene.geometry_cache_key(case, True) != scene.geometry_cache_key(fewer, True)


def test_is_cached_sees_only_entries_of_this_code_and_key(cache_dir, monkeypatch):
    assert not _cache.is_cached("key")  # nothing yet
    cached("key", Counter())
    assert _cache.is_cached("key") and not _cache.is_cached("other key")
    monkeypatch.setattr(_cache, "_fingerprint", "another version of the code")
    assert not _cache.is_cached("key")  # written by other code: not usable
    monkeypatch.setattr(_cache, "_fingerprint", None)
    monkeypatch.setenv("AOCONTROL_CACHE", "off")
    assert not _cache.is_cached("key")


# A tiny scene (32-pixel pupil, 9x9 DMs, 20 + 10 modes): its calibrations take about 2 s.
TINY = {
    "simulation.n_pix": 32,
    "science.field_of_view": 12.0,
    "stage1.n_actuators": 9,
    "stage1.n_subapertures": 8,
    "stage1.n_modes": 20,
    "stage2.n_actuators": 9,
    "stage2.n_subapertures": 8,
    "stage2.n_modes": 10,
}


def test_a_calibration_built_says_what_it_builds_and_where_it_is_cached(cache_dir, capsys):
    # Issue 33: the first use of a scene builds its calibrations (minutes at full scale): a
    # progress bar names the case, the steps and the cache folder; from the cache, no bar.
    scene.clear_scene_cache()
    scene.build_scene("bright1-best", overrides=TINY, progress=True)
    err = capsys.readouterr().err
    assert f"calibrating bright1-best (once: cached in {cache_dir})" in err
    for step in ("KL bases (20 + 10 modes)", "pyramid interaction matrix", "5/5 steps"):
        assert step in err, step
    assert len(_entries(cache_dir)) == 1
    scene.clear_scene_cache()
    scene.build_scene("bright1-best", overrides=TINY, progress=True)
    assert "calibrating" not in capsys.readouterr().err
