"""Plots: every function writes a non-blank PNG with labelled axes (units) and log scales."""

import matplotlib

matplotlib.use("Agg")  # tests choose the backend; the library never does

import matplotlib.image as mpimg
import numpy as np
import pytest

from aocontrol.analysis import margins, sensitivity
from aocontrol.controllers import Integrator
from aocontrol.plant import loop_plant
from aocontrol.sim import ScienceCamera, ScienceResult, vlt_pupil
from aocontrol.study import plot

FS = 1000.0
FREQS = np.linspace(0.0, FS / 2, 400)


def _png_ok(path):
    """The PNG exists and is not blank (its pixels vary)."""
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert float(img[..., :3].std()) > 0.01
    return img


def _labelled(ax):
    # Units in brackets on both axes.
    assert "[" in ax.get_xlabel() and "]" in ax.get_xlabel(), ax.get_xlabel()
    assert "[" in ax.get_ylabel() and "]" in ax.get_ylabel(), ax.get_ylabel()


def _controllers():
    plant = loop_plant(FS, 0.5)
    ctrls = {"g=0.3": Integrator(0.3, fs=FS), "g=0.6": Integrator(0.6, fs=FS)}
    return plant, ctrls


def test_sensitivity_plot(tmp_path):
    plant, ctrls = _controllers()
    S = {k: sensitivity(plant, c, FREQS)[0] for k, c in ctrls.items()}
    psd = 1e3 / (1.0 + (FREQS / 5.0) ** (11 / 3))
    fig = plot.plot_sensitivity(
        FREQS,
        S,
        disturbance_psd=psd,
        noise_psd=0.1,
        modulus_margin=0.5,
        path=tmp_path / "s.png",
    )
    _png_ok(tmp_path / "s.png")
    ax_s, ax_t = fig.axes[0], fig.axes[1]
    _labelled(ax_t)
    assert ax_s.get_ylabel() == r"$|S|$ [dB]" and ax_t.get_ylabel() == r"$|T|$ [dB]"
    assert ax_s.get_xscale() == "log"
    # Oracle: the drawn T is 1 - S, so at low frequency (integrator: S -> 0) |T| -> 0 dB.
    t_line = ax_t.get_lines()[0].get_ydata()
    assert abs(t_line[0]) < 0.5
    # Half-frame latency: G(-1) = 0, so T = 0 at Nyquist (-240 dB at the floor); the axis
    # stops at -80 dB so that the notch does not squash the useful range.
    assert t_line[-1] < -200
    assert ax_t.get_ylim()[0] == -80.0
    # The disturbance PSD is on a log twin axis.
    assert any(a.get_yscale() == "log" and "disturbance" in a.get_ylabel() for a in fig.axes)


def test_rejection_and_residual_psd_plots(tmp_path):
    plant, ctrls = _controllers()
    S = {k: sensitivity(plant, c, FREQS)[0] for k, c in ctrls.items()}
    fig = plot.plot_rejection(FREQS, S, psd=np.ones_like(FREQS), path=tmp_path / "r.png")
    _png_ok(tmp_path / "r.png")
    assert fig.axes[0].get_xscale() == "log"
    psd2d = np.ones((3, FREQS.size))
    fig = plot.plot_residual_psd(FREQS, {"a": psd2d, "b": psd2d[0] * 2}, path=tmp_path / "p.png")
    _png_ok(tmp_path / "p.png")
    ax = fig.axes[0]
    _labelled(ax)
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    # A 2-D PSD is summed over modes: 3 modes of unit PSD draw a line at 3.
    np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), 3.0)


def test_contrast_plot_takes_arrays_and_results(tmp_path):
    radii = np.arange(1, 20) * 0.5
    prof = 1e-2 * np.exp(-radii)
    prof[0] = 1e-14  # the perfect coronagraph's dark core
    sci = ScienceResult(0.8, 1e-4, radii, prof, n_frames=10)
    fig = plot.plot_contrast(None, {"result": sci}, path=tmp_path / "c.png")
    _png_ok(tmp_path / "c.png")
    ax = fig.axes[0]
    _labelled(ax)
    assert ax.get_yscale() == "log"
    # The axis is scaled on the halo beyond 1 lambda/D, not on the dark core.
    assert ax.get_ylim()[0] == pytest.approx(0.3 * prof[radii >= 1.0].min(), rel=1e-12)
    np.testing.assert_array_equal(ax.get_lines()[0].get_xdata(), radii)
    with pytest.raises(ValueError, match="radii_ld"):
        plot.plot_contrast(None, {"bare": np.ones(3)})


def test_images_plot(tmp_path):
    cam = ScienceCamera(vlt_pupil(32))
    exposure = cam.long_exposure()
    rng = np.random.default_rng(0)
    exposure.add(rng.standard_normal((4, 32, 32)) * 50.0)  # 50 nm RMS residual
    fig = plot.plot_images(
        {"PSF": exposure.psf, "coronagraph": exposure.coronagraphic},
        pixel_scale=cam.pixel_scale,
        path=tmp_path / "i.png",
    )
    _png_ok(tmp_path / "i.png")
    ax = fig.axes[0]
    _labelled(ax)
    # Oracle: the extent is the image size times the pixel scale, centred on the star.
    x0, x1, _, _ = ax.get_images()[0].get_extent()
    assert x1 - x0 == pytest.approx(cam.n_image * cam.pixel_scale, rel=1e-12)
    assert ax.get_images()[0].norm.__class__.__name__ == "LogNorm"


