"""A cheaper data-driven bank: cold designs on a subset of modes, the others warm-started.

Neighbouring modes of a modal basis (KL, Zernike) have similar disturbance PSDs, so the cold
design of one mode is a good start for its neighbours. :func:`datadriven_neighbours` designs
every ``stride``-th mode cold (:func:`~aocontrol.synthesis.datadriven` with the caller's
options), then every other mode from the design of its nearest designed mode, with few convex
iterations on a coarser grid (``warm_max_iter``, ``warm_n_grid``, ``warm_tol``), its
structure kept (integral action fixed where the neighbour has it). Every mode goes through
the same synthesis, so every mode carries the same certificates as in the cold bank (the
exact modulus margin over the whole circle and closed-loop stability, not grid samples;
``test_every_mode_certified_like_cold`` recomputes them independently) and the same
"never worse than its start" check, which is a residual on the synthesis' fine frequency
grid: a sample, not a certificate.

It changes results: the tolerance against the full cold bank is measured, not assumed
(``tests/test_datadriven_neighbours.py`` and ``docs/benchmarks.md``). The cold bank itself
already starts each mode from the previous mode's design within a chunk (a few convex solves
per mode), so the saving is the per-mode overhead of the coarser, shorter warm designs, not
a 1-iteration-for-60 trade.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from aocontrol._validation import check_int, check_nonnegative
from aocontrol.controllers import IIRBank
from aocontrol.synthesis._datadriven import datadriven
from aocontrol.synthesis._dd_results import DataDrivenError, DataDrivenResult

__all__ = ["datadriven_neighbours", "nearest_designed"]

# Relative size of a(1) below which a controller has a pole at z = 1 (integral action).
_INTEGRATOR_RTOL = 1e-9


def nearest_designed(n_modes: int, stride: int) -> np.ndarray:
    """Index into the designed modes ``0, stride, 2 stride...`` of each mode's nearest one
    (ties to the lower mode), shape ``(n_modes,)``."""
    rep = np.arange(0, n_modes, stride)
    dist = np.abs(np.arange(n_modes)[:, None] - rep[None, :])
    return np.argmin(dist, axis=1)


def has_integrator(bank: IIRBank) -> np.ndarray:
    """Modes whose controller has a pole at ``z = 1`` (``a(1) = 0``: integral action).

    Parameters
    ----------
    bank : IIRBank
        The controller bank, one transfer function per mode.

    Returns
    -------
    numpy.ndarray of bool, shape (n_modes,)
        True where ``|a(1)|`` is below a relative tolerance of the denominator's size.
    """
    scale = np.abs(bank.a).sum(axis=1)
    return np.abs(bank.a.sum(axis=1)) <= _INTEGRATOR_RTOL * scale


def _design(*args, **kwargs) -> tuple[DataDrivenResult, dict[int, str]]:
    try:
        return datadriven(*args, **kwargs), {}
    except DataDrivenError as exc:
        return exc.result, dict(exc.failed)


def datadriven_neighbours(
    plant,
    freqs: object,
    psd: object,
    *,
    stride: int = 4,
    noise_psd: object = 0.0,
    warm_max_iter: int = 2,
    warm_n_grid: int = 32,
    warm_tol: float = 1e-2,
    n_jobs: int | None = None,
    progress: bool = False,
    client: object = None,
    **options: object,
) -> DataDrivenResult:
    """Data-driven bank from cold designs of every ``stride``-th mode and warm neighbours.

    Modes ``0, stride, 2 stride...`` are designed by :func:`~aocontrol.synthesis.datadriven`
    with ``options`` (its cold start, its structure choice); each other mode starts from the
    design of its nearest designed mode (:func:`nearest_designed`) and runs the same
    synthesis with at most ``warm_max_iter`` convex iterations on ``warm_n_grid`` design
    points, tolerance ``warm_tol``, keeping that start's structure (integral action fixed,
    ``fixed_denominator = 1 - z^-1``, where the start has a pole at ``z = 1``; every pole
    free otherwise). Every mode is certified as in a cold bank (exact modulus margin and
    stability): the warm calls are the same synthesis, which never returns a design worse
    than its start on its fine-grid residual check. A warm start the
    synthesis refuses (its convexified problem infeasible around the neighbour's design) is
    designed cold.

    The summed residual of a whole bank stays within a fraction of a per cent of the cold
    bank's for less CPU, but single modes can lose up to ~20 % (``docs/benchmarks.md``): the
    paper's comparison keeps the cold bank (option ``stride`` of the registry's design,
    default 1).

    Parameters
    ----------
    plant, freqs, psd, noise_psd
        As :func:`~aocontrol.synthesis.datadriven`.
    stride : int, default 4
        Every ``stride``-th mode is designed cold (1: every mode, the cold bank itself).
    warm_max_iter : int, default 2
        ``max_iter`` of the warm-started modes.
    warm_n_grid : int, default 32
        ``n_grid`` of the warm-started modes (8 to 4096).
    warm_tol : float, default 1e-2
        ``tol`` of the warm-started modes.
    n_jobs, progress, client
        As :func:`~aocontrol.synthesis.datadriven` (every call of the bank on ``client``).
    **options
        Other keywords of :func:`~aocontrol.synthesis.datadriven` (``order``,
        ``modulus_margin``, ``hinf_weight``...), used by every call; ``initial``,
        ``fixed_denominator``, ``max_iter``, ``n_grid`` and ``tol`` apply to the cold designs
        only.

    Returns
    -------
    DataDrivenResult
        Every mode in input order; ``initial`` holds each mode's start (the cold start for
        the designed modes, the neighbour's design for the others); a warm-started mode's
        ``ModeReport.start`` names its neighbour.

    Raises
    ------
    ValueError
        ``stride`` or a warm setting out of range (named), or any error of the synthesis.
    DataDrivenError
        Some modes failed (``error.result`` holds every mode).
    """
    stride = check_int("stride", stride, minimum=1)
    warm_max_iter = check_int("warm_max_iter", warm_max_iter, minimum=1)
    warm_n_grid = check_int("warm_n_grid", warm_n_grid, minimum=8)
    warm_tol = check_nonnegative("warm_tol", warm_tol)
    common = dict(n_jobs=n_jobs, progress=progress, client=client)
    psd2 = np.atleast_2d(np.asarray(psd, dtype=float))
    n = psd2.shape[0]
    if stride == 1 or n <= 1:  # the cold bank, inputs passed as given
        return datadriven(plant, freqs, psd, noise_psd=noise_psd, **common, **options)
    noise = np.asarray(noise_psd, dtype=float)
    if noise.ndim < 2:  # one white level per mode (a scalar: the same for every mode)
        noise = np.broadcast_to(noise, (n,)).copy()
    rep = np.arange(0, n, stride)
    cold, failed_cold = _design(plant, freqs, psd2[rep], noise_psd=noise[rep], **common, **options)
    near = nearest_designed(n, stride)
    rest = np.setdiff1d(np.arange(n), rep)
    start = cold.controller.rows(near)
    integral = has_integrator(start)
    warm_opts = {
        k: v
        for k, v in options.items()
        if k not in ("initial", "fixed_denominator", "max_iter", "n_grid", "tol")
    }
    warm_opts.update(max_iter=warm_max_iter, n_grid=warm_n_grid, tol=warm_tol)
    results: list[tuple[np.ndarray, DataDrivenResult, bool]] = [(rep, cold, False)]
    failed = {int(rep[i]): msg for i, msg in failed_cold.items()}
    redo = np.zeros(0, int)
    for take, fixed in ((integral, [1.0, -1.0]), (~integral, None)):
        modes = rest[take[rest]]
        if not modes.size:
            continue
        res, bad = _design(
            plant,
            freqs,
            psd2[modes],
            noise_psd=noise[modes],
            initial=start.rows(modes),
            fixed_denominator=fixed,
            **common,
            **warm_opts,
        )
        ok = np.ones(modes.size, bool)
        ok[list(bad)] = False
        if ok.any():
            results.append((modes[ok], _subset(res, np.flatnonzero(ok)), True))
        redo = np.concatenate([redo, modes[~ok]])
    if redo.size:
        # A warm start the synthesis refuses (e.g. its convexified problem is infeasible
        # around the neighbour's design on the coarser grid): that mode is designed cold.
        redo = np.sort(redo)
        res, bad = _design(plant, freqs, psd2[redo], noise_psd=noise[redo], **common, **options)
        results.append((redo, res, False))
        failed.update({int(redo[i]): msg for i, msg in bad.items()})
    out = _combine_results(n, near, rep, results, cold)
    if failed:
        raise DataDrivenError(dict(sorted(failed.items())), out)
    return out


def _subset(res: DataDrivenResult, idx: np.ndarray) -> DataDrivenResult:
    """The modes ``idx`` of a result (reports kept in order, indices fixed by _combine_results)."""

    def rows(x):
        return None if x is None else x[idx]

    return dataclasses.replace(
        res,
        controller=res.controller.rows(idx),
        initial=res.initial.rows(idx),
        reports=tuple(res.reports[i] for i in idx),
        residual_variance=rows(res.residual_variance),
        initial_residual_variance=rows(res.initial_residual_variance),
        residual_variance_fine=rows(res.residual_variance_fine),
        initial_residual_variance_fine=rows(res.initial_residual_variance_fine),
    )


def _combine_results(n, near, rep, results, cold: DataDrivenResult) -> DataDrivenResult:
    """One result over every mode from the per-subset results (mode indices restored)."""
    reports: list = [None] * n
    fields = {
        k: np.full(n, np.nan)
        for k in (
            "residual_variance",
            "initial_residual_variance",
            "residual_variance_fine",
            "initial_residual_variance_fine",
        )
    }
    for modes, res, warm in results:
        for j, m in enumerate(modes):
            r = res.reports[j]
            if warm:
                r = dataclasses.replace(r, start=f"mode {rep[near[m]]} ({r.start})")
            reports[m] = dataclasses.replace(r, mode=int(m))
        for k, arr in fields.items():
            val = getattr(res, k)
            if val is not None:
                arr[modes] = val
    return DataDrivenResult(
        controller=IIRBank.from_parts([(m, r.controller) for m, r, _ in results], n),
        initial=IIRBank.from_parts([(m, r.initial) for m, r, _ in results], n),
        reports=tuple(reports),
        design_freqs=cold.design_freqs,
        verification=cold.verification,
        **fields,
    )
