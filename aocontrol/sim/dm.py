"""Deformable mirror: square actuator grid with Gaussian influence functions, stroke clipping.

Conventions: commands are in nm -- a unit command on one actuator raises the optical path by
1 nm at that actuator's centre (the influence function is normalised to a peak of 1), so
commands, stroke and phase maps share one unit (OPD in nm, wavelength independent). Command
vectors have shape ``(..., n_act)`` over the *valid* actuators (see
:class:`DeformableMirror`), phase vectors ``(..., n_valid)`` over the valid pupil pixels of the
:class:`~aocontrol.sim.pupil.Pupil`.

Influence function
------------------
The Gaussian model of OOPAO (``mechCoupling``) and HCIPy (``crosstalk``), one of COMPASS's
influence types: for an actuator at ``(xa, ya)``,
``IF(x, y) = exp(ln(c) ((x - xa)^2 + (y - ya)^2) / pitch^2)`` with ``c`` the mechanical
coupling, the value of an influence function at the neighbouring actuator (0.3 is a common
value for piezo-stack mirrors). Its fitting-error coefficient, ``sigma^2 = a_F (pitch/r0)^(5/3)``
rad^2 at 500 nm, is ~0.23 (0.226 at 6 pixels per pitch, 0.233 for 25 actuators at 4 pixels
per pitch; exact covariance, L0 = infinity), the value of a perfect Fourier-filter DM
(0.232, Rigaut et al. 1998); tested in ``tests/test_dm_modes.py``.

Geometry
--------
Fried geometry, as for a Shack-Hartmann with ``n_actuators - 1`` sub-apertures across the
pupil (SAXO: 40x40 lenslets, 41x41 actuators): ``n_actuators`` actuators across the diameter,
the outermost ones on the pupil edge, ``pitch = diameter / (n_actuators - 1)``.
"""

from __future__ import annotations

import logging
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
from aocontrol.sim.pupil import Pupil

__all__ = [
    "DeformableMirror",
    "MIN_PIXELS_PER_PITCH",
    "SAXO_N_ACTUATORS",
    "SAXO_PLUS_N_ACTUATORS",
]

logger = logging.getLogger(__name__)

#: Actuators across the diameter of SAXO's high-order DM (41x41, Fried geometry with the
#: 40x40 Shack-Hartmann; Fusco et al. 2006, Sauvage et al. 2016).
SAXO_N_ACTUATORS = 41
#: Default actuators across the diameter for the SAXO+ second stage. The published design
#: value could not be checked here; 28 is chosen so that the 400-540 KL modes of the SAXO+
#: study are at most ~85 % of the valid actuators (644 on the VLT pupil), close to the ratio of
#: SAXO's 1200 modes to its 1360 valid actuators. Override it when the instrument value is
#: known. Needs ``n_pix >= 54`` (2 pixels per pitch).
SAXO_PLUS_N_ACTUATORS = 28
#: Minimum pupil samples per actuator pitch: below 2 the influence functions (and the
#: waffle pattern) are not resolved. Point sampling at 2 pixels per pitch underestimates the
#: fitting error by ~10 % (a_F 0.20-0.22 instead of ~0.23).
MIN_PIXELS_PER_PITCH = 2.0


