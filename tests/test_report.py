"""HTML reports read as a reader's browser would: parsed, every image whole, every row there.

The reports are built from plain objects (banks, PSDs, cells) so the tests run in seconds; the
command line's comparison writes the same report (tests/test_cli.py).
"""

import base64
import math
import pathlib
from html.parser import HTMLParser

import numpy as np
import pytest

from aocontrol.analysis import margins, residual_variance, white_noise_psd, wiener_bound
from aocontrol.controllers import Integrator
from aocontrol.disturbance import synthetic_turbulence_psd
from aocontrol.plant import loop_plant
from aocontrol.study.compare import CaseComparison, Cell, DesignInputs
from aocontrol.study.report import (
    DesignReportData,
    comparison_report,
    design_report,
    design_report_data,
)
from aocontrol.synthesis import optimal_modal_gain

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk and its CRC: a PNG written whole ends so


class _Page(HTMLParser):
    """Images (src, alt), tables by id (rows of cell texts), and any external reference."""

    def __init__(self) -> None:
        super().__init__()
        self.images: list[tuple[str, str]] = []
        self.tables: dict[str, list[list[str]]] = {}
        self.external: list[str] = []
        self._rows = self._row = self._cell = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append((a.get("src") or "", a.get("alt") or ""))
        elif tag in ("link", "script", "iframe", "object") or "src" in a or "href" in a:
            self.external.append(tag)
        if tag == "table":
            self._rows = self.tables.setdefault(a.get("id"), [])
        elif tag == "tr" and self._rows is not None:
            self._row = []
        elif tag in ("td", "th") and self._row is not None:
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._row.append("".join(self._cell).strip())
            self._cell = None
        elif tag == "tr" and self._row is not None:
            self._rows.append(self._row)
            self._row = None
        elif tag == "table":
            self._rows = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def _read(path) -> _Page:
    page = _Page()
    page.feed(open(path, encoding="utf-8").read())
    page.close()
    return page


def _broken_images(page: _Page) -> list[str]:
    """Alt texts of the images that are not a whole PNG embedded in the page."""
    bad = []
    prefix = "data:image/png;base64,"
    for src, alt in page.images:
        if not src.startswith(prefix):
            bad.append(alt)
            continue
        try:
            png = base64.b64decode(src[len(prefix) :], validate=True)
        except ValueError:
            bad.append(alt)
            continue
        if not (png.startswith(PNG_SIGNATURE) and png.endswith(PNG_END) and len(png) > 2000):
            bad.append(alt)
    return bad


def _rows(page: _Page, table: str) -> list[list[str]]:
    rows = page.tables[table]
    return rows[1:]  # the first row is the header


def test_the_checker_sees_a_broken_image():
    # Twin of the checks below: a truncated PNG, a file reference and a bad base64 are caught.
    good = base64.b64encode(PNG_SIGNATURE + b"x" * 3000 + PNG_END).decode()
    page = _Page()
    page.feed(
        f'<img src="data:image/png;base64,{good}" alt="ok">'
        f'<img src="data:image/png;base64,{good[:-40]}" alt="cut">'
        '<img src="figure.png" alt="file"><img src="data:image/png;base64,@@" alt="junk">'
    )
    assert _broken_images(page) == ["cut", "file", "junk"]


@pytest.fixture(scope="module")
def loop():
    fs = 1000.0
    plant = loop_plant(fs, 0.5)
    f = np.concatenate([[0.0], np.geomspace(0.05, fs / 2, 400)])
    psd = synthetic_turbulence_psd(f, 6, fs=fs)
    noise = np.full(6, float(white_noise_psd(1.0, fs)))
    return plant, f, psd, noise


