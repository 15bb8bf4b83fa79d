"""Modal basis: Karhunen-Loève modes of the DM space, tip and tilt first.

Conventions: modes are phase vectors on the valid pixels of a
:class:`~aocontrol.sim.pupil.Pupil`, shape ``(n_modes, n_valid)``, orthonormal over the pupil
in the mean sense, ``mean(M_i * M_j) = delta_ij``, so a unit coefficient is 1 nm RMS of OPD.
They are piston-free (zero mean over the pupil). Projection is the least-squares one,
``coeffs = v @ modes.T / n_valid``. Modal coefficients are in nm RMS; ``m2c`` maps them to
DM commands in nm (:class:`~aocontrol.sim.dm.DeformableMirror`).

KL construction (:func:`kl_basis`)
----------------------------------
The DM-space KL modes of Gendron (1995, PhD thesis, "Optimisation de la commande modale en
optique adaptative") and Dessenne (1998), the "double diagonalisation":

1. Geometric step. Diagonalise the geometric covariance of the influence functions
   ``G = F F^T / n_valid``; the rows of ``Lambda^(-1/2) U^T F`` are orthonormal over the
   pupil and span the DM space (directions with eigenvalue below ``1e-10`` of the largest are
   unobservable and dropped).
2. Piston. Remove the DM's best fit of a piston (its command direction) from the space, then
   the residual mean of each mode (the DM reproduces a mode up to an irrelevant piston), and
   re-orthonormalise.
3. Tip and tilt. The DM's best fits of a pure tip ``x`` and tilt ``y`` (normalised to 1 nm RMS,
   tilt orthogonalised to tip) are modes 0 and 1.
4. Turbulent step. In the remaining space diagonalise the von Kármán covariance of the modal
   coefficients, ``C = B C_phi B^T / n_valid^2``; eigenvectors sorted by decreasing eigenvalue
   (the turbulent variance of each mode) give the other modes.
5. Canonical orientation. The pupil's symmetry makes many KL variances degenerate (pairs of
   modes, as Zernike's cos/sin pairs), and an eigensolver returns any orthonormal basis of a
   degenerate eigenspace (LAPACK's depends on the BLAS threads and code path, so two processes
   built different modes from the same settings). Eigenvalues whose consecutive gaps are at
   most ``_DEGENERATE_RTOL`` (1e-8) of the largest form one eigenspace; it is rotated to the
   Gram-Schmidt basis of the projections of fixed references (alternately the x-even and
   x-odd parts of fixed pseudo-random maps, so on a pupil symmetric under ``x -> -x`` the
   modes of a pair are one even, one odd in x), and its modes get the eigenspace's mean
   variance. Then every mode from mode 2 is signed to a positive overlap with a fixed
   pseudo-random map. The basis is the same in every process to rounding (tested with 1 and
   2 BLAS threads).

``C_phi`` is never formed: for piston-free vectors the phase covariance acts as the
convolution with ``-D(r)/2`` (``D`` the structure function; the huge von Kármán piston term
cancels exactly), computed by FFT on the pupil grid; all other steps work on
``(n_act, n_act)`` command-space matrices. Memory is three ``(n_act, n_valid)`` arrays, the
cost ``n_act`` FFTs of ``(2 n_pix)^2`` plus two ``n_act^2 n_valid`` products and
``n_act^3`` eigendecompositions: seconds for SAXO's 1200 modes (``docs/benchmarks.md``). So
the pixel-space method is used at every size; a pupil much finer than 2-4 pixels per pitch
only costs memory.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft

from aocontrol._validation import check_finite_array, check_instance, check_int, check_positive
from aocontrol.sim._projection import ModalProjector, SeparableMirror
from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.turbulence import opd_per_radian, structure_function

__all__ = ["ModalBasis", "ModalProjector", "SeparableMirror", "kl_basis", "fitting_error"]

logger = logging.getLogger(__name__)

# Relative eigenvalue below which a command direction of the DM is considered unobservable
# over the pupil (geometric covariance); 1e-10 keeps waffle-like modes of Gaussian IFs.
_GEOMETRIC_RCOND = 1e-10
# Number of maps per batch in the FFT covariance operator (memory ~ batch * (2 n_pix)^2).
_FFT_BATCH = 64
# Canonical orientation of the KL modes (see kl_basis, Notes): eigenvalues whose gap is at
# most this fraction of the largest turbulent eigenvalue form one degenerate eigenspace
# (rounding splits an exact pair by at most 4e-14 of it, measured from 6 to 1200 modes; true
# gaps below it are lumped, an off-diagonal covariance of at most this fraction, and a gap
# just above it is rotated by rounding at most ~4e-14 / 1e-8); the fixed references' seed;
# a reference whose projection keeps less than this fraction of its norm once the previous
# ones are removed is skipped.
_DEGENERATE_RTOL = 1e-8
_REFERENCE_SEED = 0x4B4C  # "KL"
_SIGN_STREAM = 1_000_000  # the references' stream of the sign map (far from theirs)
_REFERENCE_RCOND = 1e-6


@dataclass(frozen=True, eq=False)
class ModalBasis:
    """Orthonormal modal basis over a pupil, with the DM commands that produce each mode.

    Parameters
    ----------
    pupil : Pupil
        Pupil on which the modes are sampled.
    modes : ndarray, shape (n_modes, n_valid)
        Modes on the valid pixels [nm per unit coefficient], orthonormal over the pupil:
        ``modes @ modes.T / n_valid = I`` (a unit coefficient is 1 nm RMS).
    m2c : ndarray, shape (n_act, n_modes)
        Modes-to-commands matrix [nm of command per nm RMS]: ``dm.shape(m2c[:, i])`` is mode
        ``i`` up to a piston.
    variances : ndarray, shape (n_modes,), or None
        Von Kármán turbulent variance of each mode's coefficient [nm^2] for ``r0``, ``L0``.
    r0 : float or None
        Fried parameter at 500 nm [m] the variances were computed for.
    L0 : float or None
        Outer scale [m] the variances were computed for.
    mirror : SeparableMirror or None
        The factors of the mirror's Gaussian influence functions when ``modes = m2c^T (F -
        mean(F))`` for that mirror (set by :func:`kl_basis`): they let the cascade project
        phases through the mirror (:mod:`aocontrol.sim._projection`); ``None`` otherwise.

    Raises
    ------
    ValueError
        Inconsistent shapes, non-finite entries or negative variances.

    Notes
    -----
    Arrays are stored as read-only copies. ``variances`` scale as ``r0^(-5/3)``.
    """

    pupil: Pupil
    modes: np.ndarray
    m2c: np.ndarray
    variances: np.ndarray | None = None
    r0: float | None = None
    L0: float | None = None
    mirror: SeparableMirror | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.pupil, Pupil):
            raise TypeError(f"pupil must be a Pupil, got {type(self.pupil).__name__}")
        modes = check_finite_array("modes", self.modes, ndim=2).copy()
        if modes.shape[1] != self.pupil.n_valid:
            raise ValueError(
                f"modes must have shape (n_modes, n_valid={self.pupil.n_valid}), got {modes.shape}"
            )
        m2c = check_finite_array("m2c", self.m2c, ndim=2).copy()
        if m2c.shape[1] != modes.shape[0]:
            raise ValueError(
                f"m2c must have shape (n_act, n_modes={modes.shape[0]}), got {m2c.shape}"
            )
        for arr in (modes, m2c):
            arr.setflags(write=False)
        object.__setattr__(self, "modes", modes)
        object.__setattr__(self, "m2c", m2c)
        if self.variances is not None:
            var = check_finite_array("variances", self.variances, ndim=1).copy()
            if var.shape != (modes.shape[0],) or np.any(var < 0):
                raise ValueError(
                    f"variances must be >= 0 with shape ({modes.shape[0]},), got shape "
                    f"{var.shape}, min {var.min() if var.size else None}"
                )
            var.setflags(write=False)
            object.__setattr__(self, "variances", var)
        if self.mirror is not None:
            check_instance("mirror", self.mirror, SeparableMirror)
            if self.mirror.act_index.shape != (m2c.shape[0],):
                raise ValueError(
                    f"mirror must have n_act={m2c.shape[0]} actuators (rows of m2c), got "
                    f"{self.mirror.act_index.shape[0]}"
                )
        if self.r0 is not None:
            check_positive("r0", self.r0)
        if self.L0 is not None:
            check_positive("L0", self.L0)

    @property
    def n_modes(self) -> int:
        """Number of modes."""
        return int(self.modes.shape[0])

    @property
    def n_act(self) -> int:
        """Length of the command vectors ``m2c`` produces."""
        return int(self.m2c.shape[0])

    def project(self, phase: np.ndarray) -> np.ndarray:
        """Least-squares modal coefficients of ``phase``.

        Parameters
        ----------
        phase : array_like, shape (..., n_pix, n_pix) or (..., n_valid)
            Phase maps, or vectors on the valid pixels [nm of OPD].

        Returns
        -------
        ndarray, shape (..., n_modes)
            Coefficients [nm RMS], ``v @ modes.T / n_valid``. Piston is ignored (modes are
            piston-free).
        """
        v = self.pupil.as_vectors(phase, "phase")
        return v @ self.modes.T / self.pupil.n_valid

    def synthesize(self, coeffs: np.ndarray) -> np.ndarray:
        """Phase vectors from modal coefficients.

        Parameters
        ----------
        coeffs : array_like, shape (..., n_modes)
            Coefficients [nm RMS].

        Returns
        -------
        ndarray, shape (..., n_valid)
            Phase on the valid pixels [nm]; ``pupil.to_map`` gives maps.
        """
        c = check_finite_array("coeffs", coeffs)
        if c.ndim == 0 or c.shape[-1] != self.n_modes:
            raise ValueError(
                f"coeffs must end with n_modes={self.n_modes} values, got shape {c.shape}"
            )
        return c @ self.modes

    def residual(self, phase: np.ndarray) -> np.ndarray:
        """Fitting residual: the phase minus its projection on the basis.

        Parameters
        ----------
        phase : array_like, shape (..., n_pix, n_pix) or (..., n_valid)
            Phase maps or vectors [nm].

        Returns
        -------
        ndarray, shape (..., n_valid)
            Residual phase on the valid pixels [nm] (``pupil.to_map`` for maps). The piston
            of ``phase`` (not in the basis) stays in the residual; subtract the mean for a
            piston-free residual.
        """
        v = self.pupil.as_vectors(phase, "phase")
        return v - (v @ self.modes.T / self.pupil.n_valid) @ self.modes

    def commands(self, coeffs: np.ndarray) -> np.ndarray:
        """DM commands [nm] producing the modal ``coeffs`` ``(..., n_modes)``: ``(..., n_act)``."""
        c = check_finite_array("coeffs", coeffs)
        if c.ndim == 0 or c.shape[-1] != self.n_modes:
            raise ValueError(
                f"coeffs must end with n_modes={self.n_modes} values, got shape {c.shape}"
            )
        return c @ self.m2c.T

    def truncate(self, n_modes: int) -> ModalBasis:
        """The first ``n_modes`` modes (highest turbulent variance), as a new basis."""
        n = check_int("n_modes", n_modes, minimum=1)
        if n > self.n_modes:
            raise ValueError(f"n_modes must be <= {self.n_modes} (modes in the basis), got {n}")
        return ModalBasis(
            pupil=self.pupil,
            modes=self.modes[:n],
            m2c=self.m2c[:, :n],
            variances=None if self.variances is None else self.variances[:n],
            r0=self.r0,
            L0=self.L0,
            mirror=self.mirror,
        )


# ---------------------------------------------------------------------------- covariance
class _PistonFreeCovariance:
    """Von Kármán phase covariance [nm^2] acting on piston-free vectors on the pupil, by FFT.

    For ``v`` with zero sum over the valid pixels, ``C_phi v = K v`` with the kernel
    ``K(r) = -D(r) / 2`` (``D`` the structure function in nm^2), evaluated on all pixel
    offsets and applied as a zero-padded circular convolution.
    """

    def __init__(self, pupil: Pupil, r0: float, L0: float) -> None:
        n = pupil.n_pix
        self.pupil = pupil
        self.size = sfft.next_fast_len(2 * n - 1, real=True)
        d = np.arange(-(n - 1), n) * pupil.pixel_scale
        r = np.hypot(d[:, None], d[None, :])
        kern = -0.5 * structure_function(r, r0, L0) * opd_per_radian() ** 2
        full = np.zeros((self.size, self.size))
        idx = np.arange(-(n - 1), n) % self.size
        full[np.ix_(idx, idx)] = kern
        self.kernel_ft = sfft.rfft2(full)

    def apply(self, vectors: np.ndarray) -> np.ndarray:
        """``C_phi @ vectors.T`` as rows: ``(m, n_valid)`` -> ``(m, n_valid)`` [nm^2 * unit]."""
        p = self.pupil
        n, s = p.n_pix, self.size
        out = np.empty_like(vectors)
        for start in range(0, vectors.shape[0], _FFT_BATCH):
            block = vectors[start : start + _FFT_BATCH]
            maps = np.zeros((block.shape[0], s, s))
            maps[:, :n, :n] = p.to_map(block)
            conv = sfft.irfft2(sfft.rfft2(maps) * self.kernel_ft, s=(s, s))
            out[start : start + _FFT_BATCH] = p.to_vector(conv[:, :n, :n])
        return out


def _orthonormal_complement(vectors: np.ndarray) -> np.ndarray:
    """Orthonormal basis ``(n, n - k)`` of the complement of the columns of ``(n, k)``."""
    q, _ = np.linalg.qr(vectors, mode="complete")
    return q[:, vectors.shape[1] :]


def _reference_maps(pupil: Pupil, count: int) -> np.ndarray:
    """The fixed reference vectors of the canonical orientation, shape ``(count, n_valid)``.

    Reference ``2j`` is the x-even part, ``2j + 1`` the x-odd part (under ``x -> -x``, a flip
    of the pupil grid's columns) of the fixed pseudo-random map ``j`` (standard normal pixels,
    PCG64 seeded with ``(_REFERENCE_SEED, j)``): deterministic, the same in every process,
    and almost surely not orthogonal to any mode.
    """
    out = np.empty((count, pupil.n_valid))
    for j in range((count + 1) // 2):
        g = np.random.default_rng([_REFERENCE_SEED, j]).standard_normal((pupil.n_pix,) * 2)
        flipped = g[:, ::-1]
        pair = pupil.to_vector(np.stack([g + flipped, g - flipped]) / 2)
        out[2 * j : 2 * j + 2] = pair[: count - 2 * j]
    return out


def _sign_reference(pupil: Pupil) -> np.ndarray:
    """The fixed vector ``(n_valid,)`` every mode's sign is taken against (see kl_basis)."""
    g = np.random.default_rng([_REFERENCE_SEED, _SIGN_STREAM]).standard_normal((pupil.n_pix,) * 2)
    return pupil.to_vector(g)


