"""Residual variance of an AO loop from disturbance and noise PSDs."""

from __future__ import annotations

import logging
import math

import control
import numpy as np

from aocontrol._validation import (
    check_broadcast,
    check_finite_array,
    check_frequency_grid,
    check_positive,
    mode_psds,
)
from aocontrol.analysis._loop import loop_response
from aocontrol.analysis._stability import is_stable
from aocontrol.controllers import ControllerBank
from aocontrol.plant import plant_fs

__all__ = ["mean_square_sampling_variance", "residual_psd", "residual_variance"]

logger = logging.getLogger(__name__)


def _integrate(y: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """Trapezoidal integral over the last axis (one-sided PSD -> variance)."""
    if freqs.size == 1:
        raise ValueError("freqs must have at least 2 points to integrate a PSD")
    return np.trapezoid(y, freqs, axis=-1)


def residual_psd(
    plant: object,
    controller: object,
    freqs: object,
    psd: object,
    noise_psd: object = 0.0,
    *,
    fs: float | None = None,
    loop_gain: object = None,
) -> np.ndarray:
    """One-sided residual PSD ``|S|^2 psd + |T|^2 noise_psd`` [units^2/Hz] on ``freqs``.

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    controller : control.TransferFunction, control.FRD or ControllerBank
        Controller at the plant's rate; a bank needs ``psd`` with one row per mode (or one
        row for all).
    freqs : array_like, shape (n_freqs,)
        Increasing grid in [0, fs/2] [Hz].
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz] (``scipy.signal.welch`` density).
    noise_psd : float or array_like
        Measurement-noise PSD, one-sided [units^2/Hz]: a scalar (white), ``(n_freqs,)``,
        ``(n_modes, n_freqs)`` or ``(n_modes,)`` (one white level per mode, 2-D ``psd``).
        White noise of per-frame variance ``s2`` has ``noise_psd = 2 s2 / fs``.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    loop_gain : float or array_like of shape (n_modes,), optional
        A gain the loop has beyond ``plant`` and ``controller`` (default 1), per mode for a
        bank: the loop is ``loop_gain G K``, e.g. the optical gains of a sensor read by its
        raw reconstructor (``S = 1 / (1 + og G K)``, the PSDs then referred to the
        residual). ``S`` is rescaled as ``S / (S + g (1 - S))``, exact where ``L = G K`` is
        infinite (an integrator at 0 Hz).

    Returns
    -------
    ndarray, shape (n_freqs,) or (n_modes, n_freqs)

    Raises
    ------
    ValueError
        A grid, PSD or control object that is invalid (named), or PSD rows that do not match
        the controller bank's modes.
    """
    fs_ = plant_fs(plant, fs)
    freqs = check_frequency_grid("freqs", freqs, fs_)
    psd_b, noise_b, single = mode_psds(psd, noise_psd, freqs.size)
    r = loop_response(plant, controller, freqs, fs_)
    if r.sensitivity.ndim == 2 and r.sensitivity.shape[0] > 1:
        # A bank: one PSD row per controller mode (or one row shared by all).
        n_ctrl = r.sensitivity.shape[0]
        expected = f"(n_freqs,) = ({freqs.size},) or (n_modes, n_freqs) = ({n_ctrl}, {freqs.size})"
        if psd_b.shape[0] not in (1, n_ctrl):
            check_broadcast("psd", np.asarray(psd), r.sensitivity.shape, expected)
        if noise_b.shape[0] not in (1, n_ctrl):
            check_broadcast("noise_psd", np.asarray(noise_psd), r.sensitivity.shape, expected)
    sens, comp = r.sensitivity, r.complementary
    if loop_gain is not None:
        lg = _loop_gain(loop_gain, sens.shape[0] if sens.ndim == 2 else 1)
        lg = lg[:, None] if sens.ndim == 2 else lg[0]
        sens = sens / (sens + lg * (1.0 - sens))
        comp = 1.0 - sens
    out = np.abs(sens) ** 2 * psd_b + np.abs(comp) ** 2 * noise_b
    return out[0] if single and sens.ndim == 1 else out


def _loop_gain(loop_gain: object, n_modes: int) -> np.ndarray:
    """``loop_gain`` as ``(n_modes,)`` values > 0 (a scalar broadcast)."""
    lg = np.atleast_1d(np.asarray(loop_gain, dtype=float))
    if lg.size == 1:
        lg = np.full(n_modes, float(lg[0]))
    if lg.shape != (n_modes,) or not np.all(np.isfinite(lg)) or np.any(lg <= 0):
        raise ValueError(
            f"loop_gain must be a finite value > 0 or {n_modes} of them (one per mode), got "
            f"shape {np.shape(loop_gain)} with values {np.asarray(loop_gain).ravel()[:4]!r}"
        )
    return lg


def residual_variance(
    plant: object,
    controller: object,
    freqs: object,
    psd: object,
    noise_psd: object = 0.0,
    *,
    fs: float | None = None,
    check_stability: bool = True,
    loop_gain: object = None,
) -> float | np.ndarray:
    """Residual variance ``int_0^{fs/2} (|S|^2 psd + |T|^2 noise_psd) df`` [units^2].

    The integral is a trapezoid on ``freqs``: the grid must resolve both the PSD and ``S``.
    An unstable loop has unbounded residual: ``inf`` is returned (for that mode of a bank)
    unless ``check_stability`` is False.

    Parameters
    ----------
    plant, controller, freqs, psd, noise_psd, fs, loop_gain
        As in :func:`residual_psd` (stability is certified for the loop ``loop_gain G K``).
    check_stability : bool, default True
        Return ``inf`` for an unstable closed loop (closed-loop poles, or the winding number
        for an FRD plant, which must then cover [0, fs/2]). Needs a controller with a
        transfer function: an FRD controller is refused (its unstable poles, an integrator's
        among them, are not in its response); pass ``check_stability=False`` to integrate
        its residual without a verdict.

    Returns
    -------
    float for a SISO TF/FRD controller and a 1-D ``psd``; ndarray of shape (n_modes,) for a
    ControllerBank (even with one mode) or a 2-D ``psd``.

    Raises
    ------
    ValueError
        As :func:`residual_psd`; and an FRD ``controller`` with ``check_stability`` True.

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.controllers import Integrator
    >>> G, fs = loop_plant(1000.0, 0.0), 1000.0
    >>> f = np.linspace(0, 500, 20001)
    >>> # Oracle: white noise through T of g/(z-1) plant z^-1 -> variance g/(2-g) per unit.
    >>> K = Integrator(0.5, fs=fs).transfer_function()
    >>> v = residual_variance(G, K, f, np.zeros_like(f), 2.0 / fs)
    >>> round(v, 6)
    0.333333
    """
    fs_ = plant_fs(plant, fs)
    if check_stability and isinstance(controller, control.FRD):
        raise ValueError(
            "controller is a control.FRD: closed-loop stability cannot be certified from a "
            "controller's frequency response (its unstable poles are not in it); give its "
            "transfer function or a ControllerBank, or pass check_stability=False to "
            "integrate the residual without a stability verdict"
        )
    res = _integrate(
        residual_psd(plant, controller, freqs, psd, noise_psd, fs=fs_, loop_gain=loop_gain),
        np.asarray(freqs, dtype=float),
    )
    if check_stability:
        if isinstance(controller, ControllerBank):
            n = controller.n_modes
            lg = np.ones(n) if loop_gain is None else _loop_gain(loop_gain, n)
            stable = np.array(
                [
                    is_stable(plant if lg[i] == 1 else plant * lg[i], controller, fs=fs_, mode=i)
                    for i in range(n)
                ]
            )
            if res.ndim == 0:
                res = np.full(controller.n_modes, float(res))
            res = np.where(stable, res, np.inf)
        elif not is_stable(
            plant if loop_gain is None else plant * float(_loop_gain(loop_gain, 1)[0]),
            controller,
            fs=fs_,
        ):
            res = np.full_like(res, np.inf)
        if np.any(np.isinf(res)):
            logger.warning("unstable closed loop: residual variance is infinite")
    return float(res) if np.ndim(res) == 0 else res


def mean_square_sampling_variance(freqs: object, psd: object, seconds: float) -> np.ndarray:
    """Variance of the mean square of a ``seconds``-long record of a stationary Gaussian
    signal of one-sided PSD ``psd``: ``int psd^2 df / seconds`` [units^4] per mode.

    The mean square of a record is itself a random variable: for a zero-mean Gaussian
    signal ``Cov(x^2(t), x^2(t + tau)) = 2 R(tau)^2`` (Isserlis), and Parseval gives
    ``sum_tau R(tau)^2 = (fs / 2) int_0^{fs/2} psd^2 df``, so the mean of ``n = fs T``
    samples has variance ``int psd^2 df / T`` (white noise of variance ``s2``: ``2 s2^2 /
    n``, the chi-square's). Valid for a record much longer than the signal's correlation
    time; the modes are taken independent (the variances of their mean squares add). A
    residual dominated by slow modes (tip and tilt behind a slow loop) scatters by tens of
    per cent between 0.5-s exposures: the figure a predicted-to-measured ratio is judged
    against (:class:`aocontrol.study.compare.Cell`).

    Parameters
    ----------
    freqs : array_like, shape (n_freqs,)
        Increasing grid from 0 [Hz] (the PSD's; at least 2 points).
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        One-sided PSD [units^2/Hz], >= 0, e.g. :func:`residual_psd`.
    seconds : float
        Record length [s], > 0.

    Returns
    -------
    float for a 1-D ``psd``, ndarray of shape (n_modes,) for a 2-D one.

    Raises
    ------
    ValueError
        ``freqs`` not increasing or negative, ``psd`` of the wrong shape, negative or not
        finite, ``seconds`` not > 0.

    Examples
    --------
    >>> fs, s2 = 1000.0, 4.0
    >>> f = np.linspace(0, fs / 2, 101)
    >>> v = mean_square_sampling_variance(f, np.full(f.size, 2 * s2 / fs), 2.0)
    >>> round(v * 2000 / (2 * s2**2), 12)  # 2 s2^2 / n for n = 2000 white samples
    1.0
    """
    t = check_positive("seconds", seconds)
    f = check_frequency_grid("freqs", freqs, math.inf)  # the PSD's grid; no rate given
    if f.size < 2:
        raise ValueError(f"freqs must hold at least 2 frequencies, got {f.size}")
    p = check_finite_array("psd", psd)
    if p.ndim not in (1, 2) or p.shape[-1] != f.size:
        raise ValueError(f"psd must have shape ({f.size},) or (n_modes, {f.size}), got {p.shape}")
    if np.any(p < 0):
        raise ValueError("psd must be >= 0 (a one-sided PSD)")
    out = _integrate(p**2, f) / t
    return float(out) if out.ndim == 0 else out
