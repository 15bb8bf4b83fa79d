"""Controller export for a real-time computer (aocontrol.io.export_controller): FITS and CSV."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from aocontrol.controllers import IIRBank, Integrator
from aocontrol.io import export_controller, iir_coefficients, read_exported_controller
from aocontrol.plant import loop_plant
from aocontrol.synthesis import lqg

FS = 1000.0
N_MODES = 4
# Two floating-point implementations of the same recursion on O(1) data: rounding only.
TOL = 1e-12


def _stable_bank(rng: np.random.Generator, order: int = 5) -> IIRBank:
    """Random stable IIR filters of ``order`` (poles inside radius 0.9), one per mode."""
    rows_b, rows_a = [], []
    for _ in range(N_MODES):
        radius = rng.uniform(0.2, 0.9, order)
        angle = rng.uniform(0, np.pi, order)
        poles = radius * np.exp(1j * angle)
        a = np.real(np.poly(np.concatenate([poles[: order // 2], poles[: order // 2].conj()])))
        a = np.convolve(a, [1.0, -radius[-1]]) if order % 2 else a
        rows_a.append(a)
        rows_b.append(rng.normal(size=order + 1))
    return IIRBank(np.array(rows_b), np.array(rows_a), FS)


def _direct_form_one(b: np.ndarray, a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Independent Direct Form I: u[k] = sum b_i m[k-i] - sum_{i>=1} a_i u[k-i], per mode.

    Plain loops over frames and taps (what an RTC does), vectorised over modes only.
    """
    n_frames, n_modes = m.shape
    u = np.zeros((n_frames, n_modes))
    for k in range(n_frames):
        acc = np.zeros(n_modes)
        for i in range(b.shape[1]):
            if k - i >= 0:
                acc += b[:, i] * m[k - i]
        for i in range(1, a.shape[1] + 1):
            if k - i >= 0:
                acc -= a[:, i - 1] * u[k - i]
        u[k] = acc
    return u


def _columns(exp_path: str) -> tuple[np.ndarray, np.ndarray]:
    """The b and a columns of an export, read without our reader (FITS or CSV)."""
    if exp_path.endswith(".csv"):
        names = open(exp_path).readline().strip().split(",")
        table = np.loadtxt(exp_path, delimiter=",", skiprows=1, ndmin=2)
    else:
        from astropy.io import fits

        with fits.open(exp_path) as hdul:
            data = hdul["AOCONTROL_IIR"].data
            names = [n.lower() for n in data.columns.names]
            table = np.column_stack([np.asarray(data[n], dtype=float) for n in data.columns.names])
    b = table[:, [j for j, n in enumerate(names) if n[0] == "b"]]
    a = table[:, [j for j, n in enumerate(names) if n[0] == "a"]]
    return b, a


@pytest.mark.parametrize("ext", [".fits", ".csv"])
@pytest.mark.parametrize("kind", ["iir", "integrator", "lqg"])
def test_independent_direct_form_one_on_exported_coefficients_matches_step(tmp_path, ext, kind):
    # Oracle: the exported coefficients, read back without our reader and run by a plain DF-I
    # loop written here, give the bank's real-time commands to rounding.
    rng = np.random.default_rng(11)
    plant = loop_plant(FS, 0.3)
    if kind == "iir":
        bank = _stable_bank(rng)
    elif kind == "integrator":
        bank = Integrator(np.linspace(0.2, 0.5, N_MODES), fs=FS, n_modes=N_MODES)
    else:
        f = np.linspace(0.0, FS / 2, 513)
        psd = 1.0 / (1.0 + (f[None, :] / np.array([5.0, 10.0, 20.0, 40.0])[:, None]) ** 2)
        bank = lqg(plant, f, psd, noise_psd=1e-3, n_vibrations=0)
    path = export_controller(
        bank, tmp_path / f"k{ext}", latency_frames=0.3, modulus_margin=np.full(N_MODES, 0.6)
    )
    b, a = _columns(path)
    m = rng.normal(size=(400, N_MODES))
    bank.reset()
    expected = np.array([bank.step(x) for x in m])
    got = _direct_form_one(b, a, m)
    assert np.max(np.abs(got - expected)) <= TOL * max(1.0, np.max(np.abs(expected)))
    # Twin: a coefficient off by 1e-6 is seen.
    b_bad = b.copy()
    b_bad[0, 0] += 1e-6
    assert np.max(np.abs(_direct_form_one(b_bad, a, m) - expected)) > 100 * TOL


