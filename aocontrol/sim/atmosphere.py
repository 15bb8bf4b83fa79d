"""Multi-layer frozen-flow von Kármán atmosphere with infinite (extruded) phase screens.

Each layer is a square phase screen on the pupil's grid (same pixel size), a few times wider
than the pupil. It starts as an FFT screen with subharmonics and, as the wind carries it
across the pupil, it is extended on the fly by the autoregressive extrusion of Assémat,
Wilson & Gendron (2006): new columns (or rows, for the y component of the wind) are drawn
from their von Kármán distribution conditioned on the existing screen, and the oldest ones
are dropped. Runs of any length therefore never wrap around, with memory bounded by one
screen per layer. See :mod:`aocontrol.sim._screens` for the generators.

Frozen flow: at frame ``k`` (time ``k dt``, ``dt = 1/fs``) the layer seen by the pupil is
``phi_k(x) = phi_0(x - v k dt)``: the screen moves by ``v dt`` per frame, towards
``wind_direction`` (degrees counter-clockwise from the pupil's +x axis, the column index,
towards +y, the row index). At kHz rates this is a fraction of a pixel per frame, so the
pupil samples the screen by interpolation, **bilinear** by default, **bicubic** (Keys) on
request. Because the screen and the pupil share one grid, all pixels of a frame share the
same interpolation weights, and a frame is a weighted sum of 4 (16) integer-shifted windows;
a block of frames of all layers is one sparse-times-dense product (vectorised over frames).

Effect of the interpolation on the statistics (exact for a Gaussian field; fraction ``f``
of a pixel ``dx`` along one axis, weights ``w_m`` on the pixels at ``m dx``):
``D_I(r) = sum_{m,m'} w_m w_m' ([D(r+d) + D(|r-d|)]/2 - D(|d|))``, ``d = (m - m') dx``.
For bilinear interpolation this is
``D_f(r) = (f^2 + (1-f)^2) D(r) + f (1-f) [D(r+dx) + D(r-dx) - 2 D(dx)]``, an absolute
deficit of about ``2 f (1-f) D(dx)``: at most ``D(dx)/2 = 3.44 (dx/r0)^(5/3)`` rad^2 at
``f = 1/2``, ``D(dx)/3`` on average over ``f`` (twice that with fractions on both axes).
Relative to ``D(r)``: ``0.5 (dx/r)^(5/3)`` for ``r << L0`` (5 % at 4 pixels, 1.6 % at 8),
somewhat more where the von Kármán ``D(r)`` saturates (at f = 1/2, 8 % at 4 pixels and
4 % at 8 pixels of 0.5 m with L0 = 25 m). Bicubic interpolation divides these deficits by
about 3 (2.5 % and 1.2 %) for twice the cost. Both are tested against the formula. The
effect is confined to spatial frequencies near the pixel Nyquist frequency ``1/(2 dx)``
(the piston-removed pupil variance loses at most ``D(dx)/4``, 0.3 % with 64 pixels across
8 m), above the DM cut-off when the pupil has 1.5 pixels or more per actuator pitch; it
also modulates the pixel-scale variance at the pixel-crossing rate ``v / dx``.

Low orders: with the default screen of ``2 n_pix`` pixels (16 m for the VLT) the extruded
screens reproduce the von Kármán (L0 = 25 m) tip/tilt variance and the piston-removed pupil
variance within a few per cent over long extrusions (the tests check 10 %; figures in
``docs/benchmarks.md``).

Drifting turbulence (argument ``drift``, a :class:`aocontrol.sim.drift.Drift`): frame ``k`` is
multiplied by ``seeing(k dt)^(5/6)`` (the phase of a screen scales as ``r0^(-5/6)``, so the
statistics at each instant are those of ``r0(t)``), and each layer's window sits at
``-X(k dt)``, ``X`` the exact time integral of the layer's time-varying wind velocity (no jump
when the wind changes). Both are functions of the frame index: frames stay independent of the
split into calls.

Units: phase maps are optical path differences in nm (wavelength independent): radians at
500 nm times ``500 / (2 pi)``. ``r0`` is quoted at 500 nm.

Building one: :class:`Atmosphere` ``(pupil, r0, layers, fs)`` for any profile (the one
constructor); :func:`aocontrol.sim.profiles.eso_atmosphere` ``(pupil, seeing, tau0, fs)`` for
the ESO median profile at a seeing and a coherence time, the atmosphere of the science cases
(``aocontrol.study`` scenes build theirs with it).
"""

