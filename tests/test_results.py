"""Results files: HDF5 layout (xarray, h5py), round trips, atomic writes, npz conversion."""

import dataclasses
import json
import subprocess
import sys

import h5py
import numpy as np
import pytest
import xarray as xr

import aocontrol
from aocontrol.controllers import Integrator
from aocontrol.sim import LoopResult, ModalTimeSeries, ScienceResult, Stage, run_loop
from aocontrol.study import results
from aocontrol.study.results import (
    convert_npz,
    flatten_settings,
    load_result,
    read_psds,
    read_settings,
    save_result,
    summary_table,
)

FS = 1000.0
SETTINGS = {
    "case": {"name": "bright1_best", "seeing_arcsec": 0.55, "stage2": {"fs_hz": 3000.0}},
    "controller": {"name": "integrator", "gain": 0.4, "parameters": [0.4, 0.0]},
    "scheme": "single",
    "seed": 7,
    "quick": True,
}


def _science(n_bins=12, strehl=0.8):
    radii = np.arange(n_bins) * 0.5 + 0.25
    return ScienceResult(
        strehl=strehl,
        mean_contrast_4_6=3e-4,
        radii_ld=radii,
        contrast_profile=1e-2 * np.exp(-radii),
        n_frames=50,
        wavelength=1.65e-6,
        coronagraph=True,
    )


def _loop(n_frames=600, n_modes=3, seed=0, gain=0.4):
    rng = np.random.default_rng(seed)
    d = np.cumsum(rng.standard_normal((n_frames, n_modes)), axis=0)  # random walk [nm]
    res = run_loop(
        Stage(Integrator(gain, fs=FS, n_modes=n_modes), latency_frames=0.5),
        ModalTimeSeries(d),
        n_frames,
        metadata={"case": "test"},
    )
    return dataclasses.replace(res, science=_science())


