"""AOT telemetry in and out: aocontrol.io (reader, temporal filter) and aocontrol.study.aot."""

from __future__ import annotations

import aotpy
import numpy as np
import pytest

from aocontrol.controllers import IIRBank, Integrator
from aocontrol.io import AOTError, aot_loops, read_aot, read_aot_filter, write_aot_filter
from aocontrol.sim import LinearModalSensor, ModalTimeSeries, Stage, run_loop
from aocontrol.study.aot import write_run_aot
from aocontrol.study.cli import main
from aocontrol.synthesis import design_from_telemetry

FS = 1000.0
LATENCY = 0.4
N_MODES = 3
N_SUB = 8  # valid subapertures of the hand-built Shack-Hartmann (2 x 8 slopes)
N_ACT = 5


def _run(n_frames=2048, seed=0):
    """Closed loop of a noisy integrator on AR(1) disturbances (pole 0.98) [nm]."""
    rng = np.random.default_rng(seed)
    white = rng.standard_normal((n_frames, N_MODES)) * np.array([20.0, 10.0, 5.0])
    d = np.empty_like(white)
    acc = np.zeros(N_MODES)
    for k in range(n_frames):
        acc = 0.98 * acc + white[k]
        d[k] = acc
    stage = Stage(
        Integrator(0.3, fs=FS, n_modes=N_MODES),
        sensor=LinearModalSensor(noise_std=2.0),
        latency_frames=LATENCY,
    )
    return run_loop(stage, ModalTimeSeries(d), n_frames, rng=seed + 1, settle_frames=0)


def _parts():
    return aotpy.MainTelescope("VLT"), aotpy.NaturalGuideStar("NGS")


def _system(loops, tel, src):
    """An aotpy system holding ``loops`` (built with aotpy, not with our writer)."""
    sys_ = aotpy.AOSystem(ao_mode="SCAO", main_telescope=tel, sources=[src])
    for lp in loops:
        sys_.wavefront_sensors.append(lp.input_sensor)
        sys_.wavefront_correctors.append(lp.commanded_corrector)
        sys_.loops.append(lp)
    return sys_


def _slope_loop(tel, src, m_act, u_act, *, name="HO", cm=None, **fields):
    """A loop whose sensor records slopes s with control_matrix @ s = m_act (actuator space)."""
    rng = np.random.default_rng(5)
    if cm is None:
        cm = rng.normal(size=(N_ACT, 2, N_SUB))
    slopes = m_act @ np.linalg.pinv(cm.reshape(N_ACT, -1)).T  # (t, 2 N_SUB), CM s = m
    wfs = aotpy.ShackHartmann(
        f"{name} WFS",
        source=src,
        n_valid_subapertures=N_SUB,
        measurements=aotpy.Image(f"{name} SLOPES", slopes.reshape(-1, 2, N_SUB)),
    )
    dm = aotpy.DeformableMirror(f"{name} DM", telescope=tel, n_valid_actuators=N_ACT)
    base = {
        "commands": aotpy.Image(f"{name} CMD", u_act),
        "framerate": FS,
        "delay": 1.0 + LATENCY,
        "control_matrix": aotpy.Image(f"{name} CM", cm),
    }
    base.update(fields)
    return aotpy.ControlLoop(name, commanded_corrector=dm, input_sensor=wfs, **base)


# --------------------------------------------------------------------------- our writer
def test_simulated_run_round_trips_through_aotpy(tmp_path):
    # Oracle: aotpy's own reader finds what we wrote (rate, AOT delay = 1 + latency, modal
    # measurements, commands in m mapped back to nm by commands_to_modes), and read_aot
    # returns the run's telemetry to float32 rounding.
    res = _run(512)
    path = write_run_aot(
        res, tmp_path / "run.fits", controllers={"stage": Integrator(0.3, fs=FS, n_modes=3)}
    )
    system = aotpy.AOSystem.read_from_file(path)
    (loop,) = system.loops
    assert loop.framerate == FS and loop.delay == pytest.approx(1.0 + LATENCY, abs=1e-15)
    m = res.telemetry["measurements"].astype(float)
    u = res.telemetry["commands"].astype(float)
    np.testing.assert_array_equal(loop.modal_coefficients.data, m)
    back = loop.commands.data @ loop.commands_to_modes.data.T
    np.testing.assert_allclose(back, u, rtol=1e-12, atol=1e-12 * np.abs(u).max())
    assert loop.commands.unit == "m" and np.abs(loop.commands.data).max() < 1e-6
    tel = read_aot(path)
    assert tel.fs == FS and tel.latency_frames == pytest.approx(LATENCY, abs=1e-12)
    np.testing.assert_array_equal(tel.measurements, m)
    np.testing.assert_allclose(tel.commands, u, rtol=1e-12, atol=1e-12 * np.abs(u).max())
    # The filter in aotpy's documented convention: 0.3 z / (z - 1), ascending powers of z.
    np.testing.assert_array_equal(loop.time_filter_num.data, np.tile([0.0, 0.3], (3, 1)))
    np.testing.assert_array_equal(loop.time_filter_den.data, np.tile([-1.0, 1.0], (3, 1)))
    back = read_aot_filter(path)
    np.testing.assert_array_equal(back.b, np.full((3, 1), 0.3))
    np.testing.assert_array_equal(back.a, np.tile([1.0, -1.0], (3, 1)))


