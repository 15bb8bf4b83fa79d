"""Deformable mirror: square actuator grid with Gaussian influence functions, stroke clipping.

:class:`DeformableMirror` is the physical mirror (geometry, influence functions, fit);
:class:`ModalDM` is a simulator stage's mirror in modal space, the one owner of the stroke
(modal and actuator limits, saturation counts); both clip through :func:`clip_to_stroke`.

Stroke: one model, three names
------------------------------
* ``actuator_stroke`` [nm of actuator command]: the physical limit ``|c_a| <= actuator_stroke``
  of every actuator (3200 for the SAXO+ stage-2 DM, +-3.2 um). Owned by the DM
  (:class:`DeformableMirror`, :class:`ModalDM`); a case file gives it in metres
  (``dm_stroke``), converted once (``StageSpec.dm_stroke_nm``).
* ``modal_stroke`` [nm RMS per mode]: a limit per mode of a :class:`ModalDM` (a simplified DM
  model without actuators), and :func:`modal_stroke`, the per-mode bound an actuator stroke
  implies (a mode alone stays within the actuator stroke), derived from ``m2c`` in that one
  function; :attr:`ModalDM.command_bound` gives it for a stage's DM.
* ``command_limit`` [units of the command]: a controller's own clip of its modal command
  (``IIRBank``, ``LQGBank``: anti-windup) or the MPC's hard constraint (``MPCBank``): a
  controller setting, not the DM's. In the case comparison the MPC's is the DM's
  :attr:`~ModalDM.command_bound`.

The older names (``DeformableMirror(stroke=)``, ``ModalDM(stroke=)``, ``Stage(stroke=,
dm_stroke=)``, the controllers' ``stroke=``) still work with a ``DeprecationWarning``.

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
from typing import Any

import numpy as np

from aocontrol._deprecation import DeprecatedAttribute, renamed_keyword
from aocontrol._validation import (
    check_finite_array,
    check_in_range,
    check_int,
    check_nonnegative,
    check_positive,
)
from aocontrol.sim.model_errors import DMResponse
from aocontrol.sim.pupil import Pupil

__all__ = [
    "DeformableMirror",
    "ModalDM",
    "ModalDMState",
    "clip_to_stroke",
    "modal_stroke",
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


@renamed_keyword("stroke", "actuator_stroke", "the actuator stroke [nm]")
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
    actuator_stroke : float or None, default None
        Maximum |command| of every actuator [nm of OPD], finite and > 0; None for an
        unlimited stroke. The SAXO+ stage-2 DM has +-3.2 um, i.e. ``actuator_stroke=3200.0``.
        (``stroke`` is its deprecated name.)
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
        (0, 1), or if ``actuator_stroke`` is not finite and > 0.

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
    actuator_stroke: float | None = None
    margin: float = 1.0

    #: Deprecated name of :attr:`actuator_stroke`.
    stroke = DeprecatedAttribute("actuator_stroke", "the actuator stroke [nm]")

    def __post_init__(self) -> None:
        if not isinstance(self.pupil, Pupil):
            raise TypeError(f"pupil must be a Pupil, got {type(self.pupil).__name__}")
        check_int("n_actuators", self.n_actuators, minimum=2)
        check_in_range("coupling", self.coupling, 0.0, 1.0, low_inclusive=False)
        if self.actuator_stroke is not None:
            object.__setattr__(
                self, "actuator_stroke", check_positive("actuator_stroke", self.actuator_stroke)
            )
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
    def positions(self) -> np.ndarray:
        """``(x, y)`` of the valid actuators [m], shape ``(n_act, 2)``, full-grid row-major."""
        c = (np.arange(self.n_actuators) - (self.n_actuators - 1) / 2.0) * self.pitch
        ya, xa = np.meshgrid(c, c, indexing="ij")
        xa, ya = xa.ravel(), ya.ravel()
        r = np.hypot(xa, ya)
        r_out = self.pupil.diameter / 2 + self.margin * self.pitch
        r_in = self.pupil.obstruction * self.pupil.diameter / 2 - self.margin * self.pitch
        valid = (r <= r_out * (1 + 1e-12)) & (r >= r_in * (1 - 1e-12))
        pos = np.stack([xa[valid], ya[valid]], axis=1)
        pos.setflags(write=False)
        return pos

    @property
    def n_act(self) -> int:
        """Number of valid actuators: the length of a command vector."""
        return int(self.positions.shape[0])

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
        return self.pupil.as_vectors(phase, "phase") @ self._fit_matrix

    # ------------------------------------------------------------------ stroke
    def clip(self, commands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Clip commands to the actuator stroke and count the saturated actuators.

        Parameters
        ----------
        commands : array_like, shape (..., n_act)
            Commands [nm].

        Returns
        -------
        clipped : ndarray, shape (..., n_act)
            ``commands`` clipped to ``[-actuator_stroke, actuator_stroke]`` (a copy; unchanged
            values when ``actuator_stroke`` is None).
        n_saturated : ndarray of int, shape (...)
            Number of actuators whose command exceeded the stroke, per command vector.

        Examples
        --------
        >>> from aocontrol.sim.pupil import vlt_pupil
        >>> dm = DeformableMirror(vlt_pupil(32), n_actuators=15, actuator_stroke=100.0)
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
        if self.actuator_stroke is None:
            return c, np.zeros(c.shape[:-1], dtype=int)
        clipped, over = clip_to_stroke(c, self.actuator_stroke)
        return clipped, over.sum(axis=-1)


def clip_to_stroke(values: np.ndarray, stroke: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Clip values to ``[-stroke, stroke]``: the one stroke-clipping implementation.

    Parameters
    ----------
    values : ndarray, shape (..., n)
        Commands [nm] (modal coefficients or actuator commands).
    stroke : float or ndarray, shape (n,)
        Limit per entry [nm], > 0.

    Returns
    -------
    clipped : ndarray, shape (..., n)
        The clipped values (a new array).
    over : ndarray of bool, shape (..., n)
        Where ``|values| > stroke``.
    """
    over = np.abs(values) > stroke
    return np.clip(values, -stroke, stroke), over


