"""No silent wrong answer from the control layer (issue 8): what arrives inside control objects.

Each class below was a silent wrong answer or a misleading error before its fix: a stability
verdict from an FRD that misses part of [0, fs/2], an improper controller taken for another
one, ``dt = 1.0`` refused, NaN/inf inside transfer functions and FRDs, one mode's numerical
failure aborting a whole bank, errors that blame the wrong argument, unbounded requests.
"""

from __future__ import annotations

import control
import numpy as np
import pytest
from conftest import integrator_stability_limit

from aocontrol import frequency_response, loop_plant, measured_plant
from aocontrol.analysis import (
    closed_loop_poles,
    is_stable,
    loop_response,
    margins,
    residual_psd,
    residual_variance,
    wiener_bound,
    winding_stability,
)
from aocontrol.controllers import IIRBank, Integrator
from aocontrol.disturbance import synthetic_turbulence_psd
from aocontrol.plant import check_frd_coverage, tf_from_z_inverse, z_inverse_coefficients
from aocontrol.synthesis import (
    DataDrivenError,
    ModalGainError,
    datadriven,
    integrator_gain_limit,
    optimal_modal_gain,
)

FS = 1000.0


def _frd(plant, f):
    return measured_plant(f, frequency_response(plant, f), FS)


# -- 1. FRD that does not cover [0, fs/2] ----------------------------------------------------


@pytest.fixture(scope="module")
def unstable_case():
    # G = z^-2 (limit g = 1) with g = 1.5: unstable, its -1 crossing at fs/6 ~ 167 Hz... and a
    # partial FRD measured on [200, 500] Hz or [0, 150] Hz that does not see it close.
    plant = loop_plant(FS, 1.0)
    return plant, Integrator(1.5, fs=FS)


@pytest.mark.parametrize(
    ("band", "missing"),
    [((0.0, 150.0), r"\[150, 500\] Hz"), ((200.0, 500.0), r"\[0, 200\] Hz"), ((5.0, 495.0), "and")],
)
def test_partial_frd_refuses_to_certify_stability(unstable_case, band, missing):
    plant, ctrl = unstable_case
    full = _frd(plant, np.linspace(0.0, FS / 2, 2001))
    assert not is_stable(full, ctrl)  # oracle: g = 1.5 > 1 with d = 2
    partial = _frd(plant, np.linspace(*band, 601))
    for call in (
        lambda: is_stable(partial, ctrl),
        lambda: winding_stability(partial, ctrl),
        lambda: margins(partial, ctrl),
        lambda: integrator_gain_limit(partial),
        lambda: optimal_modal_gain(partial, np.linspace(*band, 601), np.ones(601)),
        lambda: wiener_bound(partial, np.linspace(*band, 601), np.ones(601)),
    ):
        with pytest.raises(ValueError, match=f"plant must cover.*{missing}.*missing"):
            call()


def test_partial_grid_for_a_tf_plant_is_refused_too(unstable_case):
    plant, ctrl = unstable_case
    with pytest.raises(ValueError, match=r"freqs must cover.*\[0, 200\] Hz"):
        winding_stability(plant, ctrl, freqs=np.linspace(200.0, 500.0, 301))


def test_datadriven_refuses_a_partial_frd():
    f = np.linspace(0.0, 300.0, 121)
    with pytest.raises(ValueError, match=r"plant must cover.*\[300, 500\] Hz"):
        datadriven(_frd(loop_plant(FS, 1.0), f), f, np.ones(f.size), n_jobs=1, progress=False)


def test_frd_ending_half_a_step_short_is_covered():
    # An odd-length Welch grid ends half a step below Nyquist: that is the documented
    # tolerance (FRD_END_GAP_FRACTION = 0.5 of the end step), and the verdicts stay right.
    n = 401
    f = np.arange(n) * FS / (2 * n - 1)  # last point fs/2 - step/2
    check_frd_coverage("plant", f, FS)
    frd = _frd(loop_plant(FS, 1.0), f)
    # (g = 1 +- 10 %: zeros of P at |w| = 1/sqrt(g), resolved by this 1.25 Hz grid.)
    assert is_stable(frd, Integrator(0.9, fs=FS))
    assert not is_stable(frd, Integrator(1.1, fs=FS))
    with pytest.raises(ValueError, match="missing"):
        check_frd_coverage("plant", f[:-1], FS)


# -- 2. improper (non-causal) controllers ----------------------------------------------------


