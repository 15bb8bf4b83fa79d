"""Two-stage cascade: timing, schemes, rates and the control layer's rejection."""

import numpy as np
import pytest
from scipy import signal

from aocontrol import loop_plant
from aocontrol.controllers import IIRBank, Integrator
from aocontrol.plant import z_inverse_coefficients
from aocontrol.sim import (
    LinearModalSensor,
    LoopDivergedError,
    Stage,
    run_cascade,
)
from aocontrol.sim.dm import DeformableMirror, ModalDM
from aocontrol.sim.loop import CascadeResult, DiffractiveSensor, projection_matrix
from aocontrol.sim.modes import kl_basis
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.synthesis import pseudo_open_loop

FS2 = 3000.0
LAT1, LAT2 = 0.84, 0.83


@pytest.fixture(scope="module")
def bases():
    pupil = vlt_pupil(24)
    b1 = kl_basis(DeformableMirror(pupil, n_actuators=11), 24, r0=0.15)
    b2 = kl_basis(DeformableMirror(pupil, n_actuators=8), 10, r0=0.15)
    return b1, b2


class _ModalPhase:
    """Phase synthesised from random modal coefficients (optionally a red AR(1) spectrum),
    plus an optional part outside the basis, generated at once (independent of how a run
    reads it); carries its rate."""

    def __init__(self, basis, fs, seed, n_frames=6000, *, pole=0.0, scale=None, extra=0.0):
        self.fs = fs
        rng = np.random.default_rng(seed)
        n = basis.n_modes
        scale = np.ones(n) if scale is None else np.asarray(scale, dtype=float)
        c = rng.standard_normal((n_frames, n)) * scale
        if pole:
            c = signal.lfilter([1.0], [1.0, -pole], c, axis=0)
        self.coeffs = c
        self.phase = c @ basis.modes
        if extra:
            self.phase = self.phase + extra * rng.standard_normal(self.phase.shape)
        self._pos = 0

    def phase_vectors(self, n_frames):
        out = self.phase[self._pos : self._pos + n_frames]
        self._pos += n_frames
        return out


def _filter_s(plant, ctrl, x):
    """Apply S = 1/(1+GK) per mode (zero initial state) along the frame axis."""
    bg, ag = z_inverse_coefficients(plant)
    out = np.empty_like(x)
    for i in range(x.shape[1]):
        bk, ak = ctrl.b[i], ctrl.a[i]
        num = np.convolve(ag, ak)
        den = np.polynomial.polynomial.polyadd(num, np.convolve(bg, bk))
        out[:, i] = signal.lfilter(num, den, x[:, i])
    return out


def _stages(n1, n2, fs1, *, g1=0.4, g2=0.5, sensor1=None, sensor2=None):
    s1 = Stage(
        Integrator(np.linspace(0.3, g1, n1), fs=fs1),
        sensor1 or LinearModalSensor(1.0, 0.0),
        LAT1,
        name="SAXO",
    )
    s2 = Stage(
        Integrator(np.linspace(0.35, g2, n2), fs=FS2),
        sensor2 or LinearModalSensor(1.0, 0.0),
        LAT2,
        name="SAXO+",
    )
    return s1, s2


