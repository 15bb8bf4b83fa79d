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


def _documented_order(b, a, x, stroke=None):
    """The IIRBank command in its documented summation order, one mode, plain Python floats."""
    nb, na = len(b), len(a)
    m_hist, u_hist, out = [0.0] * nb, [0.0] * na, []
    for xk in x:
        m_hist = [float(xk)] + m_hist[:-1]
        s_b = b[0] * m_hist[0]
        for i in range(1, nb):
            s_b += b[i] * m_hist[i]
        s_a = -a[1] * u_hist[1] if na > 1 else 0.0
        for i in range(2, na):
            s_a += -a[i] * u_hist[i]
        u = s_b + s_a
        if stroke is not None:
            u = min(max(u, -stroke), stroke)
        u_hist = [0.0, u] + u_hist[1:-1]
        out.append(u)
    return np.array(out)


@pytest.mark.parametrize(
    ("nb", "na", "stroke"), [(6, 6, None), (2, 6, None), (6, 2, 1.5), (1, 1, None)]
)
def test_step_is_bit_identical_to_its_documented_summation_order(nb, na, stroke):
    # Two implementations of the one documented order (vectorised circular buffer vs a scalar
    # loop per mode and tap) agree bit for bit, whatever the lengths of b and a (the shorter
    # side is padded with zero weights) and with clipping. A reordered sum would fail here
    # (it differs in the last bits on about half the frames).
    rng = np.random.default_rng(3)
    n_modes, n = 4, 300
    a = np.array([np.poly(p) for p in rng.uniform(-0.9, 0.9, size=(n_modes, na - 1))])
    b = rng.normal(size=(n_modes, nb))
    x = rng.normal(size=(n, n_modes))
    bank = IIRBank(b, a.reshape(n_modes, na), fs=1000.0, command_limit=stroke)
    y = np.array([bank.step(xk) for xk in x])
    for mode in range(n_modes):
        ref = _documented_order(bank.b[mode].tolist(), bank.a[mode].tolist(), x[:, mode], stroke)
        np.testing.assert_array_equal(y[:, mode], ref)


def test_finite_frame_whose_sum_overflows_is_not_rejected():
    # The fast finiteness check is a dot product of the frame with itself; finite values
    # whose squares overflow must fall back to the element-wise test and be accepted.
    c = IIRBank([1e-300], [1.0], fs=100.0, n_modes=2)
    u = c.step(np.array([1.5e308, 1.5e308]))
    assert c.n_rejected == 0
    np.testing.assert_allclose(u, [1.5e8, 1.5e8], rtol=1e-15)


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
    c = Integrator(1.0, fs=1000.0, command_limit=1.0)
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
    c = IIRBank([1.0], [1.0], fs=100.0, n_modes=3, command_limit=[1.0, 2.0, 3.0])
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
        (
            lambda: IIRBank([1.0], [1.0], fs=10.0, command_limit=-1.0),
            ValueError,
            "command_limit must be > 0",
        ),
        (lambda: Integrator("a", fs=1000.0), TypeError, "gain must be array-like"),
        (
            lambda: Integrator([0.1, 0.2], fs=1000.0, command_limit=[1.0, 2.0, 3.0]),
            ValueError,
            r"command_limit must have shape scalar or \(n_modes,\) = \(2,\), got shape \(3,\)",
        ),
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


# -- real-time policy for non-finite frames (shared by every ControllerBank) -------------------