def test_actuator_commands_with_a_modes_to_actuators_matrix(tmp_path):
    # Oracle: commands written as actuator commands M u and mapped back with pinv(M).
    res = _run(256)
    mat = np.random.default_rng(1).normal(size=(N_ACT, N_MODES))
    path = write_run_aot(res, tmp_path / "run.fits", modes_to_actuators={"stage": mat})
    (loop,) = aotpy.AOSystem.read_from_file(path).loops
    assert loop.commands.data.shape == (256, N_ACT)
    u = res.telemetry["commands"].astype(float)
    np.testing.assert_allclose(read_aot(path).commands, u, atol=1e-9 * np.abs(u).max())
    with pytest.raises(ValueError, match=r"stages \['nope'\]; the run has stages \['stage'\]"):
        write_run_aot(res, tmp_path / "x.fits", modes_to_actuators={"nope": mat})


# ----------------------------------------------------------- a file built with aotpy
def test_reader_projects_slopes_with_the_control_matrix_of_a_foreign_file(tmp_path):
    # Oracle: a file built with aotpy directly (slopes, control matrix, actuator commands):
    # the modal measurements are control_matrix @ slopes, the commands as recorded. Neither
    # states a BUNIT: the commands are in AOT's metres, and so are the actuator commands the
    # control matrix reconstructs; both are read in nm (1e9 per metre; issue 30: they were
    # taken for nm before).
    rng = np.random.default_rng(2)
    m_act, u_act = rng.normal(size=(300, N_ACT)), rng.normal(size=(300, N_ACT))
    tel, src = _parts()
    lp = _slope_loop(tel, src, m_act, u_act)
    sys_ = _system([lp], tel, src)
    path = tmp_path / "foreign.fits"
    sys_.write_to_file(path)
    assert aot_loops(path) == ["HO"]
    got = read_aot(path, "HO")
    np.testing.assert_allclose(got.measurements, 1e9 * m_act, atol=1e-1)
    np.testing.assert_allclose(got.commands, 1e9 * u_act, rtol=1e-15)
    assert got.unit == "nm"
    assert got.fs == FS and got.latency_frames == pytest.approx(LATENCY)
    # A given projection (here the control matrix's negative) is used instead of the file's;
    # its unit is not the file's: stated here as the metres it is.
    cm = lp.control_matrix.data
    neg = read_aot(
        path, projection=-cm, command_projection=np.eye(N_ACT), command_sign=-1.0, unit="m"
    )
    np.testing.assert_allclose(neg.measurements, -1e9 * m_act, atol=1e-1)
    np.testing.assert_allclose(neg.commands, -1e9 * u_act, rtol=1e-15)


def test_reader_uses_modal_fields_when_the_file_has_them(tmp_path):
    # Oracle: measurements_to_modes R (m x d x s) and commands_to_modes C (m x a): modal
    # measurements R s and commands C u.
    rng = np.random.default_rng(4)
    m_modal = rng.normal(size=(200, N_MODES))
    u_act = rng.normal(size=(200, N_ACT))
    r = rng.normal(size=(N_MODES, 2, N_SUB))
    c = rng.normal(size=(N_MODES, N_ACT))
    tel, src = _parts()
    slopes = m_modal @ np.linalg.pinv(r.reshape(N_MODES, -1)).T
    wfs = aotpy.ShackHartmann(
        "WFS", source=src, n_valid_subapertures=N_SUB,
        measurements=aotpy.Image("S", slopes.reshape(-1, 2, N_SUB)),
    )  # fmt: skip
    dm = aotpy.DeformableMirror("DM", telescope=tel, n_valid_actuators=N_ACT)
    lp = aotpy.ControlLoop(
        "MODAL", commanded_corrector=dm, input_sensor=wfs, commands=aotpy.Image("U", u_act),
        framerate=FS, delay=2.0, measurements_to_modes=aotpy.Image("R", r),
        commands_to_modes=aotpy.Image("C", c),
    )  # fmt: skip
    _system([lp], tel, src).write_to_file(tmp_path / "modal.fits")
    got = read_aot(tmp_path / "modal.fits")
    np.testing.assert_allclose(got.measurements, m_modal, atol=1e-10)
    np.testing.assert_allclose(got.commands, u_act @ c.T, atol=1e-12)
    assert got.latency_frames == 1.0