@pytest.mark.parametrize("scheme", ["standalone", "dcao"])
def test_same_rate_same_basis_is_exactly_the_product_of_sensitivities(bases, scheme):
    # Exact oracle on the realisation: both stages at 3 kHz on the same basis (P = I):
    # standalone e2 = S2 S1 d, dCAO e2 = S2 d; stage 1 e1 = S1 d in both.
    b1, _ = bases
    n, n_frames = b1.n_modes, 3000
    s1, s2 = _stages(n, n, FS2)
    res = run_cascade(
        s1,
        s2,
        _ModalPhase(b1, FS2, 1),
        n_frames,
        scheme=scheme,
        basis1=b1,
        basis2=b1,
        settle_frames=0,
    )
    assert isinstance(res, CascadeResult) and res.scheme == scheme and res.rate_ratio == 1
    d = res.stage1.telemetry["disturbance"].astype(float)
    e1 = _filter_s(loop_plant(FS2, LAT1), s1.controller, d)
    e2 = _filter_s(loop_plant(FS2, LAT2), s2.controller, e1 if scheme == "standalone" else d)
    # float32 telemetry and projection: relative rounding ~1e-7 of the largest value.
    scale = np.abs(d).max()
    assert np.max(np.abs(e1 - res.stage1.telemetry["residuals"])) < 1e-5 * scale
    assert np.max(np.abs(e2 - res.stage2.telemetry["residuals"])) < 1e-5 * scale
    # The test can fail: the other scheme's oracle is far off.
    other = _filter_s(loop_plant(FS2, LAT2), s2.controller, d if scheme == "standalone" else e1)
    assert np.max(np.abs(other - res.stage2.telemetry["residuals"])) > 0.05 * scale


@pytest.mark.parametrize("scheme", ["standalone", "dcao"])
def test_pseudo_open_loop_of_stage_2_is_its_input(bases, scheme):
    # Oracle: pol = m + G u = z^-1 (input of stage 2): d2 - P y1 in standalone, d2 in dCAO,
    # with d2 the projection of the phase on basis 2 (computed here independently) and y1
    # stage 1's held DM shape. Stages at 3 kHz / 1 kHz on different bases.
    b1, b2 = bases
    n_frames, ratio = 1800, 3
    s1, s2 = _stages(b1.n_modes, b2.n_modes, FS2 / ratio)
    res = run_cascade(
        s1,
        s2,
        _ModalPhase(b1, FS2, 4, pole=0.95, extra=20.0),
        n_frames,
        scheme=scheme,
        basis1=b1,
        basis2=b2,
        settle_frames=0,
    )
    t2 = res.stage2.telemetry
    pol = pseudo_open_loop(
        t2["measurements"].astype(float), t2["commands"].astype(float), loop_plant(FS2, LAT2)
    )
    d2 = b2.project(_ModalPhase(b1, FS2, 4, pole=0.95, extra=20.0).phase_vectors(n_frames))
    y1 = np.repeat(res.stage1.telemetry["dm"].astype(float), ratio, axis=0)
    expected = d2 - y1 @ projection_matrix(b1, b2).T if scheme == "standalone" else d2
    scale = np.abs(d2).max()
    # float32 telemetry/projection rounding (~1e-7 relative) accumulated through G u.
    assert np.max(np.abs(pol[1:] - expected[:-1])) < 1e-5 * scale
    np.testing.assert_allclose(t2["disturbance"][:-1], expected[:-1], atol=1e-5 * scale)


def test_slow_stage_averages_its_frame_and_holds_its_dm(bases):
    # Stage 1 at 300 Hz under a 3 kHz clock: its disturbance telemetry is the mean of the 10
    # fast frames of each of its frames, and its DM shape is held (what stage 2 receives):
    # stage 2's standalone input equals d2 - P y1 with y1 repeated 10 times.
    b1, b2 = bases
    ratio, n_frames = 10, 2000
    s1, s2 = _stages(b1.n_modes, b2.n_modes, FS2 / ratio)
    src = _ModalPhase(b1, FS2, 9, pole=0.9)
    res = run_cascade(
        s1, s2, src, n_frames, scheme="standalone", basis1=b1, basis2=b2, settle_frames=0
    )
    phase = _ModalPhase(b1, FS2, 9, pole=0.9).phase_vectors(n_frames)
    d1 = b1.project(phase)
    assert res.stage1.n_frames == n_frames // ratio and res.stage1.fs == FS2 / ratio
    np.testing.assert_allclose(
        res.stage1.telemetry["disturbance"],
        d1.reshape(-1, ratio, b1.n_modes).mean(axis=1),
        atol=1e-5 * np.abs(d1).max(),
    )
    # Stage-1 fast residual variance = mean over the fast frames of (d1 - held y1)^2.
    y1 = np.repeat(res.stage1.telemetry["dm"].astype(float), ratio, axis=0)
    np.testing.assert_allclose(
        res.stage1.residual_variance, np.mean((d1 - y1) ** 2, axis=0), rtol=1e-4
    )


