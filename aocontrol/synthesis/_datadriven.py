"""Frequency-based data-driven controller synthesis (the paper's "Data-driven controller").

Per mode, an IIR controller ``K = X / Y`` (powers of ``z^-1``) minimises on a frequency grid

    J(K) = ( ||W1 S||_2^2 + ||Wn T||_2^2 ) / v_ref  +  hinf_weight * ||T||_inf^2
    subject to ||S||_inf <= 1 / modulus_margin,

with ``S = Y/P``, ``T = G X / P``, ``P = Y + G X``, ``W1^2 = psd`` and ``Wn^2 = noise_psd``.
The non-convex problem is solved by convex-concave iterations around the previous controller
(second-order cone programs, cvxpy + Clarabel, see :mod:`aocontrol.synthesis._socp`).
PSDs are one-sided [units^2/Hz]: integrated over [0, fs/2] they give the variance
(``scipy.signal.welch(..., scaling="density")``).

This module holds the public call; the preparation (inputs checked, starts, grids) is in
:mod:`._dd_prepare`, the per-mode design in :mod:`._dd_mode` and the result's assembly in
:mod:`._dd_assemble`.
"""

from __future__ import annotations

import inspect
from typing import Any

import control
import numpy as np  # noqa: F401 - the namespace of datadriven's doctest

from aocontrol._deprecation import renamed_keyword
from aocontrol._validation import check_int
from aocontrol.analysis import UncertaintySet
from aocontrol.controllers import IIRBank
from aocontrol.synthesis._dd_assemble import _assemble
from aocontrol.synthesis._dd_dask import check_client, check_memory
from aocontrol.synthesis._dd_mode import _run, chunks, local_workers
from aocontrol.synthesis._dd_prepare import DEFAULT_POLE_RADIUS, _Setup, prepare
from aocontrol.synthesis._dd_results import (
    GRID_DISAGREEMENT,
    DataDrivenError,
    DataDrivenResult,
    GridResolutionWarning,
    InitialPoleRadiusError,
    ModeReport,
)

__all__ = [
    "GRID_DISAGREEMENT",
    "DataDrivenError",
    "DataDrivenResult",
    "GridResolutionWarning",
    "InitialPoleRadiusError",
    "ModeReport",
    "datadriven",
]


