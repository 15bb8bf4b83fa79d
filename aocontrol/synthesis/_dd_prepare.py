"""The preparation of a data-driven design (private to :mod:`aocontrol.synthesis._datadriven`).

:func:`prepare` validates :func:`~aocontrol.synthesis.datadriven`'s inputs, chooses each mode's
start controller and structure (the optimal modal-gain integrator, leaky or with integral
action; scaled down until certified over an uncertainty set), builds the design, dense and
winding grids with the plant's response on them (:class:`DesignContext`) and the per-mode work
items: everything the per-mode designs (:mod:`._dd_mode`) and the assembly of the result
(:mod:`._dd_assemble`) need, as a :class:`_Setup`.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import control
import numpy as np

from aocontrol._validation import (
    check_finite_array,
    check_frequency_grid,
    check_in_range,
    check_int,
    check_nonnegative,
    check_psd,
    mode_psds,
)
from aocontrol.analysis import (
    UncertaintySet,
    is_stable,
    residual_psd,
    robust_from_coefficients,
)
from aocontrol.controllers import IIRBank
from aocontrol.plant import (
    check_frd_coverage,
    check_system,
    frequency_response,
    plant_fs,
    plant_latency,
    with_latency,
    z_inverse_coefficients,
)
from aocontrol.synthesis._dd_context import (
    DesignContext,
    ModeItem,
    design_margin,
    exact_quotient,
)
from aocontrol.synthesis._dd_grids import (
    _dense_grid,
    _design_indices,
    _trapezoid_weights,
    unresolved_intervals,
)
from aocontrol.synthesis._dd_mode import _START_LEAK_MARGIN
from aocontrol.synthesis._dd_results import (
    GridResolutionWarning,
    InitialPoleRadiusError,
)
from aocontrol.synthesis._dd_starts import bound_start_modes

logger = logging.getLogger(__name__)

# Points of the fine grid on which each step keeps the winding number (linear constraints).
_N_WIND = 256
#: Default radius inside which the free controller poles are kept (``max_pole_radius``).
DEFAULT_POLE_RADIUS = 0.9999
# The integral-action structure is chosen where its start's residual is below this fraction
# of the leaky start's.
# Measured on the 20 lowest of 540 turbulence modes (3 kHz, order 5): 0.8 left modes 2 to 4
# (integrator start 0.85x the leaky one) in the free structure, where the iterations stall at
# 1.6 to 1.8x the Wiener bound (median 1.11); 0.9 gives them integral action, 1.17x (median
# 1.075); 1.0 (integral action everywhere) costs 3 to 4 % on modes 6 to 19 (median 1.124).
_INTEGRATOR_START_GAIN = 0.9
#: Orders tried by ``order="auto"``, lowest first.
AUTO_ORDERS = (2, 3, 5, 8, 12)
#: Largest controller order accepted (an AO controller has a few to a few tens of
#: coefficients; the SOCP grows as order x n_grid and polynomial roots lose accuracy beyond).
MAX_ORDER = 64
#: Largest design grid accepted [points] (the SOCP has one cone per point and per constraint).
MAX_N_GRID = 4096
#: Largest number of convex solves per mode accepted.
MAX_ITER = 10000


def _check_bounded_int(name: str, value: object, low: int, high: int) -> int:
    return check_int(name, value, minimum=low, maximum=high)


def _initial_coefficients(initial: object, n_modes: int, fs: float) -> list:
    """Per-mode (b, a) of the user's initial controller."""
    if isinstance(initial, IIRBank):
        if abs(initial.fs - fs) > 1e-9 * fs:
            raise ValueError(
                f"initial runs at fs={initial.fs!r} Hz, expected the rate of the plant ({fs!r} Hz)"
            )
        if initial.n_modes not in (1, n_modes):
            raise ValueError(
                f"initial must have 1 or {n_modes} modes (one per PSD row), got {initial.n_modes}"
            )
        rows = [min(i, initial.n_modes - 1) for i in range(n_modes)]
        return [(initial.b[r], initial.a[r]) for r in rows]
    if isinstance(initial, (control.TransferFunction, control.FRD)):
        check_system("initial", initial, fs, rate_of="the plant")
        if isinstance(initial, control.FRD):
            raise TypeError("initial must be a transfer function or an IIRBank, got a control.FRD")
        b, a = z_inverse_coefficients(initial, "initial")
        return [(b, a)] * n_modes
    raise TypeError(
        "initial must be an IIRBank (e.g. Integrator), a control.TransferFunction "
        f"or None, got {type(initial).__name__}"
    )


