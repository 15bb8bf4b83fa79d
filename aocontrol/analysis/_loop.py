"""Closed-loop frequency responses of an AO loop.

Sign and signal conventions: the residual is ``e = S d - T n`` up to a unit-modulus delay on
the noise path, and the command ``u = K S (z^-1 d + n)``, with ``S = 1/(1+GK)``,
``T = GK/(1+GK)``. PSDs are one-sided [units^2/Hz]: integrated over [0, fs/2] they give the
variance (``scipy.signal.welch(..., scaling="density")``).
"""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np

from aocontrol._validation import check_finite_array, check_frequency_grid, check_positive
from aocontrol.controllers import ControllerBank, IIRBank
from aocontrol.plant import check_system, frequency_response, plant_fs

__all__ = [
    "LoopResponse",
    "loop_response",
    "controller_response",
    "sensitivity",
    "complementary_sensitivity",
    "noise_transfer",
    "command_transfer",
    "white_noise_psd",
]


def _as_siso_controller(controller: object, fs: float) -> object:
    """Validate a controller for analysis: TF/FRD (discrete, same rate) or a bank."""
    if isinstance(controller, ControllerBank):
        if abs(controller.fs - fs) > 1e-9 * fs:
            raise ValueError(
                f"controller runs at fs={controller.fs!r} Hz, expected the rate of the plant "
                f"({fs!r} Hz)"
            )
        return controller
    if isinstance(controller, (control.TransferFunction, control.FRD)):
        # SISO, finite, causal, discrete and at the plant's rate; errors name the controller.
        check_system("controller", controller, fs, rate_of="the plant")
        return controller
    raise TypeError(
        "controller must be a control.TransferFunction, control.FRD or a ControllerBank, "
        f"got {type(controller).__name__}"
    )


def controller_response(controller: object, freqs: object, fs: float) -> np.ndarray:
    """Frequency response of a controller at ``freqs`` [Hz].

    Returns shape ``(n_freqs,)`` for a SISO TF/FRD, ``(n_modes, n_freqs)`` for a bank
    (evaluated from the bank's coefficients, vectorised over modes).

    Parameters
    ----------
    controller : control.TransferFunction, control.FRD or ControllerBank
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in [0, fs/2].
    fs : float
        Loop rate [Hz] (must match the controller's).
    """
    fs = check_positive("fs", fs)
    controller = _as_siso_controller(controller, fs)
    freqs = check_frequency_grid("freqs", freqs, fs)
    if isinstance(controller, IIRBank):
        zi = np.exp(-2j * np.pi * freqs / fs)
        nb, na = controller.b.shape[1], controller.a.shape[1]
        vb = zi[None, :] ** np.arange(nb)[:, None]
        va = zi[None, :] ** np.arange(na)[:, None]
        return (controller.b @ vb) / (controller.a @ va)
    if isinstance(controller, ControllerBank):
        return np.stack(
            [
                frequency_response(controller.transfer_function(i), freqs, fs)
                for i in range(controller.n_modes)
            ]
        )
    return frequency_response(controller, freqs, fs)


@dataclass(frozen=True)
class LoopResponse:
    """Loop frequency responses on a grid.

    Attributes
    ----------
    freqs : ndarray, shape (n_freqs,)
        Frequencies [Hz].
    plant, controller, loop : ndarray of complex
        ``G``, ``K`` and ``L = G K``; shape ``(n_freqs,)`` or ``(n_modes, n_freqs)``.
    sensitivity : ndarray of complex
        ``S = 1/(1+L)``: disturbance to residual.
    complementary : ndarray of complex
        ``T = L/(1+L)``: measurement noise to residual (and stroke objective of the paper).
    command : ndarray of complex
        ``K S``: noise (or delayed disturbance) to command.
    """

    freqs: np.ndarray
    plant: np.ndarray
    controller: np.ndarray
    loop: np.ndarray
    sensitivity: np.ndarray
    complementary: np.ndarray
    command: np.ndarray


