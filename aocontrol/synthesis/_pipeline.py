"""Telemetry in, certified controller out: the one pipeline of the control layer.

:func:`design_from_telemetry` chains what a user with closed-loop telemetry (a bench, an
instrument, an AOT file through :func:`aocontrol.io.read_aot`) needs: the disturbance and
noise estimate (:func:`aocontrol.synthesis.disturbance_from_telemetry`, pre-whitened by
default), a registered design (:data:`aocontrol.synthesis.CONTROLLERS`), the margins of every
mode's loop (:func:`aocontrol.analysis.margins`), the predicted residual against the bounds
of any linear controller (:func:`aocontrol.analysis.wiener_bound`, and with the modulus
margin :func:`aocontrol.analysis.constrained_bound`), and the starting integrator's figures
for reference. The CLI's ``design`` is a thin wrapper over it.
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

import control
import numpy as np

from aocontrol._deprecation import renamed_keyword
from aocontrol._validation import check_in_range, check_int
from aocontrol.analysis import (
    Margins,
    UncertaintySet,
    constrained_bound,
    is_stable,
    margins,
    multimode_certificate,
    residual_variance,
    robust_margin,
    wiener_bound,
)
from aocontrol.controllers import IIRBank, MultiModeBank
from aocontrol.plant import loop_plant, plant_fs, split_latency
from aocontrol.synthesis._dd_dask import check_client
from aocontrol.synthesis._design_report import TelemetryDesign
from aocontrol.synthesis._loop_check import (
    MIN_CHECK_FRAMES,
    TelemetryCheckError,
    check_loop_telemetry,
)
from aocontrol.synthesis._modal_gain import optimal_modal_gain
from aocontrol.synthesis._registry import (
    MODULUS_MARGIN,
    DesignInputs,
    get_controller,
)
from aocontrol.synthesis._telemetry import LoopTelemetry, TelemetryPSD, disturbance_from_telemetry

__all__ = ["BOUNDS", "design_from_telemetry"]

logger = logging.getLogger(__name__)

#: Bounds :func:`design_from_telemetry` can compute.
BOUNDS = ("wiener", "constrained")


def _conflict(name: str, given: float, known: float, where: str) -> str | None:
    """The message for a ``given`` value that contradicts the telemetry's, else None."""
    if np.isclose(float(given), float(known), rtol=1e-9, atol=1e-12):
        return None
    return (
        f"{name}={given!r} contradicts the telemetry{where} ({name} = {known!r}); pass "
        "override_metadata=True (CLI: --override-metadata) to use the given value"
    )


def _as_loop(
    telemetry: object, fs: float | None, latency: float | None, override: bool
) -> LoopTelemetry:
    if isinstance(telemetry, LoopTelemetry):
        where = f" ({telemetry.source})" if telemetry.source else ""
        if not override:
            problems = [
                _conflict(name, given, known, where)
                for name, given, known in (
                    ("fs", fs, telemetry.fs),
                    ("latency_frames", latency, telemetry.latency_frames),
                )
                if given is not None and known is not None
            ]
            problems = [p for p in problems if p]
            if problems:
                raise ValueError("; ".join(problems))
        fs_ = telemetry.fs if fs is None else fs
        lat = telemetry.latency_frames if latency is None else latency
        return LoopTelemetry(
            telemetry.measurements,
            telemetry.commands,
            fs_,
            lat,
            telemetry.source,
            unit=telemetry.unit,
        )
    if isinstance(telemetry, Sequence) and len(telemetry) == 2:
        if fs is None:
            raise ValueError("fs [Hz] is required with telemetry given as (measurements, commands)")
        m, u = (np.asarray(x, dtype=float) for x in telemetry)
        m, u = (x[:, None] if x.ndim == 1 else x for x in (m, u))
        return LoopTelemetry(m, u, fs, latency)
    raise TypeError(
        "telemetry must be a LoopTelemetry (e.g. aocontrol.io.read_aot), a TelemetryPSD or a "
        f"(measurements, commands) pair, got {type(telemetry).__name__}"
    )


