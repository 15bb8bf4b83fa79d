"""Two AO stages cascaded on one fast clock: ``standalone`` and ``dcao`` (standalone+).

Clock: the fast clock is stage 2's rate ``fs2``; stage 1 runs at ``fs1 = fs2 / R`` with an
integer ratio ``R``. Stage-1 frame ``j`` covers the fast frames ``jR ... jR + R - 1``.

Per chunk of fast frames the phase ``phi`` (valid pupil pixels, nm) of the disturbance source
is projected once on both bases, in float32 (far below any AO residual; float32 halves the
dominant cost), giving ``d1`` (stage-1 modes) and ``d2`` (stage-2 modes): for KL bases of
Gaussian-influence mirrors through the mirrors' separable influence functions (3x fewer
operations at 1200 + 540 modes on 96 pixels; relative rounding ~6e-7 RMS, ~2e-4 of a mode's
largest coefficient at worst), else by one dense product (~3e-7, ~2e-5), see
:mod:`aocontrol.sim._projection`. The projector and ``P`` below are built once per pair of
basis objects. Then:

* **stage 1** (its own rate, independent of stage 2): its WFS integrates the residual over
  its frame, i.e. sees the mean of ``d1 - y1`` over the frame's ``R`` fast frames; its plant
  timing (``split_latency`` of its latency, in its own frames) applies at its own rate; its DM
  shape ``y1`` is held over the ``R`` fast frames of its frame. With ``R = 1`` this is
  exactly the single-stage loop.
* **projection** ``P = basis2.modes @ basis1.modes.T / n_valid`` (stage-1 modes to stage-2
  modes over the pupil, computed once): the residual left by stage 1 in stage-2 modes is
  ``r2 = d2 - P y1``.
* **stage 2** (fast rate) measures its residual ``e2 = r2 - y2_dm``.
  *standalone*: ``y2_dm = delay(u2)`` (the single-stage DM, stroke clipped on the command).
  *dcao*: stage 2's DM adds ``-P y1`` (stage 1's DM shape projected on stage-2 modes),
  synchronous with stage 1's DM: ``y2_dm = delay(u2) - P y1``, so ``e2 = d2 - delay(u2)``:
  stage 2 sees the full disturbance ``d2`` in its modes. With a stroke the DM clips the total
  shape ``y2_dm`` (what the mirror must produce), not ``u2``.
* **science**: residual phase ``phi - B1 y1 - B2 y2_dm`` (everything outside both bases,
  fitting error included, stays), formed only for the science frames (every
  ``science_every`` fast frames after settling).

Telemetry of stage 2: ``commands`` is the controller output ``u2`` (before the dCAO term),
``measurements`` ``m2``, ``dm`` ``y2_dm``, ``residuals`` ``e2``, ``disturbance`` its input:
``r2`` in standalone, ``d2`` in dCAO. So
``aocontrol.synthesis.disturbance_from_telemetry(m2, u2, G2)`` gives the pseudo-open loop
``d2 - P y1`` (standalone) or ``d2`` (dCAO). Stage 1's telemetry is per stage-1 frame: the
frame means of ``d1`` and ``e1``, its measurements, commands and (held) DM shape.

Sensors: any sensor of the protocol of :mod:`aocontrol.sim.wfs.sensors`, called the same way
for every kind. A sensor that reads phase maps (a :class:`~aocontrol.sim.wfs.DiffractiveSensor`,
e.g. the stage-2 pyramid) is given the residual OPD map of its previous frame, formed only for
it: stage 2 sees ``phi - B1 y1 - B2 y2_dm`` (the disturbance minus both DMs, fitting error
included); stage 1 sees its frame's mean phase minus ``B1 y1`` (it is upstream of stage 2's
DM). Linear modal sensors read the modal residuals ``e1`` and ``e2`` above.
"""

from __future__ import annotations

import dataclasses
import weakref
from typing import Any

import numpy as np

from aocontrol._validation import check_int
from aocontrol.sim._phase_maps import shape_synthesizer
from aocontrol.sim._projection import ModalProjector
from aocontrol.sim._result import TELEMETRY, CascadeResult, LoopResult
from aocontrol.sim._runner import (
    _check_common,
    _check_finite_disturbance,
    _ResidualMap,
    _settle,
    drive,
    science_frames,
)
from aocontrol.sim._sources import PhaseDisturbance, check_rate
from aocontrol.sim._stage import Stage
from aocontrol.sim._stage_run import _StageRun
from aocontrol.sim.science import LongExposure

