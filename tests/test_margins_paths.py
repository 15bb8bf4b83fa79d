"""margins() computes its stability verdict, its modulus certificate and its families from
coefficients checked once; the public calls that compute each alone must agree bit for bit.

Oracles: :func:`aocontrol.analysis.is_stable` and :func:`aocontrol.analysis.modulus_certificate`
(each validates its inputs and extracts the coefficients itself), and for the delay margin's
small-gain test a dense evaluation of ``|L|``: a loop whose gain stays below 1 on the whole
circle is never destabilised by latency (``delay_margin = inf``), one whose gain exceeds 1
somewhere is (a finite margin, at most the search's cap).
"""

from __future__ import annotations

import numpy as np
import pytest

from aocontrol.analysis import DELAY_SEARCH_FRAMES, is_stable, margins, modulus_certificate
from aocontrol.plant import loop_plant, tf_from_z_inverse

FS = 1000.0
# |L| on this many points of [0, pi] decides "below 1 everywhere" for the oracle; the loops
# below keep away from |L| = 1 by far more than the grid's error (smooth, poles inside 0.99).
_DENSE = 2**15
# Distance of max |L| from 1 that the oracle demands before it decides either way.
_CLEAR = 1e-3


def _random_loops(seed: int, n: int) -> list:
    """Plants and controllers: poles from 0.5 to beyond the circle, resonances, leaks, every
    order to 6, gains from tiny to destabilising (unstable loops, several crossovers)."""
    rng = np.random.default_rng(seed)
    plants = [loop_plant(FS, lat) for lat in (0.0, 0.3, 0.83, 1.0, 2.5)]
    loops = []
    for _ in range(n):
        order = int(rng.integers(1, 7))
        radius = rng.choice([0.5, 0.9, 0.99, 0.999, 1.0, 1.01])
        poles = radius * np.exp(1j * rng.uniform(0.0, np.pi, order // 2))
        den = np.real(np.poly(np.concatenate([poles, poles.conj()])))
        if order % 2:
            den = np.polymul(den, [1.0, -rng.choice([1.0, 0.99, -0.5])])
        num = rng.standard_normal(den.size) * rng.choice([0.01, 0.1, 0.5, 2.0])
        loops.append((plants[int(rng.integers(len(plants)))], tf_from_z_inverse(num, den, 1 / FS)))
    # Integrators at and around the stability limit of the 2-frame delay (g = 1).
    for g in (0.5, 0.999999, 1.0, 1.000001, 1.5):
        loops.append((loop_plant(FS, 1.0), tf_from_z_inverse([g], [1.0, -1.0], 1 / FS)))
    return loops


@pytest.mark.parametrize("seed", [0, 1])
def test_margins_agree_bit_for_bit_with_is_stable_and_the_certificate(seed):
    loops = _random_loops(seed, 40)
    n_unstable = 0
    for G, K in loops:
        m = margins(G, K)
        cert = modulus_certificate(G, K)
        assert m.stable == is_stable(G, K)
        # The same arithmetic on the same coefficients: equal, not close.
        assert m.modulus_margin == cert.value
        assert m.modulus_frequency_hz == cert.frequency_hz
        n_unstable += not m.stable
    # The corpus holds both kinds of loop (else the comparison would test one branch).
    assert 0 < n_unstable < len(loops)


def _max_loop_gain(G, K) -> float:
    theta = np.linspace(0.0, np.pi, _DENSE + 1)
    w = np.exp(-1j * theta)
    (bg,), (ag,) = G.num[0], G.den[0]
    (bk,), (ak,) = K.num[0], K.den[0]
    z = 1.0 / w
    with np.errstate(divide="ignore", invalid="ignore"):  # an integrator's pole at z = 1
        L = np.polyval(bg, z) * np.polyval(bk, z) / (np.polyval(ag, z) * np.polyval(ak, z))
    L = np.where(np.isnan(L), np.inf, L)
    return float(np.max(np.abs(L)))


@pytest.mark.parametrize(
    ("num", "den", "small"),
    [
        ([0.3], [1.0, -0.5], True),  # low-pass, |L| <= 0.6
        ([0.2, 0.1], [1.0, 0.4], True),  # |L| <= 0.3 (0 at Nyquist)
        ([0.4], [1.0, -1.0], False),  # integrator: |L(0)| infinite (the ends decide)
        ([0.9], [1.0, -0.2], False),  # |L(0)| = 1.125 > 1 at an end
        # resonance at 0.3 rad/sample (48 Hz), radius 0.95: |L| = 0 at both ends, about 2
        # in between (the ends do not decide: the certificate does)
        ([0.1, 0.0, -0.1], [1.0, -1.9 * np.cos(0.3), 0.95**2], False),
    ],
)
def test_delay_margin_is_infinite_exactly_when_the_loop_gain_stays_below_one(num, den, small):
    G = loop_plant(FS, 0.5)
    K = tf_from_z_inverse(num, den, 1 / FS)
    peak = _max_loop_gain(G, K)
    assert abs(peak - 1.0) > _CLEAR  # the oracle decides this loop
    assert (peak < 1.0) == small
    m = margins(G, K)
    assert m.stable
    if small:
        assert m.delay_margin == np.inf
    else:
        assert 0.0 < m.delay_margin <= DELAY_SEARCH_FRAMES


def test_small_gain_oracle_can_fail():
    # Twin of the test above: a loop gain above 1 (g = 1.2, |L(0)| = 1.2 / 0.8 = 1.5 > 1)
    # must not report an infinite delay margin; the oracle sees the peak.
    G = loop_plant(FS, 0.5)
    K = tf_from_z_inverse([0.3], [1.0, -0.8], 1 / FS)
    assert _max_loop_gain(G, K) > 1.0 + _CLEAR
    m = margins(G, K)
    assert m.stable and np.isfinite(m.delay_margin)