def multimode_residual_variance(
    bank: MultiModeBank, pseudo_open_loop: np.ndarray, noise_variance: np.ndarray
) -> np.ndarray:
    """Per-mode residual variance a multi-mode controller would give on this telemetry.

    The bank's predictor ``u[k] = sum_j A_j p[k-j]`` on the pseudo-open loop ``p`` (``p[k] =
    d[k-1] + n[k]``), the DM shape ``y[k]`` through the plant's latency, and the residual
    ``p[k+1] - y[k]``: the loop's residual ``d[k] - y[k]`` plus the target's white noise
    ``n[k+1]``, whose variance is subtracted (the noise's own path through the loop is
    ``-T n``, and for white noise and a loop delayed by at least a frame ``E|S n|^2 = E|T
    n|^2 + sigma^2``: the same subtraction). An estimate on one record (its sampling
    scatter as any residual's).

    Parameters
    ----------
    bank : MultiModeBank
    pseudo_open_loop : ndarray, shape (n_frames, n_modes)
        ``m + G u`` of the telemetry [units].
    noise_variance : ndarray, shape (n_modes,)
        White measurement-noise variance per frame [units^2].

    Returns
    -------
    ndarray, shape (n_modes,)
    """
    p = np.asarray(pseudo_open_loop, dtype=float)
    taps = np.asarray(bank.taps, dtype=float)  # (h, n, n): u[k] = sum_j taps[j] @ p[k-j]
    h = taps.shape[0]
    k0, f = split_latency(bank.latency_frames)
    n_frames = p.shape[0]
    u = np.zeros_like(p)
    for j in range(h):
        u[j:] += p[: n_frames - j] @ taps[j].T
    y = np.zeros_like(p)
    y[k0:] += (1.0 - f) * u[: n_frames - k0]
    if f:
        y[k0 + 1 :] += f * u[: n_frames - k0 - 1]
    start = h + k0 + 1
    e = p[start + 1 :] - y[start:-1]
    return np.maximum(np.mean(e**2, axis=0) - np.asarray(noise_variance, dtype=float), 0.0)


def _per_mode_margins(plant: Any, bank: Any, modes: Sequence[int]) -> tuple[list, list]:
    """:func:`aocontrol.analysis.margins` of ``modes``; a mode it cannot certify gets ``nan``.

    Such a mode keeps the stability verdict of :func:`aocontrol.analysis.is_stable` and
    ``nan`` margins (so :attr:`TelemetryDesign.meets_margin` is False for it): no margin is
    reported that was not computed. Returns the margins and the ``(mode, reason)`` failures
    (:func:`_warn_margin_failures` names them).
    """
    out, failed = [], []
    for i in modes:
        try:
            out.append(margins(plant, bank, mode=i))
        except ValueError as exc:
            failed.append((i, str(exc)))
            stable = is_stable(plant, bank.transfer_function(i))
            out.append(Margins.unknown(stable))
    return out, failed


def _warn_margin_failures(failed: list, label: str) -> None:
    if failed:
        logger.warning(
            "margins of the %s not computed for modes %s (%s): reported as nan",
            label,
            [i for i, _ in failed][:10],
            failed[0][1],
        )


#: Most modes per task of the certificate and bound steps on worker processes (a task's
#: bounds share one objective grid and basis; 540 modes make 10 tasks of 54 for 2 workers).
_CERTIFY_CHUNK = 64


def _first_of_each_filter(bank: Any, n_modes: int) -> np.ndarray:
    """``first[i]``: the first mode whose filter is mode ``i``'s, coefficient for coefficient.

    A mode's margins are a function of its filter alone (the plant and the rate are the
    bank's), so a filter that several modes share (a data-driven bank gives neighbouring
    modes one controller) is certified once, its margins the same bits for each. Only for a
    bank whose transfer function is its coefficient rows (:class:`IIRBank`'s); otherwise
    every mode is its own.
    """
    own = np.arange(n_modes)
    if not isinstance(bank, IIRBank) or type(bank).transfer_function is not (
        IIRBank.transfer_function
    ):
        return own
    seen: dict[bytes, int] = {}
    b, a = np.asarray(bank.b), np.asarray(bank.a)
    for i in range(n_modes):
        own[i] = seen.setdefault(b[i].tobytes() + a[i].tobytes(), i)
    return own