# A robust start's numerator shrinks by this factor until it is certified over the set.
_ROBUST_START_SHRINK = 0.8
_ROBUST_START_STEPS = 40


def _robust_start(plant, bank: IIRBank, uset: UncertaintySet, mu_d: float) -> IIRBank:
    """The start, each mode's loop gain scaled down until the margin ``mu_d`` is certified over
    the uncertainty set (a small enough gain always is: the loop tends to the open one).

    Raises
    ------
    ValueError
        A mode that no scaled start certifies (named, with the set).
    """
    bg, ag = z_inverse_coefficients(plant, "plant")
    b = bank.b.copy()
    failed = []
    for i in range(bank.n_modes):
        for _ in range(_ROBUST_START_STEPS):
            rm = robust_from_coefficients(bg, ag, b[i], bank.a[i], bank.fs, uset)
            if rm.stable and rm.value >= mu_d:
                break
            b[i] *= _ROBUST_START_SHRINK
        else:
            failed.append(i)
    if failed:
        raise ValueError(
            f"no start certified over the uncertainty set ({uset.describe()}) for modes "
            f"{failed[:10]}: the set is too wide for modulus_margin (a static gain ratio "
            "beyond what a margin allows, or a latency range no controller of this start "
            "survives)"
        )
    return IIRBank(b, bank.a, bank.fs)


@dataclass(frozen=True)
class _Setup:
    """Validated inputs, shared context and per-mode work items of one call."""

    plant: object
    fs: float
    freqs: np.ndarray
    psd: np.ndarray
    noise: np.ndarray
    ctx: DesignContext
    items: list
    init_bank: IIRBank
    user_initial: bool = False


