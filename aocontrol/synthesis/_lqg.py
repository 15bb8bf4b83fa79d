"""LQG design: steady-state Kalman predictor and minimum-variance control through the delays.

Loop (the conventions of :mod:`aocontrol.analysis`): the residual is ``e[k] = d[k] - y[k]``,
the DM shape ``y[k] = (1 - f) u[k-k0] + f u[k-k0-1]`` and the measurement
``m[k] = d[k-1] - y[k-1] + n[k]`` (WFS integration of one frame), i.e. the plant
``G = z^-1 ((1 - f) z^-k0 + f z^-(k0+1))`` of :func:`aocontrol.plant.loop_plant` with
``(k0, f) = split_latency(latency_frames)``.

The command ``u[j]`` first acts on ``e[j+k0]``: the regulator minimises
``sum_j e[j+k0]^2 + rho u[j]^2`` with ``e[j+k0] = d[j+k0] - f u[j-1] - (1 - f) u[j]``, an LQ
problem on ``z[j] = (x_d[j+k0], u[j-1])`` with a cross term, solved by the discrete Riccati
equation (:func:`scipy.linalg.solve_discrete_are`). For ``rho = 0`` and ``f < 0.5`` its law is
the deconvolution ``u[j] = (d_hat[j+k0] - f u[j-1]) / (1 - f)`` (the DM shape equals the
predicted disturbance; stable since ``|f / (1 - f)| < 1``). For ``f > 0.5`` that inverse of
``(1 - f) + f z^-1`` is unstable; the DARE gives the optimal stable law instead (closed-loop
pole ``-(1 - f) / f``), whose residual is the Wiener bound with the all-pass cost of the
non-minimum-phase interpolation. At ``f = 0.5`` the optimum is marginal (pole at -1): a small
``rho`` is then required.

By separation the LQG command is that law applied to the Kalman estimate (certainty
equivalence); with the true model it reaches :func:`aocontrol.analysis.wiener_bound`.
PSDs are one-sided [units^2/Hz].
"""

from __future__ import annotations

import logging

import control
import numpy as np
import scipy.linalg

from aocontrol._validation import (
    check_finite_array,
    check_frequency_grid,
    check_nonnegative,
    mode_psds,
)
from aocontrol.controllers import LQGBank, LQGStateSpace
from aocontrol.plant import plant_fs, split_latency, z_inverse_coefficients
from aocontrol.synthesis._arfit import fit_disturbance_model
from aocontrol.synthesis._armodel import DisturbanceModel
from aocontrol.synthesis._telemetry import disturbance_from_telemetry

__all__ = ["lqg", "lqg_from_telemetry", "lqg_state_space", "plant_latency"]

logger = logging.getLogger(__name__)

# The filter's measurement-noise variance is floored at this fraction of the mode's
# disturbance variance: with no noise the Riccati equation is singular; a floor of 1e-9
# changes the residual by a relative ~1e-9.
_R_FLOOR = 1e-9
# Fractional latencies this close to 0.5 make the rho = 0 optimum marginal (pole at -1).
_HALF_TOL = 1e-6
# A Riccati solution is accepted when its relative residual is below this.
_DARE_RTOL = 1e-8
# Iterations of the doubling algorithm (quadratic convergence: ~30 suffice for any pole
# within 1e-9 of the unit circle).
_DOUBLING_ITER = 100
# Relative tolerance of the loop-plant structure check (coefficients from a TF round trip).
_PLANT_RTOL = 1e-9


def plant_latency(plant: control.TransferFunction) -> float:
    """Latency ``latency_frames`` of a :func:`aocontrol.plant.loop_plant` transfer function.

    The strict reading the LQG needs (a pure delay line of unit gain, which its state space
    models exactly); :func:`aocontrol.plant.plant_latency` reads the latency of any plant with
    that delay (a DM's lag or a gain beside it).

    Parameters
    ----------
    plant : control.TransferFunction
        ``G = z^-1 ((1-f) z^-k + f z^-(k+1))``.

    Returns
    -------
    float
        ``k + f`` [frames].

    Raises
    ------
    TypeError
        If ``plant`` is not a transfer function (a measured FRD has no state-space model).
    ValueError
        If it is not of the loop-plant form (LQG models that delay line exactly).
    """
    if not isinstance(plant, control.TransferFunction):
        raise TypeError(
            "plant must be a control.TransferFunction of the loop_plant form (LQG needs the "
            f"delay line as a state space), got {type(plant).__name__}"
        )
    plant_fs(plant)
    b, a = z_inverse_coefficients(plant)
    if a.size > 1 and np.any(np.abs(a[1:]) > _PLANT_RTOL):
        raise ValueError("plant must be a pure delay line z^-1((1-f) z^-k + f z^-(k+1)) (no poles)")
    nz = np.flatnonzero(np.abs(b) > _PLANT_RTOL * np.max(np.abs(b)))
    ok = (
        nz.size in (1, 2)
        and nz[0] >= 1
        and (nz.size == 1 or nz[1] == nz[0] + 1)
        and abs(b[nz].sum() - 1) < 1e-6
        and np.all(b[nz] > 0)
    )
    if not ok:
        raise ValueError(
            "plant must be of the loop_plant form z^-1((1-f) z^-k + f z^-(k+1)) with unit "
            f"DC gain, got z^-1 coefficients {np.round(b, 12).tolist()}"
        )
    k = int(nz[0]) - 1
    f = float(b[nz[1]]) if nz.size == 2 else 0.0
    return k + f