@pytest.mark.parametrize("ctrl", _controllers(), ids=repr)
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_frame_is_rejected_and_state_kept_clean(ctrl, bad):
    # Oracle: the run with a bad frame at j equals the run with frame j removed, the command
    # of frame j being the held command of frame j-1 (bit for bit: same operations).
    rng = np.random.default_rng(2)
    n, j = 60, 23
    x = rng.normal(size=(n, ctrl.n_modes))
    x_bad = x.copy()
    x_bad[j, ctrl.n_modes // 2] = bad
    ctrl.reset()
    y_bad = np.array([ctrl.step(xk) for xk in x_bad])
    assert ctrl.n_rejected == 1
    ctrl.reset()
    assert ctrl.n_rejected == 0
    y_ref = np.array([ctrl.step(xk) for xk in np.delete(x, j, axis=0)])
    np.testing.assert_array_equal(y_bad[:j], y_ref[:j])
    np.testing.assert_array_equal(y_bad[j], y_bad[j - 1])
    np.testing.assert_array_equal(y_bad[j + 1 :], y_ref[j:])


def test_rejected_frame_after_reset_holds_zero_and_logs_sparingly(caplog):
    c = Integrator([0.5, 0.5], fs=1000.0)
    c.step(np.array([1.0, 1.0]))
    c.reset()
    with caplog.at_level("WARNING", logger="aocontrol.controllers._base"):
        for _ in range(2500):
            np.testing.assert_array_equal(c.step(np.array([np.nan, 1.0])), [0.0, 0.0])
    assert c.n_rejected == 2500
    # First rejection, then the 1000th and 2000th: not one line per frame.
    assert len(caplog.records) == 3
    assert "not finite for 1 mode" in caplog.records[0].getMessage()
    # The state is clean: the next valid frame is the first integrator step.
    np.testing.assert_array_equal(c.step(np.array([1.0, 1.0])), [0.5, 0.5])


def test_held_command_is_not_aliased():
    # Mutating a returned held command must not change what the controller holds.
    c = Integrator(1.0, fs=1000.0)
    c.step(np.array([2.0]))
    held = c.step(np.array([np.nan]))
    held[0] = 99.0
    assert c.step(np.array([np.inf]))[0] == 2.0


def test_subclass_implementing_step_hook_shares_the_policy():
    # A new controller implements _step/reset only; the base's step applies the policy and
    # its reset also clears the shared real-time state.
    class Gain(ControllerBank):
        n_modes = 2
        fs = 100.0

        def _step(self, m):
            self.calls += 1
            return 2.0 * m

        def reset(self):
            self.calls = 0

        def transfer_function(self, mode=0):
            return control.tf([2.0], [1.0], 1.0 / self.fs)

    g = Gain()
    g.reset()
    np.testing.assert_array_equal(g.step([1.0, 2.0]), [2.0, 4.0])
    np.testing.assert_array_equal(g.step([np.nan, 2.0]), [2.0, 4.0])
    assert (g.calls, g.n_rejected) == (1, 1)
    g.reset()
    assert g.n_rejected == 0
    np.testing.assert_array_equal(g.step([np.inf, 0.0]), [0.0, 0.0])


def test_bank_row_operations_keep_filters_and_limits():
    # The bank owns its row operations: taking rows keeps their command limits, replacing
    # rows pads orders and keeps this bank's limits, choosing per mode is take-or-keep, and
    # the parts of a bank reassemble it exactly.
    a = IIRBank([[0.5, 0.0], [0.3, 0.1], [0.2, 0.0]], [[1.0, -1.0], [1.0, -0.9], [1.0, -1.0]],
                fs=1000.0, command_limit=[1.0, 2.0, 3.0])  # fmt: skip
    sub = a.rows([2, 0])
    np.testing.assert_array_equal(sub.b, a.b[[2, 0]])
    np.testing.assert_array_equal(sub.command_limit, [3.0, 1.0])
    other = IIRBank.from_rows([[0.1, 0.2, 0.3]], [[1.0, -0.5, 0.1, 0.05]], 1000.0)
    c = a.with_rows([1], other)
    assert c.b.shape == (3, 3) and c.a.shape == (3, 4)
    np.testing.assert_array_equal(c.b[1], [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(c.b[0], [0.5, 0.0, 0.0])
    np.testing.assert_array_equal(c.command_limit, a.command_limit)
    # Impulse responses are those of the chosen filters (zero padding changes nothing).
    for i, src in ((0, a), (1, other), (2, a)):
        j = 0 if src is other else i
        np.testing.assert_allclose(c.impulse_response(8)[:, i], src.impulse_response(8)[:, j])
    w = a.where([True, False, True], c)
    np.testing.assert_array_equal(w.b[:, :2], a.b)
    whole = IIRBank.from_parts([([0, 2], a.rows([0, 2])), ([1], a.rows([1]))], 3)
    np.testing.assert_array_equal(whole.b, a.b)
    np.testing.assert_array_equal(whole.a, a.a)
    np.testing.assert_array_equal(whole.command_limit, a.command_limit)
    with pytest.raises(ValueError, match="do not cover modes \\[1\\]"):
        IIRBank.from_parts([([0, 2], a.rows([0, 2]))], 3)
    with pytest.raises(ValueError, match="mode indices in \\[0, 2\\]"):
        a.rows([3])
    with pytest.raises(ValueError, match="take must be a boolean array of shape \\(3,\\)"):
        a.where([True], c)
