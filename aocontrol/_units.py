"""Length units of telemetry: the one place that knows how many nanometres a unit is.

The project's convention (DESIGN.md): wavefronts are optical path in nm and modal coefficients
are in nm RMS (KL modes orthonormal over the pupil). Telemetry files use other units: AOT fixes
a loop's ``commands`` in metres (``aotpy``: "in m units"), and its modal coefficients and
matrices in "user defined units" (a FITS ``BUNIT`` may say which). A unit that is a length is
converted to nm once, where the telemetry is read; any other unit (``rad``, ``V``, ``count``)
or none at all is carried with the figures, never printed as nm.

>>> nm_per_unit("m"), nm_per_unit("um"), nm_per_unit("nm"), nm_per_unit("rad")
(1000000000.0, 1000.0, 1.0, None)
>>> unit_label(None), unit_label("rad")
('a.u.', 'rad')
"""

from __future__ import annotations

__all__ = ["NM", "UNKNOWN_UNIT_LABEL", "nm_per_unit", "unit_label"]

#: The project's unit of modal telemetry (modal coefficients of 1 nm RMS, optical path).
NM = "nm"
#: Label of figures whose unit nobody stated ("arbitrary units": the file's own).
UNKNOWN_UNIT_LABEL = "a.u."

# Length units (FITS BUNIT spellings, case-insensitive) -> nanometres per unit.
_NM_PER = {
    "m": 1e9,
    "meter": 1e9,
    "meters": 1e9,
    "metre": 1e9,
    "metres": 1e9,
    "mm": 1e6,
    "um": 1e3,
    "µm": 1e3,
    "μm": 1e3,
    "micron": 1e3,
    "microns": 1e3,
    "nm": 1.0,
    "nanometer": 1.0,
    "nanometers": 1.0,
    "nanometre": 1.0,
    "nanometres": 1.0,
    "pm": 1e-3,
}


def nm_per_unit(unit: str | None) -> float | None:
    """Nanometres in one ``unit`` (a length), or ``None`` when ``unit`` is not a length.

    Parameters
    ----------
    unit : str or None
        A unit name as a FITS ``BUNIT`` writes it (``"m"``, ``"um"``, ``"nm"``...; case and
        surrounding spaces ignored).

    Returns
    -------
    float or None
    """
    if unit is None:
        return None
    return _NM_PER.get(str(unit).strip().lower())


def unit_label(unit: str | None) -> str:
    """The label printed with a figure: the unit, or ``"a.u."`` when nobody stated it."""
    return UNKNOWN_UNIT_LABEL if not unit else str(unit)