def _dare_residual(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray, x: np.ndarray):
    """Relative residual of ``X = A^T X A - A^T X B (R + B^T X B)^-1 B^T X A + Q``."""
    axb = a.T @ x @ b
    rhs = a.T @ x @ a - axb @ np.linalg.solve(r + b.T @ x @ b, axb.T) + q
    return float(np.max(np.abs(rhs - x)) / max(np.max(np.abs(x)), np.max(np.abs(q)), 1e-300))


def _doubling_dare(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Stabilising DARE solution by the structure-preserving doubling algorithm.

    Chu, Fan & Lin (2005): ``A_0 = A``, ``G_0 = B R^-1 B^T``, ``H_0 = Q``;
    ``W = I + G H``, ``A <- A W^-1 A``, ``G <- G + A W^-1 G A^T``, ``H <- H + A^T H W^-1 A``;
    ``H`` converges quadratically to ``X``. It stays accurate where scipy's ordered QZ fails
    (poles of ``A`` within ~1e-5 of the unit circle, e.g. a tip AR(2) at 3 kHz).
    """
    n = a.shape[0]
    eye = np.eye(n)
    ak, gk, hk = a.copy(), b @ np.linalg.solve(r, b.T), q.copy()
    for _ in range(_DOUBLING_ITER):
        w = eye + gk @ hk
        w_a = np.linalg.solve(w, ak)
        w_g = np.linalg.solve(w, gk)
        h_new = hk + ak.T @ hk @ w_a
        gk = gk + ak @ w_g @ ak.T
        ak = ak @ w_a
        done = np.max(np.abs(h_new - hk)) <= 1e-15 * max(np.max(np.abs(h_new)), 1e-300)
        hk = (h_new + h_new.T) / 2
        if done:
            break
    return hk


def _dare(a, b, q, r, what="") -> np.ndarray:
    """Stabilising solution of the DARE: scipy, or the doubling algorithm where scipy fails
    or is inaccurate; the result is checked by its residual."""
    try:
        x = scipy.linalg.solve_discrete_are(a, b, q, r)
        ok = np.all(np.isfinite(x)) and _dare_residual(a, b, q, r, x) < _DARE_RTOL
    except (np.linalg.LinAlgError, ValueError) as exc:
        logger.debug("scipy DARE failed (%s); doubling algorithm", exc)
        ok = False
    if not ok:
        x = _doubling_dare(a, b, q, r)
        if not (np.all(np.isfinite(x)) and _dare_residual(a, b, q, r, x) < _DARE_RTOL):
            raise ValueError(f"the {what} Riccati equation has no stabilising solution")
    return x


def _regulator_riccati(
    A: np.ndarray, C: np.ndarray, f: float, rho: float
) -> tuple[np.ndarray, np.ndarray]:
    """Stabilising solution and gain of the regulator DARE, solved block-wise.

    System ``z = (x, u_prev)``, ``z+ = (A x, u)``, stage cost
    ``(C x - f u_prev - (1 - f) u)^2 + rho u^2`` (a cross term). The disturbance block is
    uncontrollable, so a general solver (scipy's symplectic pencil) fails when its poles
    approach the unit circle; the blocks of the same Riccati equation solve in turn:

    * ``P_uu``: the scalar DARE of the command delay,
      ``P_uu^2 + (R - f^2) P_uu - f^2 rho = 0`` with ``R = (1 - f)^2 + rho``; its larger root
      is the stabilising one (closed-loop pole ``-g``, ``g = f (1 - f) / (R + P_uu)``:
      ``-f / (1 - f)`` for ``f < 0.5``, ``-(1 - f) / f`` for ``f > 0.5`` when ``rho = 0``);
    * ``P_xu = (g (1 - f) - f) (I + g A^T)^-1 C^T`` (linear);
    * ``P_xx``: the Stein equation ``P_xx = A^T P_xx A + C^T C - k k^T (R + P_uu)``,
      ``k = (A^T P_xu - (1 - f) C^T) / (R + P_uu)`` (``A`` stable).

    Returns ``P`` of shape ``(nx + 1, nx + 1)`` and the gain ``(k^T, g)`` of ``u = -gain z``.
    """
    R = (1 - f) ** 2 + rho
    b = R - f * f
    puu = (-b + np.sqrt(b * b + 4 * f * f * rho)) / 2
    den = R + puu
    g = f * (1 - f) / den
    nx = A.shape[0]
    pxu = (g * (1 - f) - f) * np.linalg.solve(np.eye(nx) + g * A.T, C)
    k = (A.T @ pxu - (1 - f) * C) / den
    pxx = scipy.linalg.solve_discrete_lyapunov(A.T, np.outer(C, C) - den * np.outer(k, k))
    P = np.zeros((nx + 1, nx + 1))
    P[:nx, :nx] = (pxx + pxx.T) / 2
    P[:nx, nx] = P[nx, :nx] = pxu
    P[nx, nx] = puu
    return P, np.concatenate([k, [g]])


def lqg_state_space(
    model: DisturbanceModel,
    latency_frames: float,
    noise_variance: object,
    *,
    control_weight: float = 0.0,
) -> LQGStateSpace:
    """Steady-state LQG of every mode: Kalman gain (filter DARE) and control law (LQ DARE).

    The loop state is ``xi[j] = (x_d[j-1], u[j-1], ..., u[j-n_u])`` (see
    :class:`aocontrol.controllers.LQGStateSpace`); the filter DARE runs on the disturbance
    block (the delay line is known exactly), the LQ DARE on ``z = (x_d[j+k0], u[j-1])``
    (module docstring).

    Parameters
    ----------
    model : DisturbanceModel
        Per-mode disturbance model.
    latency_frames : float
        RTC latency beyond the one-frame WFS integration [frames] (the plant's; split by
        :func:`aocontrol.plant.split_latency`).
    noise_variance : float or array_like of shape (n_modes,)
        White measurement-noise variance per frame [units^2] (``noise_psd * fs / 2``), >= 0.
        It is floored at ``1e-9`` of each mode's disturbance variance (a singular filter
        Riccati equation otherwise).
    control_weight : float, default 0.0
        ``rho >= 0``, weight of ``u^2`` in the stage cost ``e^2 + rho u^2`` (0: minimum
        residual variance). Required > 0 when the fractional latency is 0.5.

    Returns
    -------
    LQGStateSpace

    Raises
    ------
    ValueError
        Bad noise variance, ``f = 0.5`` with ``control_weight = 0``, or a Riccati equation
        without a stabilising solution (naming the mode).
    """
    if not isinstance(model, DisturbanceModel):
        raise TypeError(f"model must be a DisturbanceModel, got {type(model).__name__}")
    k0, f = split_latency(latency_frames)
    rho = check_nonnegative("control_weight", control_weight)
    if rho == 0 and abs(f - 0.5) < _HALF_TOL:
        raise ValueError(
            f"latency_frames={latency_frames!r} has the fractional part 0.5: the minimum-"
            "variance command is then marginally stable (a closed-loop pole at -1); pass "
            "control_weight > 0 (e.g. 1e-4)"
        )
    n, nx = model.n_modes, model.nx
    nv = check_finite_array("noise_variance", noise_variance, ndim=(0, 1))
    nv = np.broadcast_to(nv, (n,)).astype(float) if nv.ndim == 0 or nv.size == n else None
    if nv is None:
        raise ValueError(f"noise_variance must be a scalar or have shape ({n},)")
    if np.any(nv < 0):
        raise ValueError(f"noise_variance must be >= 0, got min {nv.min()!r}")
    R = np.maximum(nv, _R_FLOOR * np.maximum(model.variance, 1e-300))
    n_u = k0 + 1 if f == 0.0 else k0 + 2
    ns = nx + n_u
    nz = nx + 1
    A = np.zeros((n, ns, ns))
    A[:, :nx, :nx] = model.A
    for i in range(1, n_u):
        A[:, nx + i, nx + i - 1] = 1.0
    B = np.zeros((n, ns))
    B[:, nx] = 1.0
    C = np.zeros((n, ns))
    C[:, :nx] = model.C
    C[:, nx + k0] = -(1.0 - f)
    if f:
        C[:, nx + k0 + 1] = -f
    Q = np.zeros((n, ns, ns))
    Q[:, :nx, :nx] = model.Q
    P = np.zeros((n, ns, ns))
    K = np.zeros((n, ns))
    Az = np.zeros((n, nz, nz))
    Az[:, :nx, :nx] = model.A
    Bz = np.zeros((n, nz))
    Bz[:, nx] = 1.0
    Hz = np.zeros((n, nz))
    Hz[:, :nx] = model.C
    Hz[:, nx] = -f
    Dz = np.full(n, -(1.0 - f))
    Tz = np.zeros((n, nz, ns))
    Pz = np.zeros((n, nz, nz))
    L = np.zeros((n, ns))
    for mode in range(n):
        Ad, Cd = model.A[mode], model.C[mode]
        try:
            Pd = _dare(Ad.T, Cd[:, None], model.Q[mode], np.array([[R[mode]]]), what="filter")
            Pd = (Pd + Pd.T) / 2
            P[mode, :nx, :nx] = Pd
            K[mode, :nx] = Pd @ Cd / (Cd @ Pd @ Cd + R[mode])
            est = Ad - Ad @ np.outer(K[mode, :nx], Cd)
            if np.max(np.abs(np.linalg.eigvals(est))) >= 1.0:
                raise ValueError("the Kalman predictor is not stable")
        except ValueError as exc:
            raise ValueError(f"LQG design failed for mode {mode}: {exc}") from exc
        Pz[mode], gain = _regulator_riccati(Ad, Cd, f, rho)
        b = Bz[mode]
        Tz[mode, :nx, :nx] = np.linalg.matrix_power(Ad, k0 + 1)
        Tz[mode, nx, nx] = 1.0
        L[mode] = -gain @ Tz[mode]
        closed = Az[mode] - np.outer(b, gain)
        if np.max(np.abs(np.linalg.eigvals(closed))) >= 1.0:
            raise ValueError(f"LQG design failed for mode {mode}: the control law is not stable")
    return LQGStateSpace(
        A=A,
        B=B,
        C=C,
        Q=Q,
        R=R,
        P=P,
        kalman_gain=K,
        control_gain=L,
        regulator_A=Az,
        regulator_B=Bz,
        regulator_H=Hz,
        regulator_D=Dz,
        regulator_map=Tz,
        regulator_P=Pz,
        control_weight=rho,
        nx=nx,
        latency_frames=float(k0 + f),
        fs=model.fs,
    )


def _white_noise_variance(noise_psd: object, n_modes: int, freqs: np.ndarray, fs: float):
    """Per-frame variance of a white noise PSD given as scalar / per mode / per frequency."""
    _, noise2, _ = mode_psds(np.zeros((n_modes, freqs.size)), noise_psd, freqs.size)
    level = noise2.mean(axis=1)
    if not np.allclose(noise2, level[:, None], rtol=1e-9, atol=0):
        raise ValueError("noise_psd must be white (one level per mode): LQG models white noise")
    return level, level * fs / 2


def lqg(
    plant: control.TransferFunction,
    freqs: object,
    psd: object,
    *,
    noise_psd: object = 0.0,
    n_vibrations: int = 2,
    control_weight: float = 0.0,
    model: DisturbanceModel | None = None,
    peak_ratio: float = 4.0,
    min_vibration_fraction: float = 1e-2,
    n_jobs: int | None = 1,
) -> LQGBank:
    """LQG bank from disturbance and noise PSDs (the conventions of ``datadriven``).

    Fits the per-mode model (:func:`fit_disturbance_model`: AR(2) turbulence plus up to
    ``n_vibrations`` AR(2) resonances) unless ``model`` is given, then designs the
    steady-state LQG through the plant's delays (:func:`lqg_state_space`). LQG promises no
    margin: check it with :func:`aocontrol.analysis.margins`.

    Parameters
    ----------
    plant : control.TransferFunction
        Loop plant :func:`aocontrol.plant.loop_plant` (its latency, fractional included).
    freqs : array_like, shape (n_freqs,)
        Strictly increasing grid in ``[0, fs/2]`` [Hz].
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Disturbance PSD, one-sided [units^2/Hz].
    noise_psd : float or array_like, default 0.0
        White measurement-noise PSD, one-sided [units^2/Hz]: scalar or one level per mode
        (per-frame variance ``noise_psd * fs / 2``).
    n_vibrations : int, default 2
        Largest number of resonances fitted per mode.
    control_weight : float, default 0.0
        Weight ``rho`` of ``u^2`` in the LQ cost (see :func:`lqg_state_space`).
    model : DisturbanceModel, optional
        A known model (then ``psd`` only fixes the number of modes, which must agree).
    peak_ratio, min_vibration_fraction : float
        Peak detection of the fit (see :func:`fit_disturbance_model`).
    n_jobs : int or None, default 1
        Worker processes of the fit (``None``: every core).

    Returns
    -------
    LQGBank
        With the model in ``.model``.

    Raises
    ------
    ValueError, TypeError
        Bad inputs (see :func:`fit_disturbance_model`, :func:`lqg_state_space`), a plant not
        of the loop-plant form, a model whose rate or mode count disagrees.

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.analysis import residual_variance, wiener_bound
    >>> fs = 1000.0
    >>> f = np.geomspace(1e-3, fs / 2, 4000)
    >>> d = DisturbanceModel([[1.9, -0.9025]], [1.0], [[60.0]], [[0.02]], [[0.5]], fs=fs)
    >>> G = loop_plant(fs, 1.0)
    >>> bank = lqg(G, f, d.psd(f), noise_psd=1e-4, model=d)
    >>> ratio = residual_variance(G, bank, f, d.psd(f), 1e-4) / wiener_bound(G, f, d.psd(f), 1e-4)
    >>> bool(abs(ratio[0] - 1) < 0.02)
    True
    """
    latency = plant_latency(plant)
    fs = plant_fs(plant)
    freqs = check_frequency_grid("freqs", freqs, fs)
    psd2, _, _ = mode_psds(psd, 0.0, freqs.size)
    level, noise_var = _white_noise_variance(noise_psd, psd2.shape[0], freqs, fs)
    if model is None:
        model = fit_disturbance_model(
            freqs,
            psd2,
            fs,
            n_vibrations=n_vibrations,
            noise_psd=level,
            peak_ratio=peak_ratio,
            min_vibration_fraction=min_vibration_fraction,
            n_jobs=n_jobs,
        )
    elif not isinstance(model, DisturbanceModel):
        raise TypeError(f"model must be a DisturbanceModel or None, got {type(model).__name__}")
    if abs(model.fs - fs) > 1e-9 * fs:
        raise ValueError(f"model runs at fs={model.fs} Hz, the plant at {fs} Hz")
    if model.n_modes != psd2.shape[0]:
        raise ValueError(f"model has {model.n_modes} modes, psd has {psd2.shape[0]} rows")
    ss = lqg_state_space(model, latency, noise_var, control_weight=control_weight)
    return LQGBank(ss, model=model)


def lqg_from_telemetry(
    measurements: object,
    commands: object,
    plant: control.TransferFunction,
    *,
    nperseg: int | None = None,
    noise_band: tuple[float, float] = (0.8, 1.0),
    n_vibrations: int = 2,
    control_weight: float = 0.0,
    n_jobs: int | None = 1,
    method: str = "prewhitened",
) -> LQGBank:
    """LQG bank from closed-loop telemetry: pseudo open loop -> PSD and noise -> model -> LQG.

    :func:`aocontrol.synthesis.disturbance_from_telemetry` (pre-whitened Welch PSD of
    ``m + G u`` by default, white noise floor) then :func:`lqg` on its PSD and per-mode noise
    level.

    Parameters
    ----------
    measurements : array_like, shape (n_frames, n_modes) or (n_frames,)
        Closed-loop modal measurements [units].
    commands : array_like, same shape
        Modal commands computed from them at the same frame [units].
    plant : control.TransferFunction
        Loop plant :func:`aocontrol.plant.loop_plant`.
    nperseg : int, optional
        Welch segment length [frames] (default
        :func:`aocontrol.synthesis.default_nperseg`).
    noise_band : (float, float), default (0.8, 1.0)
        Noise-floor band as fractions of Nyquist.
    n_vibrations : int, default 2
        Largest number of resonances fitted per mode.
    control_weight : float, default 0.0
        Weight ``rho`` of ``u^2`` in the LQ cost.
    n_jobs : int or None, default 1
        Worker processes of the fit (``None``: every core).
    method : {"prewhitened", "welch"}, default "prewhitened"
        Disturbance estimator of :func:`aocontrol.synthesis.disturbance_from_telemetry`.

    Returns
    -------
    LQGBank
    """
    tel = disturbance_from_telemetry(
        measurements, commands, plant, nperseg=nperseg, noise_band=noise_band, method=method
    )
    return lqg(
        plant,
        tel.freqs,
        tel.psd,
        noise_psd=tel.noise_psd,
        n_vibrations=n_vibrations,
        control_weight=control_weight,
        n_jobs=n_jobs,
    )