def prepare(
    plant,
    freqs,
    psd,
    *,
    order,
    noise_psd,
    modulus_margin,
    hinf_weight,
    fixed_denominator,
    initial,
    max_pole_radius,
    bound_start,
    max_iter,
    tol,
    n_grid,
    fs,
    uncertainty,
    integral_action,
) -> _Setup:
    """Validate the inputs, build the grids and the initial controllers.

    The keywords are :func:`~aocontrol.synthesis.datadriven`'s (``n_jobs`` and ``progress``
    apart), every one given.
    """
    if uncertainty is not None and not isinstance(uncertainty, UncertaintySet):
        raise TypeError(
            f"uncertainty must be an aocontrol.analysis.UncertaintySet, got "
            f"{type(uncertainty).__name__}"
        )
    if uncertainty is not None and uncertainty.nominal_only:
        uncertainty = None
    if integral_action:
        if fixed_denominator is not None:
            raise ValueError(
                "integral_action=True fixes the denominator factor [1, -1]: give it or "
                f"fixed_denominator, not both (got fixed_denominator={fixed_denominator!r})"
            )
        fixed_denominator = [1.0, -1.0]
    fs_ = plant_fs(plant, fs)
    if isinstance(plant, control.FRD):
        # Every result is verified on [0, fs/2]: a measured plant must cover it.
        check_frd_coverage("plant", plant, fs_)
    freqs = check_frequency_grid("freqs", freqs, fs_)
    if freqs.size < 3:
        raise ValueError(f"freqs must have at least 3 points, got {freqs.size}")
    check_psd("psd", psd, freqs.size, allow_all_zero=False)
    psd2, noise2, _ = mode_psds(psd, noise_psd, freqs.size)
    n_modes = psd2.shape[0]
    unresolved = unresolved_intervals(freqs, psd2)
    if unresolved:
        i, (f_lo, f_hi, ratio, share) = next(iter(unresolved.items()))
        warnings.warn(
            f"freqs does not resolve the PSD of {len(unresolved)} mode(s) "
            f"{list(unresolved)[:10]}: between {f_lo:.4g} and {f_hi:.4g} Hz (mode {i}) the PSD "
            f"changes {ratio:.3g}x and that interval holds {100 * share:.0f} % of its "
            "integral, so the design weighs it with two points (e.g. a turbulence knee below "
            "the first nonzero frequency); give a denser or log-spaced grid there, e.g. "
            f"np.concatenate([[0.0], np.geomspace({fs_ * 1e-5:.3g}, {fs_ / 2:g}, 500)])",
            GridResolutionWarning,
            stacklevel=4,
        )
    if isinstance(order, str):
        if order != "auto":
            raise ValueError(
                f"order must be an integer in [1, {MAX_ORDER}] or 'auto', got {order!r}"
            )
        orders = AUTO_ORDERS
    else:
        orders = ()
        order = _check_bounded_int("order", order, 1, MAX_ORDER)
    if max_pole_radius is not None:
        max_pole_radius = check_in_range(
            "max_pole_radius", max_pole_radius, 0.0, 1.0, low_inclusive=False, high_inclusive=True
        )
    mu = check_in_range("modulus_margin", modulus_margin, 0.0, 1.0, low_inclusive=False)
    use_bound = bound_start_modes(bound_start, plant, freqs, psd2, noise2)
    hinf_weight = check_nonnegative("hinf_weight", hinf_weight)
    max_iter = _check_bounded_int("max_iter", max_iter, 1, MAX_ITER)
    tol = check_nonnegative("tol", tol)
    n_grid = _check_bounded_int("n_grid", n_grid, 8, MAX_N_GRID)
    if fixed_denominator is None:
        fixed = np.array([1.0])
    else:
        fixed = np.trim_zeros(
            check_finite_array("fixed_denominator", fixed_denominator, ndim=1), "b"
        )
        if fixed.size == 0 or fixed[0] == 0:
            raise ValueError(
                "fixed_denominator must have a nonzero first coefficient "
                f"(causal, powers of z^-1), got {fixed_denominator!r}"
            )
        fixed = fixed / fixed[0]
    if orders:
        orders = tuple(o for o in orders if o >= max(fixed.size - 1, 1))
        order = orders[0]
    elif fixed.size - 1 > order:
        raise ValueError(
            f"order must be >= the degree of fixed_denominator ({fixed.size - 1}), got {order}"
        )

    # Initial controllers (and the fixed factor of each mode's denominator).
    fixed_modes = [fixed] * n_modes
    if initial is None:
        from aocontrol.synthesis._modal_gain import ModalGainError, optimal_modal_gain

        leak = 0.0
        if fixed.size == 2 and -1.0 <= fixed[1] < 0.0:
            leak = 1.0 + float(fixed[1])
        elif fixed.size > 1:
            logger.warning(
                "fixed_denominator %s is not an integrator or leak factor: the "
                "default integrator start lies outside the parameter set",
                fixed.tolist(),
            )
        # With the design grid's margin (slightly above mu) it is feasible at every step.
        mu_start = design_margin(mu)

        def start(leak: float) -> IIRBank:
            try:
                return optimal_modal_gain(
                    plant, freqs, psd2, noise2, modulus_margin=mu_start, leak=leak, fs=fs_
                )
            except ModalGainError as exc:
                # Failed modes start from the fallback gain (small, stabilising).
                logger.warning("initial integrator: %s", exc)
                return exc.result

        if fixed.size == 1 and fixed_denominator is not None and max_pole_radius is not None:
            # Every pole free (asked for) and inside the radius: the leaky integrator start.
            leak = 1.0 - max_pole_radius * (1.0 - _START_LEAK_MARGIN)
        init_bank = start(leak)
        if fixed_denominator is None and max_pole_radius is not None:
            # Every pole free and inside the radius: the integrator's pole at z = 1 is not in
            # the set. Per mode, the structure: every pole free, from the leaky integrator
            # whose pole lies just inside the radius, unless the integrator (its pole fixed at
            # z = 1: integral action, which low-order modes with decades of power below the
            # loop bandwidth need) starts clearly better. Measured on 540 turbulence modes:
            # the free structure ends 3 to 7 % closer to the Wiener bound where the two starts
            # are within 10 %; tip/tilt start 2.4x better as integrators.
            leaky = start(1.0 - max_pole_radius * (1.0 - _START_LEAK_MARGIN))
            v_int = np.trapezoid(residual_psd(plant, init_bank, freqs, psd2, noise2, fs=fs_), freqs)
            v_leak = np.trapezoid(residual_psd(plant, leaky, freqs, psd2, noise2, fs=fs_), freqs)
            use_leak = v_int >= _INTEGRATOR_START_GAIN * v_leak
            fixed_modes = [np.array([1.0]) if u else np.array([1.0, -1.0]) for u in use_leak]
            init_bank = init_bank.where(use_leak, leaky)
        init = _initial_coefficients(init_bank, n_modes, fs_)
    else:
        init = _initial_coefficients(initial, n_modes, fs_)
    init_bank = IIRBank.from_rows([b for b, _ in init], [a for _, a in init], fs_)
    b0s, a0s = init_bank.b, init_bank.a
    unstable = [
        i for i in range(n_modes) if not is_stable(plant, init_bank.transfer_function(i), fs=fs_)
    ]
    if unstable:
        raise ValueError(
            f"initial controller does not stabilise the plant for modes "
            f"{unstable[:10]}{' ...' if len(unstable) > 10 else ''}"
        )
    variants: tuple = ()
    if uncertainty is not None:
        if not isinstance(plant, control.TransferFunction):
            raise TypeError(
                "uncertainty needs a transfer-function plant (the certificate over the set "
                f"is polynomial), got {type(plant).__name__}"
            )
        latency0 = plant_latency(plant)
        if latency0 is None and uncertainty.latency != (0.0, 0.0):
            raise ValueError("a latency interval needs a plant with a pure delay to move")
        variants = tuple(
            k * (plant if d == 0.0 else with_latency(plant, max(latency0 + d, 0.0)))
            for k, d in uncertainty.corners()
        )
        init_bank = _robust_start(plant, init_bank, uncertainty, design_margin(mu))
        b0s, a0s = init_bank.b, init_bank.a
    if max_pole_radius is not None:
        outside = {}
        for i in range(n_modes):
            quot = exact_quotient(a0s[i], fixed_modes[i])
            if quot is None:
                continue  # outside the parameter set: the design starts from its response
            r = np.abs(np.roots(quot)) if quot.size > 1 else np.zeros(1)
            # Strictly inside: the convexified radius constraint needs the start's scaled
            # denominator nonzero on the circle (a start pole on the radius has none).
            if r.size and r.max() >= max_pole_radius * (1 - 1e-12):
                outside[i] = float(r.max())
        if outside:
            raise InitialPoleRadiusError(outside, max_pole_radius)

    # Design grid: the input grid (subsampled) plus margin-only points covering [0, fs/2]
    # beyond it (a TF plant, or an FRD that covers [0, fs/2]: checked above).
    idx = _design_indices(freqs, psd2 + noise2, n_grid)
    f_h2 = freqs[idx]
    lo, hi = 0.0, fs_ / 2
    step = (f_h2[-1] - f_h2[0]) / max(f_h2.size - 1, 1)
    first = f_h2[f_h2 > 0][0]
    extra = np.concatenate(
        [
            np.arange(0.0, f_h2[0], step),
            np.geomspace(hi * 1e-5, first, 8)[:-1] if first > hi * 1e-5 else [],
            np.arange(f_h2[-1] + step, hi, step),
            [hi],
        ]
    )
    extra = extra[~np.isin(extra, f_h2) & (extra <= hi)]
    f_design = np.unique(np.concatenate([f_h2, extra]))
    tw = _trapezoid_weights(freqs)
    g_design = frequency_response(plant, f_design, fs_)
    if np.any(g_design == 0):
        raise ValueError("plant response must be nonzero on the design grid")
    f_dense = _dense_grid(f_design, lo, hi)
    wind_targets = np.concatenate(
        [np.linspace(lo, hi, _N_WIND), np.geomspace(max(lo, hi * 2e-6), hi, _N_WIND // 8)]
    )
    wind_index = np.unique(np.clip(np.searchsorted(f_dense, wind_targets), 0, f_dense.size - 1))
    ctx = DesignContext(
        plant=plant,
        fs=fs_,
        input_freqs=freqs,
        input_weights=tw,
        h2_freqs=f_h2,
        design_freqs=f_design,
        design_response=g_design,
        dense_freqs=f_dense,
        dense_response=frequency_response(plant, f_dense, fs_),
        winding_index=wind_index,
        fixed_factor=fixed,
        free_order=order - (fixed.size - 1),
        modulus_margin=mu,
        hinf_weight=hinf_weight,
        response_scale=float(np.median(np.abs(g_design))),
        plant_coefficients=(
            z_inverse_coefficients(plant, "plant")
            if isinstance(plant, control.TransferFunction)
            else None
        ),
        max_iter=max_iter,
        tol=tol,
        extrapolate=True,
        max_pole_radius=max_pole_radius,
        auto_orders=orders,
        uncertainty=uncertainty,
        variant_plants=variants,
    )

    items = [
        ModeItem(i, psd2[i], noise2[i], b0s[i], a0s[i], fixed_modes[i], bool(use_bound[i]))
        for i in range(n_modes)
    ]
    return _Setup(plant, fs_, freqs, psd2, noise2, ctx, items, init_bank, initial is not None)