def modal_stroke(m2c: object, actuator_stroke: float) -> np.ndarray:
    """Per-mode command bound [nm] that an actuator stroke implies, from the modes' shapes.

    Mode ``i`` alone at amplitude ``u_i`` drives actuator ``a`` to ``m2c[a, i] u_i``: it stays
    within ``+-actuator_stroke`` iff ``|u_i| <= actuator_stroke / max_a |m2c[a, i]|``. The one
    place a modal bound is derived from the DM's stroke (through
    :attr:`ModalDM.command_bound`, the MPC's command limit in the case comparison); a
    combination of modes may still reach the stroke earlier, where the DM (:class:`ModalDM`
    with ``actuator_stroke``) clips.

    Parameters
    ----------
    m2c : array_like, shape (n_act, n_modes)
        Modes to actuator commands [nm of command per nm RMS of mode].
    actuator_stroke : float
        Largest |actuator command| [nm], > 0.

    Returns
    -------
    numpy.ndarray, shape (n_modes,)
        [nm RMS per mode]; ``inf`` for a mode that moves no actuator.

    Examples
    --------
    >>> modal_stroke([[1.0, 0.5], [-2.0, 0.25]], 100.0)
    array([ 50., 200.])
    """
    m2c = check_finite_array("m2c", m2c, ndim=2)
    stroke = check_positive("actuator_stroke", actuator_stroke)
    peak = np.max(np.abs(m2c), axis=0)
    return np.where(peak > 0, stroke / np.where(peak > 0, peak, 1.0), np.inf)


