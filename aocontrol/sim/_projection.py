"""Projection of phase vectors on modal bases: dense, or through a DM's separable influences.

A KL basis of a :class:`~aocontrol.sim.dm.DeformableMirror` is ``modes = m2c^T (F - f 1^T)``
(``F`` the influence functions on the valid pupil pixels, ``f`` their pupil means: the modes
are piston-free), so the least-squares coefficients of a phase vector ``phi`` are

    c = phi @ modes^T / n_valid = ((phi @ F^T) @ m2c - sum(phi) (f @ m2c)) / n_valid.

The DM's influence functions are Gaussians on a square grid, ``exp(k (x - x_a)^2) exp(k (y -
y_b)^2)``: separable, so ``phi @ F^T`` over the whole actuator grid is two small matrix
products on the phase *map*, ``G_y Phi G_x^T`` (``G_x``, ``G_y`` of shape ``(n_actuators,
n_pix)``), followed by the selection of the valid actuators; the first product runs on the
phase vectors themselves, one product per run of valid pixels of a map row (no map is formed,
the pixels outside the pupil cost nothing). For SAXO's 41x41 DM (1360 valid actuators, 1200
modes) on a 96-pixel pupil (7084 valid pixels) and SAXO+'s 28x28 (540 modes) that is ~2.7 M
multiply-adds per frame instead of the dense ``n_valid (1200 + 540)`` = 12.3 M.

:class:`ModalProjector` takes that path when every basis carries its mirror's factors
(:class:`SeparableMirror`, set by :func:`~aocontrol.sim.modes.kl_basis`), when it is
markedly cheaper (``_SEPARABLE_COST_FRACTION``: many modes on a finely sampled pupil), and
when a probe on random phases agrees with the dense
product (else it logs why and projects densely). Precision: both paths run in float32 (the
coefficients are returned in float64); the separable one adds the rounding of the
``m2c`` product (KL command vectors of up to ~50 nm per nm RMS, whose float32 rounding
partly cancels): relative error up to ~2e-4 of the largest coefficient of a mode instead of
~2e-5 for the dense product -- both far below the AO residuals (``tests/test_projection.py``).
"""

from __future__ import annotations

import logging
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["SeparableMirror", "ModalProjector", "projector_for"]

logger = logging.getLogger(__name__)

#: Precision of the projection (module docstring).
PROJECTION_DTYPE = np.float32
# The separable path is used when its cost -- its multiply-adds plus _MAP_COST per map pixel
# (the per-row products and their outputs: calls and memory traffic) -- is at most this
# fraction of the dense multiply-adds. Measured (float32, one and two BLAS threads): 1200 +
# 540 modes, 96 px (fraction 0.26): 2.1x faster than the dense product; 400 + 200 modes,
# 84 px (0.47): 1.4x slower.
_SEPARABLE_COST_FRACTION = 0.3
_MAP_COST = 40
# Probe of the separable path against the dense product (float64 both): relative agreement
# required (rounding of float64 products: ~1e-13; a mirror that is not the basis' gives O(1)).
_PROBE_RTOL = 1e-8


def _flush_subnormal(a: np.ndarray, dtype: type) -> np.ndarray:
    """A C-contiguous copy of ``a`` in ``dtype`` with its subnormal numbers set to zero.

    The Gaussian influences' far tails (``exp(k d^2)`` over the whole grid) fall below the
    smallest normal number of float32 (1.2e-38): as operands of the BLAS products they cost a
    microcode assist per multiply on x86 (figures in ``docs/benchmarks.md``). Their
    contribution is below any float32
    sum of the projection, so flushing them changes no result beyond its rounding.
    """
    out = np.array(a, dtype=dtype, order="C", copy=True)
    out[np.abs(out) < np.finfo(dtype).tiny] = 0.0
    return out


