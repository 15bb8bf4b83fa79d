"""Telescope pupil sampled on a square grid.

Geometry is decoupled from sampling: the physical pupil (diameter, central obstruction,
spiders) is fixed, ``n_pix`` sets how finely it is sampled. Phase maps on this grid are
optical path differences in nm, arrays of shape ``(..., n_pix, n_pix)``; values outside the
mask are ignored (kept at 0). Vectors "on valid pixels" have shape ``(..., n_valid)`` in the
row-major order of ``mask``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from aocontrol._validation import (
    check_finite_array,
    check_in_range,
    check_int,
    check_nonnegative,
    check_positive,
)

__all__ = ["Pupil", "vlt_pupil"]


@dataclass(frozen=True)
class Pupil:
    """Annular telescope pupil with optional spiders, sampled on ``n_pix x n_pix`` points.

    Parameters
    ----------
    diameter : float
        Outer diameter [m] (8.0 for the VLT).
    n_pix : int
        Samples across the diameter (the grid spans exactly ``diameter``), >= 8.
    obstruction : float
        Central obstruction as a fraction of the diameter, in [0, 1) (0.14 for the VLT).
    spider_width : float
        Width of each of 4 spider arms [m] (0 for none).
    spider_angle : float
        Angle of the first spider arm [deg]; arms every 90 deg.

    Attributes
    ----------
    mask : ndarray of bool, shape (n_pix, n_pix)
    x, y : ndarray, shape (n_pix, n_pix)
        Pixel-centre coordinates [m], origin at the pupil centre.
    """

    diameter: float = 8.0
    n_pix: int = 64
    obstruction: float = 0.14
    spider_width: float = 0.0
    spider_angle: float = 45.0

    def __post_init__(self) -> None:
        check_positive("diameter", self.diameter)
        check_int("n_pix", self.n_pix, minimum=8)
        check_in_range("obstruction", self.obstruction, 0.0, 1.0)
        check_nonnegative("spider_width", self.spider_width)

    @property
    def pixel_scale(self) -> float:
        """Grid step [m]."""
        return self.diameter / self.n_pix

    @cached_property
    def _xy(self) -> tuple[np.ndarray, np.ndarray]:
        c = (np.arange(self.n_pix) - (self.n_pix - 1) / 2.0) * self.pixel_scale
        y, x = np.meshgrid(c, c, indexing="ij")
        x.setflags(write=False)
        y.setflags(write=False)
        return x, y

    @property
    def x(self) -> np.ndarray:
        return self._xy[0]

    @property
    def y(self) -> np.ndarray:
        return self._xy[1]

    @cached_property
    def mask(self) -> np.ndarray:
        r = np.hypot(self.x, self.y)
        m = (r <= self.diameter / 2) & (r >= self.obstruction * self.diameter / 2)
        if self.spider_width > 0:
            for k in range(4):
                a = np.radians(self.spider_angle + 90.0 * k)
                along = self.x * np.cos(a) + self.y * np.sin(a)
                across = -self.x * np.sin(a) + self.y * np.cos(a)
                m &= ~((np.abs(across) < self.spider_width / 2) & (along > 0))
        m.setflags(write=False)
        return m

    @cached_property
    def index(self) -> np.ndarray:
        """Flat indices of the valid pixels, shape ``(n_valid,)``."""
        idx = np.flatnonzero(self.mask)
        idx.setflags(write=False)
        return idx

    @cached_property
    def runs(self) -> tuple[tuple[int, int, int, int], ...]:
        """Runs of consecutive valid pixels along the map rows, in the order of :attr:`index`.

        Each run is ``(row, first, stop, column)``: the vector elements ``first ... stop - 1``
        are the map pixels ``(row, column ... column + stop - first - 1)``; so a map is
        filled from valid-pixel vectors by slices (``maps[..., row, column : column + stop -
        first] = vectors[..., first:stop]``), without a scatter.
        """
        flat = self.index
        n = self.n_pix
        breaks = np.flatnonzero((np.diff(flat) != 1) | (flat[1:] % n == 0)) + 1
        starts, stops = np.r_[0, breaks], np.r_[breaks, flat.size]
        return tuple(
            (int(flat[a]) // n, int(a), int(b), int(flat[a]) % n)
            for a, b in zip(starts, stops, strict=True)
        )

    @property
    def n_valid(self) -> int:
        """Number of pixels inside the pupil."""
        return int(self.index.size)

    @property
    def area(self) -> float:
        """Sampled collecting area [m^2]."""
        return self.n_valid * self.pixel_scale**2

    def to_vector(self, maps: np.ndarray) -> np.ndarray:
        """``(..., n_pix, n_pix)`` maps -> ``(..., n_valid)`` values on valid pixels."""
        maps = np.asarray(maps)
        if maps.shape[-2:] != (self.n_pix, self.n_pix):
            raise ValueError(
                f"maps must end with shape ({self.n_pix}, {self.n_pix}), got {maps.shape}"
            )
        return maps.reshape(*maps.shape[:-2], -1)[..., self.index]

    def as_vectors(self, data: object, name: str = "data") -> np.ndarray:
        """``(..., n_pix, n_pix)`` maps or ``(..., n_valid)`` vectors -> ``(..., n_valid)``.

        The one reader of "a phase on this pupil, as maps or as valid-pixel vectors" (the
        mirror's fit and the modal basis' projection use it).

        Parameters
        ----------
        data : array_like, shape (..., n_pix, n_pix) or (..., n_valid)
            Finite values.
        name : str, default "data"
            Argument name for the messages (e.g. ``"phase"``).

        Returns
        -------
        numpy.ndarray, shape (..., n_valid)

        Raises
        ------
        ValueError
            Non-finite values, or a shape that ends with neither.
        """
        arr = check_finite_array(name, data)
        if arr.ndim >= 1 and arr.shape[-1] == self.n_valid:
            return arr
        if arr.ndim >= 2 and arr.shape[-2:] == (self.n_pix, self.n_pix):
            return self.to_vector(arr)
        raise ValueError(
            f"{name} must end with ({self.n_pix}, {self.n_pix}) (maps) or n_valid="
            f"{self.n_valid} (vectors on valid pixels), got shape {arr.shape}"
        )

    def to_map(self, vectors: np.ndarray) -> np.ndarray:
        """``(..., n_valid)`` values -> ``(..., n_pix, n_pix)`` maps, zero outside the pupil."""
        vectors = np.asarray(vectors)
        if vectors.shape[-1] != self.n_valid:
            raise ValueError(
                f"vectors must end with n_valid={self.n_valid} values, got {vectors.shape}"
            )
        out = np.zeros((*vectors.shape[:-1], self.n_pix * self.n_pix), dtype=vectors.dtype)
        out[..., self.index] = vectors
        return out.reshape(*vectors.shape[:-1], self.n_pix, self.n_pix)


def vlt_pupil(n_pix: int = 64, *, spiders: bool = False) -> Pupil:
    """The VLT pupil: 8 m, central obstruction 0.14, optional 4 spiders of 5 cm.

    Parameters
    ----------
    n_pix : int, default 64
        Samples across the 8-m pupil.
    spiders : bool, default False
        Add the four 5-cm spiders.
    """
    return Pupil(diameter=8.0, n_pix=n_pix, obstruction=0.14, spider_width=0.05 if spiders else 0.0)
