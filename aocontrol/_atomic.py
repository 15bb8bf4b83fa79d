"""Atomic file writes: the one owner of "a file that exists is complete".

Every writer of the package (controller files, results files, loop results, sweep records)
goes through :func:`atomic_path`: the data is written to a temporary name in the target's
folder, flushed to disk, given the permissions a plain ``open(path, "w")`` would give, and
renamed over the target with :func:`os.replace` (atomic on POSIX). An interrupted write leaves
no file with the final name and no temporary file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator

__all__ = ["atomic_path"]


def _default_mode() -> int:
    """``0o666`` less the process umask (what ``open(path, "w")`` creates)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[str]:
    """Yield a temporary file name next to ``path``; rename it to ``path`` on success.

    The caller writes and closes the temporary file inside the ``with`` block. On success the
    file is flushed to disk (``fsync``), given the default permissions (``0o666`` less the
    umask; :func:`tempfile.mkstemp` creates ``0o600``) and renamed with :func:`os.replace`,
    so a file with the final name is always complete. On any error the temporary file is
    removed and the exception propagates; ``path`` is never created or touched.

    Parameters
    ----------
    path : str or os.PathLike
        Final file name.
    suffix : str
        Suffix of the temporary file.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> target = pathlib.Path(tempfile.mkdtemp()) / "out.txt"
    >>> with atomic_path(target) as tmp:
    ...     _ = pathlib.Path(tmp).write_text("done")
    >>> target.read_text(), oct(target.stat().st_mode & 0o777) == oct(_default_mode())
    ('done', True)
    """
    final = os.path.abspath(os.fspath(path))
    directory = os.path.dirname(final)
    fd, tmp = tempfile.mkstemp(
        dir=directory, prefix="." + os.path.basename(final) + ".", suffix=suffix
    )
    os.close(fd)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, _default_mode())
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