def _spread(results: dict, failed: list, first: np.ndarray) -> tuple[list, list]:
    """Every mode's margins from ``results`` (mode -> margins, for the first mode of each
    filter, :func:`_first_of_each_filter`), and the ``(mode, reason)`` failures of every
    mode, in mode order."""
    reasons = dict(failed)
    return (
        [results[j] for j in first],
        [(i, reasons[int(j)]) for i, j in enumerate(first) if int(j) in reasons],
    )


def _certify_modes(
    plant: Any,
    bank: Any,
    reference: Any,
    modes: list[int],
    spectra: tuple[np.ndarray, np.ndarray, np.ndarray],
    modulus_margin: float,
    bounds: tuple[str, ...],
    n_taps: int,
    margin_modes: tuple[list[int], list[int]] | None = None,
) -> dict:
    """Steps 3 and 4 of :func:`design_from_telemetry` for ``modes`` (a bank of one mode per
    row; ``bank`` None: a multi-mode bank, certified elsewhere), on one BLAS thread.
    ``spectra``: the estimate's ``(freqs, psd, noise_psd)``, the PSD rows of ``modes`` only
    (what a worker needs, not the estimate's telemetry). ``margin_modes``: the modes whose
    margins to compute, of ``bank`` and of ``reference`` (default ``modes``; the others'
    are those of a mode with the same filter, :func:`_first_of_each_filter`).

    Every figure is per mode, so a chunk gives each of its modes the figures the whole bank
    would (the same arithmetic on the same rows): the chunks may run on worker processes.
    """
    from threadpoolctl import threadpool_limits

    out: dict = {}
    freqs, psd, noise = spectra
    bank_modes, reference_modes = (modes, modes) if margin_modes is None else margin_modes
    with threadpool_limits(limits=1, user_api="blas"):
        if bank is not None:
            out["margins"] = _per_mode_margins(plant, bank, bank_modes)
        out["reference_margins"] = _per_mode_margins(plant, reference, reference_modes)
        if "wiener" in bounds:
            out["wiener"] = np.atleast_1d(wiener_bound(plant, freqs, psd, noise))
        if "constrained" in bounds:
            out["constrained"] = constrained_bound(
                plant,
                freqs,
                psd,
                noise,
                modulus_margin,
                n_taps=n_taps,
                raise_on_failure=False,
            )
    return out


