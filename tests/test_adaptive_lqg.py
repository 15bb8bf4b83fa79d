"""Issue 17: the adaptive LQG diverged at a bumpless switch although certified.

The LQG's exact transfer function (``ss2tf`` of its state space) has nearly cancelling
pole/zero pairs at the disturbance model's poles near ``z = 1``; run as one Direct-Form I
recursion these are internal modes that turn a tiny mismatch of the filter state into a
transient of ``1e7`` to ``1e9`` times its size, while the transfer function's closed loop is
stable with a good modulus margin. Oracles: a time-domain simulation of the Direct-Form I
closed loop (the amplification of a state mismatch) against :func:`recursion_gain`, and the
LQG's own state-space frequency response against the bank the designer proposes.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from aocontrol import loop_plant
from aocontrol.adaptive import certify, lqg_designer
from aocontrol.adaptive._redesign import MAX_RECURSION_GAIN, recursion_gain
from aocontrol.controllers import IIRBank, Integrator
from aocontrol.synthesis import DisturbanceModel, TelemetryPSD, lqg

FS = 3000.0
LATENCY = 0.828
R, THETA = 0.99846, 0.00174  # turbulence AR(2) poles of mode 13 of the run


@pytest.fixture(scope="module")
def case():
    """An LQG on the issue's disturbance model (slow turbulence, two sharp resonances)."""
    plant = loop_plant(FS, LATENCY)
    model = DisturbanceModel(
        [[2 * R * np.cos(THETA), -R * R]],
        [100.0],
        [[4.8, 11.7]],
        [[0.005, 0.012]],
        [[0.1, 0.1]],
        fs=FS,
    )
    freqs = np.linspace(0.0, FS / 2, 1025)
    psd = model.psd(freqs)
    noise = np.array([1e-3])
    tel = TelemetryPSD(
        freqs=freqs,
        psd=psd,
        noise_psd=noise,
        pseudo_open_loop=np.zeros((8, 1)),
        pol_psd=psd,
        fs=FS,
        noise_band=(0.8, 1.0),
        method="welch",
    )
    return plant, tel, lqg(plant, freqs, psd, noise_psd=noise, model=model)


def _mismatch_peak(plant, b, a, n=20000):
    """Largest |u| of the Direct-Form I closed loop (no disturbance, no noise) after a unit
    mismatch of the recursion at frame 0: the time-domain oracle of recursion_gain."""
    gb, ga = (np.atleast_1d(np.squeeze(c)) for c in (plant.num[0][0], plant.den[0][0]))
    gb = np.concatenate([np.zeros(ga.size - gb.size), gb]) / ga[0]  # powers of z^-1
    ch = np.zeros(max(a.size, b.size + gb.size - 1))
    ch[: a.size] += a
    ch[: b.size + gb.size - 1] += np.convolve(b, gb)
    x = np.zeros(n)
    x[0] = 1.0
    return np.abs(signal.lfilter([1.0], ch, x)).max()


def test_exact_lqg_transfer_function_is_refused_by_the_recursion_gain(case):
    plant, _, bank = case
    exact = IIRBank.from_transfer_functions([bank.transfer_function(0)])
    b, a = exact.b[0], exact.a[0]
    g = recursion_gain(plant, b, a)
    peak = _mismatch_peak(plant, b, a)
    # Stable with a margin (what certify checked before issue 17), yet a unit mismatch of
    # the recursion gives a command of 1e6 and more: the switch transient that diverged.
    assert peak > 1e6
    assert g >= peak  # the H-infinity gain bounds the impulse response's peak from above
    ok, margin, reasons = certify(plant, exact, modulus_margin=0.3)
    assert margin[0] > 0.3 and not ok[0]
    assert "recursion gain" in reasons[0]