def test_noise_streams_reproducible_and_independent(bases):
    b1, b2 = bases
    s1, s2 = _stages(
        b1.n_modes,
        b2.n_modes,
        1000.0,
        sensor1=LinearModalSensor(1.0, 2.0),
        sensor2=LinearModalSensor(1.0, 1.0),
    )

    def run(seed):
        return run_cascade(
            s1, s2, _ModalPhase(b1, FS2, 3), 600, scheme="dcao", basis1=b1, basis2=b2, rng=seed
        )

    a, b, c = run(5), run(5), run(6)
    for i in range(2):
        np.testing.assert_array_equal(
            a.stages[i].telemetry["measurements"], b.stages[i].telemetry["measurements"]
        )
        assert not np.array_equal(
            a.stages[i].telemetry["measurements"], c.stages[i].telemetry["measurements"]
        )
    with pytest.raises(ValueError, match="rng is required"):
        run_cascade(s1, s2, _ModalPhase(b1, FS2, 3), 600, scheme="dcao", basis1=b1, basis2=b2)


def test_unstable_stage_named_in_the_error(bases):
    b1, b2 = bases
    s1 = Stage(Integrator(0.3, fs=1000.0, n_modes=b1.n_modes), latency_frames=LAT1, name="SAXO")
    gains = np.full(b2.n_modes, 0.4)
    gains[3] = 1.6  # beyond the stability limit (~1.0) for 1.83 frames of delay
    s2 = Stage(Integrator(gains, fs=FS2), latency_frames=LAT2, name="SAXO+")
    with pytest.raises(LoopDivergedError, match=r"stage 'SAXO\+'.*modes \[3\]") as info:
        run_cascade(
            s1, s2, _ModalPhase(b1, FS2, 2), 3000, scheme="standalone", basis1=b1, basis2=b2
        )
    assert info.value.stage == "SAXO+" and 0 < info.value.frame < 3000


def test_bad_input(bases):
    b1, b2 = bases
    s1, s2 = _stages(b1.n_modes, b2.n_modes, 1000.0)
    src = _ModalPhase(b1, FS2, 0)
    kw = dict(basis1=b1, basis2=b2)
    with pytest.raises(ValueError, match=r"scheme must be one of \('standalone', 'dcao'\)"):
        run_cascade(s1, s2, src, 300, scheme="dCAO+", **kw)
    s1b, _ = _stages(b1.n_modes, b2.n_modes, 1250.0)
    with pytest.raises(ValueError, match=r"integer multiple.*fs2=3000 Hz, fs1=1250 Hz"):
        run_cascade(s1b, s2, src, 300, scheme="dcao", **kw)
    with pytest.raises(ValueError, match=r"fs=1000 Hz but the fast clock .* 3000 Hz"):
        run_cascade(s1, s2, _ModalPhase(b1, 1000.0, 0), 300, scheme="dcao", **kw)
    with pytest.raises(ValueError, match="multiple of the rate ratio 3"):
        run_cascade(s1, s2, src, 301, scheme="dcao", **kw)
    with pytest.raises(ValueError, match="basis1 has 10 modes, 'SAXO' controls 24"):
        run_cascade(s1, s2, src, 300, scheme="dcao", basis1=b2, basis2=b2)
    nan_src = _ModalPhase(b1, FS2, 0, scale=np.r_[np.nan, np.ones(b1.n_modes - 1)])
    with pytest.raises(ValueError, match="disturbance .*is not finite .* frame 0"):
        run_cascade(s1, s2, nan_src, 300, scheme="dcao", **kw)

    # A diffractive sensor on another pupil than the stage's basis is refused, naming it.
    from aocontrol.sim.wfs import PyramidWFS

    other = PyramidWFS(vlt_pupil(16), 1.04e-6, n_subapertures=8, modulation=2.0)
    diff = Stage(
        Integrator(0.3, fs=FS2, n_modes=b2.n_modes),
        DiffractiveSensor(other, np.ones((b2.n_modes, other.n_signals))),
    )
    with pytest.raises(ValueError, match=r"sensor.wfs.pupil must equal the stage basis's pupil"):
        run_cascade(s1, diff, src, 300, scheme="dcao", **kw)
    with pytest.raises(ValueError, match="sensor.wfs.pupil"):
        Stage(diff.controller, diff.sensor, basis=b2)
    with pytest.raises(ValueError, match="reconstructor is required"):
        DiffractiveSensor(other, None)


