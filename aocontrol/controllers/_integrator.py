"""Leaky integrator bank, the reference AO controller."""

from __future__ import annotations

import numpy as np

from aocontrol._deprecation import renamed_keyword
from aocontrol._validation import check_finite_array, check_in_range, check_int
from aocontrol.controllers._base import _LIMIT_NOTE, IIRBank

__all__ = ["Integrator"]


class Integrator(IIRBank):
    """Leaky integrator bank, ``C(z) = g / (1 - (1 - leak) z^-1)``, one gain per mode.

    The command is ``u[k] = (1 - leak) u[k-1] + g m[k]``.

    Parameters
    ----------
    gain : float or array_like of shape (n_modes,)
        Loop gain per mode (dimensionless, >= 0). A scalar with ``n_modes`` gives a bank of
        equal gains.
    fs : float
        Loop rate [Hz].
    leak : float, default 0.0
        Leak in [0, 1); 0 is a pure integrator.
    n_modes : int, optional
        Number of modes when ``gain`` is a scalar (default 1).
    command_limit : float or array_like, optional
        The controller's limit on its command, with anti-windup (see :class:`IIRBank`;
        ``stroke`` is its deprecated name).

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.analysis import is_stable
    >>> is_stable(loop_plant(1000.0, 1.0), Integrator(0.99, fs=1000.0).transfer_function())
    True
    """

    @renamed_keyword("stroke", "command_limit", _LIMIT_NOTE)
    def __init__(
        self,
        gain: float | np.ndarray,
        fs: float,
        leak: float = 0.0,
        *,
        n_modes: int | None = None,
        command_limit: float | np.ndarray | None = None,
    ) -> None:
        g = check_finite_array("gain", gain, ndim=(0, 1))
        if np.any(g < 0):
            raise ValueError(f"gain must be >= 0, got min {g.min()!r}")
        leak = check_in_range("leak", leak, 0.0, 1.0)
        if g.ndim == 1:
            if n_modes is not None and check_int("n_modes", n_modes, minimum=1) != g.size:
                raise ValueError(f"n_modes={n_modes} disagrees with len(gain)={g.size}")
            if g.size == 0:
                raise ValueError("gain must not be empty")
            b = g[:, None]
            a = np.tile([1.0, -(1.0 - leak)], (g.size, 1))
            super().__init__(b, a, fs, command_limit=command_limit)
        else:
            super().__init__(
                [float(g)], [1.0, -(1.0 - leak)], fs, n_modes=n_modes, command_limit=command_limit
            )
        self._leak = leak

    @property
    def gain(self) -> np.ndarray:
        """Gain per mode, shape ``(n_modes,)``."""
        return self.b[:, 0].copy()

    @property
    def leak(self) -> float:
        """Leak in [0, 1)."""
        return self._leak

    def __repr__(self) -> str:
        g = self.gain
        gtxt = f"{g[0]:.4g}" if np.all(g == g[0]) else f"[{g.min():.4g}..{g.max():.4g}]"
        return f"Integrator(gain={gtxt}, fs={self.fs}, leak={self._leak}, n_modes={self.n_modes})"