__all__ = ["run_cascade", "projection_matrix", "SCHEMES", "UpstreamRecord"]

#: Cascade schemes.
SCHEMES = ("standalone", "dcao")
# Relative tolerance for an integer rate ratio (floating-point noise of the rates).
_RATIO_RTOL = 1e-9
# Default chunk (run_cascade's ``chunk``): at most _MAX_CHUNK fast frames, and a float32 phase
# of at most _CHUNK_PHASE_BYTES (below glibc's largest dynamic mmap threshold, 32 MiB).
_MAX_CHUNK = 1200
_CHUNK_PHASE_BYTES = 24 * 2**20


def default_chunk(n_valid: int) -> int:
    """The default chunk of :func:`run_cascade` [fast frames] for ``n_valid`` pupil pixels.

    At most 1200 frames, and a float32 phase of at most ``_CHUNK_PHASE_BYTES`` (24 MiB), below
    glibc's largest dynamic mmap threshold (see ``run_cascade``'s ``chunk``).
    """
    return max(1, min(_MAX_CHUNK, _CHUNK_PHASE_BYTES // (4 * int(n_valid))))


def projection_matrix(basis_from: Any, basis_to: Any) -> np.ndarray:
    """Projection of one modal basis on another over the pupil.

    Parameters
    ----------
    basis_from : ModalBasis-like
        Source basis, ``modes`` (n_from, n_valid), orthonormal (``modes @ modes.T / n_valid =
        I``).
    basis_to : ModalBasis-like
        Target basis on the same pupil pixels, ``modes`` (n_to, n_valid).

    Returns
    -------
    ndarray, shape (n_to, n_from)
        ``P = basis_to.modes @ basis_from.modes.T / n_valid``: coefficients in ``basis_to``
        of the shape of unit coefficients in ``basis_from`` (least squares, exact for
        orthonormal target modes).

    Raises
    ------
    ValueError
        If the bases are sampled on different numbers of pupil pixels.
    """
    a = np.asarray(basis_from.modes, dtype=float)
    b = np.asarray(basis_to.modes, dtype=float)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(
            "both bases must have modes of shape (n_modes, n_valid) on the same pupil, got "
            f"{a.shape} and {b.shape}"
        )
    return b @ a.T / a.shape[1]


# Per pair of bases, the projection matrix P and the projector on both bases (seconds at
# 1200 + 540 modes), kept while the bases live: the runs of a study share them.
_PAIRS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _pair_setup(basis1: Any, basis2: Any) -> tuple[np.ndarray, ModalProjector]:
    """``(P, projector)`` of two bases, built once per pair of live basis objects."""

    def build() -> tuple[np.ndarray, ModalProjector]:
        p_mat = projection_matrix(basis1, basis2)
        p_mat.setflags(write=False)
        return p_mat, ModalProjector((basis1, basis2))

    try:
        inner = _PAIRS.setdefault(basis1, weakref.WeakKeyDictionary())
        hit = inner.get(basis2)
        if hit is None:
            hit = inner[basis2] = build()
    except TypeError:  # a basis-like object that cannot be weakly referenced or hashed
        return build()
    return hit


def _rate_ratio(stage1: Stage, stage2: Stage) -> int:
    ratio = stage2.fs / stage1.fs
    r = int(round(ratio))
    if r < 1 or abs(ratio - r) > _RATIO_RTOL * ratio:
        raise ValueError(
            f"stage 2's rate must be an integer multiple of stage 1's: fs2={stage2.fs:g} Hz, "
            f"fs1={stage1.fs:g} Hz, ratio {ratio:.6g}"
        )
    return r


def run_cascade(
    stage1: Stage,
    stage2: Stage,
    disturbance: PhaseDisturbance,
    n_frames: int,
    *,
    scheme: str,
    basis1: Any = None,
    basis2: Any = None,
    rng: np.random.Generator | int | None = None,
    science: Any = None,
    science_every: int = 10,
    record: tuple[str, ...] = TELEMETRY,
    settle_frames: int | None = None,
    chunk: int | None = None,
    progress: bool = False,
    metadata: dict | None = None,
    upstream: UpstreamRecord | None = None,
) -> CascadeResult:
    """Run two cascaded AO stages in closed loop (see the module docstring for the model).

    Parameters
    ----------
    stage1 : Stage
        First (slow) stage, rate ``fs1`` [Hz], modes of ``basis1``, linear modal sensor.
    stage2 : Stage
        Second (fast) stage, rate ``fs2 = R fs1`` (integer ``R``) [Hz], modes of ``basis2``.
    disturbance : PhaseDisturbance
        Phase on the valid pupil pixels at ``fs2`` (``fs`` and ``phase_vectors(n)``): an
        :class:`~aocontrol.sim.atmosphere.Atmosphere`, a
        :class:`~aocontrol.sim.loop.PhaseSource` (e.g. with a tilt vibration) or a
        :class:`~aocontrol.sim.loop.TurbulenceSource`.
    n_frames : int
        Fast (stage-2) frames to run, a multiple of ``R``.
    scheme : {"standalone", "dcao"}
        Cascade scheme.
    basis1, basis2 : ModalBasis-like, optional
        The stages' modal bases (``modes`` (n_modes, n_valid), ``synthesize``, ``pupil``), on
        the disturbance's pupil pixels; default each stage's ``basis``.
    rng : numpy.random.Generator or int, optional
        Source of the measurement noise (required when a sensor is noisy); stage 1 and stage
        2 draw from two independent children (``rng.spawn(2)``).
    science : object with ``add(maps (n, n_pix, n_pix))`` and ``result()``, optional
        Long-exposure accumulator, fed every ``science_every`` fast frames after settling
        with the residual phase after both stages.
    science_every : int
        Fast frames between two science frames.
    record : tuple of str
        Telemetry kept for both stages (float32), among ``disturbance, measurements,
        commands, dm, residuals``.
    settle_frames : int, optional
        Fast frames excluded from the statistics and the science (default 1 % of the run, at
        least 20), rounded up to a multiple of ``R``.
    chunk : int, optional
        Fast frames generated and projected at once, rounded up to a multiple of ``R``.
        Default: at most 1200, and few enough that the chunk's phase in float32 stays within
        ``_CHUNK_PHASE_BYTES`` (24 MiB; 888 frames on 7084 pupil pixels). glibc's allocator
        returns a larger block to the system when it is freed (above its largest dynamic
        mmap threshold, 32 MiB), so every chunk's phase would be fresh pages (chosen by
        ``benchmarks/bench_cascade.py``, ``docs/benchmarks.md``). The chunking changes the
        results at the float32 rounding of the projection only.
    progress : bool
        Show a tqdm progress bar.
    metadata : dict, optional
        Case/controller settings stored with the result.
    upstream : UpstreamRecord, optional
        An empty record is filled by this run (what stage 2 does not change: see
        :class:`UpstreamRecord`); a filled one is replayed instead of the disturbance, the
        projection and stage 1, with the same result bit for bit as a full run of the same
        disturbance, stage 1 and ``rng`` (the caller's contract; the record checks the rest).

    Returns
    -------
    CascadeResult
        ``stages[0]`` at ``fs1`` in ``basis1`` modes, ``stages[1]`` at ``fs2`` in ``basis2``
        modes, ``science`` after both stages.

    Raises
    ------
    ValueError
        Unknown scheme, non-integer rate ratio, a disturbance at another rate or not finite,
        mismatched or missing bases, ``n_frames`` not a multiple of ``R``.
    LoopDivergedError
        If either stage diverges (named, with the frame of its own rate and the modes).
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    for name, st in (("stage1", stage1), ("stage2", stage2)):
        if not isinstance(st, Stage):
            raise TypeError(f"{name} must be a Stage, got {type(st).__name__}")
    chunk_given = chunk
    chunk = _MAX_CHUNK if chunk is None else chunk
    n_frames, chunk, science_every = _check_common(n_frames, chunk, science_every, record)
    ratio = _rate_ratio(stage1, stage2)
    if n_frames % ratio:
        raise ValueError(
            f"n_frames={n_frames} (fast frames) must be a multiple of the rate ratio {ratio}"
        )
    if not isinstance(disturbance, PhaseDisturbance):
        raise TypeError(
            "disturbance must provide fs and phase_vectors(n_frames) (phase on the valid "
            f"pupil pixels), got {type(disturbance).__name__}"
        )
    check_rate(disturbance, stage2.fs, f"the fast clock (stage 2, {stage2.name!r})", required=True)
    n1, n2 = stage1.n_modes, stage2.n_modes
    basis1 = stage1.basis if basis1 is None else basis1
    basis2 = stage2.basis if basis2 is None else basis2
    for name, basis, n, st in (("basis1", basis1, n1, stage1), ("basis2", basis2, n2, stage2)):
        if basis is None:
            raise ValueError(f"{name} is required (or a basis on {st.name!r})")
        if int(basis.n_modes) != n:
            raise ValueError(f"{name} has {basis.n_modes} modes, {st.name!r} controls {n}")
        if st.basis is None:
            st.sensor.check(n, basis)
    p_mat, project = _pair_setup(basis1, basis2)
    n_valid = basis1.modes.shape[1]
    settle = _settle(n_frames, settle_frames)
    settle = -(-settle // ratio) * ratio
    if settle >= n_frames:
        raise ValueError(
            f"settle_frames={settle} (rounded up to a multiple of {ratio}) must be < "
            f"n_frames={n_frames}"
        )
    if chunk_given is None:
        chunk = default_chunk(n_valid)
    chunk = -(-chunk // ratio) * ratio
    check_int("chunk", chunk, minimum=1)
    dcao = scheme == "dcao"
    rng1, rng2 = np.random.default_rng(rng).spawn(2)
    replay = upstream is not None and upstream.filled
    if upstream is not None:
        setup = _UpstreamSetup(
            basis1, basis2, n_frames, chunk, settle, ratio, science_every, science is not None
        )
        upstream.check_or_start(setup, stage2.name)
    run1 = None
    if not replay:
        run1 = _StageRun(
            stage1,
            n_frames=n_frames // ratio,
            record=record,
            settle=settle // ratio,
            rng=rng1,
            pupil=basis1.pupil,
            accumulate=False,
        )
    run2 = _StageRun(
        stage2, n_frames=n_frames, record=record, settle=settle, rng=rng2, pupil=basis2.pupil
    )
    if replay and run2.needs_phase:
        raise ValueError(
            f"upstream: stage {stage2.name!r} reads phase maps, which a record does not keep; "
            "run it without a filled record"
        )
    for run in (run1, run2):
        if run is not None and rng is None and (run.noisy or run.tracker is not None):
            raise ValueError(
                "rng is required with a noisy sensor or an optical-gain tracker "
                f"(reproducibility; stage {run.name!r})"
            )
    # ``project`` projects on both bases at once and synthesises both DM shapes for the
    # science (float32, through the mirrors when cheaper: aocontrol.sim._projection).
    stats1 = [np.zeros(n1), np.zeros(n1)]  # sums of e1^2 and d1^2 over the fast frames
    # Residual maps, formed only for a sensor that reads them (references kept per frame).
    resid1 = _ResidualMap(basis1.pupil, n_valid)
    resid2 = _ResidualMap(basis2.pupil, n_valid)
    # DM shapes for the maps, float32 through the mirrors (aocontrol.sim._phase_maps); only
    # for a sensor that reads maps.
    reads_maps = run2.needs_phase or (run1 is not None and run1.needs_phase)
    synth1 = shape_synthesizer(basis1) if reads_maps else None
    synth2 = shape_synthesizer(basis2) if reads_maps else None
    shape1 = _HeldShape(synth1)

    def form1(block: np.ndarray, y1: np.ndarray) -> np.ndarray:
        # Stage 1's WFS integrates its frame: the mean phase minus its (held) DM shape.
        return block.mean(axis=0, dtype=float) - synth1(y1)

    def form2(phase_j: np.ndarray, j1: int, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
        return phase_j - shape1(j1, y1) - synth2(y2)

    def stage1_chunk(k: int, m: int) -> tuple:
        """Disturbance, projection and stage 1 of fast frames ``k ... k + m - 1``: what
        stage 2 does not change. Returns ``(d2, P y1, science inputs, phase, y1s)``."""
        ns = m // ratio
        phase = np.asarray(disturbance.phase_vectors(m))
        if phase.shape != (m, n_valid):
            raise ValueError(
                f"the disturbance gave phase of shape {phase.shape}, expected ({m}, "
                f"{n_valid}) (frames, valid pupil pixels of the bases)"
            )
        coeffs = project(phase)
        _check_finite_disturbance(coeffs, k, "disturbance (phase)")
        d1, d2 = coeffs[:, :n1], coeffs[:, n1:]

        # Stage 1 at its own rate on the frame means of its disturbance.
        d1_avg = d1.reshape(ns, ratio, n1).mean(axis=1)
        run1.begin_chunk(d1_avg, ns)
        if run1.needs_phase:
            for j in range(ns):
                y1 = run1.step(j, d1_avg[j], resid1)
                resid1.set(form1, phase[j * ratio : (j + 1) * ratio], y1)
        else:
            run1.run_frames(d1_avg, resid1)
        y1s = run1.chunk_dm  # the chunk's DM shapes, (ns, n1)
        run1.end_chunk(d1_avg, k // ratio)
        first_stat = max(settle - k, 0)
        if first_stat < m:
            # Fast-frame residual of stage 1, its DM shape held over each of its frames.
            e1 = (d1.reshape(ns, ratio, n1) - y1s[:, None, :]).reshape(m, n1)[first_stat:]
            stats1[0] += np.einsum("ij,ij->j", e1, e1)
            stats1[1] += np.einsum("ij,ij->j", d1[first_stat:], d1[first_stat:])
        sci = None
        if science is not None:
            idx = science_frames(k, m, settle, science_every)
            sci = (phase[idx], y1s[idx // ratio])
        return d2, y1s @ p_mat.T, sci, phase, y1s

    def advance(k: int, m: int) -> None:
        if replay:
            d2, py1s, sci = upstream.chunk(k)
            phase = y1s = None
        else:
            d2, py1s, sci, phase, y1s = stage1_chunk(k, m)
            if upstream is not None:
                d2, py1s, sci = upstream.add(k, d2, py1s, sci)
        ns = m // ratio

        # Stage 2 at the fast rate on the residual of stage 1 in its modes.
        r2 = (d2.reshape(ns, ratio, n2) - py1s[:, None, :]).reshape(m, n2)
        d2_rec = d2 if dcao else r2
        run2.begin_chunk(d2_rec, m)
        j1_0 = k // ratio
        if not run2.needs_phase:
            if dcao:  # the dCAO offset of each fast frame
                run2.run_frames(d2, resid2, r2, np.repeat(-py1s, ratio, axis=0))
            else:
                run2.run_frames(r2, resid2)
        else:  # a sensor that reads maps: its residual map of each frame
            step2 = run2.step
            neg = np.repeat(-py1s, ratio, axis=0) if dcao else None
            for j in range(m):
                if dcao:
                    y2 = step2(j, d2[j], resid2, r2[j], neg[j])
                else:
                    y2 = step2(j, r2[j], resid2)
                resid2.set(form2, phase[j], j1_0 + j // ratio, y1s[j // ratio], y2)
        y2s = run2.chunk_dm  # the chunk's DM shapes, (m, n2)
        run2.end_chunk(d2_rec, k)

        if science is not None:
            idx = science_frames(k, m, settle, science_every)
            if idx.size:
                sci_phase, sci_y1 = sci
                shape = np.concatenate([sci_y1, y2s[idx]], axis=1)
                resid = sci_phase - project.synthesize(shape)
                # The camera reads valid-pixel vectors as they are (no map round trip).
                science.add(
                    resid if isinstance(science, LongExposure) else basis2.pupil.to_map(resid)
                )

    runs = (run2,) if replay else (run1, run2)
    drive(n_frames, chunk, advance, runs, progress=progress, desc=f"{scheme} cascade")
    n_stat = n_frames - settle
    if replay:
        res1 = upstream.stage1_result(metadata)
    else:
        sum_e1, sum_d1 = stats1
        res1 = run1.result(stage1.fs, n_frames // ratio, n_stat, None, metadata)
        res1 = dataclasses.replace(
            res1, residual_variance=sum_e1 / n_stat, disturbance_variance=sum_d1 / n_stat
        )
        if upstream is not None:
            upstream.finish(res1, metadata)
    res2 = run2.result(stage2.fs, n_frames, n_stat, None, metadata)
    result_science = science.result() if science is not None else None
    meta = dict(
        metadata or {},
        scheme=scheme,
        fs1=stage1.fs,
        fs2=stage2.fs,
        rate_ratio=ratio,
        n_frames=n_frames,
        settle_frames=settle,
        science_every=science_every,
        stages=[stage1.name, stage2.name],
    )
    return CascadeResult(
        scheme=scheme, stages=(res1, res2), science=result_science, metadata=meta, fs=stage2.fs
    )


@dataclasses.dataclass(frozen=True, eq=False)
class _UpstreamSetup:
    """What a record's chunks depend on besides the caller's contract (bases by identity)."""

    basis1: Any
    basis2: Any
    n_frames: int
    chunk: int
    settle: int
    ratio: int
    science_every: int
    science: bool

    def mismatch(self, other: _UpstreamSetup) -> str:
        """The first setting that differs from ``other`` (empty if none)."""
        for f in dataclasses.fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if (a is not b) if f.name.startswith("basis") else (a != b):
                return f"{f.name} ({b!r} recorded, {a!r} now)"
        return ""


class UpstreamRecord:
    """What a cascade run computes upstream of stage 2, kept to run other stage-2 controllers.

    In both schemes stage 1 does not see stage 2: its sensor reads ``d1 - y1`` (or its frame's
    mean phase minus its own DM) and its noise draws from its own child of ``rng``
    (``rng.spawn(2)[0]``). So for one disturbance stream, one stage 1 (controller, sensor,
    latency, DM) and one ``rng``, the following are the same whatever stage 2's controller or
    the scheme: per chunk the disturbance on stage 2's modes ``d2``, stage 1's DM projected on
    them ``P y1``, and at the science frames the phase and stage 1's DM coefficients; and
    stage 1's result. A first :func:`run_cascade` with an empty record fills it; later runs
    given the filled record replay it instead of generating the atmosphere, projecting it and
    running stage 1, and return the same result bit for bit as a full run (tested).

    The caller keeps the contract that the disturbance, stage 1 and ``rng`` are those of the
    recording run (e.g. by keying records on the seed and the stage-1 settings); the record
    checks the rest (the same basis objects, frames, chunk, settling, science cadence) and
    refuses a stage 2 whose sensor reads phase maps (they are not kept). Memory: per fast
    frame ``n2`` float32, per stage-1 frame ``n2`` floats, per science frame the phase
    vector and ``n1`` floats, and stage 1's telemetry.
    """

    def __init__(self) -> None:
        self._setup: _UpstreamSetup | None = None
        self._chunks: dict[int, tuple] = {}
        self._stage1: LoopResult | None = None
        self._stage1_meta: dict = {}

    @property
    def filled(self) -> bool:
        """True once a run has recorded every chunk and stage 1's result."""
        return self._stage1 is not None

    @property
    def stage1(self) -> LoopResult:
        """Stage 1's result of the recording run."""
        if self._stage1 is None:
            raise ValueError("upstream record is empty: no run has filled it")
        return self._stage1

    def check_or_start(self, setup: _UpstreamSetup, stage2_name: str) -> None:
        """Start recording (empty record) or check that a replay matches the recording."""
        if self._setup is None or not self.filled:
            self._setup, self._chunks, self._stage1 = setup, {}, None
            return
        why = setup.mismatch(self._setup)
        if why:
            raise ValueError(f"upstream record does not match this run ({stage2_name!r}): {why}")

    def add(self, k: int, d2: np.ndarray, py1s: np.ndarray, sci: tuple | None) -> tuple:
        """Keep the chunk starting at fast frame ``k`` (copies, returned: the recording run
        uses the very arrays a replay will)."""
        sci = None if sci is None else tuple(np.array(a) for a in sci)
        self._chunks[k] = (np.array(d2), np.array(py1s), sci)
        return self._chunks[k]

    def chunk(self, k: int) -> tuple:
        """The chunk starting at fast frame ``k``: ``(d2, P y1, science inputs)``."""
        return self._chunks[k]

    def finish(self, stage1: LoopResult, metadata: dict | None) -> None:
        """Keep stage 1's result (the record is then filled)."""
        base = metadata or {}
        self._stage1_meta = {
            k: v for k, v in stage1.metadata.items() if k not in base or base[k] is not v
        }
        self._stage1 = stage1

    def stage1_result(self, metadata: dict | None) -> LoopResult:
        """Stage 1's result with this run's ``metadata``, as a full run would give it."""
        return dataclasses.replace(self.stage1, metadata=dict(metadata or {}, **self._stage1_meta))


class _HeldShape:
    """Stage 1's DM shape on the pupil pixels, synthesised once per stage-1 frame (it is held
    over the frame's fast frames) by ``synth`` (:func:`shape_synthesizer`)."""

    def __init__(self, synth: Any) -> None:
        self.synth = synth
        self.key = -1
        self.value: np.ndarray | None = None

    def __call__(self, j1: int, y1: np.ndarray) -> np.ndarray:
        if j1 != self.key:
            self.key = j1
            self.value = self.synth(y1)
        return self.value