def loop_response(
    plant: control.TransferFunction | control.FRD,
    controller: object,
    freqs: object,
    fs: float | None = None,
) -> LoopResponse:
    """Evaluate ``G, K, L, S, T, KS`` on ``freqs`` [Hz] (grid in [0, fs/2]).

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    controller : control.TransferFunction, control.FRD or ControllerBank
        Causal controller at the plant's rate (a bank gives every mode at once, arrays of
        shape ``(n_modes, n_freqs)``).
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in [0, fs/2].
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.

    Returns
    -------
    LoopResponse

    Examples
    --------
    >>> from aocontrol.plant import loop_plant
    >>> from aocontrol.controllers import Integrator
    >>> r = loop_response(loop_plant(1000.0, 0.0), Integrator(0.5, fs=1000.0), [0.0, 500.0])
    >>> np.round(np.abs(r.sensitivity), 6)   # G = z^-1: S(1) = 0; S(-1) = 1/(1 - g/2)
    array([[0.      , 1.333333]])
    """
    fs_ = plant_fs(plant, fs)
    freqs = check_frequency_grid("freqs", freqs, fs_)
    G = frequency_response(plant, freqs, fs_)
    with np.errstate(divide="ignore", invalid="ignore"):
        K = controller_response(controller, freqs, fs_)
        L = G * K
        onepl = 1.0 + L
        S = np.where(np.isfinite(L), 1.0 / onepl, 0.0)
        T = np.where(np.isfinite(L), L / onepl, 1.0)
        KS = np.where(np.isfinite(K), K / onepl, 1.0 / G)
    return LoopResponse(freqs, G, K, L, S, T, KS)


def sensitivity(
    plant: object, controller: object, freqs: object, fs: float | None = None
) -> np.ndarray:
    """Sensitivity ``S = 1/(1+GK)`` (disturbance to residual) at ``freqs`` [Hz].

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    controller : control.TransferFunction, control.FRD or ControllerBank
        Controller (a bank gives every mode, shape ``(n_modes, n_freqs)``).
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in [0, fs/2].
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    """
    return loop_response(plant, controller, freqs, fs).sensitivity


def complementary_sensitivity(
    plant: object, controller: object, freqs: object, fs: float | None = None
) -> np.ndarray:
    """Complementary sensitivity ``T = GK/(1+GK)`` at ``freqs`` [Hz].

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    controller : control.TransferFunction, control.FRD or ControllerBank
        Controller (a bank gives every mode, shape ``(n_modes, n_freqs)``).
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in [0, fs/2].
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    """
    return loop_response(plant, controller, freqs, fs).complementary


def noise_transfer(
    plant: object, controller: object, freqs: object, fs: float | None = None
) -> np.ndarray:
    """Measurement noise to residual transfer at ``freqs`` [Hz].

    Equal to ``-T`` up to a pure delay (unit modulus); its squared modulus multiplies the
    noise PSD in the residual PSD.

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    controller : control.TransferFunction, control.FRD or ControllerBank
        Controller (a bank gives every mode, shape ``(n_modes, n_freqs)``).
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in [0, fs/2].
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    """
    return -loop_response(plant, controller, freqs, fs).complementary


def command_transfer(
    plant: object, controller: object, freqs: object, fs: float | None = None
) -> np.ndarray:
    """Measurement noise to command transfer ``K S`` at ``freqs`` [Hz].

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant.
    controller : control.TransferFunction, control.FRD or ControllerBank
        Controller (a bank gives every mode, shape ``(n_modes, n_freqs)``).
    freqs : array_like, shape (n_freqs,)
        Frequencies [Hz] in [0, fs/2].
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    """
    return loop_response(plant, controller, freqs, fs).command


def white_noise_psd(variance: object, fs: float) -> np.ndarray:
    """One-sided PSD [units^2/Hz] of white noise of per-frame ``variance`` at rate ``fs``.

    ``2 * variance / fs``, flat on [0, fs/2], so that its integral is ``variance``.

    Parameters
    ----------
    variance : float or array_like
        Per-frame noise variance [units^2], >= 0.
    fs : float
        Frame rate [Hz].

    Returns
    -------
    numpy.ndarray
        PSD [units^2/Hz], the shape of ``variance``.

    Examples
    --------
    >>> float(white_noise_psd(1.0, fs=1000.0))
    0.002
    """
    fs = check_positive("fs", fs)
    var = check_finite_array("variance", variance)
    if np.any(var < 0):
        raise ValueError(f"variance must be >= 0, got min {var.min()!r}")
    return 2.0 * var / fs