@dataclass(frozen=True, eq=False)
class SeparableMirror:
    """The Gaussian influence functions of a square-grid DM, as two 1-D factors.

    Parameters
    ----------
    gx, gy : ndarray, shape (n_actuators, n_pix)
        ``exp(k (x_j - a_i)^2)`` along the map's columns (``x``) and rows (``y``), ``a_i`` the
        grid's actuator coordinates [m], ``k = log(coupling) / pitch^2``.
    act_index : ndarray of int, shape (n_act,)
        Flat index ``row * n_actuators + column`` (row along ``y``) of each valid actuator in
        the full grid, in the order of the command vector.
    mean : ndarray, shape (n_act,)
        Pupil mean of each influence function (over the valid pixels).

    Notes
    -----
    ``influence[i] = (gy[r_i][:, None] * gx[c_i][None, :])`` on the valid pixels, with
    ``(r_i, c_i) = divmod(act_index[i], n_actuators)``.
    """

    gx: np.ndarray
    gy: np.ndarray
    act_index: np.ndarray
    mean: np.ndarray

    @classmethod
    def from_dm(cls, dm: Any) -> SeparableMirror:
        """The factors of a :class:`~aocontrol.sim.dm.DeformableMirror` (its geometry)."""
        na, pupil = dm.n_actuators, dm.pupil
        c = (np.arange(na) - (na - 1) / 2.0) * dm.pitch
        k = dm._log_coupling / dm.pitch**2
        x = np.asarray(pupil.x)[0]
        y = np.asarray(pupil.y)[:, 0]
        gx = np.exp(k * (c[:, None] - x[None, :]) ** 2)
        gy = np.exp(k * (c[:, None] - y[None, :]) ** 2)
        pos = np.asarray(dm.positions)
        col = np.rint(pos[:, 0] / dm.pitch + (na - 1) / 2.0).astype(np.intp)
        row = np.rint(pos[:, 1] / dm.pitch + (na - 1) / 2.0).astype(np.intp)
        act_index = row * na + col
        # Pupil means of the influence functions from the factors (sum over the valid pixels).
        mask = np.asarray(pupil.mask, dtype=float)
        mean = np.einsum("rj,jk,ck->rc", gy, mask, gx).ravel()[act_index] / pupil.n_valid
        out = cls(gx=gx, gy=gy, act_index=act_index, mean=mean)
        for arr in (gx, gy, act_index, mean):
            arr.setflags(write=False)
        return out

    @property
    def n_actuators(self) -> int:
        """Actuators across the grid."""
        return int(self.gx.shape[0])


