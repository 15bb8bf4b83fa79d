"""Rejection of two cascaded AO stages (standalone and dCAO), at the fast rate.

Model (the simulator's, :mod:`aocontrol.sim.loop`): stage 2 runs at ``fs2``, stage 1 at
``fs1 = fs2 / R`` (integer ``R``). Stage 1's WFS averages its residual over its ``R`` fast
frames, its loop runs at ``fs1`` (plant ``G1`` and controller ``K1`` at ``fs1``), and its DM
shape is held for ``R`` fast frames. Such a multi-rate loop is periodically time varying, not
LTI; what is computed here is its **baseband response**, the part of the fast-rate residual
at frequency ``f`` that is coherent with the disturbance at ``f``:

``S1_eff(f) = 1 - |A_R(f)|^2 T1(exp(2j pi f / fs1))``,
``|A_R(f)|^2 = [sin(pi R f / fs2) / (R sin(pi f / fs2))]^2``,

with ``T1 = 1 - S1`` the complementary sensitivity of stage 1 at its own rate (evaluated at
``f`` by periodicity) and ``A_R`` the frame average, whose phase the hold cancels (the
average looks back over the frame, the hold forward). For a stationary disturbance it is
exactly what a cross-spectral (H1) estimate of the simulator measures at every ``f`` up to
``fs2 / 2``; the residual PSD also holds the aliased power (disturbance near multiples of
``fs1`` folded by the decimation), small below ``fs1 / 2`` for AO spectra. With ``R = 1`` it
is ``S1`` exactly.

Schemes, per mode (mode ``i`` of stage 1 taken as mode ``i`` of stage 2: the leading KL
modes of nested DMs, the projection ``P`` close to the identity on them; exact when the two
bases share their modes):

* ``standalone``: ``S1_eff S2`` in the modes both stages control, ``S1_eff`` in the modes
  only stage 1 controls, ``S2`` in the modes only stage 2 controls;
* ``dcao``: ``S2`` in stage 2's modes (it sees the full disturbance), ``S1_eff`` outside them.
"""

from __future__ import annotations

import numpy as np

from aocontrol._validation import check_frequency_grid, check_positive
from aocontrol.analysis._loop import sensitivity
from aocontrol.plant import plant_fs

__all__ = ["slow_stage_sensitivity", "cascade_sensitivity", "cascade_rejection"]

_SCHEMES = ("standalone", "dcao")
# Relative tolerance for an integer rate ratio.
_RATIO_RTOL = 1e-9


def _ratio(fs1: float, fs2: float) -> int:
    ratio = fs2 / fs1
    r = int(round(ratio))
    if r < 1 or abs(ratio - r) > _RATIO_RTOL * ratio:
        raise ValueError(
            f"the fast rate must be an integer multiple of stage 1's rate: fs2={fs2:g} Hz, "
            f"fs1={fs1:g} Hz, ratio {ratio:.6g}"
        )
    return r


def slow_stage_sensitivity(
    plant1: object, controller1: object, freqs: object, fs: float
) -> np.ndarray:
    """Baseband sensitivity ``S1_eff`` of a stage at ``fs1 = fs / R``, seen at the fast rate.

    Parameters
    ----------
    plant1 : control.TransferFunction or control.FRD
        Stage 1's plant at its own rate ``fs1`` (e.g. ``loop_plant(fs1, latency1)``).
    controller1 : control.TransferFunction, control.FRD or ControllerBank
        Stage 1's controller at ``fs1``.
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in ``[0, fs / 2]`` (the fast band).
    fs : float
        Fast rate [Hz], an integer multiple ``R`` of ``fs1``.

    Returns
    -------
    ndarray of complex, shape (n_freqs,) or (n_modes, n_freqs)
        ``1 - |A_R(f)|^2 T1(f)`` (module docstring); ``S1(f)`` when ``R = 1``.

    Raises
    ------
    ValueError
        If ``fs / fs1`` is not an integer or ``freqs`` is not a grid in ``[0, fs / 2]``.
    """
    fs = check_positive("fs", fs)
    fs1 = plant_fs(plant1, None)
    ratio = _ratio(fs1, fs)
    freqs = check_frequency_grid("freqs", freqs, fs)
    # Stage 1's response at f by periodicity (period fs1) and conjugate symmetry.
    folded = np.mod(freqs, fs1)
    mirror = folded > fs1 / 2
    folded = np.where(mirror, fs1 - folded, folded)
    grid, inverse = np.unique(folded, return_inverse=True)
    s1 = np.asarray(sensitivity(plant1, controller1, grid))[..., inverse]
    s1 = np.where(mirror, np.conj(s1), s1)
    if ratio == 1:
        return s1
    x = np.pi * freqs / fs
    with np.errstate(invalid="ignore", divide="ignore"):
        avg = np.sin(ratio * x) / (ratio * np.sin(x))
    avg = np.where(np.abs(np.sin(x)) < 1e-12, 1.0, avg)
    return 1.0 - avg**2 * (1.0 - s1)


