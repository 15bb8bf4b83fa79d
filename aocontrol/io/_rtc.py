"""Controller export for a real-time computer: one FITS table or a plain CSV.

Layout (both formats, one row per mode)::

    MODE  B0 .. Bn  A1 .. An  FS  LATENCY  MARGIN

* ``MODE`` (int): mode index.
* ``B0 .. Bn``, ``A1 .. An`` (float64): the mode's filter in Direct Form I, powers of
  ``z^-1``, ``a_0 = 1`` implied (not stored)::

      u[k] = sum_{i=0}^{n} b_i m[k-i] - sum_{i=1}^{n} a_i u[k-i]

  with ``m`` the modal measurement and ``u`` the modal command of the same frame (the
  convention of :class:`aocontrol.controllers.IIRBank`). Shorter filters are zero-padded:
  ``n`` is the largest order of the bank (numerator and denominator may have different
  lengths: ``nb - 1`` and ``na - 1``).
* ``FS`` [Hz]: loop rate. ``LATENCY`` [frames]: the RTC latency beyond the one-frame WFS
  integration the controller was designed for (``nan`` if unknown). ``MARGIN``: modulus
  margin ``min |1 + G K|`` certified for that plant (``nan`` if unknown).

FITS: a binary table HDU named ``AOCONTROL_IIR`` (columns as above, upper case), its header
stating ``NB``, ``NA`` and the convention (``IIRFORM = 'DF1'``, ``IIRCONV``). CSV: one header
line ``mode,b0,..,bn,a1,..,an,fs,latency,margin``, values printed with 17 significant digits
(``repr`` round trip), no comment lines. Files are written whole or not at all
(:mod:`aocontrol._atomic`).
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass

import numpy as np

from aocontrol._atomic import atomic_path
from aocontrol._validation import check_broadcast, check_finite_array
from aocontrol.controllers import ControllerBank, IIRBank
from aocontrol.plant import z_inverse_coefficients

__all__ = [
    "EXPORT_FORMATS",
    "ExportedController",
    "export_controller",
    "iir_coefficients",
    "read_exported_controller",
]

#: File formats of :func:`export_controller` (by extension).
EXPORT_FORMATS = {".fits": "fits", ".fit": "fits", ".csv": "csv"}
# FITS table name of the export.
_EXTNAME = "AOCONTROL_IIR"


def iir_coefficients(bank: ControllerBank) -> tuple[np.ndarray, np.ndarray]:
    """Direct Form I coefficients of a linear bank, ``(b, a)`` in powers of ``z^-1``.

    An :class:`~aocontrol.controllers.IIRBank` (integrators included) gives its own rows;
    any other bank with a ``transfer_function(mode)`` (LQG, the MPC's unconstrained
    equivalent) gives that transfer function's coefficients, zero-padded to a common length.

    Parameters
    ----------
    bank : ControllerBank
        A linear bank.

    Returns
    -------
    b : ndarray, shape (n_modes, nb)
    a : ndarray, shape (n_modes, na), ``a[:, 0] == 1``

    Raises
    ------
    TypeError
        A bank without a transfer function.
    """
    if isinstance(bank, IIRBank):
        return np.array(bank.b), np.array(bank.a)
    if not isinstance(bank, ControllerBank):
        raise TypeError(f"bank must be a ControllerBank, got {type(bank).__name__}")
    rows = [
        z_inverse_coefficients(bank.transfer_function(i), f"controller mode {i}")
        for i in range(bank.n_modes)
    ]
    nb = max(r[0].size for r in rows)
    na = max(r[1].size for r in rows)
    b = np.array([np.pad(r[0] / r[1][0], (0, nb - r[0].size)) for r in rows])
    a = np.array([np.pad(r[1] / r[1][0], (0, na - r[1].size)) for r in rows])
    return b, a


@dataclass(frozen=True, eq=False)
class ExportedController:
    """A controller read back from an export (:func:`read_exported_controller`).

    Attributes
    ----------
    bank : IIRBank
        The filters, ready to run (``bank.step``).
    modes : ndarray of int, shape (n_modes,)
        The ``MODE`` column.
    latency_frames : ndarray, shape (n_modes,)
        The ``LATENCY`` column [frames].
    modulus_margin : ndarray, shape (n_modes,)
        The ``MARGIN`` column.
    """

    bank: IIRBank
    modes: np.ndarray
    latency_frames: np.ndarray
    modulus_margin: np.ndarray


def _format(path: str, fmt: str | None) -> str:
    if fmt is not None:
        if fmt not in ("fits", "csv"):
            raise ValueError(f"format must be 'fits' or 'csv', got {fmt!r}")
        return fmt
    ext = os.path.splitext(path)[1].lower()
    if ext not in EXPORT_FORMATS:
        raise ValueError(
            f"path {path!r}: extension {ext!r} does not say the format; expected one of "
            f"{sorted(EXPORT_FORMATS)} or format='fits'/'csv'"
        )
    return EXPORT_FORMATS[ext]


def _columns(nb: int, na: int) -> list[str]:
    return ["mode", *(f"b{i}" for i in range(nb)), *(f"a{i}" for i in range(1, na)), "fs"] + [
        "latency",
        "margin",
    ]


def export_controller(
    bank: ControllerBank,
    path: str | os.PathLike,
    *,
    latency_frames: float | np.ndarray = np.nan,
    modulus_margin: float | np.ndarray = np.nan,
    format: str | None = None,
) -> str:
    """Write a controller bank for a real-time computer (module docstring: the layout).

    Parameters
    ----------
    bank : ControllerBank
        An IIR bank, or any linear bank (:func:`iir_coefficients`).
    path : str or os.PathLike
        Output file (``.fits`` or ``.csv`` unless ``format`` is given). Written atomically.
    latency_frames : float or array of shape (n_modes,), default nan
        RTC latency the design assumed [frames].
    modulus_margin : float or array of shape (n_modes,), default nan
        Certified modulus margin per mode.
    format : {"fits", "csv"}, optional
        Overrides the extension.

    Returns
    -------
    str
        The path written.
    """
    path = os.fspath(path)
    fmt = _format(path, format)
    b, a = iir_coefficients(bank)
    n = b.shape[0]
    lat = check_broadcast(
        "latency_frames",
        np.asarray(latency_frames, dtype=float),
        (n,),
        f"scalar or (n_modes,) = ({n},)",
    )
    mar = check_broadcast(
        "modulus_margin",
        np.asarray(modulus_margin, dtype=float),
        (n,),
        f"scalar or (n_modes,) = ({n},)",
    )
    names = _columns(b.shape[1], a.shape[1])
    table = np.column_stack(
        [np.arange(n), b, a[:, 1:], np.full(n, float(bank.fs)), lat, mar]
    ).astype(float)
    with atomic_path(path, suffix="." + fmt) as tmp:
        if fmt == "csv":
            with open(tmp, "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(names)
                for row in table:
                    w.writerow([str(int(row[0]))] + [repr(float(x)) for x in row[1:]])
        else:
            from astropy.io import fits

            cols = [fits.Column(name="MODE", format="J", array=np.arange(n, dtype=np.int32))]
            cols += [
                fits.Column(name=name.upper(), format="D", array=table[:, j])
                for j, name in enumerate(names)
                if j > 0
            ]
            hdu = fits.BinTableHDU.from_columns(cols, name=_EXTNAME)
            hdu.header["NB"] = (b.shape[1], "numerator taps B0..B(NB-1)")
            hdu.header["NA"] = (a.shape[1], "denominator taps, A0 = 1 not stored")
            hdu.header["IIRFORM"] = ("DF1", "Direct Form I, powers of z^-1")
            hdu.header["IIRCONV"] = ("u[k]=sum b_i m[k-i]-sum_{i>=1} a_i u[k-i]", "")
            hdu.header["FS_UNIT"] = ("Hz", "unit of column FS")
            hdu.header["LAT_UNIT"] = ("frame", "unit of LATENCY (beyond WFS integration)")
            fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(tmp, overwrite=True)
    return path


def _split(names: list[str], table: np.ndarray, path: str) -> ExportedController:
    lower = [x.lower() for x in names]
    need = ("mode", "b0", "fs", "latency", "margin")
    missing = [c for c in need if c not in lower]
    if missing:
        raise ValueError(
            f"controller export {path!r}: columns {missing} missing; expected mode, b0..bn, "
            "a1..an, fs, latency, margin"
        )
    col = {name: table[:, i] for i, name in enumerate(lower)}
    nb = sum(1 for x in lower if x.startswith("b") and x[1:].isdigit())
    na = 1 + sum(1 for x in lower if x.startswith("a") and x[1:].isdigit())
    b = np.column_stack([col[f"b{i}"] for i in range(nb)])
    a = np.column_stack([np.ones(table.shape[0])] + [col[f"a{i}"] for i in range(1, na)])
    fs = col["fs"]
    if fs.size == 0 or not np.all(fs == fs[0]):
        raise ValueError(f"controller export {path!r}: column fs must hold one rate, got {fs}")
    b = check_finite_array(f"b columns of {path!r}", b)
    a = check_finite_array(f"a columns of {path!r}", a)
    return ExportedController(
        bank=IIRBank(b, a, float(fs[0])),
        modes=col["mode"].astype(int),
        latency_frames=col["latency"],
        modulus_margin=col["margin"],
    )


def read_exported_controller(
    path: str | os.PathLike, *, format: str | None = None
) -> ExportedController:
    """Read a file written by :func:`export_controller`.

    Parameters
    ----------
    path : str or os.PathLike
        The export (``.fits`` or ``.csv``).
    format : {"fits", "csv"}, optional
        Overrides the extension.

    Returns
    -------
    ExportedController

    Raises
    ------
    ValueError
        Missing columns, several rates, non-finite coefficients, an unknown format; the
        message names the file.
    """
    path = os.fspath(path)
    fmt = _format(path, format)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"controller export {path!r} does not exist")
    if fmt == "csv":
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
        if len(rows) < 2:
            raise ValueError(f"controller export {path!r}: a header line and one row per mode")
        try:
            table = np.array([[float(x) for x in r] for r in rows[1:]])
        except ValueError as exc:
            raise ValueError(f"controller export {path!r}: non-numeric value ({exc})") from exc
        if table.ndim != 2 or table.shape[1] != len(rows[0]):
            raise ValueError(f"controller export {path!r}: rows must have {len(rows[0])} values")
        return _split(rows[0], table, path)
    from astropy.io import fits

    with fits.open(path) as hdul:
        if _EXTNAME not in hdul:
            raise ValueError(f"controller export {path!r} has no {_EXTNAME} table")
        data = hdul[_EXTNAME].data
        names = list(data.columns.names)
        table = np.column_stack([np.asarray(data[n], dtype=float) for n in names])
    return _split(names, table, path)
