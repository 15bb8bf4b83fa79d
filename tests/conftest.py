"""Set-up shared by every test: a private calibration cache for the session.

The scene calibrations are cached on disk (:mod:`aocontrol.study._cache`); the tests use a
fresh folder of their own (deleted at exit), shared by the session's processes (Dask workers
inherit the environment), never the user's cache. Set ``AOCONTROL_CACHE`` to choose another.
"""

import atexit
import os
import shutil
import tempfile

if "AOCONTROL_CACHE" not in os.environ:
    _CACHE = tempfile.mkdtemp(prefix="aocontrol-test-cache-")
    os.environ["AOCONTROL_CACHE"] = _CACHE
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
