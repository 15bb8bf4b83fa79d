"""PSD estimation from telemetry, the convention of the whole project."""

from __future__ import annotations

import numpy as np
from scipy import signal

from aocontrol._validation import check_finite_array, check_int, check_positive

__all__ = ["welch_psd"]


def welch_psd(x: object, fs: float, nperseg: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD [units^2/Hz] of modal telemetry ``(n_frames, n_modes)``.

    ``scipy.signal.welch`` (Hann window, 50 % overlap, density scaling) with two choices made
    for AO telemetry: the mean of the whole record is removed once, not per segment (a
    per-segment detrend also removes the lowest frequencies of a disturbance dominated by
    them: up to 70 % of a low-order mode's variance in a 4-s record), and the 0 Hz and Nyquist
    bins are doubled so that the result is the one-sided density at every frequency
    (integrated over [0, fs/2] it gives the variance; white noise is flat).

    Parameters
    ----------
    x : array_like, shape (n_frames,) or (n_frames, n_modes)
        Telemetry [units].
    fs : float
        Frame rate [Hz].
    nperseg : int
        Segment length [frames]; reduced to ``n_frames`` for short records.

    Returns
    -------
    freqs : ndarray, shape (n_freqs,)
        [Hz], from 0 to fs/2.
    psd : ndarray, shape (n_freqs,) or (n_modes, n_freqs)
        [units^2/Hz].

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> f, p = welch_psd(rng.standard_normal((100000, 1)), fs=1000.0, nperseg=256)
    >>> round(float(np.trapezoid(p[0], f)), 1)                # unit variance
    1.0
    """
    fs = check_positive("fs", fs)
    arr = check_finite_array("x", x, ndim=(1, 2))
    nperseg = check_int("nperseg", nperseg, minimum=2)
    if arr.shape[0] < 2:
        hint = " (transposed? frames go along the first axis)" if arr.ndim == 2 else ""
        raise ValueError(
            f"x must have shape (n_frames,) or (n_frames, n_modes) with n_frames >= 2, "
            f"got {arr.shape}{hint}"
        )
    nper = min(nperseg, arr.shape[0])
    freqs, pxx = signal.welch(
        arr - arr.mean(axis=0),
        fs=fs,
        window="hann",
        nperseg=nper,
        noverlap=nper // 2,
        detrend=False,
        return_onesided=True,
        scaling="density",
        axis=0,
    )
    pxx = np.moveaxis(pxx, 0, -1).copy()
    pxx[..., 0] *= 2
    if nper % 2 == 0:
        pxx[..., -1] *= 2
    return freqs, pxx
