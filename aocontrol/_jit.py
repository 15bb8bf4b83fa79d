"""numba on first use, for every layer: one switch and one cache of compiled loops.

The compiled loops of the simulator (:mod:`aocontrol.sim._fused`,
:mod:`aocontrol.sim.wfs._pyramid_fused`) and of the synthesis layer's fine residual check
(:mod:`aocontrol.synthesis._dd_grids`) are plain Python functions compiled here on first
use (``cache=True``: the machine code is kept on disk for the next processes; ``nogil=True``:
threads run them side by side). numba is imported then, not with :mod:`aocontrol`. Without
numba (import error), or with ``$AOCONTROL_NO_NUMBA`` set to a non-empty value, the callers
run their numpy paths (each documents how close the two are).
"""

from __future__ import annotations

import logging
import os

logger = logging.getLogger(__name__)

#: Environment variable: set (non-empty) to run the numpy paths instead of the compiled loops.
ENV_NO_NUMBA = "AOCONTROL_NO_NUMBA"


def compile_once(store: list, functions: tuple, fallback: str) -> tuple | None:
    """The ``functions`` compiled by numba (``cache=True, nogil=True``) on first use and kept
    in ``store`` (a module's one-item list), or ``None`` without numba (logging
    ``fallback``, what runs instead) or with ``$AOCONTROL_NO_NUMBA`` set."""
    if os.environ.get(ENV_NO_NUMBA):
        return None
    if not store:
        try:
            import numba
        except ImportError:  # pragma: no cover - numba is a dependency
            logger.info("numba is not installed: %s", fallback)
            store.append(None)
        else:
            jit = numba.njit(cache=True, nogil=True)
            store.append(tuple(jit(f) for f in functions))
    return store[0]
