"""Loop analysis: closed-loop responses, margins, stability, residual variance.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
PSDs are one-sided [units^2/Hz]: integrated over [0, fs/2] they give the variance.
"""

from aocontrol.analysis._cascade import (
    cascade_rejection,
    cascade_sensitivity,
    slow_stage_sensitivity,
)
from aocontrol.analysis._certificate import ModulusCertificate, modulus_certificate
from aocontrol.analysis._certificate import polynomial_certificate as polynomial_certificate
from aocontrol.analysis._certificate import rational_modulus_minima as rational_modulus_minima
from aocontrol.analysis._constrained import (
    ConstrainedBound,
    ConstrainedBoundError,
    constrained_bound,
)
from aocontrol.analysis._loop import (
    LoopResponse,
    command_transfer,
    complementary_sensitivity,
    controller_response,
    loop_response,
    noise_transfer,
    sensitivity,
    white_noise_psd,
)
from aocontrol.analysis._margins import DELAY_SEARCH_FRAMES, Margins, margins
from aocontrol.analysis._multimode import (
    MultiModeCertificate,
    multimode_certificate,
    multimode_closed_loop_poles,
)
from aocontrol.analysis._psd import welch_psd
from aocontrol.analysis._residual import (
    mean_square_sampling_variance,
    residual_psd,
    residual_variance,
)
from aocontrol.analysis._robust import (
    RobustMargin,
    UncertaintySet,
    robust_from_coefficients,
    robust_margin,
)
from aocontrol.analysis._stability import (
    closed_loop_poles,
    is_stable,
    winding_stability,
    winding_zeros,
)
from aocontrol.analysis._wiener import wiener_bound

__all__ = [
    "ConstrainedBound",
    "ConstrainedBoundError",
    "constrained_bound",
    "cascade_rejection",
    "cascade_sensitivity",
    "slow_stage_sensitivity",
    "LoopResponse",
    "DELAY_SEARCH_FRAMES",
    "Margins",
    "ModulusCertificate",
    "MultiModeCertificate",
    "multimode_certificate",
    "multimode_closed_loop_poles",
    "modulus_certificate",
    "closed_loop_poles",
    "command_transfer",
    "complementary_sensitivity",
    "controller_response",
    "is_stable",
    "loop_response",
    "margins",
    "mean_square_sampling_variance",
    "noise_transfer",
    "residual_psd",
    "residual_variance",
    "RobustMargin",
    "UncertaintySet",
    "robust_margin",
    "robust_from_coefficients",
    "sensitivity",
    "welch_psd",
    "white_noise_psd",
    "wiener_bound",
    "winding_stability",
    "winding_zeros",
]