def test_design_and_cli_on_a_file_another_system_wrote(tmp_path, capsys):
    # A simulated closed loop written with aotpy directly (modal "actuators"), two loops in
    # the file: design_from_telemetry finds stable designs meeting the margin, and the CLI
    # `aocontrol design run.fits --loop NAME` works end to end (controller, RTC export, AOT
    # copy with the filter, which aotpy reads back).
    res = _run(4096)
    m = res.telemetry["measurements"].astype(float)
    u = res.telemetry["commands"].astype(float)
    tel, src = _parts()
    loops = []
    for name in ("TT", "HO"):
        wfs = aotpy.ShackHartmann(f"{name} WFS", source=src, n_valid_subapertures=N_MODES)
        dm = aotpy.DeformableMirror(f"{name} DM", telescope=tel, n_valid_actuators=N_MODES)
        loops.append(
            aotpy.ControlLoop(
                name,
                commanded_corrector=dm,
                input_sensor=wfs,
                framerate=FS,
                delay=1.0 + LATENCY,
                commands=aotpy.Image(f"{name} U", u),
                modal_coefficients=aotpy.Image(f"{name} M", m),
                commands_to_modes=aotpy.Image(f"{name} C", np.eye(N_MODES)),
            )  # fmt: skip
        )
    path = tmp_path / "run.fits"
    _system(loops, tel, src).write_to_file(path)
    rep = design_from_telemetry(read_aot(path, "HO"), "omgi", bounds=("wiener",))
    assert rep.meets_margin.all() and rep.n_modes == N_MODES
    # Oracle: no causal linear controller beats the Wiener bound.
    assert np.all(rep.residual_variance >= rep.wiener_variance * (1 - 1e-3))

    out = tmp_path / "k.h5"
    argv = ["design", str(path), "--loop", "HO", "--controller", "omgi", "--bounds", "wiener"]
    argv += ["--out", str(out), "--export", str(tmp_path / "k.csv")]
    argv += ["--aot-out", str(tmp_path / "with_filter.fits")]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "fs = 1000 Hz, latency = 0.4 frame" in text and "estimator: prewhitened" in text
    assert out.exists() and (tmp_path / "k.csv").exists()
    (ho,) = [lp for lp in aotpy.AOSystem.read_from_file(tmp_path / "with_filter.fits").loops
             if lp.uid == "HO"]  # fmt: skip
    # The gain is the coefficient of z^1 of g z / (z - 1) (aotpy's convention, ascending).
    np.testing.assert_allclose(ho.time_filter_num.data[:, 1], rep.controller.b[:, 0], rtol=1e-6)
    np.testing.assert_allclose(
        read_aot_filter(tmp_path / "with_filter.fits", "HO").b[:, 0], rep.controller.b[:, 0]
    )
    # Several loops and none chosen: the error lists them.
    assert main(["design", str(path), "--out", str(tmp_path / "x.h5")]) == 2
    assert "2 control loops ['TT', 'HO']" in capsys.readouterr().err