@renamed_keyword("stroke", "modal_stroke", "the DM's limit per mode [nm RMS]")
@dataclass(frozen=True, eq=False)
class ModalDM:
    """The DM of a simulator stage in modal space: owns the stroke and clips the commands.

    A modal command ``u`` (n_modes,) [nm RMS per mode] is clipped first per mode to
    ``modal_stroke`` (a modal limit), then, with ``actuator_stroke``, in actuator space: the
    actuator commands ``m2c @ u`` are clipped to ``+-actuator_stroke`` and projected back on
    the modes (least squares, ``pinv(m2c)``); the part of the clipped shape outside the modes
    is dropped (approximation of the modal simulator). Saturations are counted in a
    :class:`ModalDMState` (per mode: frames with a clipped mode or a clipped actuator the
    mode drives; per actuator: clipped frames). See the module notes for the stroke's names.

    Parameters
    ----------
    n_modes : int
        Number of modes commanded.
    modal_stroke : float or array_like (n_modes,), optional
        Limit per mode [nm RMS], finite and > 0; ``None`` for no modal limit. (``stroke`` is
        its deprecated name.)
    actuator_stroke : float, optional
        Actuator stroke [nm of command], finite and > 0 (3200 for the SAXO+ stage-2 DM,
        +-3.2 um); needs ``m2c``. ``None`` for no actuator limit.
    m2c : array_like (n_act, n_modes), optional
        Modes-to-commands matrix (``ModalBasis.m2c``).
    response : DMResponse, optional
        The mirror's temporal response (:class:`aocontrol.sim.model_errors.DMResponse`), a
        model error: the shape the WFS sees is the applied shape through it. ``None``: the
        mirror follows its command within the frame (the model's DM).
    mixing : array_like (n_modes, n_modes), optional
        The modes the mirror actually makes, in the basis (column ``i``: command ``i``), a
        model error: a misregistration after calibration
        (:func:`aocontrol.sim.model_errors.misregistration_matrix`). ``None``: the identity.

    Raises
    ------
    ValueError
        Non-finite or non-positive strokes (naming ``modal_stroke`` or ``actuator_stroke``),
        ``m2c`` missing or of the wrong shape, ``mixing`` not ``(n_modes, n_modes)``.
    TypeError
        ``response`` not a :class:`~aocontrol.sim.model_errors.DMResponse`.

    Examples
    --------
    >>> dm = ModalDM(2, actuator_stroke=100.0, m2c=[[1.0, 0.5], [-2.0, 0.25]])
    >>> dm.command_bound   # each mode alone, at its bound, drives one actuator to 100 nm
    array([ 50., 200.])
    """

    n_modes: int
    modal_stroke: Any = None
    actuator_stroke: float | None = None
    m2c: Any = None
    response: Any = None
    mixing: Any = None

    #: Deprecated name of :attr:`modal_stroke`.
    stroke = DeprecatedAttribute("modal_stroke", "the DM's limit per mode [nm RMS]")

    def __post_init__(self) -> None:
        n = check_int("n_modes", self.n_modes, minimum=1)
        if self.modal_stroke is not None:
            s = check_finite_array("modal_stroke", self.modal_stroke, ndim=(0, 1))
            if s.ndim == 1 and s.shape != (n,):
                raise ValueError(
                    f"modal_stroke must be a float or have shape ({n},), got {s.shape}"
                )
            if np.any(s <= 0):
                raise ValueError(
                    f"modal_stroke must be > 0 [nm] for every mode, got min {float(s.min())!r}"
                )
            s = np.broadcast_to(s, (n,)).copy()
            s.setflags(write=False)
            object.__setattr__(self, "modal_stroke", s)
        if self.actuator_stroke is not None:
            object.__setattr__(
                self, "actuator_stroke", check_positive("actuator_stroke", self.actuator_stroke)
            )
            m2c = None if self.m2c is None else check_finite_array("m2c", self.m2c, ndim=2)
            if m2c is None or m2c.shape[1] != n:
                raise ValueError(
                    f"actuator_stroke needs m2c of shape (n_act, n_modes) with n_modes={n}, "
                    f"got {None if m2c is None else m2c.shape}"
                )
            m2c = m2c.copy()
            m2c.setflags(write=False)
            object.__setattr__(self, "m2c", m2c)
        elif self.m2c is not None:
            m2c = check_finite_array("m2c", self.m2c, ndim=2).copy()
            m2c.setflags(write=False)
            object.__setattr__(self, "m2c", m2c)
        if self.response is not None:
            if not isinstance(self.response, DMResponse):
                raise TypeError(
                    f"response must be a DMResponse, got {type(self.response).__name__}"
                )
            if self.response.is_identity:
                object.__setattr__(self, "response", None)
        if self.mixing is not None:
            mix = check_finite_array("mixing", self.mixing, ndim=2)
            if mix.shape != (n, n):
                raise ValueError(f"mixing must have shape ({n}, {n}), got {mix.shape}")
            mix = mix.copy()
            mix.setflags(write=False)
            object.__setattr__(self, "mixing", mix)

    @property
    def dynamic(self) -> bool:
        """Whether the mirror's shape is not the applied command (a response or mixing)."""
        return self.response is not None or self.mixing is not None

    @classmethod
    def from_basis(
        cls, basis: Any, *, actuator_stroke: float | None = None, modal_stroke: Any = None
    ) -> ModalDM:
        """The DM of a modal basis: ``basis.n_modes`` modes, ``m2c = basis.m2c``.

        Parameters
        ----------
        basis : ModalBasis-like
            With ``n_modes`` and ``m2c`` (n_act, n_modes).
        actuator_stroke : float, optional
            Actuator stroke [nm]; ``None``: unlimited.
        modal_stroke : float or array_like (n_modes,), optional
            Limit per mode [nm RMS]; ``None``: none.
        """
        if not hasattr(basis, "n_modes") or not hasattr(basis, "m2c"):
            raise TypeError(
                f"basis must be a ModalBasis-like object (n_modes, m2c), got {type(basis).__name__}"
            )
        return cls(
            int(basis.n_modes),
            modal_stroke=modal_stroke,
            actuator_stroke=actuator_stroke,
            m2c=basis.m2c,
        )

    @property
    def limited(self) -> bool:
        """Whether any stroke limit applies."""
        return self.modal_stroke is not None or self.actuator_stroke is not None

    @cached_property
    def command_bound(self) -> np.ndarray | None:
        """Per-mode bound on a modal command [nm RMS], shape (n_modes,), or ``None``.

        What a controller's ``command_limit`` should be for this DM (the MPC's bound in the
        case comparison): ``modal_stroke`` and, with an actuator stroke, the bound it implies
        for each mode alone (:func:`modal_stroke`, from ``m2c``), the smaller of the two; a
        combination of modes may still reach the actuator stroke earlier, where the DM
        clips. ``inf`` for a mode that neither limits; ``None`` for an unlimited DM.
        """
        if not self.limited:
            return None
        bound = np.full(self.n_modes, np.inf)
        if self.modal_stroke is not None:
            bound = np.minimum(bound, self.modal_stroke)
        if self.actuator_stroke is not None:
            bound = np.minimum(bound, modal_stroke(self.m2c, self.actuator_stroke))
        bound.setflags(write=False)
        return bound

    @property
    def n_act(self) -> int | None:
        """Actuators (rows of ``m2c``), or ``None`` without ``m2c``."""
        return None if self.m2c is None else int(self.m2c.shape[0])

    @cached_property
    def c2m(self) -> np.ndarray:
        """Commands-to-modes matrix ``pinv(m2c)``, shape ``(n_modes, n_act)``."""
        if self.m2c is None:
            raise ValueError("c2m needs m2c")
        out = np.linalg.pinv(self.m2c)
        out.setflags(write=False)
        return out

    def new_state(self, fs: float | None = None) -> ModalDMState:
        """Zeroed saturation counters (and response memory) for one run at ``fs`` [Hz].

        ``fs`` is needed by a DM with a temporal response only.
        """
        state = ModalDMState(
            saturation=np.zeros(self.n_modes, dtype=np.int64),
            actuator_saturation=(
                None
                if self.actuator_stroke is None
                else np.zeros(self.m2c.shape[0], dtype=np.int64)
            ),
        )
        if self.response is not None:
            if fs is None:
                raise ValueError("a DM with a temporal response needs the loop rate fs")
            b, a = self.response.coefficients(fs)
            state.response = (
                b[:, None] / a[0],
                a[1:, None] / a[0],
                np.zeros((b.size, self.n_modes)),
                np.zeros((max(a.size - 1, 1), self.n_modes)),
            )
        return state

    def respond(self, y: np.ndarray, state: ModalDMState) -> None:
        """The shape the mirror makes for the applied shape ``y`` (n_modes,), in place: the
        modes it actually makes (``mixing``), then its temporal response (Direct-Form I,
        memory in ``state``)."""
        if self.mixing is not None:
            y[...] = self.mixing @ y
        if state.response is not None:
            b, a, x_hist, y_hist = state.response
            x_hist[1:] = x_hist[:-1]
            x_hist[0] = y
            out = (b * x_hist).sum(axis=0)
            if a.size:
                out -= (a * y_hist[: a.shape[0]]).sum(axis=0)
                y_hist[1:] = y_hist[:-1]
                y_hist[0] = out
            y[...] = out

    def clip(self, u: np.ndarray, state: ModalDMState) -> np.ndarray:
        """Clip one modal command to the stroke(s), counting saturations in ``state``.

        Parameters
        ----------
        u : ndarray, shape (n_modes,)
            Modal command [nm].
        state : ModalDMState
            Counters updated in place.

        Returns
        -------
        ndarray, shape (n_modes,)
            The command the DM applies (``u`` itself when nothing is clipped).
        """
        if self.modal_stroke is not None:
            clipped, over = clip_to_stroke(u, self.modal_stroke)
            if over.any():
                state.saturation += over
                u = clipped
        if self.actuator_stroke is not None:
            clipped, over = clip_to_stroke(self.m2c @ u, self.actuator_stroke)
            if over.any():
                state.actuator_saturation += over
                c2m = self.c2m
                state.saturation += np.abs(c2m[:, over]).sum(axis=1) > 0
                u = c2m @ clipped
        return u


@dataclass
class ModalDMState:
    """Saturation counters of a :class:`ModalDM` during one run (mutable).

    Parameters
    ----------
    saturation : ndarray (n_modes,) of int
        Frames in which each mode was clipped (or drives a clipped actuator).
    actuator_saturation : ndarray (n_act,) of int or None
        Frames in which each actuator was clipped (with an actuator stroke).
    response : tuple or None
        The temporal response's filter and memory ``(b, a[1:], inputs, outputs)``.
    """

    saturation: np.ndarray
    actuator_saturation: np.ndarray | None = None
    response: tuple | None = None