@dataclass(frozen=True)
class DeformableMirror:
    """Deformable mirror conjugated to the pupil, square grid, Gaussian influence functions.

    Parameters
    ----------
    pupil : Pupil
        Pupil the mirror acts on; it must sample the pitch with at least
        :data:`MIN_PIXELS_PER_PITCH` pixels (``pitch / pupil.pixel_scale >= 2``).
    n_actuators : int, default 41
        Actuators across the diameter (Fried geometry, ``pitch = D / (n_actuators - 1)``);
        41 for SAXO (:data:`SAXO_N_ACTUATORS`), see :data:`SAXO_PLUS_N_ACTUATORS` for stage 2.
    coupling : float, default 0.3
        Mechanical coupling in (0, 1): value of an influence function at the neighbouring
        actuator.
    stroke : float or None, default None
        Maximum |command| [nm of OPD]; None for an unlimited stroke. The SAXO+ stage-2 DM has
        +-3.2 um, i.e. ``stroke=3200.0``.
    margin : float, default 1.0
        Valid-actuator criterion [pitches]: an actuator is kept when its centre lies in the
        annulus ``r_in - margin * pitch <= r <= D/2 + margin * pitch`` (``r_in`` the radius of
        the central obstruction), i.e. within ``margin`` pitches of the illuminated area.
        With ``coupling=0.3`` an actuator one pitch outside the edge still moves the edge by
        30 % of its command and is needed to fit slopes there (with 0.5 pitch the DM's fit
        of a tilt leaves ~3 % residual instead of ~1 %). Geometric, so independent of the
        pupil sampling. Other actuators (corners, deep behind the obstruction) are not part
        of the command vector. SAXO (41 across, VLT pupil): 1360 valid actuators.

    Attributes
    ----------
    pitch : float
        Actuator spacing [m].
    positions : ndarray, shape (n_act, 2)
        ``(x, y)`` of the valid actuators [m], row-major order of the full grid.
    influence : ndarray, shape (n_act, n_valid)
        Influence functions on the valid pupil pixels [nm of OPD per nm of command].

    Raises
    ------
    ValueError
        If the pupil samples the pitch with fewer than 2 pixels, if ``coupling`` is not in
        (0, 1), or if ``stroke`` is not > 0.

    Examples
    --------
    >>> from aocontrol.sim.pupil import vlt_pupil
    >>> dm = DeformableMirror(vlt_pupil(32), n_actuators=15)
    >>> round(dm.pitch, 4), dm.influence.shape[1] == dm.pupil.n_valid
    (0.5714, True)
    """

    pupil: Pupil
    n_actuators: int = SAXO_N_ACTUATORS
    coupling: float = 0.3
    stroke: float | None = None
    margin: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.pupil, Pupil):
            raise TypeError(f"pupil must be a Pupil, got {type(self.pupil).__name__}")
        check_int("n_actuators", self.n_actuators, minimum=2)
        check_in_range("coupling", self.coupling, 0.0, 1.0, low_inclusive=False)
        if self.stroke is not None:
            check_positive("stroke", self.stroke)
        check_nonnegative("margin", self.margin)
        px_per_pitch = self.pitch / self.pupil.pixel_scale
        if px_per_pitch < MIN_PIXELS_PER_PITCH * (1 - 1e-9):
            needed = int(np.ceil(MIN_PIXELS_PER_PITCH * (self.n_actuators - 1)))
            raise ValueError(
                f"pupil sampling too coarse for the DM pitch: n_pix={self.pupil.n_pix} gives "
                f"{px_per_pitch:.2f} pixels per pitch for n_actuators={self.n_actuators}; "
                f"need >= {MIN_PIXELS_PER_PITCH:g}, i.e. n_pix >= {needed}"
            )
        if self.n_act == 0:
            raise ValueError(f"no valid actuator within margin={self.margin} pitches of the pupil")

    # ------------------------------------------------------------------ geometry
    @property
    def pitch(self) -> float:
        """Actuator spacing [m]: ``diameter / (n_actuators - 1)``."""
        return self.pupil.diameter / (self.n_actuators - 1)

    @property
    def _log_coupling(self) -> float:
        return float(np.log(self.coupling))

    @cached_property
    def _grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Valid-actuator flags on the full grid and the valid actuators' (x, y) [m]."""
        c = (np.arange(self.n_actuators) - (self.n_actuators - 1) / 2.0) * self.pitch
        ya, xa = np.meshgrid(c, c, indexing="ij")
        xa, ya = xa.ravel(), ya.ravel()
        r = np.hypot(xa, ya)
        r_out = self.pupil.diameter / 2 + self.margin * self.pitch
        r_in = self.pupil.obstruction * self.pupil.diameter / 2 - self.margin * self.pitch
        valid = (r <= r_out * (1 + 1e-12)) & (r >= r_in * (1 - 1e-12))
        pos = np.stack([xa[valid], ya[valid]], axis=1)
        valid.setflags(write=False)
        pos.setflags(write=False)
        return valid, pos

    @property
    def valid_grid(self) -> np.ndarray:
        """Boolean map of the valid actuators, shape ``(n_actuators, n_actuators)``."""
        return self._grid[0].reshape(self.n_actuators, self.n_actuators)

    @property
    def positions(self) -> np.ndarray:
        """``(x, y)`` of the valid actuators [m], shape ``(n_act, 2)``."""
        return self._grid[1]

    @property
    def n_act(self) -> int:
        """Number of valid actuators: the length of a command vector."""
        return int(self._grid[1].shape[0])

    # ------------------------------------------------------------------ influence
    @cached_property
    def influence(self) -> np.ndarray:
        """Influence functions on the valid pupil pixels, shape ``(n_act, n_valid)`` [nm/nm]."""
        xp = self.pupil.to_vector(self.pupil.x)
        yp = self.pupil.to_vector(self.pupil.y)
        pos = self.positions
        d2 = (pos[:, 0, None] - xp[None, :]) ** 2 + (pos[:, 1, None] - yp[None, :]) ** 2
        out = np.exp(self._log_coupling / self.pitch**2 * d2)
        out.setflags(write=False)
        return out

    def shape(self, commands: np.ndarray) -> np.ndarray:
        """Mirror shape for ``commands``.

        Parameters
        ----------
        commands : array_like, shape (..., n_act)
            Actuator commands [nm].

        Returns
        -------
        ndarray, shape (..., n_valid)
            Optical path on the valid pupil pixels [nm]; ``pupil.to_map`` gives the map.
        """
        c = np.asarray(commands, dtype=float)
        if c.ndim == 0 or c.shape[-1] != self.n_act:
            raise ValueError(
                f"commands must end with n_act={self.n_act} values, got shape {c.shape}"
            )
        return c @ self.influence

    @cached_property
    def _fit_matrix(self) -> np.ndarray:
        """Least-squares reconstructor ``(n_valid, n_act)``: phase vector -> commands."""
        f = self.influence
        gram = f @ f.T
        w, v = np.linalg.eigh(gram)
        keep = w > w[-1] * 1e-10
        if not np.all(keep):
            logger.info(
                "DM fit: %d of %d command directions below 1e-10 of the largest eigenvalue dropped",
                int(np.sum(~keep)),
                w.size,
            )
        inv = (v[:, keep] / w[keep]) @ v[:, keep].T
        out = f.T @ inv
        out.setflags(write=False)
        return out

    def fit(self, phase: np.ndarray) -> np.ndarray:
        """Least-squares commands best fitting ``phase`` over the pupil (piston included).

        Parameters
        ----------
        phase : array_like, shape (..., n_pix, n_pix) or (..., n_valid)
            Phase maps or vectors on the valid pixels [nm of OPD].

        Returns
        -------
        ndarray, shape (..., n_act)
            Commands [nm] minimising ``mean((shape(c) - phase)^2)`` over the valid pixels.
        """
        return _as_vectors(self.pupil, phase, "phase") @ self._fit_matrix

    # ------------------------------------------------------------------ stroke
    def clip(self, commands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Clip commands to the stroke and count the saturated actuators.

        Parameters
        ----------
        commands : array_like, shape (..., n_act)
            Commands [nm].

        Returns
        -------
        clipped : ndarray, shape (..., n_act)
            ``commands`` clipped to ``[-stroke, stroke]`` (a copy; unchanged values when
            ``stroke`` is None).
        n_saturated : ndarray of int, shape (...)
            Number of actuators whose command exceeded the stroke, per command vector.

        Examples
        --------
        >>> from aocontrol.sim.pupil import vlt_pupil
        >>> dm = DeformableMirror(vlt_pupil(32), n_actuators=15, stroke=100.0)
        >>> c = np.zeros(dm.n_act); c[:3] = [150.0, -250.0, 50.0]
        >>> clipped, n_sat = dm.clip(c)
        >>> clipped[:3].tolist(), int(n_sat)
        ([100.0, -100.0, 50.0], 2)
        """
        c = np.array(commands, dtype=float)
        if c.ndim == 0 or c.shape[-1] != self.n_act:
            raise ValueError(
                f"commands must end with n_act={self.n_act} values, got shape {c.shape}"
            )
        if self.stroke is None:
            return c, np.zeros(c.shape[:-1], dtype=int)
        over = np.abs(c) > self.stroke
        np.clip(c, -self.stroke, self.stroke, out=c)
        return c, over.sum(axis=-1)


def _as_vectors(pupil: Pupil, data: np.ndarray, name: str) -> np.ndarray:
    """``(..., n_pix, n_pix)`` maps or ``(..., n_valid)`` vectors -> ``(..., n_valid)``."""
    arr = check_finite_array(name, data)
    if arr.ndim >= 1 and arr.shape[-1] == pupil.n_valid:
        return arr
    if arr.ndim >= 2 and arr.shape[-2:] == (pupil.n_pix, pupil.n_pix):
        return pupil.to_vector(arr)
    raise ValueError(
        f"{name} must end with ({pupil.n_pix}, {pupil.n_pix}) (maps) or n_valid="
        f"{pupil.n_valid} (vectors on valid pixels), got shape {arr.shape}"
    )