@pytest.fixture(scope="module")
def compared(loop, tmp_path_factory):
    """A two-scheme comparison of two banks and its report (built once: figures cost ~1 s)."""
    tmp_path = tmp_path_factory.mktemp("report")
    plant, f, psd, noise = loop
    design = DesignInputs(plant, f, psd, noise, 1000.0, 6, 0.4)
    banks = {
        "reference": Integrator(0.4, fs=1000.0, n_modes=6),
        "omgi": optimal_modal_gain(plant, f, psd, noise, modulus_margin=0.5),
    }
    radii = np.linspace(0.5, 15.0, 30)
    cells = []
    for scheme in ("standalone", "dcao"):
        for k, (name, bank) in enumerate(banks.items()):
            pred = math.sqrt(np.sum(residual_variance(plant, bank, f, psd, noise)))
            cells.append(
                Cell(
                    name,
                    scheme,
                    0.8 + 0.01 * k,
                    1e-4 / (k + 1),
                    pred * 1.1,
                    pred,
                    radii,
                    1e-3 * np.exp(-radii / (k + 2)),
                    {"seconds": 0.5, "quick": True},
                    None,
                    bank,
                )
            )
    psds = {s: (f, {"input": psd, **{c: psd * 0.1 for c in banks}}) for s in ("standalone", "dcao")}
    vibration = {
        "mode": 1,
        "scheme": "standalone",
        "tilt_rms_nm": {"reference": 7.0, "omgi": 5.0},
        "relative_gain": 2 / 7,
        "psd": {k: (f, psd[1] * 0.1) for k in banks},
    }
    comparison = CaseComparison(
        "demo-case",
        tuple(cells),
        {"standalone": 0.4, "dcao": 0.4},
        {},
        vibration,
        {"scan": 1.0},
        {"standalone": design, "dcao": design},
    )
    path = comparison_report(comparison, tmp_path / "report.html", residual_psds=psds)
    return comparison, path


def test_comparison_report_is_self_contained_with_every_row(loop, compared):
    comparison, path = compared
    page = _read(path)
    assert page.external == []  # nothing outside the file
    assert _broken_images(page) == []
    # margins, rejection per scheme (2), residual PSDs per scheme (2), tilt, contrast
    assert len(page.images) == 7
    expected = [[c.scheme, c.controller] for c in comparison.cells]
    results = _rows(page, "results")
    assert [r[:2] for r in results] == expected
    # Strehl column in percent, contrast in the table as written
    assert [float(r[2]) for r in results] == pytest.approx(
        [100 * c.strehl for c in comparison.cells], abs=0.006
    )
    assert [r[:2] for r in _rows(page, "margins")] == expected
    assert [r[0] for r in _rows(page, "vibration")] == ["reference", "omgi"]
    # Beside the predicted / measured column, what its interval counts and what it leaves out
    # (issue 33: the demo's 0.92-0.94 with an interval excluding 1).
    text = " ".join(pathlib.Path(path).read_text().split())
    note = text.index("takes the modes as independent")
    assert text.index("predicted / measured [2 s.e.]") < note < text.index("vibration")
    # The margins table states the banks' certified margins (min modulus margin, column 6).
    plant = loop[0]
    for row, c in zip(_rows(page, "margins"), comparison.cells, strict=True):
        mm = min(margins(plant, c.bank, mode=i).modulus_margin for i in range(6))
        assert row[2] == "6/6" and float(row[6]) == pytest.approx(mm, abs=6e-4)


def test_comparison_report_without_design_data_says_so(compared, tmp_path):
    comparison, _ = compared
    bare = CaseComparison(comparison.case, comparison.cells, comparison.reference_gains, {})
    page = _read(comparison_report(bare, tmp_path / "bare.html"))
    assert _broken_images(page) == []
    assert [r[2] for r in _rows(page, "margins")] == ["n/a"] * 4
    assert len(page.images) == 1  # the contrast curves only


