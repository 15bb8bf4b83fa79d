"""On-disk cache of scene calibrations, shared by every process and every later run.

A scene's calibrations (DMs, KL bases, the projection between the stage bases, the sensors'
reconstructors, noise coefficients and optical gains) cost from tens of seconds to minutes and
depend only on a few case values. :func:`cached` keeps them on disk, so that the workers of a
sweep and every later run build each of them once.

Location
    ``$AOCONTROL_CACHE`` if set (``off``, ``none``, ``0`` or an empty value: no disk cache),
    else the platform's user cache directory (``platformdirs.user_cache_dir("aocontrol")``:
    ``~/.cache/aocontrol`` on Linux, ``~/Library/Caches/aocontrol`` on macOS,
    ``%LOCALAPPDATA%\\aocontrol\\Cache`` on Windows), sub-folder ``calibrations``.
Content address
    An entry's name is the SHA-256 of the settings that determine it (the caller's key: the
    case values the calibration uses, the quick flag, the seed). Its header holds that key and
    the *code fingerprint*: the package version, the numpy and scipy versions and a hash of the
    source of the modules that compute calibrations (``aocontrol/sim``, the scene and this
    module), so that any change of the code invalidates every entry.
Never trusted
    An entry is used only if its header parses, names the same key, format and fingerprint, and
    the payload has the recorded length and SHA-256; anything else (a corrupt or truncated
    file, another version's entry) is reported in the log and rebuilt, and the new entry
    replaces it. Entries are written atomically (:func:`aocontrol._atomic.atomic_path`), so a
    file with an entry's name is complete.
Sharing
    A process building an entry holds an exclusive lock on ``<name>.lock`` (``fcntl.flock``
    where available): another process needing the same entry waits and then reads it instead
    of building it again.
Size and age
    After each write, entries not used for ``$AOCONTROL_CACHE_MAX_DAYS`` days (default 30) are
    deleted, then the least recently used ones until the folder holds at most
    ``$AOCONTROL_CACHE_MAX_GB`` GB (default 5). A use refreshes an entry's time.
Bad folder
    A folder that cannot be created or written is reported once (:class:`CacheWarning`) and
    bypassed: the calibrations are built in memory, as without a cache.

The payload is a pickle of the calibration objects: the folder is the user's own, like the
bytecode cache; the checks above make sure that only a complete entry written by this very code
for this very key is ever loaded.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import pathlib
import pickle
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from aocontrol._version import __version__

__all__ = [
    "CacheWarning",
    "cache_dir",
    "cache_settings",
    "cached",
    "cache_stats",
    "code_fingerprint",
    "is_cached",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")

#: Environment variables of the cache (folder, size limit [GB], age limit [days]).
ENV_DIR = "AOCONTROL_CACHE"
ENV_MAX_GB = "AOCONTROL_CACHE_MAX_GB"
ENV_MAX_DAYS = "AOCONTROL_CACHE_MAX_DAYS"
DEFAULT_MAX_GB = 5.0
DEFAULT_MAX_DAYS = 30.0
_OFF = {"", "0", "off", "none", "false", "no"}
_FORMAT = 1
_SUFFIX = ".calib"
# A temporary file of an interrupted write older than this is deleted by the policy [s].
_STALE_TMP_S = 24 * 3600.0
# Header line of an entry: at most this many bytes (the rest is the payload).
_MAX_HEADER = 1 << 16
_warned: set[str] = set()
_fingerprint: str | None = None
# What this process spent in :func:`cached` (:func:`cache_stats`): wall and CPU seconds and
# counts per part.
_PARTS = ("lock_wait", "load", "build", "write")
_stats: dict[str, float] = {f"{p}_{k}": 0.0 for p in _PARTS for k in ("s", "cpu_s", "n")}


def cache_stats() -> dict[str, float]:
    """What this process has spent in :func:`cached` so far (cumulative; take differences).

    Returns
    -------
    dict
        ``<part>_s`` (wall), ``<part>_cpu_s`` (this process's CPU) and ``<part>_n`` (count) for
        the parts ``lock_wait`` (waiting for another process building the same entry),
        ``load`` (reading and checking an entry), ``build`` (the caller's ``build``) and
        ``write`` (pickling and writing an entry, its ``fsync`` included).
    """
    return dict(_stats)


@contextlib.contextmanager
def _timed(part: str) -> Iterator[None]:
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        yield
    finally:
        _stats[f"{part}_s"] += time.perf_counter() - t0
        _stats[f"{part}_cpu_s"] += time.process_time() - c0
        _stats[f"{part}_n"] += 1


class CacheWarning(UserWarning):
    """The calibration cache folder is unusable (not writable): the cache is bypassed."""


def cache_dir() -> pathlib.Path | None:
    """The folder of calibration entries, or ``None`` when the disk cache is off.

    Returns
    -------
    pathlib.Path or None
        ``$AOCONTROL_CACHE/calibrations`` or the platform user cache dir's (module docstring).
    """
    env = os.environ.get(ENV_DIR)
    if env is not None:
        if env.strip().lower() in _OFF:
            return None
        return pathlib.Path(env).expanduser() / "calibrations"
    import platformdirs

    return pathlib.Path(platformdirs.user_cache_dir("aocontrol")) / "calibrations"


def _env_float(name: str, default: float) -> float:
    raw = os.environ.get(name)
    if raw is None:
        return default
    try:
        value = float(raw)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise ValueError(f"${name} must be a number > 0, got {raw!r}")
    return value


def cache_settings() -> dict[str, Any]:
    """Folder, size limit [bytes] and age limit [s] in force (from the environment).

    Raises
    ------
    ValueError
        ``$AOCONTROL_CACHE_MAX_GB`` or ``$AOCONTROL_CACHE_MAX_DAYS`` is not a number > 0.
    """
    return {
        "directory": cache_dir(),
        "max_bytes": int(_env_float(ENV_MAX_GB, DEFAULT_MAX_GB) * 1e9),
        "max_age_s": _env_float(ENV_MAX_DAYS, DEFAULT_MAX_DAYS) * 86400.0,
    }


def code_fingerprint() -> str:
    """Hash of the package, numpy and scipy versions and the calibration code's source.

    Computed once per process: the source files of ``aocontrol/sim`` (every sub-folder),
    ``aocontrol/study/scene.py`` and ``_seeds.py``, this module and ``aocontrol/study/cases``.
    """
    global _fingerprint
    if _fingerprint is None:
        import numpy
        import scipy

        import aocontrol

        root = pathlib.Path(aocontrol.__file__).resolve().parent
        h = hashlib.sha256()
        h.update(f"{__version__}|{numpy.__version__}|{scipy.__version__}".encode())
        files = sorted(root.joinpath("sim").rglob("*.py"))
        files += sorted(root.joinpath("study", "cases").rglob("*.py"))
        # The scene's seeds by purpose (study/_seeds.py) set its optical-gain screens.
        files += [root / "study" / "scene.py", root / "study" / "_seeds.py"]
        files += [pathlib.Path(__file__).resolve()]
        for path in files:
            h.update(path.relative_to(root).as_posix().encode())
            h.update(path.read_bytes())
        _fingerprint = h.hexdigest()
    return _fingerprint


def _warn_once(directory: pathlib.Path, reason: str) -> None:
    if str(directory) not in _warned:
        _warned.add(str(directory))
        warnings.warn(
            f"calibration cache {directory} is not usable ({reason}); calibrations are built "
            f"without it (set ${ENV_DIR} to a writable folder, or to 'off')",
            CacheWarning,
            stacklevel=3,
        )


def _usable(directory: pathlib.Path) -> bool:
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _warn_once(directory, f"cannot create it: {exc.strerror or exc}")
        return False
    if not os.access(directory, os.W_OK | os.X_OK):
        _warn_once(directory, "not writable")
        return False
    return True


@contextlib.contextmanager
def _locked(path: pathlib.Path) -> Iterator[None]:
    """Exclusive lock on ``path`` across processes (no lock where ``fcntl`` is missing)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover (Windows): atomic writes keep entries whole anyway
        yield
        return
    with open(path, "a") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _entry_path(directory: pathlib.Path, key: str) -> pathlib.Path:
    return directory / f"{hashlib.sha256(key.encode()).hexdigest()[:32]}{_SUFFIX}"


def is_cached(key: str) -> bool:
    """Whether an entry for ``key`` written by this code is on disk (its header only).

    A cheap look-ahead (e.g. for scheduling a sweep): the payload is not read, so a corrupt
    payload still says True here and is rebuilt by :func:`cached` when used.

    Parameters
    ----------
    key : str
        As given to :func:`cached`.

    Returns
    -------
    bool
        False when the disk cache is off, the entry is missing, or its header names another
        key, format or code fingerprint.
    """
    directory = cache_dir()
    if directory is None:
        return False
    try:
        with open(_entry_path(directory, key), "rb") as fh:
            header = json.loads(fh.readline(_MAX_HEADER))
    except (OSError, ValueError):
        return False
    return (
        isinstance(header, dict)
        and header.get("format") == _FORMAT
        and header.get("key") == key
        and header.get("fingerprint") == code_fingerprint()
    )


def _read(path: pathlib.Path, key: str) -> tuple[bool, Any]:
    """``(True, value)`` from a valid entry, else ``(False, reason)``."""
    try:
        with open(path, "rb") as fh:
            header = json.loads(fh.readline(_MAX_HEADER))
            payload = fh.read()
    except FileNotFoundError:
        return False, None
    except (OSError, ValueError) as exc:
        return False, f"unreadable header ({type(exc).__name__})"
    if not isinstance(header, dict) or header.get("format") != _FORMAT:
        return False, "unknown format"
    if header.get("key") != key:
        return False, "written for other settings"
    if header.get("fingerprint") != code_fingerprint():
        return False, f"written by another version ({header.get('version', '?')}) of the code"
    if len(payload) != header.get("size") or hashlib.sha256(payload).hexdigest() != header.get(
        "sha256"
    ):
        return False, "corrupt or truncated payload"
    try:
        return True, pickle.loads(payload)
    except Exception as exc:  # a payload that passed the hash but does not load: rebuild
        return False, f"payload does not load ({type(exc).__name__}: {exc})"


def _write(path: pathlib.Path, key: str, value: Any) -> None:
    from aocontrol._atomic import atomic_path

    payload = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    header = {
        "format": _FORMAT,
        "key": key,
        "fingerprint": code_fingerprint(),
        "version": __version__,
        "size": len(payload),
        "sha256": hashlib.sha256(payload).hexdigest(),
        "created": time.time(),
    }
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(json.dumps(header, sort_keys=True).encode() + b"\n")
        fh.write(payload)


def enforce_policy(directory: pathlib.Path, max_bytes: int, max_age_s: float, keep=()) -> int:
    """Delete entries unused for ``max_age_s``, then the least recently used above ``max_bytes``.

    Also deletes temporary files of interrupted writes older than a day and the lock files of
    deleted entries. Entries named in ``keep`` are never deleted.

    Returns
    -------
    int
        Number of entries deleted.
    """
    now = time.time()
    keep = {pathlib.Path(p).name for p in keep}
    entries = []
    for p in directory.iterdir():
        try:
            st = p.stat()
        except FileNotFoundError:
            continue
        if p.name.startswith(".") and now - st.st_mtime > _STALE_TMP_S:
            with contextlib.suppress(OSError):
                p.unlink()
        elif p.suffix == _SUFFIX:
            entries.append((st.st_mtime, st.st_size, p))
    removed = 0
    entries.sort()  # oldest use first
    total = sum(size for _, size, _ in entries)
    for mtime, size, p in entries:
        if p.name in keep:
            continue
        if now - mtime > max_age_s or total > max_bytes:
            with contextlib.suppress(OSError):
                p.unlink()
                p.with_suffix(".lock").unlink(missing_ok=True)
                total -= size
                removed += 1
    if removed:
        logger.info("calibration cache %s: %d old entr(y/ies) deleted", directory, removed)
    return removed


def cached(key: str, build: Callable[[], T]) -> T:
    """``build()``'s value, from the disk cache when a valid entry for ``key`` exists.

    Parameters
    ----------
    key : str
        Every setting the value depends on, as text (e.g. sorted JSON); its SHA-256 names
        the entry.
    build : callable
        Computes the value (picklable) when no valid entry exists.

    Returns
    -------
    object
        The value (built or loaded; equal either way).

    Warns
    -----
    CacheWarning
        The cache folder cannot be created or written (then bypassed).
    """
    settings = cache_settings()
    directory = settings["directory"]
    if directory is None or not _usable(directory):
        return build()
    path = _entry_path(directory, key)
    lock = _locked(path.with_suffix(".lock"))
    try:
        with _timed("lock_wait"):
            lock.__enter__()
    except OSError as exc:
        _warn_once(directory, f"cannot lock an entry: {exc}")
        return build()
    try:
        with _timed("load"):
            ok, value = _read(path, key)
        if ok:
            with contextlib.suppress(OSError):
                os.utime(path)  # least-recently-used order
            logger.info("calibrations loaded from the cache (%s)", path.name)
            return value
        if value is not None:
            logger.warning("calibration cache entry %s %s: rebuilt", path, value)
        with _timed("build"):
            value = build()
        try:
            with _timed("write"):
                _write(path, key, value)
        except OSError as exc:  # the folder became unwritable, the disk is full
            _warn_once(directory, f"cannot write an entry: {exc}")
            return value
    finally:
        lock.__exit__(None, None, None)
    logger.info("calibrations cached in %s", path)
    enforce_policy(directory, settings["max_bytes"], settings["max_age_s"], keep=(path,))
    return value


def process_usage() -> dict[str, float]:
    """This process's cumulative usage: the calibration cache's parts
    (:func:`aocontrol.study._cache.cache_stats`: lock waits, loads, builds, writes) and, where
    the ``resource`` module exists, the kernel's counts (``minflt``: page faults, ``nivcsw``:
    involuntary context switches, i.e. preemptions by other processes, ``oublock``: blocks
    written)."""
    out = cache_stats()
    try:
        import resource
    except ImportError:  # pragma: no cover (Windows)
        return out
    ru = resource.getrusage(resource.RUSAGE_SELF)
    out.update(
        user_s=ru.ru_utime,
        sys_s=ru.ru_stime,
        minflt=float(ru.ru_minflt),
        majflt=float(ru.ru_majflt),
        nvcsw=float(ru.ru_nvcsw),
        nivcsw=float(ru.ru_nivcsw),
        oublock=float(ru.ru_oublock),
    )
    return out