from __future__ import annotations

import functools
import logging
import math
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from aocontrol._blas import blas_threads
from aocontrol._validation import check_int, check_nonnegative, check_positive
from aocontrol.sim._screens import Extruder, fft_screens
from aocontrol.sim.drift import Drift
from aocontrol.sim.pupil import Pupil
from aocontrol.sim.turbulence import opd_per_radian
from aocontrol.sim.turbulence import tau0 as _tau0

__all__ = ["Layer", "Atmosphere"]

logger = logging.getLogger(__name__)

#: Tolerance on the sum of the layer fractions before they are renormalised to exactly 1.
FRACTION_SUM_TOLERANCE = 1e-3
#: Largest number of frames computed in one sparse product (bounds temporary memory).
MAX_BLOCK_FRAMES = 256
# Frames per dense product of the interpolation (Atmosphere._generate).
_SUB_BLOCK = 16


@dataclass(frozen=True)
class Layer:
    """One turbulent layer moving in frozen flow.

    Parameters
    ----------
    altitude : float
        Height above the telescope [m], >= 0 (used by profile compression and the
        isoplanatic angle; an on-axis simulation does not depend on it).
    fraction : float
        Share of the integrated Cn2 (dimensionless, in [0, 1]); the layers' fractions sum to 1.
    wind_speed : float
        Wind speed [m/s], >= 0.
    wind_direction : float
        Direction the screen moves towards [deg], counter-clockwise from the pupil's +x axis
        (columns) towards +y (rows).
    """

    altitude: float
    fraction: float
    wind_speed: float
    wind_direction: float = 0.0

    def __post_init__(self) -> None:
        for name in ("altitude", "fraction", "wind_speed"):
            object.__setattr__(self, name, check_nonnegative(name, getattr(self, name)))
        direction = self.wind_direction
        if isinstance(direction, bool) or not isinstance(direction, numbers.Real):
            raise TypeError(f"wind_direction must be a real number [deg], got {direction!r}")
        object.__setattr__(self, "wind_direction", float(direction))
        if self.fraction > 1.0:
            raise ValueError(f"fraction must be in [0, 1], got {self.fraction!r}")
        if not math.isfinite(float(self.wind_direction)):
            raise ValueError(f"wind_direction must be finite [deg], got {self.wind_direction!r}")


@functools.lru_cache(maxsize=16)
def _extruder(size: int, dx: float, L0: float) -> Extruder:
    # Immutable (read-only arrays), so atmospheres on the same grid share it.
    return Extruder.build(size, dx, L0)


def _as_generator(
    rng: np.random.Generator | int | np.random.SeedSequence | None,
) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or isinstance(rng, (int, np.integer, np.random.SeedSequence)):
        if isinstance(rng, (bool, np.bool_)):
            raise TypeError(f"rng must be a numpy Generator or an integer seed, got {rng!r}")
        return np.random.default_rng(rng)
    raise TypeError(f"rng must be a numpy Generator or an integer seed, got {rng!r}")


def _check_layers(layers: Sequence[Layer]) -> tuple[Layer, ...]:
    if isinstance(layers, Layer):
        layers = (layers,)
    try:
        layers = tuple(layers)
    except TypeError as exc:
        raise TypeError(f"layers must be a sequence of Layer, got {layers!r}") from exc
    if not layers:
        raise ValueError("layers must contain at least one Layer, got an empty sequence")
    for i, lay in enumerate(layers):
        if not isinstance(lay, Layer):
            raise TypeError(f"layers[{i}] must be a Layer, got {type(lay).__name__}")
    total = sum(lay.fraction for lay in layers)
    if abs(total - 1.0) > FRACTION_SUM_TOLERANCE:
        raise ValueError(
            f"layer fractions must sum to 1 (within {FRACTION_SUM_TOLERANCE}), got "
            f"{total!r}; normalise them, e.g. with aocontrol.sim.profiles.normalize_layers"
        )
    return tuple(
        Layer(lay.altitude, lay.fraction / total, lay.wind_speed, lay.wind_direction)
        for lay in layers
    )