def _clusters(s: np.ndarray, tol: float) -> list[np.ndarray]:
    """Runs of sorted (decreasing) eigenvalues whose consecutive gaps are <= ``tol``."""
    breaks = np.flatnonzero(-np.diff(s) > tol) + 1
    return [c for c in np.split(np.arange(s.size), breaks) if c.size > 1]


def _canonical_rotation(coords: np.ndarray) -> np.ndarray:
    """Orthogonal ``(k, k)`` rotation of a degenerate cluster to its canonical basis.

    ``coords`` ``(k, n_ref)``: the references' coordinates on the cluster's current
    orthonormal modes. The canonical modes are the Gram-Schmidt orthonormalisation of the
    references' projections on the cluster, in the references' order, skipping a reference
    whose projection is (to ``_REFERENCE_RCOND``) in the span of the previous ones; each
    canonical mode has a positive overlap with its reference. The projections do not depend
    on which orthonormal basis of the cluster ``coords`` was computed in, so neither does the
    result.
    """
    k = coords.shape[0]
    q = np.zeros((k, k))
    found = 0
    for j in range(coords.shape[1]):
        r = coords[:, j]
        scale = np.linalg.norm(r)
        r = r - q[:, :found] @ (q[:, :found].T @ r)
        r = r - q[:, :found] @ (q[:, :found].T @ r)  # re-orthogonalise (twice is enough)
        norm = np.linalg.norm(r)
        if scale == 0 or norm <= _REFERENCE_RCOND * scale:
            continue
        q[:, found] = r / norm
        found += 1
        if found == k:
            return q
    raise RuntimeError(f"kl_basis: {coords.shape[1]} references do not span a cluster of {k}")