@pytest.mark.parametrize("ext", [".fits", ".csv"])
def test_reader_round_trip_is_exact(tmp_path, ext):
    # Oracle: 17 significant digits (CSV) and float64 columns (FITS) round-trip exactly.
    bank = _stable_bank(np.random.default_rng(3))
    lat = np.array([0.5, 0.5, 0.5, 0.5])
    mar = np.array([0.51, 0.62, 0.73, 0.84])
    exp = read_exported_controller(
        export_controller(bank, tmp_path / f"k{ext}", latency_frames=lat, modulus_margin=mar)
    )
    np.testing.assert_array_equal(exp.bank.b, bank.b)
    np.testing.assert_array_equal(exp.bank.a, bank.a)
    assert exp.bank.fs == FS
    np.testing.assert_array_equal(exp.modes, np.arange(N_MODES))
    np.testing.assert_array_equal(exp.latency_frames, lat)
    np.testing.assert_array_equal(exp.modulus_margin, mar)


def test_fits_layout_is_documented_columns(tmp_path):
    from astropy.io import fits

    bank = Integrator(0.4, fs=FS, n_modes=2)
    path = export_controller(bank, tmp_path / "k.fits")
    with fits.open(path) as hdul:
        hdu = hdul["AOCONTROL_IIR"]
        assert hdu.columns.names == ["MODE", "B0", "A1", "FS", "LATENCY", "MARGIN"]
        assert hdu.header["IIRFORM"] == "DF1" and hdu.header["NB"] == 1 and hdu.header["NA"] == 2
        assert np.all(np.isnan(hdu.data["MARGIN"]))  # unknown margin: nan, not a made-up 0


def test_iir_coefficients_of_a_state_space_bank_have_its_response():
    # Oracle: the exported polynomials' frequency response equals the LQG's transfer function.
    plant = loop_plant(FS, 0.3)
    f = np.linspace(0.0, FS / 2, 257)
    bank = lqg(plant, f, 1.0 / (1.0 + (f / 8.0) ** 2), noise_psd=1e-2, n_vibrations=0)
    b, a = iir_coefficients(bank)
    w = 2 * np.pi * f[1:-1] / FS
    _, h = signal.freqz(b[0], a[0], worN=w)
    tf = bank.transfer_function(0)
    ref = np.array([complex(tf(np.exp(1j * x))) for x in w])
    assert np.max(np.abs(h - ref)) < 1e-9 * np.max(np.abs(ref))


def test_export_is_whole_or_nothing(tmp_path, monkeypatch):
    from astropy.io import fits

    bank = Integrator(0.4, fs=FS, n_modes=3)
    with pytest.raises(ValueError, match=r"modulus_margin.*\(3,\)"):
        export_controller(bank, tmp_path / "k.fits", modulus_margin=[0.5, 0.5])
    with pytest.raises(ValueError, match=r"extension '\.txt'.*\.csv"):
        export_controller(bank, tmp_path / "k.txt")

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(fits.HDUList, "writeto", boom)
    with pytest.raises(OSError, match="disk full"):
        export_controller(bank, tmp_path / "k.fits")
    assert list(tmp_path.iterdir()) == []  # neither the file nor a temporary


def test_reader_names_the_file_and_the_missing_columns(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("mode,b0,fs\n0,0.5,1000\n")
    with pytest.raises(ValueError, match=r"bad\.csv.*\['latency', 'margin'\] missing"):
        read_exported_controller(bad)
    with pytest.raises(FileNotFoundError, match="nope.csv"):
        read_exported_controller(tmp_path / "nope.csv")
