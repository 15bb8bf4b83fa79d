"""Disturbance sources of the simulator's loops, each carrying its frame rate ``fs``.

Two kinds:

* modal sources (:class:`DisturbanceSource` protocol: ``n_modes``, ``fs``,
  ``next(n_frames) -> (modal (n, n_modes), phase (n, n_valid) or None)``) for one stage:
  :class:`ModalTimeSeries`, :class:`TurbulenceSource`;
* phase sources (:class:`PhaseDisturbance` protocol: ``fs``,
  ``phase_vectors(n_frames) -> (n, n_valid)``) for a cascade, which projects the phase on
  both stages' bases itself: an :class:`~aocontrol.sim.atmosphere.Atmosphere`, a
  :class:`PhaseSource` (an atmosphere plus additive phase sources such as
  :class:`aocontrol.sim.vibration.TiltVibration`), or a :class:`TurbulenceSource`.

Frame rates are in Hz. A rate of ``None`` (a bare :class:`ModalTimeSeries`) is accepted by
the single-stage :func:`~aocontrol.sim.loop.run_loop` only, for backward compatibility.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from aocontrol._validation import check_positive
from aocontrol.sim._projection import projector_for
from aocontrol.sim.modes import ModalBasis

__all__ = [
    "DisturbanceSource",
    "PhaseDisturbance",
    "ModalTimeSeries",
    "TurbulenceSource",
    "PhaseSource",
    "check_rate",
]

# Relative tolerance to accept two rates as equal (floating-point noise of e.g. 3000/3).
_RATE_RTOL = 1e-9


@runtime_checkable
class DisturbanceSource(Protocol):
    """Anything that yields the next frames of a modal disturbance at rate ``fs`` [Hz].

    Parameters
    ----------
    *args, **kwargs
        Not used: a protocol is not instantiated; any object with the members below
        satisfies it (``isinstance`` checks them at run time).
    """

    n_modes: int

    def next(self, n_frames: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Return modal disturbance ``(n_frames, n_modes)`` [nm] and the phase on the valid
        pupil pixels ``(n_frames, n_valid)`` [nm] (or ``None`` for a purely modal source)."""


@runtime_checkable
class PhaseDisturbance(Protocol):
    """Anything that yields the next phase frames on the valid pupil pixels at ``fs`` [Hz].

    Parameters
    ----------
    *args, **kwargs
        Not used: a protocol is not instantiated; any object with the members below
        satisfies it (``isinstance`` checks them at run time).
    """

    fs: float

    def phase_vectors(self, n_frames: int) -> np.ndarray:
        """Return the phase ``(n_frames, n_valid)`` [nm of OPD] of the next frames."""


def check_rate(source: Any, fs: float, what: str, *, required: bool) -> None:
    """Check that ``source.fs`` equals ``fs`` (the rate of ``what``).

    Parameters
    ----------
    source : object
        A disturbance source; its ``fs`` attribute [Hz] may be ``None``.
    fs : float
        The rate the source must have [Hz].
    what : str
        The clock it is checked against, for the message (e.g. ``"stage 'stage 2'"``).
    required : bool
        Whether a source without a rate is refused.

    Raises
    ------
    ValueError
        If the rates differ, or the source has no rate and ``required``.
    """
    src_fs = getattr(source, "fs", None)
    if src_fs is None:
        if required:
            raise ValueError(
                f"the disturbance source {type(source).__name__} has no frame rate fs; "
                f"{what} runs at {fs:g} Hz (give the source fs=)"
            )
        return
    if not abs(float(src_fs) - fs) <= _RATE_RTOL * fs:
        raise ValueError(
            f"the disturbance source runs at fs={float(src_fs):g} Hz but {what} runs at "
            f"{fs:g} Hz: generate the disturbance at {fs:g} Hz"
        )


class ModalTimeSeries:
    """A precomputed modal disturbance.

    Parameters
    ----------
    series : array_like, shape (n_frames, n_modes)
        Modal coefficients [nm], finite.
    fs : float, optional
        Frame rate of the series [Hz]; checked against the stage's rate when given.
    """

    def __init__(self, series: np.ndarray, fs: float | None = None) -> None:
        series = np.asarray(series, dtype=float)
        if series.ndim != 2 or series.shape[0] < 1:
            raise ValueError(f"series must have shape (n_frames, n_modes), got {series.shape}")
        if not np.all(np.isfinite(series)):
            raise ValueError("series must contain only finite values")
        self._series = series
        self._pos = 0
        self.n_modes = series.shape[1]
        self.fs = None if fs is None else check_positive("fs", fs)

    def next(self, n_frames: int) -> tuple[np.ndarray, None]:
        """The next ``n_frames`` rows ``(n_frames, n_modes)`` [nm] and no phase.

        Parameters
        ----------
        n_frames : int
            Frames requested.

        Returns
        -------
        modal : ndarray (n_frames, n_modes)
        phase : None
        """
        end = self._pos + n_frames
        if end > self._series.shape[0]:
            raise ValueError(
                f"the modal time series has {self._series.shape[0]} frames, {end} were requested"
            )
        out = self._series[self._pos : end]
        self._pos = end
        return out, None