def test_margins_plot(tmp_path):
    plant, ctrls = _controllers()
    mar = {k: margins(plant, c) for k, c in ctrls.items()}
    fig = plot.plot_margins(mar, required_modulus_margin=0.5, path=tmp_path / "m.png")
    _png_ok(tmp_path / "m.png")
    assert [a.get_ylabel().split("\n")[0] for a in fig.axes] == [
        "gain margin [dB]",
        "phase margin [deg]",
        "modulus margin [1]",
        "delay margin [frames]",
    ]
    # The bars are the margins: the modulus panel's bar heights equal the computed values.
    heights = [p.get_height() for p in fig.axes[2].patches]
    np.testing.assert_allclose(heights, [m.modulus_margin for m in mar.values()])
    # Both sides of the intervals: gain up above zero, latency removed below zero.
    n = len(mar)
    gain = [p.get_height() for p in fig.axes[0].patches]
    np.testing.assert_allclose(gain[:n], [m.gain_margin_db for m in mar.values()])
    delay = [p.get_height() for p in fig.axes[3].patches]
    np.testing.assert_allclose(delay[:n], [m.delay_margin for m in mar.values()])
    np.testing.assert_allclose(delay[n:], [-m.delay_margin_removed for m in mar.values()])


def test_vibration_plot_reverse_cumulative(tmp_path):
    f = np.linspace(0.0, 500.0, 1001)
    white = np.full_like(f, 2.0)  # 2 nm^2/Hz up to 500 Hz: 1000 nm^2 in total
    fig = plot.plot_vibration(
        f,
        {"integrator": white},
        open_loop_psd=white * 10,
        vibration_hz=45.0,
        path=tmp_path / "v.png",
    )
    _png_ok(tmp_path / "v.png")
    ax_p, ax_c = fig.axes
    _labelled(ax_p)
    _labelled(ax_c)
    assert ax_p.get_yscale() == "log" and ax_c.get_xscale() == "log"
    # Oracle: for a flat PSD the RMS above f is sqrt(2 (500 - f)).
    line = next(ln for ln in ax_c.get_lines() if ln.get_label() == "integrator")
    np.testing.assert_allclose(
        line.get_ydata(), np.sqrt(2.0 * (500.0 - line.get_xdata())), rtol=1e-9, atol=1e-9
    )


def test_adapt_plot_draws_a_single_period_as_markers_and_the_fixed_design_as_a_line(tmp_path):
    # One period (the seeds study): every redesigning strategy is a visible marker at T, the
    # fixed design a horizontal line, each in its own colour.
    rows = [
        {"strategy": "fixed", "period": 1.0, "window": 1.0, "residual": 28.0},
        {"strategy": "adaptive", "period": 2.0, "window": 1.0, "residual": 22.5},
        {"strategy": "oracle", "period": 2.0, "window": 1.0, "residual": 22.2},
    ]
    fig = plot.plot_adapt({"wind": rows}, path=tmp_path / "adapt.png")
    ax = fig.axes[0]
    by_label = {line.get_label(): line for line in ax.get_lines()}
    for name, value in (("adaptive (W = 1 s)", 22.5), ("oracle (W = 1 s)", 22.2)):
        line = by_label[name]
        assert line.get_marker() == "o" and list(line.get_xdata()) == [2.0]
        assert list(line.get_ydata()) == [value]
    fixed = by_label["fixed (W = 1 s)"]
    assert list(fixed.get_ydata()) == [28.0, 28.0] and fixed.get_linestyle() == "--"
    assert len({str(line.get_color()) for line in by_label.values()}) == 3
    assert [t.get_text() for t in ax.get_xticklabels()] == ["2"]
    assert (tmp_path / "adapt.png").stat().st_size > 0


def test_robustness_plot_draws_each_controller_and_marks_a_diverged_run(tmp_path):
    # Two controllers under one error at two magnitudes, one run diverged: a line per
    # controller with the diverged point missing, a red cross at the axis' bottom, the
    # error's unit on the x axis; the loss on a log axis where it spans > 20x; a bad value
    # is named.
    rows = [{"case": "c", "error": "nominal", "label": "", "magnitude": 0.0,
             "controller": c, "status": "ok", "retained": 1.0, "loss": 1.0}
            for c in ("ref", "dd")]  # fmt: skip
    for c, (r1, r2) in {"ref": (0.9, 0.8), "dd": (0.95, None)}.items():
        for mag, r in ((1.0, r1), (2.0, r2)):
            rows.append({"case": "c", "error": "latency", "label": f"+{mag}", "magnitude": mag,
                         "unit": "frames", "controller": c,
                         "status": "ok" if r else "diverged", "retained": r or float("nan"),
                         "loss": 1.0 / r if r else float("nan")})  # fmt: skip
    fig = plot.plot_robustness(rows, path=tmp_path / "rob.png")
    _png_ok(tmp_path / "rob.png")
    ax = fig.axes[0]
    _labelled(ax)
    assert "frames" in ax.get_xlabel()
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert list(lines["ref"].get_ydata()) == [0.9, 0.8]
    dd = np.asarray(lines["dd"].get_ydata(), dtype=float)
    assert dd[0] == 0.95 and np.isnan(dd[1])
    crosses = [ln for ln in ax.get_lines() if ln.get_marker() == "x"]
    assert len(crosses) == 1 and list(crosses[0].get_xdata()) == [2.0]
    assert plot.plot_robustness(rows, value="loss").axes[0].get_yscale() == "linear"
    rows[2]["loss"] = 100.0  # a loss spanning more than 20x: a log axis
    assert plot.plot_robustness(rows, value="loss").axes[0].get_yscale() == "log"
    with pytest.raises(ValueError, match="value must be one of"):
        plot.plot_robustness(rows, value="strehl")
    with pytest.raises(ValueError, match="at least one model error"):
        plot.plot_robustness(rows[:2])