def kl_basis(dm: DeformableMirror, n_modes: int, r0: float = 0.1, L0: float = 25.0) -> ModalBasis:
    """Karhunen-Loève modes of the DM space, tip and tilt first, piston removed.

    Parameters
    ----------
    dm : DeformableMirror
        Mirror whose influence functions span the modes (on ``dm.pupil``).
    n_modes : int
        Number of modes kept, at most the DM's piston-free controllable directions
        (``dm.n_act - 1`` unless some are unobservable over the pupil).
    r0 : float, default 0.1
        Fried parameter at 500 nm [m] for the turbulence statistics (the modes do not depend
        on r0; ``variances`` scale as ``r0^(-5/3)``).
    L0 : float, default 25.0
        Von Kármán outer scale [m].

    Returns
    -------
    ModalBasis
        ``modes`` orthonormal and piston-free over the pupil; modes 0 and 1 the DM's best
        fit of tip (x) and tilt (y); then KL modes by decreasing von Kármán variance.
        ``variances`` [nm^2]: the turbulent variance of each coefficient (for tip/tilt, the
        variance of their coefficient, not an eigenvalue).

    Raises
    ------
    ValueError
        If ``n_modes`` exceeds the number of valid actuators or of controllable piston-free
        directions.

    Notes
    -----
    See the module docstring for the algorithm (Gendron 1995 double diagonalisation), the
    canonical orientation of degenerate modes and signs (step 5: the same modes in every
    process, whatever its BLAS threads) and timings; the build time is logged at INFO level
    (the degenerate eigenspaces at DEBUG). The modes do not depend on ``r0``.

    Examples
    --------
    >>> from aocontrol.sim.dm import DeformableMirror
    >>> from aocontrol.sim.pupil import vlt_pupil
    >>> basis = kl_basis(DeformableMirror(vlt_pupil(32), n_actuators=15), 50)
    >>> gram = basis.modes @ basis.modes.T / basis.pupil.n_valid
    >>> bool(np.allclose(gram, np.eye(50), atol=1e-10))
    True
    """
    check_instance("dm", dm, DeformableMirror)
    n_modes = check_int("n_modes", n_modes, minimum=1)
    r0 = check_positive("r0", r0)
    L0 = check_positive("L0", L0)
    if n_modes > dm.n_act:
        raise ValueError(
            f"n_modes={n_modes} exceeds the number of valid actuators n_act={dm.n_act} of "
            f"the DM (n_actuators={dm.n_actuators} across)"
        )
    t_start = time.perf_counter()
    pupil = dm.pupil
    n = pupil.n_valid
    f = np.asarray(dm.influence)
    mu = f.mean(axis=1)  # pupil mean (piston) of each influence function
    f_p = f - mu[:, None]  # piston-free influence functions
    # All steps work on command-space matrices M (n_act, k) whose modes are M^T F; only
    # F, F_p and C_phi F_p are (n_act, n_valid) arrays.

    # 1. Geometric step: orthonormal DM-space modes M1^T F.
    w, u = np.linalg.eigh(f @ f.T / n)
    keep = w > w[-1] * _GEOMETRIC_RCOND
    m1 = u[:, keep] / np.sqrt(w[keep])

    # 2. Piston: remove the DM-piston direction (coefficients p of the constant map), then
    #    the residual mean of each mode, and re-orthonormalise.
    p = m1.T @ mu
    q = _orthonormal_complement(p[:, None] / np.linalg.norm(p))
    mean2 = p @ q  # means of the modes (small: they are orthogonal to the DM piston)
    # Piston-free modes M^T F_p have Gram I - mean2 mean2^T; inverse square root in closed form.
    nm2 = float(mean2 @ mean2)
    h = np.eye(mean2.size)
    if nm2 > 0:
        mhat = mean2 / np.sqrt(nm2)
        h += (1.0 / np.sqrt(1.0 - nm2) - 1.0) * np.outer(mhat, mhat)
    m2 = m1 @ q @ h  # modes B2 = M2^T F_p: orthonormal, piston-free
    n_free = m2.shape[1]
    if n_modes > n_free:
        raise ValueError(
            f"n_modes={n_modes} exceeds the {n_free} piston-free directions the DM controls "
            f"over the pupil (n_act={dm.n_act} valid actuators)"
        )

    # 3. Tip and tilt: best DM fits of unit-RMS x and y, Gram-Schmidt in that order.
    xy = np.stack([pupil.to_vector(pupil.x), pupil.to_vector(pupil.y)])
    xy -= xy.mean(axis=1, keepdims=True)
    xy /= np.sqrt(np.mean(xy**2, axis=1, keepdims=True))
    a = m2.T @ (f_p @ xy.T) / n  # (n_free, 2) coefficients of the fits on B2
    tt, rr = np.linalg.qr(a)
    tt *= np.sign(np.diag(rr))  # keep +x, +y orientation
    rest = _orthonormal_complement(tt)

    # 4. Turbulent step in the remaining space: C2 = B2 C_phi B2^T / n^2.
    cov_op = _PistonFreeCovariance(pupil, r0, L0)
    a_cmd = f_p @ cov_op.apply(f_p).T  # F_p C_phi F_p^T, (n_act, n_act)
    a_cmd = 0.5 * (a_cmd + a_cmd.T)
    c2 = m2.T @ a_cmd @ m2 / n**2
    c_rest = rest.T @ c2 @ rest
    s, v = np.linalg.eigh(0.5 * (c_rest + c_rest.T))
    order = np.argsort(s)[::-1]
    s, v = s[order], v[:, order]
    # Canonical orientation of the degenerate eigenspaces (the pupil's symmetry makes KL modes
    # come in pairs; LAPACK returns any orthonormal basis of each, which depends on the BLAS
    # threads): rotate each to the Gram-Schmidt basis of the fixed references' projections.
    clusters = _clusters(s, _DEGENERATE_RTOL * max(float(s[0]), 0.0)) if s.size else []
    if logger.isEnabledFor(logging.DEBUG) and s.size > 1:
        gaps = -np.diff(s) / s[0]
        split = gaps > _DEGENERATE_RTOL
        logger.debug(
            "kl_basis: %d degenerate eigenspaces (sizes %s); relative gaps: largest inside "
            "one %.1e, smallest between two %.1e (tolerance %.0e)",
            len(clusters),
            sorted({c.size for c in clusters}),
            float(gaps[~split].max()) if np.any(~split) else 0.0,
            float(gaps[split].min()) if np.any(split) else float("inf"),
            _DEGENERATE_RTOL,
        )
    if clusters:
        size = max(c.size for c in clusters)
        refs = _reference_maps(pupil, 2 * size + 4)
        ref_coords = (m2 @ rest).T @ (f_p @ refs.T) / n  # (n_rest, n_ref): <B_i, r_j>
        for c in clusters:
            rot = _canonical_rotation(v[:, c].T @ ref_coords)
            v[:, c] = v[:, c] @ rot
            s[c] = s[c].mean()  # equal to the cluster's spread (<= the tolerance)
    transform = np.concatenate([tt, rest @ v], axis=1)[:, :n_modes]
    variances = np.concatenate([np.diag(tt.T @ c2 @ tt), s])[:n_modes]

    m2c = m2 @ transform
    modes = m2c.T @ f_p
    # Polish the orthonormality lost to rounding in the ill-conditioned DM directions
    # (symmetric orthonormalisation; the correction is tiny, see the DEBUG log).
    gram = modes @ modes.T / n
    gw, gv = np.linalg.eigh(gram)
    logger.debug(
        "kl_basis: orthonormality error before polishing %.1e",
        float(np.max(np.abs(gram - np.eye(n_modes)))),
    )
    polish = (gv / np.sqrt(gw)) @ gv.T
    modes = polish @ modes
    m2c = m2c @ polish
    # Canonical signs: every KL mode (from mode 2; tip and tilt are +x and +y) has a positive
    # overlap with the fixed sign reference.
    signs = np.ones(n_modes)
    signs[2:] = np.where(modes[2:] @ _sign_reference(pupil) < 0, -1.0, 1.0)
    modes *= signs[:, None]
    m2c = m2c * signs
    logger.info(
        "kl_basis: %d modes of %d valid actuators (n_pix=%d, %d valid pixels) in %.2f s",
        n_modes,
        dm.n_act,
        pupil.n_pix,
        n,
        time.perf_counter() - t_start,
    )
    return ModalBasis(
        pupil=pupil,
        modes=modes,
        m2c=m2c,
        variances=np.maximum(variances, 0.0),
        r0=r0,
        L0=L0,
        mirror=SeparableMirror.from_dm(dm),
    )