def test_design_report_rows_bounds_and_ratios(loop, tmp_path):
    plant, f, psd, noise = loop
    banks = {
        "omgi": optimal_modal_gain(plant, f, psd, noise, modulus_margin=0.5),
        "integrator 0.3": Integrator(0.3, fs=1000.0, n_modes=6),
    }
    wiener = np.sqrt(np.atleast_1d(wiener_bound(plant, f, psd, noise)))
    data = DesignReportData(
        plant,
        f,
        psd,
        noise,
        banks,
        bounds={"Wiener bound": wiener},
        modulus_margin=0.5,
        title="design test",
        info={"telemetry": "synthetic"},
    )
    page = _read(design_report(data, tmp_path / "design.html"))
    assert page.external == [] and _broken_images(page) == []
    assert len(page.images) == 4  # residual per mode, margins, rejection, residual PSDs
    modes = _rows(page, "modes")
    assert [int(r[0]) for r in modes] == list(range(6))
    summary = {r[0]: r for r in _rows(page, "summary")}
    assert list(summary) == ["omgi", "integrator 0.3", "Wiener bound"]
    # Oracle: no linear controller beats the Wiener bound, so every ratio is >= 1.
    for name in banks:
        assert float(summary[name][2]) >= 1.0
    assert float(summary["Wiener bound"][1]) == pytest.approx(
        math.sqrt(np.sum(wiener**2)), abs=0.006
    )
    # The per-mode margins are those of aocontrol.analysis.margins for the first bank.
    for i, row in enumerate(modes):
        m = margins(plant, banks["omgi"], mode=i)
        assert row[1] == "yes" and float(row[5]) == pytest.approx(m.modulus_margin, abs=6e-4)
        assert float(row[3]) == pytest.approx(m.gain_margin_db, abs=6e-3)


def test_design_report_data_names_the_bad_argument(loop):
    plant, f, psd, noise = loop
    bank = Integrator(0.3, fs=1000.0, n_modes=6)
    with pytest.raises(ValueError, match="psd must have shape"):
        DesignReportData(plant, f[:-1], psd, noise, {"k": bank})
    with pytest.raises(ValueError, match=r"bounds\['w'\] must have shape \(6,\)"):
        DesignReportData(plant, f, psd, noise, {"k": bank}, bounds={"w": np.ones(5)})
    with pytest.raises(ValueError, match=r"controllers\['k'\] has 2 modes"):
        DesignReportData(plant, f, psd, noise, {"k": Integrator(0.3, fs=1000.0, n_modes=2)})


def _readme_demo_figures() -> dict[str, list[tuple[float, float]]]:
    """The README's demo table: per quantity, one (low, high) per controller (a single value
    quoted to n digits is the interval of the values that round to it)."""
    import pathlib
    import re

    text = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    out = {}
    for key, label in (("contrast", "contrast"), ("strehl", "Strehl [%]")):
        row = re.search(rf"^\| {re.escape(label)}, every machine below \|(.*)\|$", text, re.M)
        cells = [c.strip() for c in row.group(1).split("|")]
        spans = []
        for cell in cells:
            values = cell.split(" to ")
            half = []
            for v in values:  # half a unit of the last digit quoted
                mantissa = v.split("e")[0]
                digits = len(mantissa.split(".")[1]) if "." in mantissa else 0
                exp = int(v.split("e")[1]) if "e" in v else 0
                half.append(0.5 * 10.0 ** (exp - digits))
            spans.append((float(values[0]) - half[0], float(values[-1]) + half[-1]))
        out[key] = spans
    return out


@pytest.mark.slow
def test_demo_comparison_shows_the_papers_ordering(tmp_path):
    # The demo's point (issue 16): on red 1 fast with enough stage-2 modes the controllers
    # differ as in the paper's table (the paper's contrasts: reference 1.00e-4, modal gains
    # 9.44e-5, data-driven 7.87e-5), and the report carries every row. Issue 33: its figures
    # are those the README quotes, within the spread measured over emulated machines.
    from aocontrol.study.demo import DEMO_STAGE2_MODES, demo_comparison

    comparison = demo_comparison(str(tmp_path))
    contrast = {c.controller: c.mean_contrast_4_6 for c in comparison.cells}
    # Modal gains and reference are 4 % apart here (within an exposure's noise): only the
    # data-driven margin is asserted.
    assert contrast["datadriven"] < 0.9 * min(contrast["omgi"], contrast["reference"])
    quoted = _readme_demo_figures()
    for cell, c_span, s_span in zip(
        comparison.cells, quoted["contrast"], quoted["strehl"], strict=True
    ):
        assert c_span[0] <= cell.mean_contrast_4_6 <= c_span[1], (cell.controller, c_span)
        assert s_span[0] <= 100 * cell.strehl <= s_span[1], (cell.controller, s_span)
    assert comparison.designs["standalone"].n_modes == DEMO_STAGE2_MODES
    page = _read(comparison_report(comparison, tmp_path / "demo.html"))
    assert _broken_images(page) == []
    assert [r[1] for r in _rows(page, "results")] == ["reference", "omgi", "datadriven"]


