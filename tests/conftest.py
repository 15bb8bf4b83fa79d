"""Set-up shared by every test, and shared test oracles.

The scene calibrations are cached on disk (:mod:`aocontrol.study._cache`); the tests use a
fresh folder of their own (deleted at exit), shared by the session's processes (Dask workers
inherit the environment), never the user's cache. Set ``AOCONTROL_CACHE`` to choose another.
The oracles are imported by the test modules (``from conftest import ...``).
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

import numpy as np

if "AOCONTROL_CACHE" not in os.environ:
    _CACHE = tempfile.mkdtemp(prefix="aocontrol-test-cache-")
    os.environ["AOCONTROL_CACHE"] = _CACHE
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)


def integrator_stability_limit(d: int) -> float:
    """Largest stable gain of ``g / (1 - z^-1)`` with a total loop delay of ``z^-d`` frames.

    Oracle (analytic): the loop ``g z^-d / (1 - z^-1)`` is stable iff
    ``g < 2 sin(pi / (2 (2d - 1)))`` (the phase crossover at ``pi / (2d - 1)``): 2 for a
    one-frame delay, 1 for two frames, 0.445 for three.

    Parameters
    ----------
    d : int
        Total delay [frames], >= 1 (WFS integration plus the RTC latency).

    Returns
    -------
    float
    """
    return float(2 * np.sin(np.pi / (2 * (2 * d - 1))))