@pytest.mark.parametrize("scheme", ["standalone", "dcao"])
def test_cascade_matches_the_golden_run(scheme):
    # Oracle: arrays recorded from the engine before the one-driver refactoring
    # (tests/_golden_loop.py), both stages noisy, stage 2 with a stroke and optical gains;
    # to the stated tolerance of runs on projected phase screens (_golden_loop.GOLDEN_RTOL:
    # the float32 projection's rounding depends on the BLAS thread count), counts exact.
    import _golden_loop

    res = _golden_loop.cascade_run(scheme)
    with np.load(_golden_loop.PATH) as z:
        for i, st in enumerate(res.stages):
            prefix = f"{scheme}{i + 1}/"
            gold = {k[len(prefix) :]: z[k] for k in z.files if k.startswith(prefix)}
            assert len(gold) >= 4
            got = {n: st.telemetry[n] if n in st.telemetry else getattr(st, n) for n in gold}
            _golden_loop.assert_close_to_golden(got, gold)
        gold = {n: z[f"{scheme}/{n}"] for n in ("strehl", "contrast_profile")}
        got = {n: getattr(res.science, n) for n in gold}
        _golden_loop.assert_close_to_golden(got, gold)


def test_result_round_trip(bases, tmp_path):
    b1, b2 = bases
    s1, s2 = _stages(b1.n_modes, b2.n_modes, 1000.0)
    res = run_cascade(
        s1,
        s2,
        _ModalPhase(b1, FS2, 0),
        600,
        scheme="dcao",
        basis1=b1,
        basis2=b2,
        metadata={"case": "unit"},
    )
    with pytest.warns(DeprecationWarning, match="save_result"):
        res.save(tmp_path / "c.npz")
    back = CascadeResult.load(tmp_path / "c.npz")
    assert back.scheme == "dcao" and back.metadata["case"] == "unit" and back.fs == FS2
    for i in range(2):
        np.testing.assert_array_equal(
            back.stages[i].telemetry["residuals"], res.stages[i].telemetry["residuals"]
        )
        assert back.stages[i].fs == res.stages[i].fs
    np.testing.assert_array_equal(back.final_residual_variance, res.final_residual_variance)


def test_iirbank_stage_pole_check_agrees_with_control_layer():
    # Two implementations: the runner's batched companion-matrix pole radius and
    # aocontrol.analysis.closed_loop_poles through python-control.
    from aocontrol.analysis import closed_loop_poles
    from aocontrol.sim.loop import closed_loop_pole_radius

    ctrl = IIRBank(np.array([[0.4, -0.1], [1.2, 0.0], [0.2, 0.1]]), [1.0, -1.0], fs=FS2)
    stage = Stage(ctrl, latency_frames=1.3)
    radius = closed_loop_pole_radius(stage, np.ones(3))
    ref = [
        np.abs(closed_loop_poles(loop_plant(FS2, 1.3), ctrl.transfer_function(i))).max()
        for i in range(3)
    ]
    np.testing.assert_allclose(radius, ref, rtol=1e-9)
    assert radius[1] > 1 > radius[0]