def test_design_report_data_from_a_telemetry_design(loop):
    # The attributes of synthesis.design_from_telemetry's result, by name (duck typed, so the
    # report does not depend on that class): the report's rows come from them unchanged.
    from types import SimpleNamespace

    plant, f, psd, noise = loop
    bank = optimal_modal_gain(plant, f, psd, noise, modulus_margin=0.5)
    ref = Integrator(0.3, fs=1000.0, n_modes=6)
    var = np.atleast_1d(residual_variance(plant, bank, f, psd, noise))
    design = SimpleNamespace(
        controller_name="omgi",
        controller=bank,
        reference=ref,
        plant=plant,
        fs=1000.0,
        latency_frames=0.5,
        estimate=SimpleNamespace(freqs=f, psd=psd, noise_psd=noise, method="prewhitened"),
        modulus_margin=0.5,
        margins=tuple(margins(plant, bank, mode=i) for i in range(6)),
        reference_margins=tuple(margins(plant, ref, mode=i) for i in range(6)),
        residual_variance=var,
        reference_residual_variance=np.atleast_1d(residual_variance(plant, ref, f, psd, noise)),
        wiener_variance=np.atleast_1d(wiener_bound(plant, f, psd, noise)),
        constrained_variance=np.full(6, np.nan),  # not computed: left out
    )
    data = design_report_data(design, info={"telemetry": "x.fits"})
    assert list(data.bounds) == ["Wiener bound"]
    assert list(data.controllers) == ["omgi", "starting integrator (optimal gain)"]
    assert data.info["estimator"] == "prewhitened" and data.info["telemetry"] == "x.fits"
    assert data.predicted_rms["omgi"] == pytest.approx(np.sqrt(var), rel=1e-12)
    assert data.margins["omgi"] is design.margins


def test_design_report_shows_the_margin_over_an_uncertainty_set(loop, tmp_path):
    # A design asked for robust margins (design_from_telemetry(uncertainty=)): the set in the
    # header and a column per controller with the certified values, unchanged; without them
    # no such column.
    from aocontrol.analysis import UncertaintySet, robust_margin
    from aocontrol.synthesis import LoopTelemetry, design_from_telemetry

    rng = np.random.default_rng(3)
    m = rng.standard_normal((4096, 2))
    tel = LoopTelemetry(m, np.zeros_like(m), fs=1000.0, latency_frames=0.5)
    uset = UncertaintySet(gain=(0.8, 1.2), latency=(-0.2, 0.2))
    rep = design_from_telemetry(tel, "omgi", bounds=(), uncertainty=uset)
    data = design_report_data(rep)
    assert data.info["robust margins over"] == uset.describe()
    expected = [robust_margin(rep.plant, rep.controller, uset, mode=i).value for i in range(2)]
    np.testing.assert_allclose(data.robust_margins["omgi"], expected, rtol=1e-12)
    page = _read(design_report(data, tmp_path / "d.html"))
    header = page.tables["modes"][0]
    col = header.index("omgi: MM over the set [1]")
    assert [float(r[col]) for r in _rows(page, "modes")] == pytest.approx(expected, abs=5e-4)
    plain = design_report_data(design_from_telemetry(tel, "omgi", bounds=()))
    assert plain.robust_margins is None and "robust margins over" not in plain.info