@pytest.mark.parametrize(
    "ctrl",
    [control.tf([3.0, 0.0], [1.0], 1 / FS), control.tf([1.0, 0.0, 0.0], [1.0, 0.5], 1 / FS)],
    ids=["3z", "z^2/(z+0.5)"],
)
def test_improper_controller_is_refused_by_name(ctrl):
    # K = 3z with G = z^-1: 1 + 3 = 4 != 0 would look "stable"; before the fix is_stable said
    # True (K was read as 0) while the closed loop z + 3 = 0 has its pole at -3.
    plant = loop_plant(FS, 0.0)
    for call in (
        lambda: is_stable(plant, ctrl),
        lambda: margins(plant, ctrl),
        lambda: closed_loop_poles(plant, ctrl),
        lambda: loop_response(plant, ctrl, [0.0, 100.0]),
        lambda: residual_variance(plant, ctrl, [0.0, 500.0], [1.0, 1.0]),
        lambda: IIRBank.from_transfer_functions([ctrl]),
    ):
        with pytest.raises(ValueError, match=r"(controller|tfs\[0\]) must be causal"):
            call()


def test_improper_plant_and_z_inverse_helpers():
    with pytest.raises(ValueError, match="plant must be causal"):
        is_stable(control.tf([1.0, 0.0], [1.0], 1 / FS), Integrator(0.5, fs=FS))
    with pytest.raises(ValueError, match="must be causal"):
        tf_from_z_inverse([1.0], [0.0, 1.0], 1 / FS)  # 1 / z^-1 = z
    # A common leading z^-1 cancels: z^-1 / z^-1 = 1 is causal.
    assert complex(tf_from_z_inverse([0.0, 2.0], [0.0, 1.0], 1 / FS)(0.3j)) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="sys must be causal"):
        z_inverse_coefficients(control.tf([3.0, 0.0], [1.0], 1 / FS))


# -- 3. dt == 1.0 exactly --------------------------------------------------------------------


def test_one_second_sampling_period_is_accepted():
    # Oracle: the same loop at 1 Hz as at 1 kHz (frequencies scale, verdicts and margins not).
    plant = loop_plant(1.0, 1.0)
    assert plant.dt == 1.0 and not isinstance(plant.dt, bool)
    ctrl = Integrator(0.5, fs=1.0)
    assert is_stable(plant, ctrl)
    m = margins(plant, ctrl.transfer_function())
    assert m.gain_margin == pytest.approx(integrator_stability_limit(2) / 0.5, rel=1e-8)
    assert m.phase_crossover_hz == pytest.approx(
        margins(loop_plant(FS, 1.0), Integrator(0.5, fs=FS)).phase_crossover_hz / FS, rel=1e-8
    )
    frd = measured_plant(
        np.linspace(0.0, 0.5, 501), frequency_response(plant, np.linspace(0.0, 0.5, 501)), 1.0
    )
    assert is_stable(frd, control.tf([0.5], [1.0, -1.0], 1.0))
    assert not is_stable(frd, control.tf([1.5], [1.0, -1.0], 1.0))


def test_dt_true_still_means_unspecified():
    plant = control.tf([1.0], [1.0, 0.0, 0.0], True)  # z^-2, period unspecified
    with pytest.raises(ValueError, match="plant must be discrete-time.*pass fs"):
        is_stable(plant, control.tf([0.5], [1.0, -1.0], True))
    # With fs given, dt=True objects are read at that rate.
    assert is_stable(plant, control.tf([0.5, 0.0], [1.0, -1.0], True), fs=FS)
    with pytest.raises(ValueError, match="tfs\\[0\\] must be discrete-time"):
        IIRBank.from_transfer_functions([control.tf([0.5], [1.0, -1.0], True)])


# -- 4. NaN / inf inside control objects -----------------------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nonfinite_transfer_function_coefficients_are_named(bad):
    good_plant, good_ctrl = loop_plant(FS, 1.0), Integrator(0.5, fs=FS).transfer_function()
    bad_plant = control.tf([bad, 1.0], [1.0, 0.0, 0.0], 1 / FS)
    bad_ctrl = control.tf([0.5], [1.0, bad], 1 / FS)
    with pytest.raises(ValueError, match="plant has NaN/inf in its numerator"):
        is_stable(bad_plant, good_ctrl)
    with pytest.raises(ValueError, match="controller has NaN/inf in its denominator"):
        is_stable(good_plant, bad_ctrl)
    with pytest.raises(ValueError, match="controller has NaN/inf"):
        margins(good_plant, bad_ctrl)
    with pytest.raises(ValueError, match="plant has NaN/inf"):
        residual_variance(bad_plant, good_ctrl, [0.0, 500.0], [1.0, 1.0])