def _h1_and_psd_ratio(d, e, fs):
    f, p_de = signal.csd(d, e, fs=fs, nperseg=1024, axis=0)
    _, p_dd = signal.welch(d, fs=fs, nperseg=1024, axis=0)
    _, p_ee = signal.welch(e, fs=fs, nperseg=1024, axis=0)
    return f, (p_de / p_dd).T, (p_ee / p_dd).T


@pytest.mark.parametrize("scheme", ["standalone", "dcao"])
@pytest.mark.parametrize("ratio", [1, 3, 10])
def test_measured_rejection_equals_the_control_layer(bases, scheme, ratio):
    # Oracle: aocontrol.analysis.cascade_sensitivity, the baseband response of the
    # multi-rate cascade (exact in expectation for an H1 estimate at every frequency; S1 S2
    # or S2 exactly when both stages run at the same rate) and cascade_rejection for the
    # PSD ratio below stage 1's Nyquist frequency (where the aliased power is small).
    from aocontrol.analysis import cascade_rejection, cascade_sensitivity

    b = bases[0].truncate(6)
    n_frames, settle = 16500, 300
    s1, s2 = _stages(b.n_modes, b.n_modes, FS2 / ratio)
    src = _ModalPhase(b, FS2, 1, n_frames, pole=0.98)
    res = run_cascade(
        s1,
        s2,
        src,
        n_frames,
        scheme=scheme,
        basis1=b,
        basis2=b,
        settle_frames=settle,
        record=("residuals",),
    )
    f, h1, psd_ratio = _h1_and_psd_ratio(
        src.coeffs[settle:], res.stage2.telemetry["residuals"][settle:].astype(float), FS2
    )
    args = (loop_plant(FS2 / ratio, LAT1), s1.controller, loop_plant(FS2, LAT2), s2.controller)
    s = cascade_sensitivity(*args, f, scheme=scheme)
    rej = cascade_rejection(*args, f, scheme=scheme)
    band = (f > 0) & (f < FS2 / ratio / 2)
    rel = np.abs(h1 - s)[:, band] / np.abs(s[:, band])
    if ratio == 1:
        # Same rate: LTI; Hann-window leakage only (as the single-stage test): ~1e-3.
        assert np.median(rel) < 2e-3 and np.max(np.abs(h1 - s)[:, 1:-1]) < 0.03
    else:
        # Multi-rate: the aliased components are uncorrelated with d at f, so they only add
        # estimator scatter (~16 segments): median ~0.5-1 %, 5 % leaves room.
        assert np.median(rel) < 0.05
    # Residual PSD / disturbance PSD within 10 % of |S_eff|^2 below stage 1's Nyquist, above
    # 30 Hz where |S|^2 spans decades and the 1024-point Welch PSD is leakage-dominated.
    sel = band & (f > 30.0)
    assert np.median(np.abs(psd_ratio[:, sel] / rej[:, sel] - 1)) < 0.1
    # ...and the wrong scheme's rejection is far off (the test can fail).
    other = cascade_rejection(*args, f, scheme="dcao" if scheme == "standalone" else "standalone")
    assert np.max(np.abs(psd_ratio[:, sel] / other[:, sel] - 1)) > 0.5


class _Capture:
    """A science accumulator that keeps the residual maps it receives."""

    def __init__(self):
        self.maps = []

    def add(self, maps):
        self.maps.append(np.array(maps))

    def result(self):
        return len(self.maps)