@renamed_keyword("stroke_weight", "hinf_weight", "the weight of ||T||_inf^2, not a stroke")
def datadriven(
    plant: control.TransferFunction | control.FRD,
    freqs: object,
    psd: object,
    *,
    order: int | str = 5,
    noise_psd: object = 0.0,
    modulus_margin: float = 0.5,
    hinf_weight: float = 1e-3,
    fixed_denominator: object = None,
    initial: IIRBank | control.TransferFunction | None = None,
    max_pole_radius: float | None = DEFAULT_POLE_RADIUS,
    bound_start: bool | None = None,
    max_iter: int = 60,
    tol: float = 1e-3,
    n_grid: int = 64,
    n_jobs: int | None = None,
    progress: bool = True,
    fs: float | None = None,
    uncertainty: UncertaintySet | None = None,
    integral_action: bool = False,
    client: Any = None,
) -> DataDrivenResult:
    r"""Data-driven IIR controllers, one per mode, from disturbance and noise PSDs.

    For each mode the controller ``K = X / Y`` (polynomials in ``z^-1``, ``Y = F Y'`` with
    ``Y'`` monic and ``F`` the fixed factor) minimises on a frequency grid

    .. math::

        J(K) = \frac{1}{v_\mathrm{ref}} \int_0^{f_s/2}
               \left(|S|^2 \Phi_d + |T|^2 \Phi_n\right) df
               + \mathtt{hinf\_weight}\, \|T\|_\infty^2
        \quad \text{s.t.} \quad \|S\|_\infty \le 1/\mu

    with ``S = 1/(1 + G K)``, ``T = G K / (1 + G K)``. The integral (the paper's
    ``||W1 S||_2^2`` with ``W1^2 = psd``, plus the noise term ``||Wn T||_2^2`` with
    ``Wn^2 = noise_psd``) is the residual variance of
    :func:`aocontrol.analysis.residual_variance` [units^2]: exactly (trapezoid rule) when
    ``freqs`` has at most ``n_grid`` points, otherwise with ``|S|^2`` and ``|T|^2`` interpolated
    linearly between the design points (the PSDs keep every input point: the disturbance
    variance is exact). ``v_ref`` is that of the initial controller, so
    ``J(initial) = 1 + hinf_weight ||T0||_inf^2`` and the H2 part of ``J`` is the residual
    variance relative to the initial controller. ``||T||_inf^2`` (the
    paper's ``||W2 T||_inf^2``, ``W2^2 = hinf_weight``) penalises the peak of the command
    response (``|T| = |K S|`` for a pure-delay plant). With ``noise_psd = 0`` this is the paper's
    objective with the disturbance normalised by a scalar instead of its value at the
    bandwidth. The noise term changes no minimiser where the noise is white and the loop
    has at least one frame of delay: ``T = 1 - S`` with ``s_0 = 1`` and ``t_k = -s_k``
    after, so (Parseval) ``||Wn T||_2^2 = ||Wn S||_2^2 -`` the noise variance, and a design
    on the noisy pseudo-open-loop PSD with ``noise_psd = 0`` (the paper's way) has the same
    H2 part up to a constant; only ``v_ref``, hence the weight of ``||T||_inf^2`` relative
    to it, differs.

    The problem is solved by convex-concave iterations: each step is a second-order cone
    program (cvxpy with Clarabel, compiled once per worker with parameters and re-solved)
    around the previous controller, which is always feasible, so the objective never
    increases. Each step also keeps ``Re(P conj Pc) > 0`` on a fine grid (linear constraints:
    same winding number, so the closed loop stays stable) and ``|P|`` away from 0 (no hidden
    pole-zero cancellation on the unit circle); long flat valleys are crossed by extrapolating
    the last step while the objective decreases. The start is the optimal modal-gain
    integrator (designed with the modulus-margin constraint; see ``max_pole_radius`` for its
    structure); modes are processed in fixed chunks of neighbouring modes, and a mode starts
    from the previous mode's design instead when that passes the certificates and is better
    for it (continuation: same result whatever ``n_jobs``).

    Certificates, not grid samples. Every candidate controller is checked by

    * the modulus margin over the whole unit circle (:func:`aocontrol.analysis.
      modulus_certificate`: exact for a transfer-function plant, from the stationary points
      of ``|1 + G K|`` as polynomial roots and the minima on a grid refined around every pole
      near the circle; a lightly damped controller pole makes a dip narrower than any
      uniform grid). Where it fails, the certified minima join the design grid as
      constraint points (cutting planes) and the step is solved again;
    * closed-loop stability (closed-loop poles; the winding number on a dense grid for a
      measured plant) and the controller's free poles inside ``max_pole_radius`` (roots),
      kept by a convexified constraint in each step (the scaled free denominator keeps its
      winding number on the circle, as ``P`` does for the closed loop) and by damped steps;
    * ``|S|`` peaks between design points (a small margin allows them): they join the grid
      as H2 points, so the objective sees them.

    The returned figures are the certified ones: ``modulus_margin`` is the certificate's
    (never above the true margin), ``residual_variance`` is on the input grid and
    ``residual_variance_fine`` on a fine check (exact ``|S|^2`` on 20,001 + 2,001 points and
    around every ``|S|`` peak, PSDs linear between input points). A design worse than its
    starting controller on either is not returned: the start is kept for that mode (logged,
    a warning for the default start, information for a user's ``initial``, the loop's running
    controller in a warm redesign; and ``start`` says so, :data:`REJECTED_WORSE`). So the
    result is never worse than the start (by default
    the optimal modal-gain integrator of that structure) on the input grid and on the fine
    check. ``result.verification`` says which certificates and grids were used. A mode for
    which no certified controller is found fails alone (see Raises).

    Parameters
    ----------
    plant : control.TransferFunction or control.FRD
        Discrete SISO plant (command to measurement), e.g. :func:`aocontrol.loop_plant`,
        shared by every mode. An FRD must cover ``[0, fs/2]`` (results are verified there).
    freqs : array_like, shape (n_freqs,)
        Strictly increasing frequencies [Hz] in ``[0, fs/2]`` on which the PSDs are given.
    psd : array_like, shape (n_freqs,) or (n_modes, n_freqs)
        Disturbance PSD per mode, one-sided [units^2/Hz]; not zero everywhere.
    order : int or "auto", default 5
        Controller order ``n`` (1 to ``MAX_ORDER`` = 64): the degree of ``Y`` (``F``
        included) and of ``X``. With a fixed factor ``F`` of degree ``d``,
        ``K = X / (F Y')`` with ``X``, ``Y'`` free of degree ``n - d`` (``order = 1`` with
        ``F = 1 - z^-1`` is the integrator ``g / (1 - z^-1)``). ``"auto"``: per mode, the
        orders of ``AUTO_ORDERS`` (2, 3, 5, 8, 12) are designed in turn, each starting from
        the previous one's design, stopping once two steps gain less than 1 % each; the lowest
        order within 2 % of the best residual on the input grid is kept (``result.order``).
        The paper raises the order for vibrations; on turbulence a low order often suffices.
    noise_psd : float or array_like, default 0.0
        Measurement-noise PSD, one-sided [units^2/Hz]: a scalar (white), ``(n_freqs,)``,
        ``(n_modes, n_freqs)`` or ``(n_modes,)`` (one white level per mode, as returned by
        :func:`aocontrol.synthesis.disturbance_from_telemetry`).
    modulus_margin : float, default 0.5
        Required ``min |1 + G K|`` in (0, 1), i.e. ``||S||_inf <= 1/modulus_margin``.
    hinf_weight : float, default 1e-3
        Weight of the H-infinity term ``||T||_inf^2`` relative to the normalised residual
        (>= 0; 0 drops it): the paper's ``alpha``, a weight on the command sensitivity
        ``T`` (``|T| = |K S|``, the control sensitivity, for a pure-delay plant), which
        limits the command's overshoot. A weight, not a stroke (the stroke is the DM's,
        :mod:`aocontrol.sim.dm`); ``stroke_weight`` is its deprecated name.
    fixed_denominator : array_like, optional
        Fixed factor ``F`` of the denominator, coefficients in powers of ``z^-1``, e.g.
        ``[1, -1]`` (integral action) or ``[1, -(1 - leak)]``.
    initial : IIRBank or control.TransferFunction, optional
        Starting controller(s) (1 or ``n_modes`` modes); must stabilise the plant and have its
        free poles strictly inside ``max_pole_radius``. Default: the optimal modal-gain
        integrator (leaky if ``F = [1, -(1 - leak)]``; see ``max_pole_radius``).
    max_pole_radius : float or None, default 0.9999
        Every free controller pole (the fixed factor ``F`` apart) stays strictly inside this
        radius, in (0, 1] (about ``1e-4`` of it inside: the convexified constraint keeps the
        scaled denominator off zero on the circle; 1.0 allows poles up to just inside the unit
        circle), so that the controller survives an open loop (a WFS dropout, a DM clipping at
        its stroke) instead of running away. ``None`` allows unstable controllers (explicit
        only). With the default ``fixed_denominator=None`` the structure is chosen per mode:
        every pole free, starting from the leaky integrator whose pole lies just inside the
        radius, or, where the integrator starts at least 10 % better (low-order modes whose
        power spans decades below the loop bandwidth), ``F = 1 - z^-1`` with the integrator's
        pole at z = 1 fixed (integral action). The default 0.9999 (a 3.3 s time constant at 3
        kHz: an open loop's command decays, where an integrator's holds) was chosen by
        ``benchmarks/bench_synthesis.py`` (``docs/benchmarks.md``).
    bound_start : bool or None, default None
        Also start from the margin-constrained bound, reduced to the design's order: the
        sensitivity of :func:`aocontrol.analysis.constrained_bound` (FIR Youla parameter of
        256 taps, margin ``1.05 modulus_margin``) fitted by a controller of the design's
        structure, its free poles reflected inside ``max_pole_radius``
        (:mod:`aocontrol.synthesis._dd_starts`). It replaces the initial controller as the
        start only where it passes every certificate (exact margin over the whole circle and
        on the dense grid, closed-loop stability, pole radius) with a lower objective (the
        result is never worse than the best certified start; ``ModeReport.start`` says
        "bound reduction"). The convex-concave iterations from an integrator stop in a local
        optimum on resonant spectra, which this start avoids (``benchmarks/bench_synthesis.py``
        part (f), ``docs/benchmarks.md``). It costs one bound per mode: tens of milliseconds
        of CPU, seconds for narrow lines whose bound needs the margin's cutting planes
        (256 taps; 3.5 s on a mode with three lines 300 times the turbulence).
        ``None``: with a stable transfer-function plant, on the modes with a line
        (``_dd_starts.has_lines``: the PSD half a decade above its
        running median over +-0.15 decades of frequency) in the disturbance PSD of a model
        (every local maximum a line: an estimate's scatter is not) or in disturbance plus
        noise. A line under the noise counts: it marks a resonant spectrum, where the bound
        start pays. Turbulence modes are rarely selected, whether from a model or estimated
        from telemetry (:func:`disturbance_from_telemetry`; ``docs/benchmarks.md``).
        ``True``: every mode (a stable transfer-function plant needed); ``False``: never.
    max_iter : int, default 60
        Maximum convex solves per mode (at most ``MAX_ITER`` = 10000).
    tol : float, default 1e-3
        Stop when three iterations lower the objective by less than ``tol`` (relative); one
        iteration for a mode started from the previous mode's design.
    n_grid : int, default 64
        Design-grid size (8 to ``MAX_N_GRID`` = 4096): an input grid with more points is
        subsampled (log- and linearly-spaced points and the PSD peaks), with quadrature
        weights that keep the integral exact for a ``|S|^2`` linear between design points.
        The default was chosen by measurement (``docs/benchmarks.md``); the dense
        verification certifies any size.
    n_jobs : int, optional
        Worker processes (joblib); ``None`` uses every core this process may use
        (``joblib.cpu_count()``: CPU affinity, cgroup limits and ``LOKY_MAX_CPU_COUNT``, which
        a sweep's workers set to their share), 1 runs in this process. Ignored with
        ``client``.
    progress : bool, default True
        Show a tqdm progress bar over modes.
    fs : float, optional
        Loop rate [Hz] if the plant lost its ``dt``.
    uncertainty : UncertaintySet, optional
        A robust design: the modulus margin (and closed-loop stability) for every loop of a
        box of loop-gain factors and latency changes
        (:class:`aocontrol.analysis.UncertaintySet`), not the nominal loop only. The convex
        steps constrain the box's corners and edge middles at every design point
        (:meth:`~aocontrol.analysis.UncertaintySet.corners`: the rows of each, beside the
        nominal plant's), and every candidate is certified over the whole box
        (:func:`aocontrol.analysis.robust_margin`: exact in the gain, a latency grid with a
        bound between points); where the certificate fails, its worst frequency joins the
        grid. The start (the modal-gain integrator) is scaled down per mode until it is
        certified over the box. ``result.uncertainty`` and ``ModeReport.robust_margin`` say
        what was certified. A transfer-function plant is needed (its pure delay moved for
        the latencies, :func:`aocontrol.with_latency`).
    integral_action : bool, default False
        A fixed pole at ``z = 1`` (``fixed_denominator = [1, -1]``): a static disturbance (a
        reference-slope change, a non-common-path aberration) is rejected entirely in steady
        state; the other poles stay inside ``max_pole_radius``.
    client : distributed.Client, optional
        Design on this Dask cluster instead of local processes: each chunk of 32 neighbouring
        modes is one task (the chunks of the serial and joblib paths: the bank is bit for bit
        the same). The client must be connected and the cluster have (or gain within 10 s) a
        worker that can import aocontrol. A task that raises is retried twice; a worker lost
        mid-task has its task run again elsewhere by Dask (``allowed-failures``); a chunk
        whose task still fails has its modes failed (:class:`DataDrivenError`, the reason per
        mode), the others designed. Memory per worker, estimated before anything is designed
        (``aocontrol.synthesis._dd_dask.task_memory``): about ``400 MB + 64 B x
        n_modes_per_chunk x n_freqs + 768 B x n_freqs + 128 B x n_dense x (2 order + 1)``
        (``n_dense`` about 6,200 for ``n_grid = 64``; about 0.42 GB in all for 32 modes at 4,097
        frequencies), plus ``0.2 GB + 24.6 kB x n_freqs`` for a chunk with a mode that tries
        the bound start (the bound's solves at 256 taps: 0.33 GB for a whole process
        designing a three-line mode, measured); a call whose estimate exceeds the smallest
        worker memory limit is refused (``MemoryError``). A worker process designs one chunk
        at a time (its compiled problems are per process): give workers one thread each.

    Returns
    -------
    DataDrivenResult
        ``.controller`` is an :class:`~aocontrol.controllers.IIRBank` (one row per mode);
        per-mode diagnostics in ``.reports``.

    Raises
    ------
    ValueError, TypeError
        Invalid inputs (named in the message), or an initial controller that does not
        stabilise the plant.
    InitialPoleRadiusError
        (A ValueError.) ``initial`` has free poles on or outside ``max_pole_radius`` (e.g. an
        integrator with ``fixed_denominator=[1]``); ``.radii`` maps the modes to their radii.
    ConnectionError
        ``client`` is not connected, or its cluster has no worker (nothing is designed).
    MemoryError
        With ``client``: the estimated memory per worker exceeds the smallest worker memory
        limit (the message gives both; nothing is designed).
    DataDrivenError
        Some modes failed (infeasible convexified problem, no verified controller, or any
        numerical failure of that mode's design: solver, linear algebra, floating point); the
        message lists them and ``error.result`` holds every mode (failed ones keep the
        initial controller).

    Warns
    -----
    GridResolutionWarning
        ``freqs`` does not resolve the PSD (an interval holding over 25 % of its integral
        across which it changes over 100x, e.g. the first nonzero point above a turbulence
        knee), or the residual on ``freqs`` and on the fine check disagree by more than
        ``GRID_DISAGREEMENT`` (2x): the message gives the interval or the figures and the fix
        (a denser or log-spaced grid).
    UserWarning
        The bound start was asked for but :func:`aocontrol.analysis.constrained_bound` failed
        (:attr:`ModeReport.bound_start_error`).

    Examples
    --------
    >>> from aocontrol import loop_plant
    >>> f = np.linspace(0.0, 500.0, 201)
    >>> psd = 1.0 / (1.0 + (f / 10.0) ** 2)                 # low-pass disturbance
    >>> res = datadriven(loop_plant(1000.0, 1.0), f, psd, order=3, noise_psd=1e-3,
    ...                  n_jobs=1, progress=False)
    >>> bool(res.residual_variance[0] < res.initial_residual_variance[0])
    True
    """
    if n_jobs is not None:
        n_jobs = check_int("n_jobs", n_jobs)
        if n_jobs == 0:
            raise ValueError("n_jobs must be a nonzero integer (negative: joblib convention)")
    workers = None if client is None else check_client(client)  # before any work
    setup = prepare(
        plant,
        freqs,
        psd,
        order=order,
        noise_psd=noise_psd,
        modulus_margin=modulus_margin,
        hinf_weight=hinf_weight,
        fixed_denominator=fixed_denominator,
        initial=initial,
        max_pole_radius=max_pole_radius,
        bound_start=bound_start,
        max_iter=max_iter,
        tol=tol,
        n_grid=n_grid,
        fs=fs,
        uncertainty=uncertainty,
        integral_action=integral_action,
    )
    if workers is not None:
        check_memory(workers, setup.ctx, chunks(setup.items))
    outcomes = _run(setup.ctx, setup.items, n_jobs, progress, client)
    return _assemble(setup, outcomes, threads=local_workers(n_jobs))


# The preparation's options and their defaults: datadriven's keywords (one source).
_PREPARE_DEFAULTS = {
    name: p.default
    for name, p in inspect.signature(datadriven).parameters.items()
    if p.kind is inspect.Parameter.KEYWORD_ONLY and name not in ("n_jobs", "progress", "client")
}


def _prepare(plant, freqs, psd, **options) -> _Setup:
    """:func:`prepare` with :func:`datadriven`'s defaults for the options not given.

    ``options`` are :func:`datadriven`'s keywords (``n_jobs``, ``progress`` and ``client``
    are not options of the preparation).
    """
    unknown = set(options) - set(_PREPARE_DEFAULTS)
    if unknown:
        raise TypeError(f"_prepare got unknown options {sorted(unknown)}")
    return prepare(plant, freqs, psd, **{**_PREPARE_DEFAULTS, **options})
