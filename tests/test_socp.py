"""Tests of the convex step of the data-driven synthesis (aocontrol.synthesis._socp) and of its
fine residual check (aocontrol.synthesis._dd_grids.fine_residual)."""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol._jit import ENV_NO_NUMBA
from aocontrol.analysis import residual_psd
from aocontrol.controllers import IIRBank
from aocontrol.plant import frequency_response, loop_plant
from aocontrol.synthesis import _dd_grids, _socp

FS = 1000.0
# Two interior-point solves of the same convex program (Clarabel, gap 1e-4 relative): the
# objectives agree to the gap, the coefficients to about its square root.
OBJ_RTOL = 3e-4
V_ATOL = 3e-2
# The fine check's refinement is a rearrangement of one trapezoid sum.
QUAD_RTOL = 1e-12


def _step_data(n: int, nq: int = 2):
    """Grid rows of ``K = X / ((1 - w) (1 + y w ...))`` on ``n`` points and an integrator
    start (gain 0.3) that meets the margin 0.4 there: (grid, v0, P0, weights)."""
    f = np.linspace(2.0, FS / 2 * 0.95, n)
    g = frequency_response(loop_plant(FS, 0.5), f, FS)
    w = np.exp(-2j * np.pi * f / FS)
    powers = w[:, None] ** np.arange(nq + 1)
    F = 1 - w
    nv = 2 * nq + 1
    AX = np.zeros((n, nv), complex)
    AY = np.zeros((n, nv), complex)
    AX[:, : nq + 1] = g[:, None] * powers
    AY[:, nq + 1 :] = F[:, None] * powers[:, 1:]
    grid = _socp.GridData(AY, AX, F, 0.4, 0.0)
    v0 = np.zeros(nv)
    v0[0] = 0.3
    P0 = grid.A @ v0 + grid.F
    assert np.all(np.abs(P0) >= 0.4 * np.abs(grid.AY @ v0 + grid.F))  # the start is feasible
    r1 = np.full(n, np.sqrt(0.9))
    rn = np.full(n, np.sqrt(0.1))
    h = 1.0 / (1.0 + (f / 20.0) ** 2)
    return grid, v0, P0, (r1, rn, h)


def test_sized_problem_solves_the_same_step_as_the_full_slot_problem():
    # 13 points in a problem of up to 24 slots: the sized problem solves it with 16 slots
    # (3 neutral), the full one with 24 (11 neutral); the neutral slots do not change the
    # optimum, so both steps agree to the solver's accuracy.
    grid, v0, P0, weights = _step_data(13)
    scale = _socp._g_scale(grid, P0, v0, *weights[:2])
    steps = []
    for prob in (
        _socp.ConvexifiedProblem(24, v0.size, False),
        _socp.SizedProblem(24, v0.size, False),
    ):
        prob.set_grid(grid, *weights)
        steps.append(prob.solve(P0, scale))
    assert (16, v0.size, False, 0) in _socp._PROBLEMS  # compiled at the grid's size
    J0 = _socp.true_objective(grid, v0, *weights)[0]
    J = [_socp.true_objective(grid, v, *weights)[0] for v in steps]
    assert J[0] < J0 and J[1] < J0  # a real step, not the start returned
    assert J[1] == pytest.approx(J[0], rel=OBJ_RTOL)
    np.testing.assert_allclose(steps[1], steps[0], atol=V_ATOL)


def test_sized_problem_switches_size_as_the_grid_grows_and_refuses_overflow():
    grid, v0, P0, weights = _step_data(13)
    prob = _socp.SizedProblem(24, v0.size, False)
    prob.set_grid(grid, *weights)
    prob.solve(P0, _socp._g_scale(grid, P0, v0, *weights[:2]))
    big, _, Pb, wb = _step_data(20)
    prob.set_grid(big, *wb)
    v = prob.solve(Pb, _socp._g_scale(big, Pb, v0, *wb[:2]))
    assert (24, v0.size, False, 0) in _socp._PROBLEMS
    # The margin rows of the 20-point grid hold at the new step (to the solver's tolerance).
    assert np.all(np.abs(big.A @ v + big.F) >= 0.4 * np.abs(big.AY @ v + big.F) * (1 - 1e-5))
    with pytest.raises(ValueError, match="exceeds the 24 slots"):
        prob.set_grid(_step_data(25)[0], *_step_data(25)[3])