def test_lqg_designer_proposal_is_the_lqg_and_certify_matches_the_time_domain(case):
    plant, tel, _ = case
    current = Integrator(0.3, fs=FS, n_modes=1)
    design = lqg_designer(realisation="direct")  # the Direct-Form I proposal, cancelled
    prop = design(tel, plant, current)
    # The designer's own LQG (same fit): its state-space response is the reference.
    bank = lqg(plant, tel.freqs, tel.psd, noise_psd=tel.noise_psd)
    F, G, H, J = (x[0] for x in bank.state_space.controller_matrices)
    w = np.linspace(0.0, np.pi, 1001)
    z = np.exp(1j * w)
    ref = np.array([J + H @ np.linalg.solve(zk * np.eye(F.shape[0]) - F, G) for zk in z])
    b, a = prop.controller.b[0], prop.controller.a[0]
    got = np.polyval(b[::-1], 1 / z) / np.polyval(a[::-1], 1 / z)
    assert np.max(np.abs(got / ref - 1)) < 0.05
    exact = IIRBank.from_transfer_functions([bank.transfer_function(0)])
    g, g_exact = recursion_gain(plant, b, a), recursion_gain(plant, exact.b[0], exact.a[0])
    assert g <= 1.01 * g_exact  # a cancellation never makes the recursion worse
    # The certificate's verdict agrees with the time domain: what it admits amplifies a
    # state mismatch by at most MAX_RECURSION_GAIN; what it refuses, by more than 100x less.
    ok, _, reasons = certify(plant, prop.controller, modulus_margin=0.3)
    peak = _mismatch_peak(plant, b, a)
    assert peak <= g * (1 + 1e-9)
    if ok[0]:
        assert peak <= MAX_RECURSION_GAIN
    else:
        assert "recursion gain" in reasons[0] and peak > MAX_RECURSION_GAIN / 100


def test_certify_checks_the_recursion_gain_argument():
    plant = loop_plant(FS, LATENCY)
    with pytest.raises(ValueError, match="max_recursion_gain"):
        certify(plant, Integrator(0.3, fs=FS), modulus_margin=0.3, max_recursion_gain=0.0)
    assert recursion_gain(plant, np.array([0.3]), np.array([1.0, -1.0])) < MAX_RECURSION_GAIN


def test_certify_gives_every_mode_the_recursion_gain_of_its_own_row():
    # Two paths that must agree: certify computes the plant's part of the gain once for the
    # bank, recursion_gain once per call. Three integrators of different gains (three
    # different recursion gains): with the threshold between two of them, exactly the modes
    # whose own recursion_gain exceeds it fail, and the reason quotes that gain.
    plant = loop_plant(FS, LATENCY)
    gains = np.array([0.2, 0.4, 0.6])
    bank = IIRBank(gains[:, None], np.tile([1.0, -1.0], (3, 1)), FS)
    own = np.array([recursion_gain(plant, bank.b[i], bank.a[i]) for i in range(3)])
    low, mid, high = np.sort(own)
    assert low < mid < high
    for limit in (0.5 * (low + mid), 0.5 * (mid + high)):  # the twin moves the threshold
        ok, _, reasons = certify(plant, bank, modulus_margin=0.0, max_recursion_gain=limit)
        np.testing.assert_array_equal(ok, own <= limit)
        for i in np.flatnonzero(~ok):
            assert reasons[i].startswith(f"recursion gain {own[i]:.3g} >")


def test_lqg_designer_logs_the_short_windows_low_frequency_note(caplog):
    # Issue 33: a W-second window resolves its PSD down to its Welch resolution only, so the
    # LQG fit notes at every redesign that a steep spectrum keeps rising below it. The adaptive
    # designer logs it (INFO) instead of printing a warning per redesign; lqg() itself warns.
    import logging
    import warnings

    plant = loop_plant(FS, LATENCY)
    freqs = np.linspace(0.0, FS / 2, 6001)  # 0.25-Hz resolution, as a 4-s window's
    psd = 1e3 / (1.0 + (freqs[None, :] / 0.01) ** 2)  # still rising at 0.25 Hz
    noise = np.array([1e-3])
    tel = TelemetryPSD(freqs, psd, noise, np.zeros((8, 1)), psd, FS, (0.8, 1.0), "welch")
    with pytest.warns(UserWarning, match="keeps rising down to the lowest grid frequency"):
        lqg(plant, freqs, psd, noise_psd=noise)
    with caplog.at_level(logging.INFO, logger="aocontrol.adaptive._designers"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            lqg_designer()(tel, plant, Integrator(0.3, fs=FS, n_modes=1))
    assert any("keeps rising" in r.getMessage() for r in caplog.records)
