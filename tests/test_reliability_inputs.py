"""No input left unchecked (issue 18): the silent paths and weak messages a new user met.

Each test below failed before its fix: a negative PSD integrated silently, a documented input
(an FRD controller) that raised a ``TypeError`` from deep inside, and errors that did not
name the argument (``kl_basis(dm="dm")``, ``step(["a", "b", "c"])``).
"""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol import frequency_response, loop_plant, measured_plant
from aocontrol.analysis import (
    constrained_bound,
    residual_psd,
    residual_variance,
    wiener_bound,
)
from aocontrol.controllers import Integrator
from aocontrol.disturbance import psd_variance
from aocontrol.synthesis import (
    datadriven,
    fit_disturbance_model,
    lqg,
    mpc,
    optimal_modal_gain,
)

FS = 1000.0
G = loop_plant(FS, 1.0)
F = np.linspace(0.0, FS / 2, 257)
GOOD = 1.0 / (1.0 + (F / 10.0) ** 2)
C = Integrator(gain=0.3, fs=FS)

# Every public function that takes a PSD (disturbance ``psd``, ``noise_psd``): name -> call.
PSD_CALLS = {
    "psd_variance": lambda p, n: psd_variance(F, p + n),
    "constrained_bound": lambda p, n: constrained_bound(G, F, p, n, n_taps=8),
    "residual_psd": lambda p, n: residual_psd(G, C, F, p, n),
    "residual_variance": lambda p, n: residual_variance(G, C, F, p, n),
    "wiener_bound": lambda p, n: wiener_bound(G, F, p, n),
    "datadriven": lambda p, n: datadriven(G, F, p, noise_psd=n, order=2, progress=False),
    "fit_disturbance_model": lambda p, n: fit_disturbance_model(F, p, FS, noise_psd=n),
    "lqg": lambda p, n: lqg(G, F, p, noise_psd=n),
    "mpc": lambda p, n: mpc(G, F, p, noise_psd=n),
    "optimal_modal_gain": lambda p, n: optimal_modal_gain(G, F, p, n),
}


@pytest.mark.parametrize("name", sorted(PSD_CALLS))
def test_negative_psd_is_refused_by_name(name):
    # A PSD is >= 0: a negative one (a sign error, a log-PSD passed as a PSD) is refused,
    # naming the argument, never integrated (psd_variance of -1 everywhere returned -500).
    call = PSD_CALLS[name]
    with pytest.raises(ValueError, match=r"^psd must be >= 0 everywhere.*min -1\.0"):
        call(-GOOD, 0.0 * GOOD)
    if name != "psd_variance":
        with pytest.raises(ValueError, match=r"^noise_psd must be >= 0 everywhere"):
            call(GOOD, -1e-3)


def test_psd_variance_of_a_valid_psd_is_its_integral():
    # Oracle: a flat PSD of 2 units^2/Hz over [0, 500] Hz has variance 1000; any leading shape.
    flat = np.full((2, 3, F.size), 2.0)
    np.testing.assert_allclose(psd_variance(F, flat), 1000.0, rtol=1e-12)
    with pytest.raises(ValueError, match="psd must have 257 values along its last axis"):
        psd_variance(F, flat[..., :-1])


def test_residual_variance_with_an_frd_controller_is_refused_by_name():
    # An FRD controller hides its unstable poles (an integrator's at z = 1): no verdict from
    # it. Documented refusal naming the controller; without the check, the integral matches
    # the transfer function's (oracle: the same controller sampled on the grid).
    f = F[1:]
    K = C.transfer_function()
    K_frd = measured_plant(f, frequency_response(K, f), FS)
    with pytest.raises(ValueError, match=r"^controller is a control\.FRD.*check_stability=False"):
        residual_variance(G, K_frd, f, GOOD[1:])
    unchecked = residual_variance(G, K_frd, f, GOOD[1:], check_stability=False)
    assert unchecked == pytest.approx(residual_variance(G, K, f, GOOD[1:]), rel=1e-12)


@pytest.mark.parametrize("bad", [["a", "b", "c"], [1 + 2j, 0, 0], object()])
def test_step_names_the_measurement_for_a_non_numeric_frame(bad):
    bank = Integrator(gain=[0.3, 0.3, 0.3], fs=FS)
    with pytest.raises(TypeError, match=r"^measurement must be array-like of numbers"):
        bank.step(bad)
    # A non-finite frame is the real-time policy's (rejected, counted), not a type error.
    assert np.all(bank.step(np.array([np.nan, 0.0, 0.0])) == 0.0)


def test_kl_basis_names_a_wrong_mirror():
    from aocontrol.sim.modes import kl_basis

    with pytest.raises(TypeError, match=r"^dm must be a DeformableMirror, got str 'dm'"):
        kl_basis(dm="dm", n_modes=3)


def test_per_mode_errors_share_one_base():
    # One base for "failed for some modes, the others kept": one except clause catches them,
    # one message format names the first ten failed modes.
    from aocontrol._validation import PerModeError
    from aocontrol.analysis import ConstrainedBoundError
    from aocontrol.synthesis import DataDrivenError, ModalGainError

    assert issubclass(ModalGainError, PerModeError)
    assert issubclass(ConstrainedBoundError, PerModeError)
    assert issubclass(DataDrivenError, PerModeError)
    failed = {m: "LinAlgError: singular" for m in range(12)}
    err = ModalGainError(failed, Integrator(gain=np.full(20, 0.1), fs=FS))
    assert str(err).startswith("optimal modal gain failed for 12 of 20 modes: mode 0: LinAlg")
    assert "(and 2 more)" in str(err) and err.failed is failed and err.result.n_modes == 20


def test_fitting_error_names_a_wrong_basis():
    from aocontrol.sim.modes import fitting_error

    with pytest.raises(TypeError, match=r"^basis must be a ModalBasis, got ndarray"):
        fitting_error(np.eye(3), r0=0.1)