def test_filter_round_trip_through_aotpy(tmp_path):
    # Oracle: a 5th-order bank written into a loop's time filter, read back by aotpy (the
    # raw fields: the rows in ascending powers of z, i.e. reversed, the convention stated)
    # and by us (an IIRBank whose step() equals the original's).
    rng = np.random.default_rng(9)
    b = rng.normal(size=(N_ACT, 6))
    a = np.column_stack([np.ones(N_ACT), 0.1 * rng.normal(size=(N_ACT, 5))])
    bank = IIRBank(b, a, FS)
    tel, src = _parts()
    loop = _slope_loop(tel, src, np.zeros((64, N_ACT)), np.zeros((64, N_ACT)))
    path = tmp_path / "loop.fits"
    _system([loop], tel, src).write_to_file(path)
    out = write_aot_filter(path, bank, "HO", out=tmp_path / "out.fits")
    (lp,) = aotpy.AOSystem.read_from_file(out).loops
    np.testing.assert_array_equal(lp.time_filter_num.data, b[:, ::-1])
    np.testing.assert_array_equal(lp.time_filter_den.data, a[:, ::-1])
    assert lp.time_filter_num.metadata_to_dict()["TFCONV"] == "z"
    back = read_aot_filter(out, "HO")
    x = rng.normal(size=(50, N_ACT))
    bank.reset()
    np.testing.assert_array_equal([back.step(v) for v in x], [bank.step(v) for v in x])


# ---------------------------------------------------------------------------- bad input
def _bad_file(tmp_path, **fields):
    rng = np.random.default_rng(0)
    tel, src = _parts()
    lp = _slope_loop(tel, src, rng.normal(size=(64, N_ACT)), rng.normal(size=(64, N_ACT)))
    for key, value in fields.items():
        setattr(lp, key, value)
    path = tmp_path / "bad.fits"
    _system([lp], tel, src).write_to_file(path)
    return path


@pytest.mark.parametrize(
    ("fields", "kwargs", "field", "reason"),
    [
        ({}, {"loop": "LO"}, "loops", r"no such control loop; the file has \['HO'\]"),
        ({"framerate": None}, {}, "framerate", "a loop rate > 0"),
        ({"delay": None}, {}, "delay", "pass latency_frames"),
        ({"delay": 0.5}, {}, "delay", ">= 1 frame"),
        (
            {"commands": aotpy.Image("U", np.zeros((60, N_ACT)))},
            {},
            "commands",
            r"\(60, 5\) and modal measurements \(64, 5\)",
        ),
        (
            {"control_matrix": aotpy.Image("CM", np.zeros((N_ACT, 2, N_SUB + 1)))},
            {},
            "control_matrix",
            r"shape \(5, 18\) cannot map measurements of 16 values",
        ),
        ({"control_matrix": None}, {}, "control_matrix", "no matrix to project"),
    ],
)
def test_bad_file_names_file_loop_and_field(tmp_path, fields, kwargs, field, reason):
    path = _bad_file(tmp_path, **fields)
    with pytest.raises(AOTError, match=reason) as info:
        read_aot(path, kwargs.get("loop", "HO"))
    text = str(info.value)
    assert "bad.fits" in text and f"field {field!r}" in text
    assert f"loop {kwargs.get('loop', 'HO')!r}" in text


def test_not_an_aot_file_and_a_filter_at_the_wrong_rate(tmp_path):
    junk = tmp_path / "junk.fits"
    junk.write_text("not fits")
    with pytest.raises(AOTError, match=r"junk\.fits.*not a readable AOT FITS"):
        read_aot(junk)
    with pytest.raises(AOTError, match="no such file"):
        read_aot(tmp_path / "none.fits")
    path = _bad_file(tmp_path)
    with pytest.raises(AOTError, match=r"field 'framerate'.*1000 Hz, bank at 500 Hz"):
        write_aot_filter(path, Integrator(0.3, fs=500.0, n_modes=N_ACT), out=tmp_path / "o.fits")
    assert not (tmp_path / "o.fits").exists()


# ------------------------------------------------------------- the temporal filter's convention
def _aotpy_reader_response(num: np.ndarray, den: np.ndarray, f: np.ndarray) -> np.ndarray:
    """A reader that follows aotpy's documentation literally (not our code): one row's
    sys(z) = sum_i b_i z^i / sum_j a_j z^j at z = exp(2 pi i f / fs)."""
    z = np.exp(2j * np.pi * f / FS)
    return np.polyval(num[::-1], z) / np.polyval(den[::-1], z)


def _filter_file(tmp_path, name="loop.fits"):
    tel, src = _parts()
    loop = _slope_loop(tel, src, np.zeros((64, N_ACT)), np.zeros((64, N_ACT)))
    path = tmp_path / name
    _system([loop], tel, src).write_to_file(path)
    return path, loop, tel, src