class ModalProjector:
    """Coefficients of phase vectors on one or more modal bases, stacked (module docstring).

    Parameters
    ----------
    bases : sequence of ModalBasis-like
        ``modes`` (n_modes, n_valid) orthonormal over the same pupil; a basis with a
        ``mirror`` (:class:`SeparableMirror`) and ``m2c`` may take the separable path.
    separable : bool or None, default None
        ``None``: the separable path when every basis allows it and it is cheaper; ``False``:
        always the dense product; ``True``: the separable path or a ``ValueError`` saying why
        not.

    Attributes
    ----------
    path : {"dense", "separable"}
        The path taken.
    n_modes : int
        Total modes (columns of the result).
    """

    def __init__(self, bases: Any, *, separable: bool | None = None) -> None:
        bases = list(bases)  # not kept: a cached projector must not hold its bases alive
        self.n_valid = int(bases[0].modes.shape[1])
        self.n_modes = int(sum(b.modes.shape[0] for b in bases))
        why = "" if separable is False else self._why_not_separable(bases, separable is None)
        if separable is True and why:
            raise ValueError(f"separable projection impossible: {why}")
        if separable is False or why:
            if why and separable is None:
                logger.debug("dense projection: %s", why)
            self.path = "dense"
            modes = np.concatenate([np.asarray(b.modes) for b in bases], axis=0)
            self._proj = (modes.T / self.n_valid).astype(PROJECTION_DTYPE)
            self._modes = modes
            self._synth: np.ndarray | None = None  # float32 modes, made on first synthesis
            return
        self.path = "separable"
        self._setup_separable(bases, PROJECTION_DTYPE)

    # -- choice -------------------------------------------------------------------------------
    def _why_not_separable(self, bases: list, check_cost: bool) -> str:
        """Why the separable path cannot (or, with ``check_cost``, should not) be taken."""
        for i, b in enumerate(bases):
            if getattr(b, "mirror", None) is None or getattr(b, "m2c", None) is None:
                return f"basis {i} has no separable mirror"
            if b.mirror.act_index.size != b.m2c.shape[0]:
                return (
                    f"basis {i}'s mirror has {b.mirror.act_index.size} actuators, its m2c "
                    f"{b.m2c.shape[0]}"
                )
        pupil = bases[0].pupil
        if any(b.pupil is not pupil and b.pupil != pupil for b in bases):
            return "the bases are on different pupils"
        npx = pupil.n_pix
        mirrors = {id(b.mirror): b.mirror for b in bases}
        sep = _MAP_COST * npx * npx
        sep += sum(npx * npx * m.n_actuators + npx * m.n_actuators**2 for m in mirrors.values())
        sep += sum(b.m2c.shape[0] * b.m2c.shape[1] for b in bases)
        dense = self.n_valid * self.n_modes
        if check_cost and sep > _SEPARABLE_COST_FRACTION * dense:
            return f"not cheaper ({sep} vs {dense} multiply-adds per frame)"
        # Probe: the separable path in float64 against the dense product on random phases.
        self._setup_separable(bases, np.float64)
        probe = np.random.default_rng(0).standard_normal((3, self.n_valid))
        modes = np.concatenate([np.asarray(b.modes) for b in bases], axis=0)
        ref = probe @ modes.T / self.n_valid
        err = np.max(np.abs(self._separable(probe) - ref))
        if not err <= _PROBE_RTOL * np.max(np.abs(ref)):
            return f"the mirror does not reproduce the modes (probe error {err:.3g})"
        return ""

    # -- separable path -----------------------------------------------------------------------
    def _setup_separable(self, bases: list, dtype: type) -> None:
        pupil = bases[0].pupil
        npx = pupil.n_pix
        self._dtype = dtype
        self._npx = npx
        # Contiguous runs of valid pixels per map row: (row, first and last vector index, first
        # column), so the columns are contracted on the vectors themselves (no map is formed).
        self._runs = list(pupil.runs)
        # The runs of each map row: (row, [(first, stop vector index, first column), ...]).
        by_row: dict[int, list] = {row: [] for row in range(npx)}
        for row, a, b, c0 in self._runs:
            by_row[row].append((a, b, c0))
        self._row_runs = list(by_row.items())
        self._mirrors = []  # (gxT, gy, [(basis columns, rows, cols, m2c / n, mean m2c / n)])
        groups: dict[int, list] = {}
        col = 0
        for b in bases:
            m = b.mirror
            k = b.modes.shape[0]
            m2c = np.asarray(b.m2c, dtype=float)
            rows, cols = np.divmod(np.asarray(m.act_index), m.n_actuators)
            entry = (
                slice(col, col + k),
                rows,
                cols,
                (m2c / self.n_valid).astype(dtype),
                (np.asarray(m.mean) @ m2c / self.n_valid).astype(dtype),
                np.ascontiguousarray(m2c.T, dtype=dtype),
                np.asarray(m.mean, dtype=dtype),
            )
            col += k
            if id(m) not in groups:
                groups[id(m)] = []
                self._mirrors.append(
                    (
                        _flush_subnormal(m.gx.T, dtype),
                        _flush_subnormal(m.gy, dtype),
                        groups[id(m)],
                    )
                )
            groups[id(m)].append(entry)

    def _separable(self, phase: np.ndarray) -> np.ndarray:
        m, npx = phase.shape[0], self._npx
        phase = phase.astype(self._dtype, copy=False)
        total = phase.sum(axis=1, dtype=self._dtype)
        out = np.empty((m, self.n_modes), dtype=self._dtype)
        for gxt, gy, entries in self._mirrors:
            na = gy.shape[0]
            # Columns (x) first, on the phase vectors themselves: for each map row, its runs
            # of valid pixels times the mirror's column factors (no map is formed, the
            # pixels outside the pupil cost nothing): half[y, frame, a_x].
            half = np.empty((npx, m, na), dtype=self._dtype)
            for row, runs in self._row_runs:
                if not runs:
                    half[row] = 0.0
                    continue
                (a, b, c0), *more = runs
                np.matmul(phase[:, a:b], gxt[c0 : c0 + b - a], out=half[row])
                for a, b, c0 in more:
                    half[row] += phase[:, a:b] @ gxt[c0 : c0 + b - a]
            # Then the rows (y), one product: grid[a_y, frame, a_x].
            grid = (gy @ half.reshape(npx, m * na)).reshape(na, m, na)
            for cols_out, rows, cols, m2c, mean_m2c, _, _ in entries:
                acts = grid[rows, :, cols]  # (n_act, frames)
                np.matmul(acts.T, m2c, out=out[:, cols_out])
                out[:, cols_out] -= total[:, None] * mean_m2c
        return out

    def _separable_synthesis(self, coeffs: np.ndarray) -> np.ndarray:
        m, npx = coeffs.shape[0], self._npx
        maps = np.zeros((npx * m, npx), dtype=self._dtype)  # maps[y, frame, x]
        piston = np.zeros(m, dtype=self._dtype)
        for gxt, gy, entries in self._mirrors:
            na = gy.shape[0]
            # Commands of the mirror (every basis on it), on its grid: grid[a_y, frame, a_x].
            grid = np.zeros((na, m, na), dtype=self._dtype)
            for cols_in, rows, cols, _, _, m2c_t, mean in entries:
                acts = coeffs[:, cols_in] @ m2c_t  # (frames, n_act)
                grid[rows, :, cols] += acts.T
                piston += acts @ mean
            # Rows (y), then columns (x): two products.
            half = (gy.T @ grid.reshape(na, m * na)).reshape(npx * m, na)
            maps += half @ gxt.T
        maps = maps.reshape(npx, m, npx)
        out = np.empty((m, self.n_valid), dtype=self._dtype)
        for row, a, b, c0 in self._runs:
            out[:, a:b] = maps[row, :, c0 : c0 + b - a]
        out -= piston[:, None]
        return out

    def synthesize(self, coeffs: np.ndarray) -> np.ndarray:
        """Phase vectors ``(m, n_valid)`` [nm, float32] of stacked coefficients ``(m, n_modes)``.

        ``coeffs @ modes`` (all bases stacked), in float32, through the mirrors on the
        separable path (the transpose of the projection; same precision).
        """
        c = np.asarray(coeffs).astype(PROJECTION_DTYPE)
        if self.path == "dense":
            if self._synth is None:
                self._synth = self._modes.astype(PROJECTION_DTYPE)
            return c @ self._synth
        return self._separable_synthesis(c)

    # -- call -----------------------------------------------------------------------------------
    def __call__(self, phase: np.ndarray) -> np.ndarray:
        """Coefficients ``(m, n_modes)`` [float64] of phase vectors ``(m, n_valid)`` [nm]."""
        if self.path == "dense":
            return (phase.astype(PROJECTION_DTYPE, copy=False) @ self._proj).astype(float)
        return self._separable(phase).astype(float)


# One projector per live basis object (built in ~0.1 s at 540 modes; the runs of a study
# share it): weak keys, so the cache never keeps a basis alive.
_SINGLE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def projector_for(basis: Any) -> ModalProjector:
    """The :class:`ModalProjector` of one basis, built once per live basis object.

    Parameters
    ----------
    basis : ModalBasis-like
        ``modes`` (n_modes, n_valid), orthonormal over ``pupil``.

    Returns
    -------
    ModalProjector
        Its coefficients are ``phase @ modes.T / n_valid`` to the projection's float32
        rounding (module docstring).
    """
    try:
        hit = _SINGLE.get(basis)
        if hit is None:
            hit = _SINGLE[basis] = ModalProjector((basis,))
    except TypeError:  # not weakly referenceable or not hashable: not cached
        return ModalProjector((basis,))
    return hit
