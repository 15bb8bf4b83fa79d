"""Turbulence profiles: the ESO 35-layer median profile, compression, tau0 scaling.

The 35-layer profile is ESO's reference median profile for Cerro Armazones, ESO-258292
("Reference atmospheric turbulence profiles for the ELT", Sarazin et al. 2013): altitudes
above the site, Cn2 fractions and wind speeds. The numbers are the published ones, as also
found in public AO simulation parameter files (e.g. COMPASS ``shesha`` ELT parameter files,
arrays ``altESO``, ``fracmed``, ``windESO``). The document gives no wind directions; see
:func:`eso_median_profile` for the default.

Compression (:func:`compress_profile`) uses equivalent layers (Fusco et al. 1999; Saxenhuber
et al. 2017): contiguous groups of layers become one layer with the group's total fraction,
the 5/3-moment altitude ``(sum f h^(5/3) / sum f)^(3/5)`` and the 5/3-moment wind speed
``(sum f v^(5/3) / sum f)^(3/5)``. This preserves exactly the total Cn2 (hence r0), the
5/3-weighted mean wind speed (hence tau0) and the 5/3-weighted mean altitude (hence the
isoplanatic angle ``theta0 = 0.314 r0 / h_bar``). Groups are chosen to minimise the
Cn2-weighted spread of altitude within groups (optimal 1-D partition by dynamic programming).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from aocontrol._validation import check_int, check_positive
from aocontrol.sim.atmosphere import Atmosphere, Layer
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.turbulence import effective_wind_speed, r0_from_seeing

__all__ = [
    "ESO_MEDIAN_ALTITUDES",
    "ESO_MEDIAN_FRACTIONS",
    "ESO_MEDIAN_WIND_SPEEDS",
    "eso_median_profile",
    "eso_atmosphere",
    "compress_profile",
    "normalize_layers",
    "scale_to_tau0",
    "effective_altitude",
    "isoplanatic_angle",
]

# ESO-258292, median profile (35 layers). Altitudes above the site [m].
ESO_MEDIAN_ALTITUDES = np.array(
    [
        30,
        90,
        150,
        200,
        245,
        300,
        390,
        600,
        1130,
        1880,
        2630,
        3500,
        4500,
        5500,
        6500,
        7500,
        8500,
        9500,
        10500,
        11500,
        12500,
        13500,
        14500,
        15500,
        16500,
        17500,
        18500,
        19500,
        20500,
        21500,
        22500,
        23500,
        24500,
        25500,
        26500,
    ],
    dtype=float,
)
# Cn2 fractions [%] of the median profile (they sum to 100; normalised on use).
ESO_MEDIAN_FRACTIONS = np.array(
    [
        24.2,
        12.0,
        9.68,
        5.9,
        4.73,
        4.73,
        4.73,
        4.73,
        3.99,
        3.24,
        1.62,
        2.6,
        1.56,
        1.04,
        1.0,
        1.2,
        0.4,
        1.4,
        1.3,
        0.7,
        1.6,
        2.59,
        1.9,
        0.99,
        0.62,
        0.4,
        0.25,
        0.22,
        0.19,
        0.14,
        0.11,
        0.06,
        0.09,
        0.05,
        0.04,
    ]
)
# Wind speeds [m/s] of the median profile.
ESO_MEDIAN_WIND_SPEEDS = np.array(
    [
        5.5,
        5.5,
        5.1,
        5.5,
        5.6,
        5.7,
        5.8,
        6.0,
        6.5,
        7.0,
        7.5,
        8.5,
        9.5,
        11.5,
        17.5,
        23.0,
        26.0,
        29.0,
        32.0,
        27.0,
        22.0,
        14.5,
        9.5,
        6.3,
        5.5,
        6.0,
        6.5,
        7.0,
        7.5,
        8.0,
        8.5,
        9.0,
        9.5,
        10.0,
        10.0,
    ]
)
for _arr in (ESO_MEDIAN_ALTITUDES, ESO_MEDIAN_FRACTIONS, ESO_MEDIAN_WIND_SPEEDS):
    _arr.setflags(write=False)


def _arrays(layers: Sequence[Layer]) -> tuple[np.ndarray, ...]:
    layers = tuple(layers)
    if not layers or not all(isinstance(lay, Layer) for lay in layers):
        raise TypeError(f"layers must be a non-empty sequence of Layer, got {layers!r}")
    return tuple(
        np.array([getattr(lay, name) for lay in layers], dtype=float)
        for name in ("altitude", "fraction", "wind_speed", "wind_direction")
    )


def normalize_layers(layers: Sequence[Layer]) -> list[Layer]:
    """Layers with their fractions divided by their sum (so that they sum to 1).

    Parameters
    ----------
    layers : sequence of Layer
        Atmospheric layers (altitude [m], Cn2 fraction, wind speed [m/s], direction [rad]).

    Raises
    ------
    ValueError
        If all fractions are zero.
    """
    h, f, v, d = _arrays(layers)
    total = f.sum()
    if total <= 0:
        raise ValueError(f"layer fractions must not all be zero, got {f.tolist()}")
    return [Layer(*args) for args in zip(h, f / total, v, d, strict=True)]


def eso_median_profile(
    n_layers: int = 35, *, wind_directions: Sequence[float] | None = None
) -> list[Layer]:
    """The ESO 35-layer median profile, or its compression to ``n_layers`` equivalent layers.

    Parameters
    ----------
    n_layers : int
        35 for the full profile, 1 to 34 for a compressed one (:func:`compress_profile`).
    wind_directions : sequence of 35 floats, optional
        Directions [deg] of the 35 layers. ESO-258292 gives none; by default the layers are
        spread evenly, ``360 i / 35`` for the i-th layer from the ground (an assumption that
        keeps the turbulence statistically isotropic).

    Returns
    -------
    list of Layer
        Fractions sum to 1; wind speeds as published (rescale them with
        :func:`scale_to_tau0`).

    Examples
    --------
    >>> layers = eso_median_profile(4)
    >>> len(layers), round(sum(lay.fraction for lay in layers), 12)
    (4, 1.0)
    """
    n_layers = check_int("n_layers", n_layers, minimum=1)
    n_full = ESO_MEDIAN_ALTITUDES.size
    if n_layers > n_full:
        raise ValueError(f"n_layers must be in [1, {n_full}], got {n_layers}")
    if wind_directions is None:
        directions = 360.0 * np.arange(n_full) / n_full
    else:
        directions = np.asarray(wind_directions, dtype=float)
        if directions.shape != (n_full,) or not np.all(np.isfinite(directions)):
            raise ValueError(
                f"wind_directions must be {n_full} finite angles [deg], got shape "
                f"{directions.shape}"
            )
    fractions = ESO_MEDIAN_FRACTIONS / ESO_MEDIAN_FRACTIONS.sum()
    layers = [
        Layer(*args)
        for args in zip(
            ESO_MEDIAN_ALTITUDES, fractions, ESO_MEDIAN_WIND_SPEEDS, directions, strict=True
        )
    ]
    return layers if n_layers == n_full else compress_profile(layers, n_layers)


def _optimal_groups(h: np.ndarray, f: np.ndarray, k: int) -> list[tuple[int, int]]:
    """Contiguous groups [start, stop) of sorted altitudes minimising the weighted spread."""
    n = h.size
    cw = np.concatenate([[0.0], np.cumsum(f)])
    cwh = np.concatenate([[0.0], np.cumsum(f * h)])
    cwh2 = np.concatenate([[0.0], np.cumsum(f * h * h)])

    def cost(i: int, j: int) -> float:  # weighted sum of squared deviations of h[i:j]
        w = cw[j] - cw[i]
        if w <= 0:
            return 0.0
        s = cwh[j] - cwh[i]
        return float(cwh2[j] - cwh2[i] - s * s / w)

    best = np.full((k + 1, n + 1), np.inf)
    arg = np.zeros((k + 1, n + 1), dtype=int)
    best[0, 0] = 0.0
    for g in range(1, k + 1):
        for j in range(g, n + 1):
            for i in range(g - 1, j):
                c = best[g - 1, i] + cost(i, j)
                if c < best[g, j]:
                    best[g, j], arg[g, j] = c, i
    groups, j = [], n
    for g in range(k, 0, -1):
        i = int(arg[g, j])
        groups.append((i, j))
        j = i
    return groups[::-1]


def compress_profile(layers: Sequence[Layer], n_layers: int) -> list[Layer]:
    """Equivalent-layer compression of a profile to ``n_layers`` layers.

    Each group of layers contiguous in altitude becomes one layer with the group's total
    fraction, the 5/3-moment altitude and the 5/3-moment wind speed (see the module notes):
    total Cn2, ``v_bar`` (tau0) and ``h_bar`` (theta0) are preserved exactly. Its direction is
    that of the group's wind vectors summed with weights ``f v^(5/3)``.

    Parameters
    ----------
    layers : sequence of Layer
        Profile to compress (any order; fractions need not be normalised).
    n_layers : int
        Number of layers wanted, in [1, len(layers)].

    Returns
    -------
    list of Layer
        Sorted by altitude.
    """
    n_layers = check_int("n_layers", n_layers, minimum=1)
    h, f, v, d = _arrays(layers)
    if n_layers > h.size:
        raise ValueError(f"n_layers must be in [1, {h.size}] (len(layers)), got {n_layers}")
    order = np.argsort(h, kind="stable")
    h, f, v, d = h[order], f[order], v[order], d[order]
    out = []
    for i, j in _optimal_groups(h, f, n_layers):
        if j == i + 1:  # a group of one layer is that layer
            out.append(Layer(h[i], f[i], v[i], d[i]))
            continue
        w = f[i:j]
        total = w.sum()
        if total <= 0:
            w = np.ones(j - i)
        hh = float((np.sum(w * h[i:j] ** (5 / 3)) / w.sum()) ** 0.6)
        vv = float((np.sum(w * v[i:j] ** (5 / 3)) / w.sum()) ** 0.6)
        vec = np.sum(w * v[i:j] ** (5 / 3) * np.exp(1j * np.radians(d[i:j])))
        direction = float(np.degrees(np.angle(vec)) % 360.0) if abs(vec) > 0 else float(d[i])
        out.append(Layer(hh, float(total), vv, direction))
    return out


def scale_to_tau0(layers: Sequence[Layer], r0: float, tau0: float) -> list[Layer]:
    """Scale every wind speed by one factor so that ``0.314 r0 / v_bar = tau0``.

    Parameters
    ----------
    layers : sequence of Layer
        Profile; ``v_bar`` is the 5/3-weighted mean speed with the fractions as weights.
    r0 : float
        Fried parameter at 500 nm [m] (e.g. from
        :func:`aocontrol.sim.turbulence.r0_from_seeing`).
    tau0 : float
        Coherence time wanted [s].

    Returns
    -------
    list of Layer
        Same altitudes, fractions and directions; speeds times ``0.314 r0 / (tau0 v_bar)``.

    Raises
    ------
    ValueError
        For non-positive ``r0`` or ``tau0``, or all wind speeds zero.
    """
    r0 = check_positive("r0", r0)
    tau0 = check_positive("tau0", tau0)
    h, f, v, d = _arrays(layers)
    v_bar = effective_wind_speed(v, f)
    if v_bar <= 0:
        raise ValueError(
            f"layers must have a non-zero wind speed to be scaled to tau0, got speeds {v.tolist()}"
        )
    factor = 0.314 * r0 / (tau0 * v_bar)
    return [Layer(*args) for args in zip(h, f, v * factor, d, strict=True)]


def effective_altitude(layers: Sequence[Layer]) -> float:
    """The 5/3-weighted mean altitude ``(sum f h^(5/3) / sum f)^(3/5)`` [m].

    Parameters
    ----------
    layers : sequence of Layer
        Atmospheric layers (altitude [m], Cn2 fraction, wind speed [m/s], direction [rad]).
    """
    h, f, _, _ = _arrays(layers)
    if f.sum() <= 0:
        raise ValueError(f"layer fractions must not all be zero, got {f.tolist()}")
    return float((np.sum(f * h ** (5 / 3)) / f.sum()) ** 0.6)


def isoplanatic_angle(layers: Sequence[Layer], r0: float) -> float:
    """Isoplanatic angle ``theta0 = 0.314 r0 / h_bar`` [rad] at zenith (Roddier 1981).

    Parameters
    ----------
    layers : sequence of Layer
        Atmospheric layers (altitude [m], Cn2 fraction, wind speed [m/s], direction [rad]).
    r0 : float
        Fried parameter at 500 nm [m].
    """
    h_bar = effective_altitude(layers)
    return math.inf if h_bar == 0 else 0.314 * check_positive("r0", r0) / h_bar


def eso_atmosphere(
    pupil: Pupil,
    seeing: float,
    tau0: float,
    fs: float,
    *,
    n_layers: int = 35,
    L0: float = 25.0,
    rng: np.random.Generator | int | None = None,
    wind_directions: Sequence[float] | None = None,
    **kwargs: object,
) -> Atmosphere:
    """An :class:`Atmosphere` with the ESO median profile at a given seeing and tau0.

    ``r0 = 0.98 lambda / seeing`` at 500 nm (:func:`aocontrol.sim.turbulence.r0_from_seeing`),
    the profile of :func:`eso_median_profile` (``n_layers`` equivalent layers) with its wind
    speeds scaled by one factor to reach ``tau0`` (:func:`scale_to_tau0`).

    Parameters
    ----------
    pupil : Pupil
        Sampling grid.
    seeing : float
        Seeing FWHM at 500 nm [arcsec].
    tau0 : float
        Coherence time [s].
    fs : float
        Frame rate [Hz].
    n_layers : int
        35, or fewer for a compressed profile.
    L0 : float
        Outer scale [m].
    rng : numpy.random.Generator or int, optional
        Randomness.
    wind_directions : sequence of 35 floats, optional
        See :func:`eso_median_profile`.
    **kwargs
        Passed to :class:`Atmosphere` (``screen_size``, ``dtype``).

    Examples
    --------
    >>> atm = eso_atmosphere(Pupil(n_pix=16), seeing=0.8, tau0=3e-3, fs=1000.0, n_layers=5,
    ...                      rng=0)
    >>> round(atm.tau0 * 1e3, 6), round(atm.r0, 4)
    (3.0, 0.1263)
    """
    r0 = r0_from_seeing(seeing)
    layers = scale_to_tau0(eso_median_profile(n_layers, wind_directions=wind_directions), r0, tau0)
    return Atmosphere(pupil, r0, layers, fs, L0=L0, rng=rng, **kwargs)  # type: ignore[arg-type]