def test_nonfinite_frd_point_is_named():
    f = np.linspace(0.0, FS / 2, 101)
    resp = frequency_response(loop_plant(FS, 1.0), f)
    resp[37] = np.nan
    frd = control.FRD(resp, 2 * np.pi * f, dt=1 / FS)  # python-control accepts it
    with pytest.raises(ValueError, match=r"plant \(FRD\) has 1 NaN/inf"):
        is_stable(frd, Integrator(0.5, fs=FS))
    with pytest.raises(ValueError, match=r"plant \(FRD\) has 1 NaN/inf"):
        residual_variance(frd, Integrator(0.5, fs=FS), f, np.ones(f.size))


# -- partial failure: one mode's numerical failure is that mode's ------------------------------


@pytest.mark.parametrize(
    "exc",
    [
        np.linalg.LinAlgError("singular matrix"),
        FloatingPointError("overflow"),
        ArithmeticError("arith"),
        ZeroDivisionError("zero"),
        ValueError("numerics"),
        pytest.param("cvxpy", id="SolverError"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_datadriven_reports_one_failed_mode_and_keeps_the_others(monkeypatch, exc):
    import aocontrol.synthesis._dd_mode as dd

    if exc == "cvxpy":
        import cvxpy

        exc = cvxpy.error.SolverError("solver died")
    real = dd._design_mode
    calls = []

    def flaky(ctx, q1, qn, b0, a0, warm=None):
        calls.append(1)
        if len(calls) == 2:  # the second mode
            raise exc
        return real(ctx, q1, qn, b0, a0, warm)

    monkeypatch.setattr(dd, "_design_mode", flaky)
    f = np.linspace(0.0, FS / 2, 101)
    psd = np.vstack([1.0 / (1.0 + (f / 10.0) ** 2)] * 3)
    with pytest.raises(DataDrivenError) as info:
        datadriven(loop_plant(FS, 1.0), f, psd, order=2, max_iter=4, n_jobs=1, progress=False)
    err = info.value
    assert list(err.failed) == [1]
    assert type(exc).__name__ in err.failed[1] or str(exc) in err.failed[1]
    np.testing.assert_array_equal(err.result.ok, [True, False, True])
    # The failed mode keeps the (stabilising) initial controller; the others their design.
    w = np.linspace(1.0, FS / 2, 7)  # (not 0 Hz: the integrator is infinite there)
    np.testing.assert_allclose(
        frequency_response(err.result.controller.transfer_function(1), w),
        frequency_response(err.result.initial.transfer_function(1), w),
        rtol=1e-12,
    )
    assert all(is_stable(loop_plant(FS, 1.0), err.result.controller, mode=i) for i in range(3))


@pytest.mark.parametrize("exc", [TypeError("bug"), AttributeError("bug"), NameError("bug")])
def test_datadriven_programming_errors_propagate(monkeypatch, exc):
    import aocontrol.synthesis._dd_mode as dd

    def broken(*args, **kwargs):
        raise exc

    monkeypatch.setattr(dd, "_design_mode", broken)
    f = np.linspace(0.0, FS / 2, 101)
    with pytest.raises(type(exc)):
        datadriven(loop_plant(FS, 1.0), f, np.ones(f.size), order=2, n_jobs=1, progress=False)


@pytest.mark.parametrize(
    "exc",
    [np.linalg.LinAlgError("x"), FloatingPointError("x"), ValueError("x"), OverflowError("x")],
    ids=lambda e: type(e).__name__,
)
def test_optimal_modal_gain_reports_one_failed_mode(monkeypatch, exc):
    import aocontrol.synthesis._modal_gain as mg

    f = np.linspace(0.0, FS / 2, 201)
    low = 1.0 / (1.0 + (f / 10.0) ** 2)
    psd = np.vstack([low, 7.0 * low, 3.0 * low])
    real = mg._residual_matrix

    def flaky(L1, w, gains, p, n):
        if np.any(p[:, 0] == 7.0):  # any block holding the marked mode fails
            raise exc
        return real(L1, w, gains, p, n)

    monkeypatch.setattr(mg, "_residual_matrix", flaky)
    plant = loop_plant(FS, 1.0)
    with pytest.raises(ModalGainError) as info:
        optimal_modal_gain(plant, f, psd, 1e-3)
    err = info.value
    assert list(err.failed) == [1]
    assert type(exc).__name__ in err.failed[1]
    # Oracle: the other modes equal the unpatched design of the same modes.
    monkeypatch.setattr(mg, "_residual_matrix", real)
    ref = optimal_modal_gain(plant, f, psd[[0, 2]], 1e-3)
    np.testing.assert_array_equal(err.result.gain[[0, 2]], ref.gain)
    assert 0 < err.result.gain[1] < 1e-3 * ref.gain.min()  # the fallback: tiny, stabilising
    monkeypatch.setattr(mg, "_residual_matrix", lambda *a: (_ for _ in ()).throw(TypeError("bug")))
    with pytest.raises(TypeError, match="bug"):
        optimal_modal_gain(plant, f, psd, 1e-3)


def test_nan_objective_does_not_win_the_gain_search():
    # A PSD at the edge of overflow makes J = inf * 0 = NaN for some gains; argmin used to pick
    # the NaN. Now the mode fails explicitly or gets a finite, stabilising gain.
    f = np.linspace(0.0, FS / 2, 201)
    psd = np.vstack([np.ones(f.size), np.full(f.size, 1e308)])
    try:
        K = optimal_modal_gain(loop_plant(FS, 1.0), f, psd)
    except ModalGainError as exc:
        assert 1 in exc.failed
        K = exc.result
    assert np.all(np.isfinite(K.gain)) and K.gain.max() < integrator_stability_limit(2)


# -- messages that blame the right argument ---------------------------------------------------


def test_controller_errors_name_the_controller():
    plant = loop_plant(FS, 1.0)
    with pytest.raises(ValueError, match="controller must be a discrete-time transfer function"):
        is_stable(plant, control.tf([1.0], [1.0, 1.0]))  # continuous time
    with pytest.raises(ValueError, match=r"controller runs at 500.0 Hz.*rate of the plant"):
        is_stable(plant, control.tf([0.5], [1.0, -1.0], 1 / 500.0))
    with pytest.raises(ValueError, match=r"controller runs at fs=500.0 Hz.*rate of the plant"):
        margins(plant, Integrator(0.5, fs=500.0))
    with pytest.raises(ValueError, match=r"initial runs at 500.0 Hz.*rate of the plant"):
        f = np.linspace(0.0, FS / 2, 11)
        datadriven(plant, f, np.ones(11), initial=control.tf([0.5], [1.0, -1.0], 1 / 500.0))


def test_psd_rows_and_bank_modes_mismatch_is_named():
    f = np.linspace(0.0, FS / 2, 11)
    bank = Integrator([0.2, 0.3], fs=FS)
    with pytest.raises(ValueError, match=r"psd must have shape .*\(2, 11\), got shape \(3, 11\)"):
        residual_psd(loop_plant(FS, 1.0), bank, f, np.ones((3, 11)))
    with pytest.raises(ValueError, match=r"noise_psd of shape \(3,\) must have 11 values"):
        residual_psd(loop_plant(FS, 1.0), bank, f, np.ones((3, 11))[0], np.ones(3))


# -- unbounded requests -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"order": 10**6}, r"order must be an integer in \[1, 64\]"),
        ({"n_grid": 10**7}, r"n_grid must be an integer in \[8, 4096\]"),
        ({"max_iter": 10**9}, r"max_iter must be an integer in \[1, 10000\]"),
    ],
)
def test_datadriven_sizes_are_bounded(kwargs, match):
    f = np.linspace(0.0, FS / 2, 11)
    with pytest.raises(ValueError, match=match):
        datadriven(loop_plant(FS, 1.0), f, np.ones(11), n_jobs=1, progress=False, **kwargs)


def test_latency_and_mode_counts_are_bounded():
    # Before: a latency of 1e9 frames or 1e9 modes tried to allocate gigabytes.
    with pytest.raises(ValueError, match="latency_frames must be <= 1000"):
        loop_plant(FS, 1e9)
    with pytest.raises(ValueError, match=r"n_modes must be an integer in \[1, 100000\]"):
        Integrator(0.5, fs=FS, n_modes=10**9)
    with pytest.raises(ValueError, match=r"n_modes must be an integer in \[1, 100000\]"):
        synthetic_turbulence_psd(np.linspace(0.0, 500.0, 11), 10**9, fs=FS)