def test_written_filter_has_its_response_for_a_reader_of_aotpy_docs(tmp_path):
    # Issue 30: aotpy documents sys(z) = sum b_i z^i / sum a_j z^j; we wrote powers of z^-1,
    # so a reader following the formula read our integrator (den [1, -1]) as 1 - z. Oracle: a
    # leaky integrator with a lead of known response, K = g (1 - c z^-1) / ((1 - z^-1)(1 - p
    # z^-1)), written by write_aot_filter and evaluated from the raw aotpy fields by a reader
    # of aotpy's formula, equals the analytic K on the circle.
    g, c, p = 0.4, 0.5, 0.9
    b = g * np.array([1.0, -c])
    a = np.convolve([1.0, -1.0], [1.0, -p])
    bank = IIRBank(np.tile(b, (N_ACT, 1)), np.tile(a, (N_ACT, 1)), FS)
    path, *_ = _filter_file(tmp_path)
    out = write_aot_filter(path, bank, "HO", out=tmp_path / "out.fits")
    (lp,) = aotpy.AOSystem.read_from_file(out).loops
    f = np.linspace(1.0, FS / 2, 50)
    zi = np.exp(-2j * np.pi * f / FS)
    analytic = g * (1 - c * zi) / ((1 - zi) * (1 - p * zi))
    for row in range(N_ACT):
        got = _aotpy_reader_response(lp.time_filter_num.data[row], lp.time_filter_den.data[row], f)
        np.testing.assert_allclose(got, analytic, rtol=1e-12)
    # Twin: the rows as we wrote them before (powers of z^-1) give that reader the conjugate
    # response (a different filter): the check above can fail.
    old = _aotpy_reader_response(b, a, f)
    assert np.max(np.abs(old - analytic)) > 0.1 * np.max(np.abs(analytic))
    np.testing.assert_allclose(old, np.conj(analytic), rtol=1e-12)
    # And our reader gives the bank back.
    back = read_aot_filter(out, "HO")
    np.testing.assert_allclose(back.b, bank.b, rtol=1e-15)
    np.testing.assert_allclose(back.a, bank.a, rtol=1e-15)


def test_unmarked_filters_old_files_and_rtc_arrays(tmp_path):
    # Files without our TFCONV keyword: read by aotpy's formula; the rows an RTC keeps (a
    # difference equation in powers of z^-1, as SPARTA's A/B terms that aotpy's ESO
    # translators copy) with convention="z^-1"; a file aocontrol wrote before issue 30
    # (images "<LOOP> TIME_FILTER_NUM/DEN", rows in z^-1) in z^-1, with a warning.
    g = 0.3
    path, loop, tel, src = _filter_file(tmp_path)
    for name, num, den in (("TERMS", [g, 0.0], [1.0, -1.0]), ("HO", [g], [1.0, -1.0])):
        loop.time_filter_num = aotpy.Image(f"{name} TIME_FILTER_NUM", np.array([num]))
        loop.time_filter_den = aotpy.Image(f"{name} TIME_FILTER_DEN", np.array([den]))
        _system([loop], tel, src).write_to_file(tmp_path / f"{name}.fits")
    foreign = tmp_path / "TERMS.fits"
    # aotpy's formula: g / (1 - z) = -g z^-1 / (1 - z^-1).
    formula = read_aot_filter(foreign)
    np.testing.assert_allclose(formula.b, [[0.0, -g]], atol=1e-15)
    np.testing.assert_allclose(formula.a, [[1.0, -1.0]])
    rtc = read_aot_filter(foreign, convention="z^-1")
    np.testing.assert_allclose(rtc.b, [[g, 0.0]])  # as stored (z^-1 rows are not trimmed)
    np.testing.assert_allclose(rtc.a, [[1.0, -1.0]])
    with pytest.warns(UserWarning, match="written by aocontrol before it stated its convention"):
        old = read_aot_filter(tmp_path / "HO.fits")
    np.testing.assert_allclose(old.b, [[g]])
    np.testing.assert_allclose(old.a, [[1.0, -1.0]])
    # A row that the formula makes non-causal names the other convention.
    loop.time_filter_num = aotpy.Image("N", np.array([[g, 0.1, 0.2]]))
    loop.time_filter_den = aotpy.Image("D", np.array([[1.0, -1.0]]))
    _system([loop], tel, src).write_to_file(tmp_path / "long.fits")
    with pytest.raises(AOTError, match=r"not causal.*convention='z\^-1'"):
        read_aot_filter(tmp_path / "long.fits")
    with pytest.raises(ValueError, match=r"convention must be one of \['z', 'z\^-1'\]"):
        read_aot_filter(foreign, convention="z+1")
