"""A loop's temporal filter in AOT (``time_filter_num``/``time_filter_den``): the convention.

What the standard says. ``aotpy`` (the AOT reference implementation, ``aotpy.core.loop``)
documents the two fields as "one set of time filter numerators [denominators] per mode (one
row: every mode). The first numerator is the loop gain. Uses standard transfer function
``sys(z) = sum_{i=0}^{N-1} b_i z^i / sum_{j=0}^{N} a_j z^j``": ascending powers of ``z``,
written ``"z"`` here. Read literally, the formula and the sentence agree only for a filter one
frame later than the RTC's (``g / (z - 1)``, numerator ``[g]``, denominator ``[-1, 1]``).

What ESO's files hold. ``aotpy``'s translators copy the RTC's own arrays unchanged: ERIS,
GALACSI (AOF) and GPAO put SPARTA's ``A_TERMS`` in ``time_filter_num`` and ``B_TERMS`` in
``time_filter_den`` (transposed: one row per mode), NAOMI (SPARTA Light) its ``TERM_A`` and
``TERM_B``, PAPYRUS the loop gain alone (no denominator). SPARTA's terms are the coefficients
of a difference equation on the current and past samples, powers of ``z^-1`` (written
``"z^-1"`` here: the first numerator multiplies the current measurement, the loop gain of an
integrator ``g / (1 - z^-1)``); a public SPARTA Light (CIAO) script sets an integrator as
``TERM_B = g [-1, 0]`` and ``TERM_A = [-1]`` (the leading ``1`` implied, the sign of its
commands the other one), which is also the reverse of the A/B roles NAOMI's translator
assumes. So files translated from ESO instruments hold ``"z^-1"`` arrays in an unstated
order, not the formula's; the standard's text does not settle it, and the two readings of one
array have conjugate frequency responses (same magnitude, opposite phase: an integrator read
the other way is ``1 - z``, a negative gain and a frame of delay).

What we do. We write the documented formula (``"z"``, ascending powers of ``z``, numerator and
denominator of one length per row, the denominator monic in its highest power), so that a
reader following ``aotpy``'s documentation finds our filter's response, and we state it in
both images' headers (``TFCONV``, :data:`TFCONV_KEY`). We read a file's own ``TFCONV``; a
file without one is read by the formula unless the caller says ``convention="z^-1"`` (files
from SPARTA-based systems), except the files aocontrol wrote before the marker (images named
``"<LOOP> TIME_FILTER_NUM"``/``"..._DEN"``, rows in ``"z^-1"``), read in ``"z^-1"`` with a
warning. A numerator without a denominator is an integrator of that gain, ``g / (1 - z^-1)``,
in either convention (AOT: "the first numerator is the loop gain"; PAPYRUS writes so).

Our RTC export (:func:`aocontrol.io.export_controller`) is a separate, documented table in
``"z^-1"`` (Direct Form I).
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from aocontrol.controllers import ControllerBank, IIRBank
from aocontrol.io._aot import (
    AOTError,
    _aotpy,
    _frame_rate,
    _image,
    _loop,
    _read_system,
    write_system,
)
from aocontrol.io._rtc import iir_coefficients

__all__ = [
    "FILTER_CONVENTIONS",
    "TFCONV_KEY",
    "aot_time_filter",
    "read_aot_filter",
    "write_aot_filter",
]

#: Conventions of a temporal filter's rows: ``"z"`` (``aotpy``'s formula, ascending powers of
#: ``z``; what we write) and ``"z^-1"`` (a difference equation, powers of ``z^-1``, the first
#: coefficient on the current sample: SPARTA's arrays, :class:`IIRBank`'s ``b`` and ``a``).
FILTER_CONVENTIONS = ("z", "z^-1")
#: Header keyword of both filter images stating their convention.
TFCONV_KEY = "TFCONV"
# The card's comment (an 80-character card leaves it about 45).
_TFCONV_COMMENT = {
    "z": "sum b_i z^i / sum a_j z^j (aotpy's formula)",
    "z^-1": "sum b_i z^-i / sum a_j z^-j, b_0 current",
}


def _check_convention(convention: object) -> str:
    if convention not in FILTER_CONVENTIONS:
        raise ValueError(
            f"convention must be one of {list(FILTER_CONVENTIONS)} ('z': aotpy's documented "
            f"sys(z) = sum b_i z^i / sum a_j z^j; 'z^-1': a difference equation), got "
            f"{convention!r}"
        )
    return str(convention)


def aot_time_filter(
    bank: ControllerBank, loop_uid: str, *, convention: str = "z"
) -> tuple[object, object]:
    """A bank's filters as a loop's ``(time_filter_num, time_filter_den)`` ``aotpy.Image``.

    Parameters
    ----------
    bank : ControllerBank
        An IIR bank or any linear bank (:func:`aocontrol.io.iir_coefficients`).
    loop_uid : str
        The loop's ``uid`` (the images are named ``"<uid> TIME_FILTER_NUM"``/``"..._DEN"``).
    convention : {"z", "z^-1"}, default "z"
        Module docstring. ``"z"``: one row per mode, ``b_i`` and ``a_j`` the coefficients of
        ``z^i`` and ``z^j`` (ascending), numerator and denominator of one length ``n + 1``
        (``n`` the bank's order), ``a_n = 1``. ``"z^-1"``: :func:`iir_coefficients` as they
        are (``a_0 = 1``).

    Returns
    -------
    num, den : aotpy.Image
        Shapes ``(n_modes, nb)`` and ``(n_modes, na)``, the convention in their ``TFCONV``
        header keyword.

    Examples
    --------
    >>> from aocontrol.controllers import Integrator
    >>> num, den = aot_time_filter(Integrator(0.3, fs=1000.0), "HO")
    >>> num.data.tolist(), den.data.tolist()   # 0.3 z / (z - 1) = 0.3 / (1 - z^-1)
    ([[0.0, 0.3]], [[-1.0, 1.0]])
    """
    convention = _check_convention(convention)
    aotpy = _aotpy()
    b, a = iir_coefficients(bank)
    if convention == "z":
        n = max(b.shape[1], a.shape[1])
        b = np.pad(b, ((0, 0), (0, n - b.shape[1])))[:, ::-1]
        a = np.pad(a, ((0, 0), (0, n - a.shape[1])))[:, ::-1]
    meta = [aotpy.Metadatum(TFCONV_KEY, convention, _TFCONV_COMMENT[convention])]
    num = aotpy.Image(f"{loop_uid} TIME_FILTER_NUM", np.ascontiguousarray(b), metadata=meta)
    den = aotpy.Image(f"{loop_uid} TIME_FILTER_DEN", np.ascontiguousarray(a), metadata=list(meta))
    return num, den


def _stated_convention(lp, path: str) -> str | None:
    """The convention the file's images state (``TFCONV``), or None."""
    found = set()
    for img in (lp.time_filter_num, lp.time_filter_den):
        if img is not None:
            value = img.metadata_to_dict().get(TFCONV_KEY)
            if value is not None:
                found.add(str(value).strip())
    if len(found) > 1:
        raise AOTError(
            path, lp.uid, "time_filter_num", f"the filter images state two conventions {found}"
        )
    if found:
        (value,) = found
        if value not in FILTER_CONVENTIONS:
            raise AOTError(
                path,
                lp.uid,
                "time_filter_num",
                f"{TFCONV_KEY} = {value!r} is not a known convention {list(FILTER_CONVENTIONS)}",
            )
        return value
    return None


def _written_by_old_aocontrol(lp) -> bool:
    """Images named as aocontrol named them before it stated the convention (rows in z^-1)."""
    num, den = lp.time_filter_num, lp.time_filter_den
    uid = str(lp.uid).upper()
    return (
        num is not None
        and den is not None
        and num.name == f"{uid} TIME_FILTER_NUM"
        and den.name == f"{uid} TIME_FILTER_DEN"
    )


def _rows_from_z(num: np.ndarray, den: np.ndarray, path: str, uid: str) -> tuple:
    """Rows in ascending powers of ``z`` -> rows in powers of ``z^-1`` (``a_0 = 1``)."""
    out_b, out_a = [], []
    for i, (b, a) in enumerate(zip(num, den, strict=True)):
        nz_a = np.flatnonzero(a)
        if nz_a.size == 0:
            raise AOTError(path, uid, "time_filter_den", f"row {i} is zero: no filter")
        deg_a = int(nz_a[-1])
        nz_b = np.flatnonzero(b)
        deg_b = int(nz_b[-1]) if nz_b.size else 0
        if deg_b > deg_a:
            raise AOTError(
                path,
                uid,
                "time_filter_num",
                f"row {i} read as aotpy's sys(z) = sum b_i z^i / sum a_j z^j has a numerator "
                f"of degree {deg_b} above the denominator's {deg_a}: not causal; if the file "
                "holds a difference equation in powers of z^-1 (an RTC's arrays, e.g. SPARTA's "
                "A/B terms), read it with convention='z^-1'",
            )
        bz = b[deg_a::-1] if deg_a < b.size else np.pad(b, (0, deg_a + 1 - b.size))[::-1]
        az = a[deg_a::-1]
        out_b.append(bz / az[0])
        out_a.append(az / az[0])
    return _stack(out_b), _stack(out_a)


def _stack(rows: list) -> np.ndarray:
    """Rows zero-padded to one length, the trailing columns zero in every row dropped (the
    padding of the equal-length rows written in ``"z"``)."""
    n = max(r.size for r in rows)
    out = np.array([np.pad(r, (0, n - r.size)) for r in rows])
    used = np.flatnonzero(np.any(out != 0, axis=0))
    return out[:, : max(int(used[-1]) + 1 if used.size else 1, 1)]


def read_aot_filter(
    path: str | os.PathLike, loop: str | None = None, *, convention: str | None = None
) -> IIRBank:
    """The temporal filter of an AOT loop as an :class:`~aocontrol.controllers.IIRBank`.

    Rows of ``time_filter_num``/``time_filter_den`` are modes (one row: every mode); the rate
    is the loop's. The convention (module docstring): ``convention`` if given, else the
    images' ``TFCONV``, else ``"z^-1"`` for a file aocontrol wrote before stating it (with a
    warning), else ``"z"`` (``aotpy``'s documented formula).

    Parameters
    ----------
    path : str or os.PathLike
        AOT FITS file.
    loop : str, optional
        The loop's ``uid`` (required when the file has several).
    convention : {"z", "z^-1"}, optional
        How to read the rows (``"z^-1"`` for an RTC's difference-equation arrays, e.g. a file
        translated from an ESO instrument).

    Returns
    -------
    IIRBank
        ``b`` and ``a`` in powers of ``z^-1``, ``a[:, 0] == 1``.

    Raises
    ------
    AOTError
        No such loop, no filter, rows that disagree, a zero leading denominator (``"z^-1"``),
        a non-causal row (``"z"``: its message names ``convention="z^-1"``), an unknown
        ``TFCONV``, no frame rate.

    Warns
    -----
    UserWarning
        The file was written by aocontrol before the convention was stated (read in
        ``"z^-1"``, as it was written).
    """
    path = os.fspath(path)
    lp = _loop(_read_system(path), path, loop)
    num = _image(lp.time_filter_num, path, lp.uid, "time_filter_num", (1, 2))
    den = _image(lp.time_filter_den, path, lp.uid, "time_filter_den", (1, 2))
    if num is None:
        raise AOTError(path, lp.uid, "time_filter_num", "the loop has no temporal filter")
    if convention is not None:
        convention = _check_convention(convention)
    else:
        convention = _stated_convention(lp, path)
        if convention is None and _written_by_old_aocontrol(lp):
            convention = "z^-1"
            warnings.warn(
                f"AOT file {path!r}, loop {lp.uid!r}: temporal filter written by aocontrol "
                f"before it stated its convention ({TFCONV_KEY}); read in powers of z^-1 as it "
                "was written (write it again with aocontrol.io.write_aot_filter to state it)",
                UserWarning,
                stacklevel=2,
            )
        convention = convention or "z"
    num = np.atleast_2d(num)
    if den is None:  # AOT: a numerator alone is an integrator's loop gain
        den, convention = np.array([[1.0, -1.0]]), "z^-1"
    den = np.atleast_2d(den)
    if num.shape[0] != den.shape[0] and 1 not in (num.shape[0], den.shape[0]):
        raise AOTError(
            path,
            lp.uid,
            "time_filter_den",
            f"{den.shape[0]} rows for {num.shape[0]} numerator rows (one per mode, or one)",
        )
    n = max(num.shape[0], den.shape[0])
    num = np.broadcast_to(num, (n, num.shape[1]))
    den = np.broadcast_to(den, (n, den.shape[1]))
    if convention == "z":
        num, den = _rows_from_z(num, den, path, lp.uid)
    elif np.any(den[:, 0] == 0):
        raise AOTError(path, lp.uid, "time_filter_den", "a_0 = 0: not a causal filter")
    return IIRBank(num, den, _frame_rate(lp, path))


def write_aot_filter(
    path: str | os.PathLike,
    bank: ControllerBank,
    loop: str | None = None,
    *,
    out: str | os.PathLike | None = None,
    convention: str = "z",
) -> str:
    """Write a bank's filters into an AOT loop's ``time_filter_num``/``time_filter_den``.

    The file is read with ``aotpy``, the loop's filter replaced (:func:`aot_time_filter`:
    one row per mode, ``aotpy``'s documented convention by default, stated in the images'
    ``TFCONV``) and the system written back with ``aotpy`` to ``out`` (default: ``path``
    itself), atomically.

    Parameters
    ----------
    path : str or os.PathLike
        AOT FITS file.
    bank : ControllerBank
        An IIR bank or any linear bank (:func:`aocontrol.io.iir_coefficients`), at the
        loop's rate.
    loop : str, optional
        The loop's ``uid`` (required when the file has several).
    out : str or os.PathLike, optional
        Output file (default ``path``).
    convention : {"z", "z^-1"}, default "z"
        Module docstring.

    Returns
    -------
    str
        The file written.

    Raises
    ------
    AOTError
        No such loop, a bank at another rate than the loop's.
    """
    path = os.fspath(path)
    convention = _check_convention(convention)
    target = path if out is None else os.fspath(out)
    system = _read_system(path)
    lp = _loop(system, path, loop)
    fs = _frame_rate(lp, path)
    if not np.isclose(bank.fs, fs, rtol=1e-12):
        raise AOTError(path, lp.uid, "framerate", f"loop at {fs:g} Hz, bank at {bank.fs:g} Hz")
    lp.time_filter_num, lp.time_filter_den = aot_time_filter(bank, lp.uid, convention=convention)
    write_system(system, target)
    return target
