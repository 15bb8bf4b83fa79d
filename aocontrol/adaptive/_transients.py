"""Switch transients of an adaptive run: the residual after each switch against before it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aocontrol._validation import check_int

#: Frames on each side of a switch over which the residual energy is compared (issue 17).
TRANSIENT_FRAMES = 50


@dataclass(frozen=True)
class SwitchTransients:
    """Residual energy in the ``frames`` frames after each switch / in the ``frames`` before,
    and the same ratio at reference frames where no switch happened (its spread is the noise
    a switch's ratio is judged against).

    Attributes
    ----------
    frames : int
        Frames on each side.
    switch_frames : ndarray of int, shape (n_switches,)
        The switches measured (those with ``frames`` frames on each side in the run).
    ratios : ndarray, shape (n_switches,)
        Energy of frames ``[k, k + frames)`` / energy of ``[k - frames, k)`` at each switch ``k``
        (the energy summed over modes and frames).
    reference_frames : ndarray of int, shape (n_reference,)
        Midpoints between consecutive switches whose ``2 frames`` frames on each side hold no
        switch: neither pair of windows overlaps a switch's.
    reference_ratios : ndarray, shape (n_reference,)
        The same ratio at each reference frame.
    p_value : float
        One-sided Mann-Whitney U test (:func:`scipy.stats.mannwhitneyu`) that the switches'
        ratios are larger than the reference's (``nan`` if either is empty): a small value
        means the switches raise the residual beyond the noise.
    """

    frames: int
    switch_frames: np.ndarray
    ratios: np.ndarray
    reference_frames: np.ndarray
    reference_ratios: np.ndarray
    p_value: float

    @property
    def median(self) -> float:
        """Median ratio over the switches (``nan`` without one)."""
        return float(np.median(self.ratios)) if self.ratios.size else float("nan")

    @property
    def worst(self) -> float:
        """Largest ratio over the switches (``nan`` without one)."""
        return float(np.max(self.ratios)) if self.ratios.size else float("nan")

    @property
    def reference_median(self) -> float:
        """Median ratio over the reference frames (``nan`` without one)."""
        return float(np.median(self.reference_ratios)) if self.reference_ratios.size else np.nan

    @property
    def reference_worst(self) -> float:
        """Largest ratio over the reference frames (``nan`` without one)."""
        return float(np.max(self.reference_ratios)) if self.reference_ratios.size else np.nan


def switch_transients(
    residuals: np.ndarray, switch_frames, frames: int = TRANSIENT_FRAMES
) -> SwitchTransients:
    """The residual energy after each switch / before it, with its no-switch reference.

    Parameters
    ----------
    residuals : ndarray, shape (n_frames,) or (n_frames, n_modes)
        Residual of each frame (of the run whose switches are ``switch_frames``).
    switch_frames : sequence of int
        Frames at which a new bank started (:attr:`AdaptiveRun.switch_frames`).
    frames : int, default :data:`TRANSIENT_FRAMES`
        Frames on each side.

    Returns
    -------
    SwitchTransients

    Raises
    ------
    ValueError
        ``frames`` not a positive integer, ``residuals`` not 1-D or 2-D, a switch frame outside
        ``[0, n_frames]``.

    Examples
    --------
    >>> e = np.ones((1000, 3))
    >>> e[500:] *= 2.0  # the residual doubles at a switch: the energy ratio is 4
    >>> t = switch_transients(e, [500, 980], frames=50)  # 980: too close to the end
    >>> t.ratios.tolist(), t.reference_frames.tolist(), t.reference_ratios.tolist()
    ([4.0], [740], [1.0])
    """
    frames = check_int("frames", frames, minimum=1)
    e = np.asarray(residuals, dtype=float)
    if e.ndim not in (1, 2):
        raise ValueError(f"residuals must be 1-D or 2-D (frames, modes), got shape {e.shape}")
    energy = (e.reshape(e.shape[0], -1) ** 2).sum(axis=1)
    n = energy.size
    ks = np.asarray(sorted(int(k) for k in switch_frames), dtype=int)
    if ks.size and (ks[0] < 0 or ks[-1] > n):
        raise ValueError(f"switch_frames must be in [0, {n}] (the residual's frames), got {ks}")
    cum = np.concatenate(([0.0], np.cumsum(energy)))

    def ratio(k: np.ndarray) -> np.ndarray:
        return (cum[k + frames] - cum[k]) / (cum[k] - cum[k - frames])

    measured = ks[(ks >= frames) & (ks <= n - frames)]
    mid = (ks[:-1] + ks[1:]) // 2
    clear = np.all(np.abs(mid[:, None] - ks[None, :]) >= 2 * frames, axis=1)
    ref = mid[clear & (mid >= frames) & (mid <= n - frames)]
    r, r0 = ratio(measured), ratio(ref)
    p = float("nan")
    if r.size and r0.size:
        from scipy.stats import mannwhitneyu

        p = float(mannwhitneyu(r, r0, alternative="greater").pvalue)
    return SwitchTransients(frames, measured, r, ref, r0, p)