def _certify(
    plant: Any,
    bank: Any,
    reference: Any,
    est: TelemetryPSD,
    modulus_margin: float,
    bounds: tuple[str, ...],
    n_taps: int,
    n_jobs: int | None,
) -> dict:
    """:func:`_certify_modes` of every mode, in chunks of :data:`_CERTIFY_CHUNK` modes on
    ``n_jobs`` worker processes (joblib; ``None`` every core, 1 this process), assembled in
    mode order."""
    from joblib import Parallel, cpu_count, delayed

    n = est.n_modes
    workers = cpu_count() if n_jobs is None else n_jobs
    if workers < 0:
        workers = max(1, cpu_count() + 1 + workers)
    # At most _CERTIFY_CHUNK modes per task (one task, in this process, for fewer), and a
    # multiple of the workers' number of tasks of equal size (540 modes on 2 workers: 10
    # tasks of 54, not 9 of 64 with one worker idle for the last).
    n_tasks = 1
    if n > _CERTIFY_CHUNK:
        n_tasks = max(1, workers) * -(-n // (max(1, workers) * _CERTIFY_CHUNK))
    size = -(-n // n_tasks)
    parts = [list(range(i, min(i + size, n))) for i in range(0, n, size)]
    workers = min(workers, len(parts))
    args = (plant, bank, reference)
    rest = (modulus_margin, bounds, n_taps)
    # Each task gets its modes' PSD rows: not the estimate, whose pseudo-open loop (66 MB for
    # 15,300 frames x 540 modes) joblib would hash and memory-map once per task.
    noise_psd = np.asarray(est.noise_psd)
    spectra = [(est.freqs, est.psd[part], noise_psd[part]) for part in parts]
    # Margins once per distinct filter: each part certifies the first mode of each of its
    # banks' filters that it holds.
    firsts = {
        "margins": _first_of_each_filter(bank, n),
        "reference_margins": _first_of_each_filter(reference, n),
    }
    margin_modes = [
        tuple([i for i in part if first[i] == i] for first in firsts.values()) for part in parts
    ]
    tasks = list(zip(parts, spectra, margin_modes, strict=True))
    if workers <= 1:
        results = [_certify_modes(*args, part, sp, *rest, mm) for part, sp, mm in tasks]
    else:
        results = Parallel(n_jobs=workers)(
            delayed(_certify_modes)(*args, part, sp, *rest, mm) for part, sp, mm in tasks
        )
    out: dict = {}
    for key in ("margins", "reference_margins"):
        if key in results[0]:
            computed = {}
            for r, mm in zip(results, margin_modes, strict=True):
                modes_done = mm[0] if key == "margins" else mm[1]
                computed.update(zip(modes_done, r[key][0], strict=True))
            failed = [f for r in results for f in r[key][1]]
            out[key] = _spread(computed, failed, firsts[key])
    if "wiener" in bounds:
        out["wiener"] = np.concatenate([r["wiener"] for r in results])
    if "constrained" in bounds:
        cbs = [r["constrained"] for r in results]
        out["constrained"] = (
            np.concatenate([cb.variance for cb in cbs]),
            np.concatenate([cb.ok for cb in cbs]),
            tuple(m for cb in cbs for m in cb.messages),
        )
    return out


@renamed_keyword("stroke", "command_limit", "the MPC's hard limit on its modal command")
def design_from_telemetry(
    telemetry: LoopTelemetry | TelemetryPSD | tuple,
    controller: str = "datadriven",
    *,
    fs: float | None = None,
    latency_frames: float | None = None,
    plant: Any = None,
    estimator: str = "prewhitened",
    nperseg: int | None = None,
    noise_band: tuple[float, float] = (0.8, 1.0),
    modulus_margin: float = MODULUS_MARGIN,
    reference_gain: float = 0.5,
    command_limit: float | np.ndarray | None = None,
    options: Mapping[str, Any] | None = None,
    bounds: Sequence[str] = BOUNDS,
    n_taps: int = 128,
    check_telemetry: bool = True,
    override_metadata: bool = False,
    uncertainty: UncertaintySet | None = None,
    client: Any = None,
    n_jobs: int | None = None,
) -> TelemetryDesign:
    """Design a controller bank from closed-loop telemetry and certify it.

    Steps (each timed in :attr:`TelemetryDesign.timings`):

    0. Check (telemetry given as frames, ``check_telemetry``):
       :func:`aocontrol.synthesis.check_loop_telemetry` on ``m`` and ``u`` with the plant:
       commands that enter with the other sign (the pseudo-open loop's innovation variance
       larger with the given sign than with the other) or in another unit than the
       measurements (``rms(G u) / rms(m)`` beyond 1e6 either way) are refused before any
       design (:class:`TelemetryCheckError`, naming ``command_sign=-1`` of
       :func:`aocontrol.io.read_aot` and ``--command-sign -1`` of the CLI).
    1. Estimate: :func:`aocontrol.synthesis.disturbance_from_telemetry` with ``estimator``
       (pre-whitened Welch by default) on ``m + G u``, ``G =``
       :func:`aocontrol.plant.loop_plant` ``(fs, latency_frames)`` unless ``plant`` is
       given. A :class:`TelemetryPSD` is used as it is.
    2. Design: the registry's ``controller`` (:data:`aocontrol.synthesis.CONTROLLERS`) on the
       estimated PSDs, ``options`` passed to it (e.g. ``{"order": 7}`` for ``datadriven``).
       The reference is the optimised modal-gain integrator at the same modulus margin
       (:func:`aocontrol.synthesis.optimal_modal_gain`, the data-driven design's start).
    3. Certify: :func:`aocontrol.analysis.margins` per mode, of the design and the
       reference (closed-loop stability and the modulus margin on the whole circle; a filter
       that several modes share is certified once, its margins theirs). A mode
       whose margins cannot be computed keeps the :func:`aocontrol.analysis.is_stable`
       verdict and ``nan`` margins (logged; it does not count as meeting the margin).
       With ``uncertainty``, also the certified modulus margin over that box of loop gains
       and latency changes, per mode, of the design and the reference
       (:func:`aocontrol.analysis.robust_margin`: exact in the gain, a latency grid with a
       bound between points), the same figure whatever the controller (a multi-mode bank
       or a measured plant: not computed, ``None``).
    4. Predict and bound: :func:`aocontrol.analysis.residual_variance` on the estimate's
       grid; the Wiener bound (any causal linear controller) and the constrained bound
       (linear controllers with ``modulus_margin``, FIR Youla of ``n_taps`` taps), each
       when named in ``bounds`` (``nan`` otherwise; a mode whose constrained bound fails is
       ``nan``, its reason in :attr:`TelemetryDesign.bound_failures`, with a warning).

    Parameters
    ----------
    telemetry : LoopTelemetry, TelemetryPSD or (measurements, commands)
        Closed-loop modal telemetry (arrays ``(n_frames, n_modes)`` [units]: its
        :attr:`LoopTelemetry.unit`, nm by convention), or an estimate already made (then
        ``plant`` or ``latency_frames`` is required).
    controller : str, default "datadriven"
        A registered name.
    fs : float, optional
        Loop rate [Hz]; default the telemetry's. A value that contradicts a
        :class:`LoopTelemetry`'s is refused unless ``override_metadata``.
    latency_frames : float, optional
        RTC latency beyond the WFS integration [frames]; default the telemetry's (refused
        when it contradicts a :class:`LoopTelemetry`'s, unless ``override_metadata``).
    plant : control.TransferFunction, optional
        Loop plant (command to measurement) instead of ``loop_plant(fs, latency_frames)``.
    estimator : {"prewhitened", "welch"}, default "prewhitened"
        Disturbance estimator (``method`` of ``disturbance_from_telemetry``).
    nperseg : int, optional
        Welch segment [frames] (default :func:`aocontrol.synthesis.default_nperseg`).
    noise_band : (float, float), default (0.8, 1.0)
        Noise-floor band as fractions of Nyquist.
    modulus_margin : float, default 0.5
        Required ``min |1 + G K|`` in (0, 1] of the designs that take one, and of the
        constrained bound.
    reference_gain : float, default 0.5
        Gain of the ``"integrator"``/``"reference"`` design.
    command_limit : float or ndarray of shape (n_modes,), optional
        Limit on the modal command [units] (:attr:`DesignInputs.command_limit`, the MPC's);
        ``stroke`` is its deprecated name.
    options : mapping, optional
        Options of the design (:attr:`aocontrol.synthesis.ControllerSpec.options`).
    bounds : sequence of str, default ("wiener", "constrained")
        Which bounds to compute (:data:`BOUNDS`; ``()`` for none: the constrained bound
        solves one SOCP per mode).
    n_taps : int, default 128
        FIR length of the constrained bound's Youla parameter.
    check_telemetry : bool, default True
        Run step 0 (False: design from telemetry whose sign or scale looks wrong).
    override_metadata : bool, default False
        Let ``fs`` and ``latency_frames`` replace a :class:`LoopTelemetry`'s own values.
    uncertainty : UncertaintySet, optional
        Report the certified modulus margin over this set (step 3); it does not change the
        design (``"datadriven-robust"`` designs for a set: its options ``gain_interval``,
        ``latency_interval``).
    client : distributed.Client, optional
        Run step 2's per-mode designs on this Dask cluster (the data-driven designs:
        :attr:`ControllerSpec.distributed`; ``client`` of
        :func:`aocontrol.synthesis.datadriven`: chunks of modes as tasks, the bank bit for
        bit the serial one, a lost worker's modes designed again, memory per worker estimated
        and refused beyond the workers' limit before anything is designed). The client is
        checked (connected, a worker) before step 0. The other steps run in this process
        and its ``n_jobs`` workers.
    n_jobs : int, optional
        Worker processes (joblib) of steps 3 and 4 (margins and bounds, per mode in chunks
        of 64 modes, each on one BLAS thread; the figures do not depend on it): ``None``
        every core this process may use, 1 this process only. Also the threads of the
        estimate (step 1, :func:`disturbance_from_telemetry`'s ``n_jobs``; per mode too).
        The design's own workers are its option ``n_jobs``.

    Returns
    -------
    TelemetryDesign

    Raises
    ------
    ValueError
        Unknown ``controller`` (the message lists the registered ones), unknown options or
        bounds, missing rate or latency, a rate or latency that contradicts the telemetry's,
        bad telemetry (see ``disturbance_from_telemetry``).
    ConnectionError
        ``client`` is not connected or its cluster has no worker (before any step).
    MemoryError
        ``client``'s workers have less memory than the design's estimate (before step 2).
    TelemetryCheckError
        (A ValueError.) Step 0 found the sign or the scale implausible; ``.check`` holds the
        statistics.

    Examples
    --------
    >>> from aocontrol.synthesis import LoopTelemetry
    >>> rng = np.random.default_rng(0)
    >>> m = rng.standard_normal((4096, 2))
    >>> tel = LoopTelemetry(m, np.zeros_like(m), fs=1000.0, latency_frames=0.5)
    >>> rep = design_from_telemetry(tel, "omgi", bounds=())
    >>> rep.n_modes, bool(rep.stable.all())
    (2, True)
    """
    spec = get_controller(controller)
    modulus_margin = check_in_range(
        "modulus_margin", modulus_margin, 0.0, 1.0, low_inclusive=False, high_inclusive=True
    )
    bounds = tuple(bounds)
    unknown = [b for b in bounds if b not in BOUNDS]
    if unknown:
        raise ValueError(f"bounds must be among {list(BOUNDS)}, got {unknown}")
    n_taps = check_int("n_taps", n_taps, minimum=1)
    spec.check_client(client)
    if client is not None:
        check_client(client)  # a clear error before anything is estimated or designed
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    unit, check = "nm", None
    if isinstance(telemetry, TelemetryPSD):
        est = telemetry
        fs_ = est.fs if fs is None else fs
        if plant is None:
            if latency_frames is None:
                raise ValueError("latency_frames [frames] or plant is required with a TelemetryPSD")
            plant = loop_plant(fs_, latency_frames)
    else:
        loop = _as_loop(telemetry, fs, latency_frames, override_metadata)
        unit = loop.unit
        fs_ = loop.fs
        if plant is None:
            if loop.latency_frames is None:
                where = f" ({loop.source})" if loop.source else ""
                raise ValueError(
                    f"latency_frames [frames] is required: the telemetry{where} does not "
                    "give the loop's delay"
                )
            plant = loop_plant(fs_, loop.latency_frames)
        if check_telemetry and loop.n_frames >= MIN_CHECK_FRAMES:
            check = check_loop_telemetry(loop.measurements, loop.commands, plant, fs=fs_)
            problems = check.problems(
                "command_sign=-1 (aocontrol.io.read_aot; CLI: --command-sign -1)"
            )
            if problems:
                where = f" {loop.source}" if loop.source else ""
                raise TelemetryCheckError(
                    f"telemetry{where} refused before the design: "
                    + "; ".join(problems)
                    + " (check_telemetry=False, CLI --no-telemetry-check, to design anyway)",
                    check,
                )
        est = disturbance_from_telemetry(
            loop.measurements,
            loop.commands,
            plant,
            nperseg=nperseg,
            noise_band=noise_band,
            method=estimator,
            n_jobs=n_jobs,
        )
    fs_ = plant_fs(plant, fs_)
    latency = latency_frames
    if latency is None and isinstance(telemetry, LoopTelemetry):
        latency = telemetry.latency_frames
    timings["estimate"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    opts = MappingProxyType(dict(options or {}))
    inputs = DesignInputs(
        plant=plant,
        freqs=est.freqs,
        psd=est.psd,
        noise_psd=est.noise_psd,
        fs=fs_,
        n_modes=est.n_modes,
        reference_gain=float(reference_gain),
        telemetry=est,
        command_limit=command_limit,
        modulus_margin=modulus_margin,
        options=opts,
        client=client,
    )
    bank, details = spec.build(inputs)
    timings["design"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    reference = optimal_modal_gain(
        plant, est.freqs, est.psd, est.noise_psd, modulus_margin=modulus_margin
    )
    timings["reference"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    multimode = isinstance(bank, MultiModeBank)
    # Steps 3 and 4 per mode, on the worker processes (the bounds' timing is in "margins"
    # then: one pass over the modes does both).
    certified = _certify(
        plant, None if multimode else bank, reference, est, modulus_margin, bounds, n_taps, n_jobs
    )
    if multimode:
        # One multivariable certificate for the whole loop (no per-mode margins): each mode
        # reports its stability verdict, its margins nan.
        cert = multimode_certificate(bank)
        mar = tuple(Margins.unknown(cert.stable) for _ in range(est.n_modes))
    else:
        mar = tuple(certified["margins"][0])
        _warn_margin_failures(certified["margins"][1], controller)
    ref_mar = tuple(certified["reference_margins"][0])
    _warn_margin_failures(certified["reference_margins"][1], "reference")
    timings["margins"] = time.perf_counter() - t0
    robust = ref_robust = None
    if uncertainty is not None:
        if not isinstance(uncertainty, UncertaintySet):
            raise TypeError(
                f"uncertainty must be an UncertaintySet, got {type(uncertainty).__name__}"
            )
        t0 = time.perf_counter()
        if not multimode:
            robust = _per_mode_robust(plant, bank, uncertainty)
        ref_robust = _per_mode_robust(plant, reference, uncertainty)
        timings["robust"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if multimode:
        # Its residual comes from the modes' cross-correlations, which the per-mode PSDs
        # lack: predicted on the telemetry's own pseudo-open loop (time domain).
        var = multimode_residual_variance(bank, est.pseudo_open_loop, est.noise_psd * fs_ / 2)
    else:
        var = np.atleast_1d(residual_variance(plant, bank, est.freqs, est.psd, est.noise_psd))
    ref_var = np.atleast_1d(residual_variance(plant, reference, est.freqs, est.psd, est.noise_psd))
    nan = np.full(est.n_modes, np.nan)
    wiener = nan.copy()
    constrained = nan.copy()
    bound_failures: dict[int, str] = {}
    if "wiener" in bounds:
        wiener = certified["wiener"]
    if "constrained" in bounds:
        cb_variance, cb_ok, cb_messages = certified["constrained"]
        constrained = np.where(cb_ok, cb_variance, np.nan)
        bound_failures = {int(i): cb_messages[i] for i in np.flatnonzero(~cb_ok)}
        if bound_failures:
            first = next(iter(bound_failures.items()))
            warnings.warn(
                f"constrained bound not computed for {len(bound_failures)} mode(s) "
                f"{list(bound_failures)[:10]}: {first[1]} (mode {first[0]}); reported as nan "
                "(TelemetryDesign.bound_failures)",
                UserWarning,
                stacklevel=3,
            )
    timings["bounds"] = time.perf_counter() - t0
    return TelemetryDesign(
        controller_name=controller,
        controller=bank,
        reference=reference,
        plant=plant,
        fs=fs_,
        latency_frames=np.nan if latency is None else float(latency),
        estimate=est,
        modulus_margin=modulus_margin,
        margins=mar,
        reference_margins=ref_mar,
        residual_variance=var,
        reference_residual_variance=ref_var,
        wiener_variance=wiener,
        constrained_variance=constrained,
        details=details,
        options=dict(opts),
        timings=timings,
        bound_failures=bound_failures,
        unit=unit,
        telemetry_check=check,
        uncertainty=uncertainty,
        robust_margins=robust,
        reference_robust_margins=ref_robust,
    )


def _per_mode_robust(plant: Any, bank: Any, uncertainty: UncertaintySet) -> tuple | None:
    """Every mode's :func:`robust_margin` over ``uncertainty``, or ``None`` for a measured
    plant (the certificate needs polynomials)."""
    if not isinstance(plant, control.TransferFunction):
        logger.info("no robust margin for a measured plant (it needs a transfer function)")
        return None
    return tuple(robust_margin(plant, bank, uncertainty, mode=i) for i in range(bank.n_modes))
