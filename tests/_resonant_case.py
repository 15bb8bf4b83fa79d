"""The resonant mode of the bound-start and auto-order tests (``test_dd_starts.py``,
``test_certified.py``): turbulence plus one sharp vibration at 47 Hz (0.3 Hz wide), 1 kHz,
one-frame latency, white noise 1e-3."""

from __future__ import annotations

import numpy as np

from aocontrol import loop_plant
from aocontrol.synthesis import datadriven

FS = 1000.0
KW = dict(noise_psd=1e-3, modulus_margin=0.5, n_jobs=1, progress=False)


def resonant_mode():
    """``(plant, freqs, psd)`` of the mode."""
    f = np.concatenate([[0.0], np.geomspace(0.05, FS / 2, 500)])
    psd = 1e2 / (1 + (f / 2.0) ** 2) ** (11 / 6) + 50.0 / (1 + ((f - 47.0) / 0.3) ** 2)
    return loop_plant(FS, 1.0), f, psd


def design(order, bound_start=None):
    """``datadriven`` on the mode with the tests' settings."""
    G, f, psd = resonant_mode()
    return datadriven(G, f, psd, order=order, bound_start=bound_start, **KW)
