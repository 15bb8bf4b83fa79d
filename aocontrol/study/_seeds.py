"""Named random streams of a study seed: ``numpy.random.SeedSequence([seed, PURPOSE])``.

One user seed drives several independent random draws in a study (the exposure, the
calibration run that the controllers are designed from, the reference gain scan, the residual
screens of the optical-gain calibration). Each draws from its own stream, the
:class:`numpy.random.SeedSequence` of the entropy ``[seed, code]`` with ``code`` the purpose's
number below: two purposes never share a stream, whatever the seeds. (Offsets did: with
``seed + 1000`` for the calibration, seed 0's calibration run was seed 1000's exposure.)

Results files record the streams used (:func:`seed_streams`), as ``{purpose: [seed, code]}``.

The exposure keeps code 7, the entropy it had before the purposes were named: exposures are
unchanged bit for bit.
"""

from __future__ import annotations

import numpy as np

from aocontrol._validation import check_int

__all__ = ["SEED_PURPOSES", "seed_sequence", "seed_streams"]

#: Purpose name -> the second word of the stream's entropy ``[seed, code]``.
SEED_PURPOSES: dict[str, int] = {
    "exposure": 7,
    "calibration": 8,
    "gain_scan": 9,
    "optical_gain_screens": 10,
    "two_pass": 11,
}


def seed_sequence(seed: int, purpose: str) -> np.random.SeedSequence:
    """The random stream of ``purpose`` for the user seed ``seed``.

    Parameters
    ----------
    seed : int
        User seed, >= 0.
    purpose : str
        A key of :data:`SEED_PURPOSES`.

    Returns
    -------
    numpy.random.SeedSequence
        Entropy ``[seed, SEED_PURPOSES[purpose]]``.

    Raises
    ------
    ValueError
        A negative seed or an unknown purpose (the message lists the known ones).

    Examples
    --------
    >>> seed_sequence(0, "calibration").entropy == seed_sequence(1000, "exposure").entropy
    False
    """
    seed = check_int("seed", seed, minimum=0)
    if purpose not in SEED_PURPOSES:
        raise ValueError(f"purpose must be one of {sorted(SEED_PURPOSES)}, got {purpose!r}")
    return np.random.SeedSequence([seed, SEED_PURPOSES[purpose]])


def seed_streams(seed: int, purposes: tuple[str, ...]) -> dict[str, list[int]]:
    """``{purpose: [seed, code]}`` for a results file (JSON-serialisable).

    Parameters
    ----------
    seed : int
        User seed, >= 0.
    purposes : tuple of str
        Keys of :data:`SEED_PURPOSES`.

    Returns
    -------
    dict
    """
    return {p: [int(x) for x in seed_sequence(seed, p).entropy] for p in purposes}