def cascade_sensitivity(
    plant1: object,
    controller1: object,
    plant2: object,
    controller2: object,
    freqs: object,
    *,
    scheme: str,
) -> np.ndarray:
    """Baseband sensitivity of a two-stage cascade per mode, at the fast rate.

    Parameters
    ----------
    plant1 : control.TransferFunction or control.FRD
        Stage 1's plant at its rate ``fs1``.
    controller1 : control.TransferFunction, control.FRD or ControllerBank
        Stage 1's controller (``n1`` modes for a bank).
    plant2 : control.TransferFunction or control.FRD
        Stage 2's plant at the fast rate ``fs2 = R fs1``.
    controller2 : control.TransferFunction, control.FRD or ControllerBank
        Stage 2's controller (``n2`` modes for a bank).
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in ``[0, fs2 / 2]``.
    scheme : {"standalone", "dcao"}
        Cascade scheme (module docstring).

    Returns
    -------
    ndarray of complex, shape (n_freqs,) or (max(n1, n2), n_freqs)
        Disturbance to final residual; row ``i`` is mode ``i`` (a SISO controller counts as
        one mode applied to every row).

    Raises
    ------
    ValueError
        Unknown scheme, non-integer rate ratio, bad frequency grid.
    """
    if scheme not in _SCHEMES:
        raise ValueError(f"scheme must be one of {_SCHEMES}, got {scheme!r}")
    fs2 = plant_fs(plant2, None)
    s1 = slow_stage_sensitivity(plant1, controller1, freqs, fs2)
    s2 = np.asarray(sensitivity(plant2, controller2, freqs))
    if s1.ndim == 1 and s2.ndim == 1:
        return s1 * s2 if scheme == "standalone" else s2
    s1 = np.atleast_2d(s1)
    s2 = np.atleast_2d(s2)
    n = max(s1.shape[0], s2.shape[0])
    # A SISO controller (one row) applies to every mode.
    if s1.shape[0] == 1:
        s1 = np.broadcast_to(s1, (n, s1.shape[1]))
    if s2.shape[0] == 1:
        s2 = np.broadcast_to(s2, (n, s2.shape[1]))
    n1, n2 = s1.shape[0], s2.shape[0]
    out = np.empty((n, s2.shape[1]), dtype=complex)
    common = min(n1, n2)
    if scheme == "standalone":
        out[:common] = s1[:common] * s2[:common]
    else:
        out[:common] = s2[:common]
    if n1 > common:
        out[common:] = s1[common:]
    if n2 > common:
        out[common:] = s2[common:]
    return out


def cascade_rejection(
    plant1: object,
    controller1: object,
    plant2: object,
    controller2: object,
    freqs: object,
    *,
    scheme: str,
) -> np.ndarray:
    """Rejection ``|cascade_sensitivity|^2`` of a two-stage cascade, at the fast rate.

    Parameters
    ----------
    plant1 : control.TransferFunction or control.FRD
        Stage 1's plant at its rate ``fs1``.
    controller1 : control.TransferFunction, control.FRD or ControllerBank
        Stage 1's controller.
    plant2 : control.TransferFunction or control.FRD
        Stage 2's plant at the fast rate ``fs2 = R fs1``.
    controller2 : control.TransferFunction, control.FRD or ControllerBank
        Stage 2's controller.
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in ``[0, fs2 / 2]``.
    scheme : {"standalone", "dcao"}
        Cascade scheme.

    Returns
    -------
    ndarray, shape (n_freqs,) or (max(n1, n2), n_freqs)
        Residual PSD over disturbance PSD (baseband, see the module docstring for the
        aliased part below ``fs1 / 2``).
    """
    s = cascade_sensitivity(plant1, controller1, plant2, controller2, freqs, scheme=scheme)
    return np.abs(s) ** 2