def _assert_loop_equal(a, b, telemetry=True):
    assert (a.fs, a.n_frames, a.settle_frames) == (b.fs, b.n_frames, b.settle_frames)
    for name in ("residual_variance", "disturbance_variance", "saturation"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    if telemetry:
        assert sorted(a.telemetry) == sorted(b.telemetry)
        for k in a.telemetry:
            np.testing.assert_array_equal(a.telemetry[k], b.telemetry[k])
    sa, sb = a.science, b.science
    assert (sa.strehl, sa.mean_contrast_4_6, sa.n_frames) == (
        sb.strehl,
        sb.mean_contrast_4_6,
        sb.n_frames,
    )
    np.testing.assert_array_equal(sa.radii_ld, sb.radii_ld)
    np.testing.assert_array_equal(sa.contrast_profile, sb.contrast_profile)
    assert a.metadata == b.metadata


def test_loop_round_trip_with_telemetry_is_exact(tmp_path):
    res = _loop()
    path = save_result(res, tmp_path / "run.h5", settings=SETTINGS, telemetry=True)
    back = aocontrol.load_result(path)
    assert isinstance(back, LoopResult)
    _assert_loop_equal(res, back)
    assert back.telemetry["residuals"].dtype == np.float32
    assert read_settings(path) == SETTINGS


def test_without_telemetry_the_psds_are_kept(tmp_path):
    res = _loop()
    path = save_result(res, tmp_path / "run.h5", settings=SETTINGS)
    back = load_result(path)
    assert back.telemetry == {}
    _assert_loop_equal(res, back, telemetry=False)
    freqs, psds = read_psds(path)
    f_ref, p_ref = res.psd("residuals", nperseg=results.PSD_NPERSEG)
    np.testing.assert_array_equal(freqs, f_ref)
    np.testing.assert_array_equal(psds["residuals"], p_ref)
    # Oracle (one-sided density convention): the PSD integrates to the residual variance
    # about the mean. The loop's statistic is the mean square; with a random walk the
    # residual mean is small but not zero, and Welch's Hann window leaks: 10 % tolerance.
    resid = res.telemetry["residuals"][res.settle_frames :].astype(float)
    var = resid.var(axis=0)
    np.testing.assert_allclose(np.trapezoid(psds["residuals"], freqs, axis=1), var, rtol=0.1)


def test_xarray_opens_the_file_with_dimensions_and_units(tmp_path):
    res = _loop(n_frames=400, n_modes=4)
    path = save_result(res, tmp_path / "run.h5", settings=SETTINGS, telemetry=True)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert ds["residual_psd"].dims == ("mode", "frequency")
        assert ds["telemetry_residuals"].dims == ("frame", "mode")
        assert ds["contrast_profile"].dims == ("radius",)
        assert ds.sizes["mode"] == 4 and ds.sizes["frame"] == 400
        assert ds["frequency"].attrs["units"] == "Hz"
        assert ds["residual_psd"].attrs["units"] == "nm^2/Hz"
        assert ds["radius"].attrs["units"] == "lambda/D"
        assert ds["residual_variance"].attrs["units"] == "nm^2"
        # Settings as root attributes, nested keys flattened (COMPASS convention).
        assert ds.attrs["case.name"] == "bright1_best"
        assert ds.attrs["case.stage2.fs_hz"] == 3000.0
        assert ds.attrs["seed"] == 7
        assert ds.attrs["software_version"] == aocontrol.__version__
        assert ds.attrs["strehl"] == 0.8
        np.testing.assert_array_equal(ds["residual_variance"].values, res.residual_variance)


def test_without_telemetry_the_file_still_has_the_readmes_four_dimensions(tmp_path):
    # The README: xarray.open_dataset("run.h5") opens a file written without telemetry with
    # the named dimensions frame, mode, frequency and radius (issue 33).
    res = _loop(n_frames=400, n_modes=4)
    path = save_result(res, tmp_path / "run.h5", settings=SETTINGS)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert {"frame", "mode", "frequency", "radius"} <= set(ds.sizes)
        assert ds.sizes["frame"] == 400 and ds["residual_rms"].dims == ("frame",)
        assert ds["residual_rms"].attrs["units"] == "nm"
        assert not any(name.startswith("telemetry_") for name in ds.variables)
        # Oracle: each frame's RMS is the root of the sum of squares of its modal residual.
        e = res.telemetry["residuals"].astype(float)
        np.testing.assert_allclose(
            ds["residual_rms"].values, np.sqrt((e**2).sum(axis=1)), rtol=1e-6
        )
        d = res.telemetry["disturbance"].astype(float)
        np.testing.assert_allclose(
            ds["disturbance_rms"].values, np.sqrt((d**2).sum(axis=1)), rtol=1e-6
        )


def test_plain_h5py_reads_it(tmp_path):
    res = _loop()
    path = save_result(res, tmp_path / "run.h5", settings=SETTINGS)
    with h5py.File(path, "r") as fh:
        assert fh.attrs["kind"] == "loop"
        assert json.loads(fh.attrs["settings_json"]) == SETTINGS
        np.testing.assert_array_equal(fh["saturation"][()], res.saturation)
        assert fh.attrs["residual_rms_nm"] == pytest.approx(res.residual_rms, rel=1e-15)


def test_cascade_has_one_group_per_stage(tmp_path):
    cls = aocontrol.sim.CascadeResult
    s1 = dataclasses.replace(_loop(n_modes=5, seed=1), science=None)
    s2 = dataclasses.replace(_loop(n_modes=3, seed=2, gain=0.3), science=None)
    fields = dict(scheme="dcao", stages=(s1, s2), science=_science(strehl=0.9), metadata={}, fs=FS)
    casc = cls(**fields)
    path = save_result(casc, tmp_path / "casc.h5", settings=SETTINGS, telemetry=True)
    with xr.open_dataset(path, group="stage1") as ds:  # engine found from the file
        assert ds.sizes["mode"] == 5
    with xr.open_dataset(path, engine="h5netcdf", group="stage2") as ds:
        assert ds.sizes["mode"] == 3
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert ds.attrs["scheme"] == "dcao" and ds["strehl"].values == 0.9
        assert ds.attrs["residual_rms_nm"] == pytest.approx(s2.residual_rms, rel=1e-15)
    back = load_result(path)
    assert type(back) is cls and back.scheme == "dcao"
    for a, b in zip(casc.stages, back.stages, strict=True):
        np.testing.assert_array_equal(a.residual_variance, b.residual_variance)
        np.testing.assert_array_equal(a.telemetry["commands"], b.telemetry["commands"])
    np.testing.assert_array_equal(back.science.contrast_profile, casc.science.contrast_profile)


def test_interrupted_write_leaves_no_file(tmp_path, monkeypatch):
    # Inject a failure inside the write: the fourth variable raises after three were written.
    real = results._write_variable
    calls = []

    def failing(group, name, *args, **kwargs):
        calls.append(name)
        if len(calls) == 4:
            raise OSError("disk full (injected)")
        return real(group, name, *args, **kwargs)

    monkeypatch.setattr(results, "_write_variable", failing)
    with pytest.raises(OSError, match="injected"):
        save_result(_loop(), tmp_path / "run.h5", settings=SETTINGS)
    assert len(calls) == 4
    assert list(tmp_path.iterdir()) == []


def test_npz_results_are_read_and_converted(tmp_path):
    res = _loop()
    with pytest.warns(DeprecationWarning, match="convert_npz"):
        res.save(tmp_path / "old.npz")
    direct = load_result(tmp_path / "old.npz")
    assert isinstance(direct.science, ScienceResult)
    path = convert_npz(tmp_path / "old.npz", tmp_path / "new.h5")
    back = load_result(path)
    _assert_loop_equal(res, back)
    assert read_settings(path) == res.metadata


def test_summary_table_rebuilds_one_row_per_file(tmp_path):
    paths = []
    for seed in (1, 2, 3):
        settings = dict(SETTINGS, seed=seed)
        res = dataclasses.replace(_loop(seed=seed), science=_science(strehl=0.5 + seed / 10))
        paths.append(save_result(res, tmp_path / f"r{seed}.h5", settings=settings))
    rows = summary_table(paths)
    assert [r["seed"] for r in rows] == [1, 2, 3]
    assert [r["strehl"] for r in rows] == pytest.approx([0.6, 0.7, 0.8], rel=1e-15)
    assert all(r["case.name"] == "bright1_best" and r["kind"] == "loop" for r in rows)


def test_flatten_settings_types():
    flat = flatten_settings({"a": {"b": True, "c": None, "d": [1, 2]}, "e": ["x", 1], "f": 2.5})
    assert flat["a.b"] == 1 and "a.c" not in flat
    np.testing.assert_array_equal(flat["a.d"], [1.0, 2.0])
    assert json.loads(flat["e"]) == ["x", 1] and flat["f"] == 2.5


def test_not_a_results_file_is_a_clear_error(tmp_path):
    with h5py.File(tmp_path / "x.h5", "w") as fh:
        fh.attrs["format"] = "other"
    with pytest.raises(ValueError, match="not an aocontrol results file"):
        load_result(tmp_path / "x.h5")
    (tmp_path / "y.h5").write_text("not hdf5")
    with pytest.raises(OSError, match="not a readable HDF5 file"):
        load_result(tmp_path / "y.h5")


def test_top_level_load_result_is_lazy():
    # The control layer stays importable alone: `import aocontrol` must not import the
    # simulator or the study layer; `aocontrol.load_result` imports them on first use.
    code = (
        "import sys, aocontrol; "
        "assert not any(m.startswith(('aocontrol.sim', 'aocontrol.study')) for m in sys.modules); "
        "f = aocontrol.load_result; assert 'aocontrol.study.results' in sys.modules"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_the_layout_stores_every_field_of_the_result_types():
    # A field added to LoopResult / CascadeResult must be added to the file layout too.
    assert {f.name for f in dataclasses.fields(LoopResult)} == results._LOOP_FIELDS
    cascade = aocontrol.sim.CascadeResult
    assert {f.name for f in dataclasses.fields(cascade)} == results._CASCADE_FIELDS