#: Interpolation taps per axis, relative to the floor of the sampled position.
_TAPS = {"linear": (0, 1), "cubic": (-1, 0, 1, 2)}


def _tap_weights(kind: str, f: np.ndarray) -> np.ndarray:
    """Interpolation weights, shape ``(len(f), n_taps)``, for fractions ``f`` in [0, 1).

    ``linear``: ``(1 - f, f)``. ``cubic``: Keys (1981) convolution kernel with ``a = -1/2``
    (exact for quadratics; weights sum to 1).
    """
    if kind == "linear":
        return np.stack([1.0 - f, f], axis=1)
    f2, f3 = f * f, f * f * f
    return np.stack(
        [
            -0.5 * f3 + f2 - 0.5 * f,
            1.5 * f3 - 2.5 * f2 + 1.0,
            -1.5 * f3 + 2.0 * f2 + 0.5 * f,
            0.5 * f3 - 0.5 * f2,
        ],
        axis=1,
    )


class _LayerState:
    """Screen, origin and random stream of one layer (internal, mutable)."""

    def __init__(
        self,
        screen: np.ndarray,
        origin: tuple[int, int],
        step: tuple[float, float],
        amplitude: float,
        rng: np.random.Generator,
        path: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> None:
        self.screen = screen  # (N, N) nm; screen[i, j] is global pixel (oy + i, ox + j)
        self.oy, self.ox = origin
        self.sy, self.sx = step  # window displacement [pixels/frame] (= -v dt / dx)
        self.amplitude = amplitude  # nm per unit (r0 = 1 m, rad at 500 nm) screen
        self.rng = rng
        self.path = path  # frames -> (rows, columns) when the wind drifts

    def positions(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global (row, column) of the window's first pixel at each frame [pixels]."""
        if self.path is not None:
            return self.path(frames)
        return frames * self.sy, frames * self.sx


class Atmosphere:
    """Stream of multi-layer frozen-flow von Kármán phase maps on a pupil, in nm of OPD.

    Parameters
    ----------
    pupil : Pupil
        Sampling grid; the screens share its pixel size ``pupil.pixel_scale`` [m].
    r0 : float
        Fried parameter at 500 nm [m] of the whole atmosphere (layer ``i`` has
        ``r0_i = r0 fraction_i^(-3/5)``).
    layers : sequence of Layer
        Layers; fractions must sum to 1 within ``FRACTION_SUM_TOLERANCE`` (1e-3) and are
        then renormalised exactly (otherwise ``ValueError``).
    fs : float
        Frame rate [Hz]; frame ``k`` is the atmosphere at time ``k / fs``.
    L0 : float
        Outer scale [m] (25 m by default), common to all layers.
    rng : numpy.random.Generator or int or None
        Randomness (a seed is turned into ``numpy.random.default_rng(seed)``). Each layer
        gets its own child stream, so the frames do not depend on how a run is split into
        calls.
    screen_size : int, optional
        Side of each layer's screen [pixels], >= ``n_pix + 4``; default ``2 n_pix``. The
        extrusion is conditioned on this length (16 m on the VLT by default, enough for the
        tip/tilt variance within 2-3 % for L0 from 25 to 100 m); larger screens cost about
        ``screen_size^2`` per extruded column.
    interpolation : {"linear", "cubic"}
        Sub-pixel sampling of the moving screens: bilinear (default, fastest) or bicubic
        (Keys, a = -1/2; a third of the pixel-scale structure-function deficit, about twice
        the cost). See the module notes.
    drift : Drift, optional
        Seeing and wind that change in time (:class:`aocontrol.sim.drift.Drift`): ``r0`` and
        the layers' winds are then the base values, scaled by the drift at each frame.
    dtype : {numpy.float64, numpy.float32}
        Floating type of the frames returned. float32 (7 significant digits, i.e. < 0.01 nm
        on a turbulent OPD of microns) makes frame synthesis 2-4 times faster; the screens and
        their extrusion stay in float64.

    Notes
    -----
    The stream is stateful: :meth:`phase` continues from the previous call and
    :meth:`reset` restarts it (bit-identical frames for the same seed). Frames are also
    independent of the split into calls: ``phase(a)`` then ``phase(b)`` equals
    ``phase(a + b)``.

    Examples
    --------
    >>> from aocontrol.sim.pupil import Pupil
    >>> atm = Atmosphere(Pupil(n_pix=16), r0=0.1, layers=[Layer(0.0, 1.0, 10.0, 30.0)],
    ...                  fs=1000.0, rng=1)
    >>> atm.phase(5).shape
    (5, 16, 16)
    """

    def __init__(
        self,
        pupil: Pupil,
        r0: float,
        layers: Sequence[Layer],
        fs: float,
        L0: float = 25.0,
        rng: np.random.Generator | int | np.random.SeedSequence | None = None,
        *,
        screen_size: int | None = None,
        interpolation: str = "linear",
        dtype: type[np.floating] | str = np.float64,
        drift: Drift | None = None,
    ) -> None:
        if not isinstance(pupil, Pupil):
            raise TypeError(f"pupil must be a Pupil, got {type(pupil).__name__}")
        self._pupil = pupil
        self._r0 = check_positive("r0", r0)
        self._fs = check_positive("fs", fs)
        self._L0 = check_positive("L0", L0)
        self._layers = _check_layers(layers)
        if not isinstance(interpolation, str) or interpolation not in _TAPS:
            raise ValueError(f"interpolation must be one of {sorted(_TAPS)}, got {interpolation!r}")
        self._dtype = np.dtype(dtype)
        if self._dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ValueError(f"dtype must be float64 or float32, got {self._dtype}")
        n = pupil.n_pix
        if screen_size is None:
            screen_size = 2 * n
        self._size = check_int("screen_size", screen_size, minimum=n + 4)
        self._extruder = _extruder(self._size, pupil.pixel_scale, self._L0)
        dx = pupil.pixel_scale
        if drift is not None and not isinstance(drift, Drift):
            raise TypeError(f"drift must be an aocontrol.sim.drift.Drift, got {drift!r}")
        self._drift = drift
        steps = []
        for lay in self._layers:
            a = math.radians(lay.wind_direction)
            shift = lay.wind_speed / self._fs / dx  # pixels per frame
            # The pupil samples phi_0(x - v t): its window moves by -v dt on the screen.
            steps.append((-shift * math.sin(a), -shift * math.cos(a)))
        self._steps = tuple(steps)
        if drift is not None:
            self._wind = (
                np.array([lay.wind_speed for lay in self._layers]),
                np.array([lay.wind_direction for lay in self._layers]),
            )
            v0 = drift.knot_velocities(*self._wind)[0] / self._fs / dx  # (n_layers, 2)
            # Start positions follow the first velocity; the block size the fastest one.
            steps = [(-float(vy), -float(vx)) for vx, vy in v0]
            self._steps = tuple(steps)
            fastest_drift = drift.max_speed(*self._wind) / self._fs / dx
        self._interp = interpolation
        taps = _TAPS[interpolation]
        # A window starting at screen index g reads g + taps[0] ... g + n - 1 + taps[-1]:
        # g ranges over [-taps[0], -taps[0] + span].
        self._span = self._size - n - (taps[-1] - taps[0])
        fastest = max(max(abs(sy), abs(sx)) for sy, sx in steps)
        if drift is not None:
            fastest = max(fastest, fastest_drift)
        self._block = (
            MAX_BLOCK_FRAMES
            if fastest == 0
            else int(max(1, min(MAX_BLOCK_FRAMES, math.floor((self._span - 2) / fastest))))
        )
        rows, cols = np.nonzero(pupil.mask)
        # Flat index in a layer's screen of each valid pupil pixel, window at the origin.
        self._window_index = rows * self._size + cols
        logger.debug(
            "Atmosphere: %d layers, screens %d px, %d frames per block, %s",
            len(self._layers),
            self._size,
            self._block,
            interpolation,
        )
        self.reset(rng)

    # ------------------------------------------------------------------ properties
    @property
    def pupil(self) -> Pupil:
        """Sampling grid."""
        return self._pupil

    @property
    def r0(self) -> float:
        """Fried parameter at 500 nm [m]."""
        return self._r0

    @property
    def L0(self) -> float:
        """Outer scale [m]."""
        return self._L0

    @property
    def fs(self) -> float:
        """Frame rate [Hz]."""
        return self._fs

    @property
    def dt(self) -> float:
        """Frame period ``1 / fs`` [s]."""
        return 1.0 / self._fs

    @property
    def layers(self) -> tuple[Layer, ...]:
        """Layers (fractions renormalised to sum to 1)."""
        return self._layers

    @property
    def screen_size(self) -> int:
        """Side of each layer's screen [pixels]."""
        return self._size

    @property
    def drift(self) -> Drift | None:
        """The seeing and wind drift, or ``None`` (stationary)."""
        return self._drift

    def r0_at(self, t: object) -> np.ndarray:
        """Fried parameter at 500 nm [m] at times ``t`` [s] (``r0`` without drift)."""
        t = np.asarray(t, dtype=float)
        if self._drift is None:
            return np.full(t.shape, self._r0)
        return self._r0 / self._drift.seeing_at(t)

    @property
    def frame(self) -> int:
        """Index of the next frame :meth:`phase` returns (frames produced since reset)."""
        return self._frame

    @property
    def tau0(self) -> float:
        """Coherence time ``0.314 r0 / v_bar`` [s] (5/3-weighted mean wind speed; inf if 0)."""
        speeds = [lay.wind_speed for lay in self._layers]
        if not any(speeds):
            return math.inf
        return _tau0(self._r0, speeds, [lay.fraction for lay in self._layers])

    def __repr__(self) -> str:
        return (
            f"Atmosphere(n_pix={self._pupil.n_pix}, r0={self._r0:g} m, "
            f"{len(self._layers)} layer(s), fs={self._fs:g} Hz, L0={self._L0:g} m, "
            f"tau0={self.tau0 * 1e3:.3g} ms, frame={self._frame})"
        )

    # ------------------------------------------------------------------ state
    def reset(
        self,
        rng: np.random.Generator | int | np.random.SeedSequence | None = None,
    ) -> None:
        """Restart the stream at frame 0.

        Parameters
        ----------
        rng : numpy.random.Generator or int, optional
            New randomness. Without it the atmosphere replays exactly the same frames as
            after construction.
        """
        if rng is not None or not hasattr(self, "_seed_sequences"):
            # One child stream per layer (and one for the initial screens), derived from
            # entropy drawn from the generator given: reproducible, independent streams.
            entropy = _as_generator(rng).integers(0, 2**63, size=4)
            self._seed_sequences = np.random.SeedSequence(entropy).spawn(len(self._layers) + 1)
        gens = [np.random.default_rng(seq) for seq in self._seed_sequences]
        size, dx = self._size, self._pupil.pixel_scale
        unit = fft_screens(len(self._layers), size, dx, self._L0, gens[0])
        scale = self._r0 ** (-5.0 / 6.0) * opd_per_radian()
        states = []
        span, first = self._span, -_TAPS[self._interp][0]
        for i, (lay, (sy, sx)) in enumerate(zip(self._layers, self._steps, strict=True)):
            amp = scale * math.sqrt(lay.fraction)
            # Start the window where it has room to move: at the far end of its motion.
            start_y = first + (span if sy < 0 else (0 if sy > 0 else span // 2))
            start_x = first + (span if sx < 0 else (0 if sx > 0 else span // 2))
            path = None if self._drift is None else functools.partial(self._drift_path, i)
            states.append(
                _LayerState(unit[i] * amp, (-start_y, -start_x), (sy, sx), amp, gens[i + 1], path)
            )
        self._states = states
        self._frame = 0

    # ------------------------------------------------------------------ frames
    def phase(self, n_frames: int) -> np.ndarray:
        """The next ``n_frames`` phase maps [nm OPD], shape ``(n_frames, n_pix, n_pix)``.

        Zero outside the pupil mask. Continues from the previous call. Memory: the result
        only (``n_frames n_pix^2`` values); split long runs into chunks of a few thousand
        frames (the frames do not depend on the split).
        """
        n_frames = check_int("n_frames", n_frames, minimum=0)
        n = self._pupil.n_pix
        maps = np.zeros((n_frames, n * n), dtype=self._dtype)
        index = self._pupil.index

        def store(rows: slice, values: np.ndarray) -> None:
            maps[rows][:, index] = values

        self._generate(n_frames, store)
        return maps.reshape(n_frames, n, n)

    def phase_vectors(self, n_frames: int) -> np.ndarray:
        """The next ``n_frames`` phases on the valid pixels [nm], shape ``(n_frames, n_valid)``.

        Same stream as :meth:`phase` (a call to either advances it), in the order of
        ``pupil.index``; cheaper when only the pupil pixels are needed.
        """
        n_frames = check_int("n_frames", n_frames, minimum=0)
        out = np.empty((n_frames, self._pupil.n_valid), dtype=self._dtype)

        def store(rows: slice, values: np.ndarray) -> None:
            out[rows] = values

        self._generate(n_frames, store)
        return out

    # ------------------------------------------------------------------ internals
    def _drift_path(self, layer: int, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Window position (rows, columns) [pixels] of ``layer`` at ``frames`` under drift:
        minus the screen's displacement, the exact integral of its velocity."""
        x = self._drift.displacement(frames / self._fs, *self._wind)[:, layer]
        dx = self._pupil.pixel_scale
        return -x[:, 1] / dx, -x[:, 0] / dx

    def _generate(self, n_frames: int, store: Callable[[slice, np.ndarray], None]) -> None:
        """Compute the next ``n_frames`` frames block by block, ``store(rows, values)``.

        Each frame is a weighted sum of ``T^2`` integer-shifted windows per layer (``T`` taps
        per axis). Per block, the distinct windows of all layers are gathered once; then per
        sub-block of ``_SUB_BLOCK`` frames, the frames are one dense product of their weights
        on the sub-block's windows (a layer moves by well under a pixel per frame, so a
        sub-block uses few more windows than one frame: ~1.4x the multiply-adds of the sparse
        product at 10 layers, but through the BLAS instead of scipy's scalar sparse loop,
        hence faster). Sub-blocks are aligned on the block's start whatever the calls (a call that
        covers part of one computes it whole), so the frames do not depend on how a run is
        split into calls.
        """
        n_valid = self._pupil.n_valid
        k0, k1 = self._frame, self._frame + n_frames
        b, sub = self._block, _SUB_BLOCK
        # Blocks are aligned on multiples of b frames whatever the calls: the extrusions, and
        # hence the frames, do not depend on how a run is split into calls.
        for j in range(k0 // b, (k1 - 1) // b + 1 if n_frames else k0 // b):
            start, stop = max(k0, j * b), min(k1, (j + 1) * b)
            # The whole sub-blocks (aligned on the block's start) that hold [start, stop).
            lo = j * b + (start - j * b) // sub * sub
            hi = min((j + 1) * b, j * b + -(-(stop - j * b) // sub) * sub)
            frames = np.arange(lo, hi, dtype=float)
            parts = []
            total = 0
            # Seeing drift: the phase of every layer scales as r0(t)^(-5/6).
            gain = None if self._drift is None else self._drift.phase_scale(frames / self._fs)
            for st in self._states:
                self._cover(st, j * b, (j + 1) * b)
                w, inverse, origins = self._interpolation(st, frames)
                if gain is not None:
                    w = w * gain[:, None]
                parts.append((w, inverse + total, origins, st))
                total += origins.size
            # The distinct integer-shifted windows of all layers, stacked: (total, n_valid).
            windows = np.empty((total, n_valid), dtype=self._dtype)
            row = 0
            for _, _, origins, st in parts:
                src = st.screen.astype(self._dtype, copy=False).ravel()
                np.take(
                    src,
                    origins[:, None] + self._window_index[None, :],
                    out=windows[row : row + origins.size],
                    mode="clip",
                )
                row += origins.size
            # Weights and window numbers of each frame, (frames, layers T^2); a frame uses a
            # window at most once (the windows of a layer are distinct, the layers' apart).
            weights = np.concatenate([p[0] for p in parts], axis=1).astype(self._dtype)
            numbers = np.concatenate([p[1] for p in parts], axis=1)
            present = np.zeros(total, dtype=bool)
            for s in range(lo, hi, sub):
                e = min(s + sub, hi)
                nums = numbers[s - lo : e - lo]
                # The windows the sub-block uses, in order, and each one's column.
                present[:] = False
                present[nums] = True
                used = np.flatnonzero(present)
                column = np.cumsum(present) - 1
                dense = np.zeros((e - s, used.size), dtype=self._dtype)
                dense[np.arange(e - s)[:, None], column[nums]] = weights[s - lo : e - lo]
                values = dense @ windows[used]
                first, last = max(s, start), min(e, stop)
                store(slice(first - k0, last - k0), values[first - s : last - s])
        self._frame = k1

    def _cover(self, st: _LayerState, first: int, stop: int) -> None:
        """Extrude ``st`` so that its screen holds every window of frames [first, stop)."""
        # Linear motion: the ends of the block bound it; under drift, every frame does.
        ends = (
            np.array([first, stop - 1], dtype=float)
            if st.path is None
            else np.arange(first, stop, dtype=float)
        )
        py, px = st.positions(ends)
        n, size = self._pupil.n_pix, self._size
        taps = _TAPS[self._interp]
        for axis, pos in ((1, px), (0, py)):
            lo = int(np.floor(pos).min()) + taps[0]  # first and last screen index used
            hi = int(np.floor(pos).max()) + n - 1 + taps[-1]
            origin = st.ox if axis == 1 else st.oy
            if hi > origin + size - 1:
                self._extrude(st, axis, +1, hi - (origin + size - 1))
            elif lo < origin:
                self._extrude(st, axis, -1, origin - lo)

    def _extrude(self, st: _LayerState, axis: int, sign: int, k: int) -> None:
        # Sequential matrix-vector products: one BLAS thread (Extruder.extrude's notes).
        with blas_threads(1):
            self._extrude_columns(st, axis, sign, k)

    def _extrude_columns(self, st: _LayerState, axis: int, sign: int, k: int) -> None:
        s = st.screen
        if axis == 1:
            view = s if sign > 0 else s[:, ::-1]
            st.ox += sign * k
        else:
            view = s.T if sign > 0 else s[::-1, :].T
            st.oy += sign * k
        self._extruder.extrude(view, st.rng.standard_normal((k, self._size)), st.amplitude)

    def _interpolation(
        self,
        st: _LayerState,
        frames: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Weights (n, T^2), window numbers (n, T^2), flat screen index of each window.

        ``T`` is the number of taps per axis (2 bilinear, 4 bicubic).
        """
        py, px = st.positions(frames)
        gy, gx = np.floor(py), np.floor(px)
        taps = _TAPS[self._interp]
        wy = _tap_weights(self._interp, py - gy)
        wx = _tap_weights(self._interp, px - gx)
        cy = gy.astype(np.intp) - st.oy
        cx = gx.astype(np.intp) - st.ox
        size, n = self._size, self._pupil.n_pix
        if (
            min(cy.min(), cx.min()) + taps[0] < 0
            or max(cy.max(), cx.max()) + n - 1 + taps[-1] > size - 1
        ):
            raise RuntimeError("internal error: pupil window outside the layer's screen")
        t, n_frames = np.asarray(taps), len(frames)
        # Window (cy + a, cx + b) for every pair of taps (a, b), weight wy[a] wx[b]; the
        # distinct windows in the order of their flat screen index, found on the small box
        # of rows and columns the block covers (what numpy.unique gives, without a sort).
        ys, xs = cy[:, None] + t, cx[:, None] + t
        y0, x0 = int(ys.min()), int(xs.min())
        hx = int(xs.max()) - x0 + 1
        local = ((ys - y0)[:, :, None] * hx + (xs - x0)[:, None, :]).reshape(n_frames, -1)
        present = np.zeros((int(ys.max()) - y0 + 1) * hx, dtype=bool)
        present[local] = True
        pos = np.flatnonzero(present)
        origins = (pos // hx + y0) * size + (pos % hx + x0)
        inverse = (np.cumsum(present) - 1)[local]
        w = (wy[:, :, None] * wx[:, None, :]).reshape(n_frames, -1)
        return w, inverse, origins