class PhaseSource:
    """Phase from an atmosphere plus additive phase sources (e.g. a tilt vibration).

    Parameters
    ----------
    atmosphere : PhaseDisturbance
        E.g. :class:`~aocontrol.sim.atmosphere.Atmosphere` (``fs``, ``phase_vectors``).
    additive : PhaseDisturbance or sequence of them, optional
        Added phase (same pupil), each at the same rate, e.g.
        :class:`aocontrol.sim.vibration.TiltVibration`.

    Raises
    ------
    ValueError
        If a source has no rate or the rates differ.
    """

    def __init__(self, atmosphere: Any, additive: Any = None) -> None:
        if not isinstance(atmosphere, PhaseDisturbance):
            raise TypeError(
                "atmosphere must provide fs and phase_vectors(n_frames), got "
                f"{type(atmosphere).__name__}"
            )
        fs = getattr(atmosphere, "fs", None)
        if fs is None:
            raise ValueError("atmosphere must have a frame rate fs [Hz]")
        self.fs = float(fs)
        self.atmosphere = atmosphere
        if additive is None:
            additive = ()
        elif isinstance(additive, PhaseDisturbance):
            additive = (additive,)
        self.additive = tuple(additive)
        for i, src in enumerate(self.additive):
            if not isinstance(src, PhaseDisturbance):
                raise TypeError(f"additive[{i}] must provide fs and phase_vectors(n_frames)")
            check_rate(src, self.fs, "the atmosphere", required=True)

    def phase_vectors(self, n_frames: int) -> np.ndarray:
        """Phase of the next ``n_frames`` frames ``(n_frames, n_valid)`` [nm].

        Parameters
        ----------
        n_frames : int
            Frames requested.

        Returns
        -------
        ndarray (n_frames, n_valid)
            Atmosphere plus every additive source [nm of OPD].
        """
        phase = self.atmosphere.phase_vectors(n_frames)
        for src in self.additive:
            phase = phase + src.phase_vectors(n_frames)
        return phase


class TurbulenceSource:
    """Phase screens from an atmosphere, projected on a modal basis.

    Parameters
    ----------
    atmosphere : object with ``phase_vectors(n_frames) -> (n_frames, n_valid)`` [nm] and ``fs``
        E.g. :class:`~aocontrol.sim.atmosphere.Atmosphere` or a :class:`PhaseSource`; its
        rate ``fs`` [Hz] is the source's rate.
    basis : object with ``project(vectors) -> (..., n_modes)``, ``synthesize`` and ``n_modes``
        E.g. :class:`~aocontrol.sim.modes.ModalBasis`.
    additive : DisturbanceSource, optional
        A modal disturbance added on top (e.g. a vibration), same modes (and rate, when it
        has one).

    Notes
    -----
    A :class:`~aocontrol.sim.modes.ModalBasis` is projected by its cached
    :class:`~aocontrol.sim._projection.ModalProjector` (as the cascade does): in float32,
    through the DM's separable influence functions when cheaper, i.e. ``basis.project`` to
    a relative rounding of ~6e-7 RMS (at most ~2e-4 of a mode's largest coefficient), far
    below any AO residual, at a fraction of the cost of the float64 product (10x fewer
    operations at 540 modes on 96 pixels). Any other basis-like object is projected by its
    own ``project``.
    """

    def __init__(
        self,
        atmosphere: Any,
        basis: Any,
        *,
        additive: DisturbanceSource | None = None,
    ) -> None:
        self.atmosphere = atmosphere
        self.basis = basis
        self.n_modes = int(basis.n_modes)
        fs = getattr(atmosphere, "fs", None)
        self.fs = None if fs is None else float(fs)
        if additive is not None and additive.n_modes != self.n_modes:
            raise ValueError(f"additive has {additive.n_modes} modes, basis {self.n_modes}")
        if additive is not None and self.fs is not None:
            check_rate(additive, self.fs, "the atmosphere", required=False)
        self.additive = additive

    def phase_vectors(self, n_frames: int) -> np.ndarray:
        """Phase of the next ``n_frames`` frames, additive part included, ``(n, n_valid)`` [nm].

        Parameters
        ----------
        n_frames : int
            Frames requested.

        Returns
        -------
        ndarray (n_frames, n_valid)
        """
        return self.next(n_frames)[1]

    def next(self, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
        """Modal disturbance ``(n, n_modes)`` and phase ``(n, n_valid)`` [nm] of the next frames.

        Parameters
        ----------
        n_frames : int
            Frames requested.

        Returns
        -------
        modal : ndarray (n_frames, n_modes)
        phase : ndarray (n_frames, n_valid)
        """
        phase = self.atmosphere.phase_vectors(n_frames)
        if isinstance(self.basis, ModalBasis):
            modal = projector_for(self.basis)(np.asarray(phase))
        else:
            modal = self.basis.project(phase)
        if self.additive is not None:
            extra, _ = self.additive.next(n_frames)
            modal = modal + extra
            phase = phase + self.basis.synthesize(extra)
        return modal, phase