def fitting_error(basis: ModalBasis, r0: float, L0: float = 25.0) -> float:
    """Von Kármán variance left after the best fit by ``basis``, piston excluded [nm^2].

    Analytic (no screens): the piston-free turbulent variance averaged over the pupil,
    ``sum_ij D(r_ij) / (2 n^2)``, minus the variance captured by the modes,
    ``sum_i M_i^T C_phi M_i / n^2`` (exact for an orthonormal piston-free basis).

    Parameters
    ----------
    basis : ModalBasis
        Orthonormal, piston-free basis (e.g. all the modes of :func:`kl_basis` for the DM
        fitting error).
    r0 : float
        Fried parameter at 500 nm [m].
    L0 : float, default 25.0
        Outer scale [m].

    Returns
    -------
    float
        Residual variance [nm^2 of OPD]; divide by ``opd_per_radian()**2`` for rad^2 at 500 nm.
    """
    check_instance("basis", basis, ModalBasis)
    r0 = check_positive("r0", r0)
    L0 = check_positive("L0", L0)
    pupil = basis.pupil
    n = pupil.n_valid
    cov_op = _PistonFreeCovariance(pupil, r0, L0)
    # K applied to the uniform vector gives row sums of -D/2 (no piston-free requirement on
    # a linear kernel product itself).
    total = -float(np.sum(cov_op.apply(np.ones((1, n))))) / n**2
    captured = float(np.sum(basis.modes * cov_op.apply(basis.modes))) / n**2
    return max(total - captured, 0.0)