def test_science_sees_the_residual_after_both_stages(bases):
    # Definition: the camera receives phi - B1 y1 - B2 y2_dm on every science_every-th fast
    # frame after settling (the part of phi outside both bases stays in).
    b1, b2 = bases
    ratio, n_frames, settle, every = 3, 900, 90, 7
    s1, s2 = _stages(b1.n_modes, b2.n_modes, FS2 / ratio)
    src = _ModalPhase(b1, FS2, 8, n_frames, pole=0.9, extra=5.0)
    cam = _Capture()
    res = run_cascade(
        s1,
        s2,
        src,
        n_frames,
        scheme="dcao",
        basis1=b1,
        basis2=b2,
        science=cam,
        science_every=every,
        settle_frames=settle,
    )
    frames = np.arange(settle, n_frames)
    frames = frames[frames % every == 0]
    y1 = np.repeat(res.stage1.telemetry["dm"].astype(float), ratio, axis=0)[frames]
    y2 = res.stage2.telemetry["dm"].astype(float)[frames]
    expected = src.phase[frames] - b1.synthesize(y1) - b2.synthesize(y2)
    got = b1.pupil.to_vector(np.concatenate(cam.maps))
    assert res.science == len(cam.maps) and got.shape == expected.shape
    # float32 synthesis and telemetry: 1e-5 of the phase scale.
    np.testing.assert_allclose(got, expected, atol=1e-5 * np.abs(src.phase).max())


def test_dcao_stroke_clips_the_total_dm_shape(bases):
    # In dCAO stage 2's controller sees the full disturbance, so its own command u2 carries
    # the large static tilt that stage 1 already corrects; the DM clips the total shape
    # u2 - P y1 (small), not u2: no saturation once converged, commands beyond the stroke.
    b1, b2 = bases
    n_frames, stroke = 1500, 5.0

    class _Static:
        fs = FS2

        def phase_vectors(self, n):
            return np.tile(100.0 * b1.modes[0], (n, 1))

    s1 = Stage(Integrator(0.4, fs=1000.0, n_modes=b1.n_modes), latency_frames=LAT1)
    s2 = Stage(
        Integrator(0.4, fs=FS2, n_modes=b2.n_modes),
        latency_frames=LAT2,
        dm=ModalDM(b2.n_modes, modal_stroke=stroke),
    )
    res = run_cascade(
        s1, s2, _Static(), n_frames, scheme="dcao", basis1=b1, basis2=b2, settle_frames=300
    )
    t2 = res.stage2.telemetry
    assert np.max(np.abs(t2["dm"])) <= stroke
    assert np.max(np.abs(t2["commands"][-100:, 0])) > 10 * stroke  # u2 itself is large
    late = res.stage2.saturation.sum()
    assert late < 200  # only during the initial transient
    assert np.max(np.abs(t2["residuals"][-100:])) < 1e-3 * 100.0  # converged


def test_default_chunk_bounds_the_chunk_phase(bases, monkeypatch):
    # The rule: at most 1200 frames, and a float32 chunk phase within _CHUNK_PHASE_BYTES
    # (24 MiB: 888 frames of the 96-pixel VLT pupil's 7084 valid pixels).
    from aocontrol.sim import _cascade

    assert _cascade.default_chunk(7084) == 888
    assert 888 * 4 * 7084 <= _cascade._CHUNK_PHASE_BYTES < 889 * 4 * 7084
    assert _cascade.default_chunk(100) == 1200
    # run_cascade takes it when no chunk is given, rounded up to the rate ratio (3): with a
    # budget of 40 frames of this pupil, chunks of 42 fast frames (the last one shorter).
    b1, b2 = bases
    n_valid = b1.modes.shape[1]
    monkeypatch.setattr(_cascade, "_CHUNK_PHASE_BYTES", 40 * 4 * n_valid)
    src = _ModalPhase(b1, FS2, 0, n_frames=300)
    sizes = []
    read = src.phase_vectors
    src.phase_vectors = lambda n: sizes.append(n) or read(n)
    s1, s2 = _stages(b1.n_modes, b2.n_modes, 1000.0)
    run_cascade(s1, s2, src, 150, scheme="dcao", basis1=b1, basis2=b2)
    assert sizes == [42, 42, 42, 24]
