"""Results and errors of the data-driven synthesis (see :mod:`aocontrol.synthesis._datadriven`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from aocontrol._validation import PerModeError
from aocontrol.controllers import IIRBank

__all__ = [
    "GRID_DISAGREEMENT",
    "DataDrivenError",
    "DataDrivenResult",
    "GridResolutionWarning",
    "InitialPoleRadiusError",
    "ModeReport",
]


class DataDrivenError(PerModeError):
    """Synthesis failed for some modes; the others are kept.

    One of the per-mode errors (:class:`aocontrol._validation.PerModeError`: ``except
    PerModeError`` catches it with the modal-gain and constrained-bound ones).

    Parameters
    ----------
    failed : dict[int, str]
        Mode index -> reason (the exception type and message of a numerical failure).
    result : DataDrivenResult
        Every mode: designed controllers for the modes that succeeded, the initial controller
        for the failed ones (``result.ok`` tells which).

    Attributes
    ----------
    failed : dict[int, str]
    result : DataDrivenResult
    """

    def __init__(self, failed: dict[int, str], result: DataDrivenResult) -> None:
        super().__init__(
            failed,
            result,
            n_modes=result.controller.n_modes,
            operation="data-driven synthesis",
            note=". The other modes are in this error's .result",
        )


class GridResolutionWarning(UserWarning):
    """A frequency grid that does not resolve the PSD: the figures on it are not the residual.

    Warned by :func:`aocontrol.synthesis.datadriven` when an interval of the input grid holds
    much of the PSD's integral while the PSD changes across it by orders of magnitude (e.g.
    the first nonzero point above a turbulence knee), or when the residual on the input grid
    and on the fine check (:attr:`DataDrivenResult.residual_variance_fine`) disagree by more
    than ``GRID_DISAGREEMENT``. The message gives the reason and the fix: a denser or
    log-spaced grid.
    """


#: Factor between the residual on the input grid and on the fine check beyond which
#: :func:`aocontrol.synthesis.datadriven` warns (:class:`GridResolutionWarning`). On a grid that
#: resolves the PSD they agree to a few per cent (the fine check's linear interpolation).
GRID_DISAGREEMENT = 2.0


class InitialPoleRadiusError(ValueError):
    """The initial controller has free poles on or outside ``max_pole_radius``.

    Raised by :func:`aocontrol.synthesis.datadriven` before any design, e.g. for an
    integrator (pole at ``z = 1``) given as ``initial`` with every pole free
    (``fixed_denominator=[1]``). A caller may catch it to start from the default instead
    (``initial=None``), or pass ``max_pole_radius=None`` to allow unstable controllers.

    Parameters
    ----------
    radii : dict[int, float]
        Mode index -> largest free pole radius of its initial controller (>= the radius).
    max_pole_radius : float
        The radius asked for.

    Attributes
    ----------
    radii : dict[int, float]
    max_pole_radius : float
    """

    def __init__(self, radii: dict[int, float], max_pole_radius: float) -> None:
        first = list(radii.items())[:5]
        super().__init__(
            f"initial has free controller poles on or outside max_pole_radius="
            f"{max_pole_radius} (mode: radius {first}{' ...' if len(radii) > 5 else ''}); give "
            "an initial controller strictly inside the radius, or max_pole_radius=None to "
            "allow unstable controllers"
        )
        self.radii = dict(radii)
        self.max_pole_radius = max_pole_radius

    def __reduce__(self):  # picklable (worker processes) despite the custom signature
        return (type(self), (self.radii, self.max_pole_radius))


@dataclass(frozen=True)
class ModeReport:
    """Diagnostics of one mode's design.

    Attributes
    ----------
    mode : int
        Mode index.
    ok : bool
        True if the design succeeded and passed verification.
    message : str
        Failure reason (empty when ``ok``).
    objective_history : ndarray, shape (n_accepted + 1,)
        Normalised objective ``J`` on the design grid, the initial controller first
        (non-increasing when the initial controller lies in the parameter set).
    solves : int
        Number of convex problems solved (all grid refinements included).
    converged : bool
        The last iterations lowered ``J`` by less than ``tol``.
    modulus_margin : float
        Certified ``min |1 + G K|`` (:func:`aocontrol.analysis.modulus_certificate`: over the
        whole unit circle for a rational plant, never above the true margin).
    stable : bool
        Closed-loop stability (:func:`aocontrol.analysis.is_stable`).
    refinements : int
        Constraint-only points added to the design grid by the dense checks.
    start : str
        ``"initial"`` (the initial controller) or ``"previous mode"`` (the design of the
        previous mode of the same chunk, used when it is feasible and better for this mode);
        ``"initial (design rejected: worse)"`` (:data:`REJECTED_WORSE`) when the design was
        worse than its start on the input grid or the fine check and the start was returned
        instead.
    certificate : str
        How ``modulus_margin`` was certified (exact over the circle for a rational plant).
    pole_radius : float
        Largest modulus of the controller's free poles (the fixed factor apart).
    order : int
        Controller order (the degree of ``Y``; chosen per mode with ``order="auto"``).
    bound_start_error : str
        Why the reduced-bound start asked for this mode (``bound_start``) is missing: the
        failure of :func:`aocontrol.analysis.constrained_bound` (then the mode started from
        its other starts, with a warning); empty when not asked or computed.
    robust_margin : float
        A robust design (``uncertainty``): the modulus margin certified over the whole set
        (:func:`aocontrol.analysis.robust_margin`, a lower bound); ``nan`` otherwise.
    """

    mode: int
    ok: bool
    message: str
    objective_history: np.ndarray
    solves: int
    converged: bool
    modulus_margin: float
    stable: bool
    refinements: int
    start: str
    certificate: str = ""
    pole_radius: float = float("nan")
    order: int = 0
    bound_start_error: str = ""
    robust_margin: float = float("nan")


@dataclass(frozen=True)
class DataDrivenResult:
    """Result of :func:`datadriven`.

    Attributes
    ----------
    controller : IIRBank
        One row of coefficients per mode (powers of ``z^-1``, ``a[:, 0] == 1``).
    initial : IIRBank
        The starting controllers (by default the optimal modal-gain integrators).
    reports : tuple of ModeReport
        Per-mode diagnostics.
    residual_variance : ndarray, shape (n_modes,)
        Predicted residual variance ``int (|S|^2 psd + |T|^2 noise_psd) df`` [units^2] on the
        input grid (trapezoid, as :func:`aocontrol.analysis.residual_variance`).
    initial_residual_variance : ndarray, shape (n_modes,)
        The same for ``initial``.
    design_freqs : ndarray, shape (n_design,)
        Design grid [Hz] (before refinements).
    residual_variance_fine, initial_residual_variance_fine : ndarray, shape (n_modes,)
        The same residuals on a fine check: exact ``|S|^2`` and ``|T|^2`` on 20,001 linear
        and 2,001 log points over the input range and around every ``|S|`` peak, the PSDs
        interpolated linearly between input points (a resonance between input points shows).
    verification : str
        Which certificates and grids the reported figures come from.
    uncertainty : UncertaintySet or None
        The set every mode was certified over (a robust design), ``None`` for the nominal
        loop only.
    """

    controller: IIRBank
    initial: IIRBank
    reports: tuple[ModeReport, ...]
    residual_variance: np.ndarray
    initial_residual_variance: np.ndarray
    design_freqs: np.ndarray = field(repr=False)
    residual_variance_fine: np.ndarray | None = field(default=None, repr=False)
    initial_residual_variance_fine: np.ndarray | None = field(default=None, repr=False)
    verification: str = ""
    uncertainty: object = None

    @property
    def ok(self) -> np.ndarray:
        """Per-mode success flags, shape ``(n_modes,)``."""
        return np.array([r.ok for r in self.reports])

    @property
    def modulus_margin(self) -> np.ndarray:
        """Certified modulus margins, shape ``(n_modes,)``."""
        return np.array([r.modulus_margin for r in self.reports])

    @property
    def stable(self) -> np.ndarray:
        """Closed-loop stability per mode, shape ``(n_modes,)``."""
        return np.array([r.stable for r in self.reports])

    @property
    def order(self) -> np.ndarray:
        """Controller order per mode, shape ``(n_modes,)``."""
        return np.array([r.order for r in self.reports])

    @property
    def pole_radius(self) -> np.ndarray:
        """Largest free controller pole modulus per mode, shape ``(n_modes,)``."""
        return np.array([r.pole_radius for r in self.reports])

    @property
    def solves(self) -> np.ndarray:
        """Convex solves per mode, shape ``(n_modes,)``."""
        return np.array([r.solves for r in self.reports])

    @property
    def objective_history(self) -> list[np.ndarray]:
        """Normalised objective per iteration, one array per mode."""
        return [r.objective_history for r in self.reports]
