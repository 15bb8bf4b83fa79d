"""Controller interface: real-time path vs transfer function, leak, clipping, bad input."""

import control
import numpy as np
import pytest
from scipy import signal

from aocontrol.controllers import ControllerBank, IIRBank, Integrator
from aocontrol.plant import z_inverse_coefficients

# step() and lfilter/the TF compute the same sums in a different order: rounding only.
ROUNDING = 1e-12


def _tf_impulse(tf: control.TransferFunction, n: int) -> np.ndarray:
    b, a = z_inverse_coefficients(tf)
    x = np.zeros(n)
    x[0] = 1.0
    return signal.lfilter(b, a, x)


def _controllers():
    rng = np.random.default_rng(0)
    # A random stable order-4 IIR bank with distinct coefficients per mode.
    poles = rng.uniform(-0.9, 0.9, size=(3, 4))
    a = np.array([np.poly(p) for p in poles])
    b = rng.normal(size=(3, 5))
    return [
        Integrator(0.4, fs=1000.0),
        Integrator([0.1, 0.5, 0.9], fs=3000.0, leak=0.01),
        IIRBank(b, a, fs=1250.0),
        IIRBank([0.3, 0.2], [1.0, -0.5, 0.1], fs=300.0, n_modes=4),
    ]


@pytest.mark.parametrize("ctrl", _controllers(), ids=repr)
def test_step_impulse_response_equals_transfer_function(ctrl):
    # Oracle: the DF-I recursion and the rational transfer function are the same LTI system.
    n = 64
    h = ctrl.impulse_response(n)
    for mode in range(ctrl.n_modes):
        np.testing.assert_allclose(
            h[:, mode], _tf_impulse(ctrl.transfer_function(mode), n), atol=ROUNDING, rtol=ROUNDING
        )


@pytest.mark.parametrize("ctrl", _controllers(), ids=repr)
def test_step_matches_lfilter_on_random_input(ctrl):
    # Linearity/time-invariance: any input, not just an impulse.
    rng = np.random.default_rng(1)
    x = rng.normal(size=(200, ctrl.n_modes))
    ctrl.reset()
    y = np.array([ctrl.step(xk) for xk in x])
    for mode in range(ctrl.n_modes):
        ref = signal.lfilter(ctrl.b[mode], ctrl.a[mode], x[:, mode])
        np.testing.assert_allclose(y[:, mode], ref, atol=1e-10)


def test_interface_is_abstract_and_shared():
    assert all(isinstance(c, ControllerBank) for c in _controllers())
    with pytest.raises(TypeError):
        ControllerBank()  # abstract


def test_integrator_transfer_function_and_leak():
    # Oracle: C(z) = g / (1 - (1 - leak) z^-1); constant input m gives u -> g m / leak.
    g, leak = 0.5, 0.05
    c = Integrator(g, fs=1000.0, leak=leak)
    w = 0.7
    expected = g / (1 - (1 - leak) * np.exp(-1j * w))
    assert complex(c.transfer_function()(np.exp(1j * w))) == pytest.approx(expected, rel=1e-12)
    u = [c.step(np.array([1.0]))[0] for _ in range(2000)]
    assert u[-1] == pytest.approx(g / leak, rel=1e-9)


def test_pure_integrator_accumulates():
    c = Integrator([0.2, 0.3], fs=1000.0)
    for _ in range(10):
        u = c.step(np.array([1.0, -1.0]))
    np.testing.assert_allclose(u, [2.0, -3.0], atol=ROUNDING)
    c.reset()
    np.testing.assert_allclose(c.step(np.array([1.0, 1.0])), [0.2, 0.3])


def test_clipping_antiwindup_keeps_state_consistent():
    # With anti-windup the recursion uses the applied (clipped) command: after the input
    # changes sign the command leaves the limit at once, instead of unwinding a huge state.
    c = Integrator(1.0, fs=1000.0, stroke=1.0)
    for _ in range(100):
        u = c.step(np.array([1.0]))
    assert u[0] == 1.0
    assert c.n_saturated[0] == 99  # first step reaches exactly 1.0 without clipping
    u = c.step(np.array([-0.5]))
    assert u[0] == pytest.approx(0.5)
    # Without a limit, the same sequence would still be at +99.5.
    free = Integrator(1.0, fs=1000.0)
    for _ in range(100):
        free.step(np.array([1.0]))
    assert free.step(np.array([-0.5]))[0] == pytest.approx(99.5)


def test_clipping_per_mode_stroke():
    c = IIRBank([1.0], [1.0], fs=100.0, n_modes=3, stroke=[1.0, 2.0, 3.0])
    np.testing.assert_allclose(c.step(np.array([5.0, -5.0, 2.5])), [1.0, -2.0, 2.5])
    np.testing.assert_array_equal(c.n_saturated, [1, 1, 0])


def test_from_transfer_functions_round_trip():
    tfs = [
        Integrator(0.3, fs=500.0).transfer_function(),
        IIRBank([0.1, 0.2], [1.0, -0.3, 0.2], fs=500.0).transfer_function(),
    ]
    bank = IIRBank.from_transfer_functions(tfs)
    assert bank.n_modes == 2
    for i, tf in enumerate(tfs):
        np.testing.assert_allclose(
            bank.impulse_response(20)[:, i], _tf_impulse(tf, 20), atol=ROUNDING
        )


def test_coefficients_are_read_only():
    c = Integrator(0.5, fs=1000.0)
    with pytest.raises(ValueError):
        c.b[0, 0] = 2.0


@pytest.mark.parametrize(
    ("make", "exc", "match"),
    [
        (lambda: Integrator(0.5, fs=0.0), ValueError, "fs must be a finite number > 0"),
        (lambda: Integrator(-0.1, fs=1000.0), ValueError, "gain must be >= 0"),
        (lambda: Integrator(0.5, fs=1000.0, leak=1.0), ValueError, r"leak must be in \[0.0, 1.0\)"),
        (lambda: Integrator([0.1, np.nan], fs=1000.0), ValueError, "gain must contain only finite"),
        (lambda: Integrator([0.1, 0.2], fs=1000.0, n_modes=3), ValueError, "disagrees"),
        (lambda: IIRBank([1.0], [0.0, 1.0], fs=10.0), ValueError, "causal"),
        (lambda: IIRBank(np.ones((2, 2)), np.ones((3, 2)), fs=10.0), ValueError, "same number"),
        (lambda: IIRBank([1.0], [1.0], fs=10.0, stroke=-1.0), ValueError, "stroke must be > 0"),
        (lambda: Integrator("a", fs=1000.0), TypeError, "gain must be array-like"),
    ],
)
def test_bad_construction(make, exc, match):
    with pytest.raises(exc, match=match):
        make()


def test_step_wrong_shape_raises():
    c = Integrator(0.5, fs=1000.0, n_modes=3)
    with pytest.raises(ValueError, match=r"measurement must have shape \(3,\).*got \(2,\)"):
        c.step(np.zeros(2))
    with pytest.raises(ValueError, match="mode must be in"):
        c.transfer_function(3)
