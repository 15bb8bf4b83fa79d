"""Switch transients of an adaptive run (aocontrol.adaptive.switch_transients)."""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol.adaptive import switch_transients


def test_piecewise_constant_residual_gives_the_amplitude_ratio_squared():
    # Oracle: a residual constant at a_j between switches has energy ratio (a_{j+1} / a_j)^2
    # at each switch; the reference frames (midpoints with no switch within 2 * 50 frames) see
    # a constant residual, ratio exactly 1. A switch within 50 frames of an end is not measured.
    amp = np.array([1.0, 2.0, 0.5, 3.0])
    ks = [400, 800, 1200]
    e = np.repeat(amp, 400)[:, None] * np.ones((1, 4))
    t = switch_transients(e, [*ks, 1580], frames=50)
    np.testing.assert_array_equal(t.switch_frames, ks)
    np.testing.assert_allclose(t.ratios, (amp[1:] / amp[:-1]) ** 2, rtol=1e-12)
    np.testing.assert_array_equal(t.reference_frames, [600, 1000, 1390])
    np.testing.assert_allclose(t.reference_ratios, 1.0, rtol=1e-12)
    assert t.worst == pytest.approx((3 / 0.5) ** 2) and t.median == pytest.approx(4.0)


def test_midpoint_too_close_to_a_switch_is_no_reference():
    # Switches 150 frames apart: the midpoint is 75 frames from each, under 2 * 50: no reference
    # (its windows would hold a switch's); 1-D residuals are accepted.
    t = switch_transients(np.ones(1000), [400, 550], frames=50)
    assert t.reference_frames.size == 0 and np.isnan(t.p_value)
    assert np.isnan(switch_transients(np.ones(1000), []).median)


def test_a_transient_is_told_from_the_noise_and_no_transient_is_not():
    # White residual (24 modes), 40 switches 500 frames apart. Without a transient the switches'
    # ratios are draws of the reference's distribution (the test must not flag them); a bump
    # of 3x amplitude over the 10 frames after each switch (energy ratio (40 + 10 * 9) / 50 = 2.6)
    # must be flagged. p thresholds: 0.01 and 1e-6, far from the values either case gives.
    rng = np.random.default_rng(3)
    n, ks = 20_500, np.arange(500, 20_001, 500)
    e = rng.standard_normal((n, 24))
    calm = switch_transients(e, ks)
    assert calm.p_value > 0.01
    assert abs(calm.median / calm.reference_median - 1) < 0.05
    bumped = e.copy()
    for k in ks:
        bumped[k : k + 10] *= 3.0
    loud = switch_transients(bumped, ks)
    assert loud.p_value < 1e-6 and loud.median == pytest.approx(2.6, rel=0.05)
    np.testing.assert_allclose(loud.reference_ratios, calm.reference_ratios)


def test_bad_transient_arguments():
    with pytest.raises(ValueError, match="frames must be an integer >= 1, got 0"):
        switch_transients(np.ones(100), [50], frames=0)
    with pytest.raises(ValueError, match=r"residuals must be 1-D or 2-D .* got shape \(2, 2, 2\)"):
        switch_transients(np.ones((2, 2, 2)), [])
    with pytest.raises(ValueError, match=r"switch_frames must be in \[0, 100\]"):
        switch_transients(np.ones(100), [101])