def test_fine_residual_is_each_modes_trapezoid_on_its_own_refined_grid(monkeypatch):
    # Oracle: np.trapezoid of aocontrol.analysis.residual_psd on the common fine points and
    # the mode's own ladders, PSDs interpolated linearly; the implementation evaluates the
    # common points for all modes at once and refines per mode. A coarse common grid (41 +
    # 11 points) makes the ladders change the integrals at the percent level.
    monkeypatch.setattr(_dd_grids, "_FINE_LINEAR", 41)
    monkeypatch.setattr(_dd_grids, "_FINE_LOG", 11)
    G = loop_plant(FS, 0.5)
    f = np.linspace(0.0, FS / 2, 21)
    psd = 1.0 / (1.0 + (f[None, :] / np.array([[10.0], [10.0], [40.0]])) ** 3)
    noise = np.full_like(psd, 1e-3)
    # Modes 0 and 1: the same controller and PSD; only mode 0 lists peaks.
    b = np.array([[0.4, -0.1, 0.0], [0.4, -0.1, 0.0], [0.2, 0.05, -0.02]])
    a = np.array([[1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, -1.2, 0.21]])
    banks = (IIRBank(b, a, FS), IIRBank(0.8 * b, a, FS))
    peaks = [np.array([3.3, 123.4, 310.0]), np.empty(0), np.array([45.678])]
    fine = _dd_grids.fine_residual(G, banks, f, psd, noise, FS, peaks)
    common = np.unique(
        np.concatenate([f, np.linspace(0.0, FS / 2, 41), np.geomspace(f[1], FS / 2, 11)])
    )
    d = np.concatenate([-_dd_grids._PEAK_OFFSETS, _dd_grids._PEAK_OFFSETS]) * FS / 2
    for i in range(3):
        own = np.unique(np.concatenate([common, (peaks[i][:, None] + d).ravel()]))
        for k, bank in enumerate(banks):
            one = IIRBank(bank.b[i : i + 1], bank.a[i : i + 1], FS)
            r = residual_psd(
                G, one, own, np.interp(own, f, psd[i])[None], np.interp(own, f, noise[i])[None]
            )
            assert fine[k][i] == pytest.approx(np.trapezoid(r[0], own), rel=QUAD_RTOL)
    # The ladders matter here: mode 0 differs from mode 1 (same controller and PSD).
    assert abs(fine[0][0] / fine[0][1] - 1) > 1e-3
    # Blocks of one mode on two threads: the same bits as on one (each mode's arithmetic
    # unchanged), and the same to rounding as one block of three.
    monkeypatch.setattr(_dd_grids, "_FINE_BLOCK", 1)
    one, two = (
        _dd_grids.fine_residual(G, banks, f, psd, noise, FS, peaks, threads=n) for n in (1, 2)
    )
    for k in range(2):
        np.testing.assert_array_equal(two[k], one[k])
        np.testing.assert_allclose(two[k], fine[k], rtol=1e-12)


def test_fine_residual_compiled_loop_equals_the_numpy_path(monkeypatch):
    # Two paths that must agree: the compiled trapezoids (numba) and numpy's np.trapezoid of
    # the integrand, on well-conditioned loops (|1 + G K| far from cancelling) with numerator
    # and denominator of different lengths, a resonant PSD and a noise floor; to rounding
    # (the two sum in different orders). A twin: a wrong coefficient is seen.
    rng = np.random.default_rng(7)
    G = loop_plant(FS, 0.8)
    f = np.linspace(0.0, FS / 2, 301)
    psd = 1.0 / (1.0 + (f / 20.0) ** (11 / 3)) + 50.0 * np.exp(-(((f - 87.0) / 0.7) ** 2))
    psd = psd[None, :] * rng.uniform(0.5, 2.0, (5, 1))
    noise = np.full_like(psd, 1e-2) * rng.uniform(0.5, 2.0, (5, 1))
    b = np.column_stack([rng.uniform(0.2, 0.5, 5), rng.uniform(-0.1, 0.1, (5, 3))])
    a = np.column_stack([np.ones(5), -np.ones(5), rng.uniform(-0.05, 0.05, 5)])
    banks = (IIRBank(b, a, FS), IIRBank(0.6 * b, a, FS))
    peaks = [np.array([87.0])] + [np.empty(0)] * 4
    compiled = _dd_grids.fine_residual(G, banks, f, psd, noise, FS, peaks)
    b2 = b.copy()
    b2[2, 1] += 1e-6
    twin = _dd_grids.fine_residual(G, (IIRBank(b2, a, FS),), f, psd, noise, FS, peaks)[0]
    monkeypatch.setenv(ENV_NO_NUMBA, "1")
    plain = _dd_grids.fine_residual(G, banks, f, psd, noise, FS, peaks)
    for k in range(2):
        np.testing.assert_allclose(compiled[k], plain[k], rtol=QUAD_RTOL)
    assert abs(twin[2] / plain[0][2] - 1) > 100 * QUAD_RTOL
    np.testing.assert_allclose(twin[[0, 1, 3, 4]], plain[0][[0, 1, 3, 4]], rtol=QUAD_RTOL)
