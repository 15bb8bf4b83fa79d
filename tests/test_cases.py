"""Science cases as data: the shipped TOML files match the paper's case tables, and the loader
rejects bad files naming the file, the key and the reason."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from aocontrol.sim.dm import DeformableMirror
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.study.cases import Case, CaseError, apply_overrides, case_path, list_cases, load_case

# The paper's case tables (section "Science cases results"): seeing ["], tau0 [ms], G, J,
# stage frequencies [Hz], modes, wavelengths [um]. Copied from the paper, the oracle here.
PAPER = {
    "bright1-best": (0.4, 9.0, 5.5, 5.2, 1000, 3000, 1200, 400, 0.69, 1.04),
    "bright1-worst": (1.0, 2.0, 5.5, 5.2, 1000, 3000, 1200, 540, 0.69, 1.04),
    "red1-fast": (0.7, 2.0, 11.9, 8.5, 300, 3000, 400, 540, 0.69, 1.04),
    "red3-medium": (0.7, 5.5, 14.5, 10.1, 50, 1250, 400, 540, 0.69, 1.14),
    "red5-best": (0.4, 9.0, 16.8, 12.5, 10, 300, 400, 400, 0.69, 1.14),
}
# Relative tolerance on the parsed values: unit conversion in decimal, exact to rounding.
REL = 1e-12


def test_list_cases_ships_the_six_cases():
    assert list_cases() == sorted([*PAPER, "vibration"])


@pytest.mark.parametrize("name", sorted(PAPER))
def test_case_matches_paper_table(name):
    c = load_case(name)
    got = (
        c.atmosphere.seeing,
        c.atmosphere.tau0 * 1e3,
        c.star.G,
        c.star.J,
        c.stage1.fs,
        c.stage2.fs,
        c.stage1.n_modes,
        c.stage2.n_modes,
        c.stage1.wavelength * 1e6,
        c.stage2.wavelength * 1e6,
    )
    for g, want in zip(got, PAPER[name], strict=True):
        assert math.isclose(g, want, rel_tol=REL), (name, got, PAPER[name])
    # Published values common to every case (issue 7, COMPASS SAXO+ files).
    assert c.science.wavelength == pytest.approx(1.65e-6, rel=REL)
    assert c.atmosphere.L0 == 25.0 and c.atmosphere.n_layers == 35
    assert c.stage1.read_noise == 0.058 and c.stage2.modulation == 3.0
    assert c.stage2.n_modulation_points == 20 and c.stage2.n_actuators == 28
    assert c.science.exposure == 5.0 and c.science.startup == pytest.approx(0.1, rel=REL)


def test_case_specific_published_values():
    assert load_case("bright1-best").stage1.latency_frames == 0.84
    assert load_case("red1-fast").stage1.latency_frames == 0.25
    red3 = load_case("red3-medium")
    assert (red3.stage2.latency_frames, red3.stage2.read_noise, red3.stage2.gain) == (
        0.375,
        0.32,
        0.3,
    )
    assert load_case("bright1-worst").stage2.latency_frames == 0.828


def test_every_value_has_a_comment_naming_its_source():
    # Each key line either carries a comment or follows a comment block (the source).
    for name in list_cases():
        lines = case_path(name).read_text().splitlines()
        for i, line in enumerate(lines):
            key = re.match(r"^\s*([A-Za-z_0-9]+)\s*=", line)
            if key and key.group(1) not in ("name", "title"):  # identifiers, not values
                assert "#" in line or lines[i - 1].lstrip().startswith("#"), (name, line)


def test_vibration_inherits_bright1_best():
    vib, base = load_case("vibration"), load_case("bright1-best")
    assert vib.vibration is not None and base.vibration is None
    assert vib.atmosphere == base.atmosphere and vib.stage2 == base.stage2
    assert vib.vibration.modes == (1,)


def test_mode_counts_fit_the_dm_oracle():
    # Oracle: the DM model's own valid-actuator count, piston removed.
    for name in list_cases():
        c = load_case(name)
        for st in (c.stage1, c.stage2):
            dm = DeformableMirror(vlt_pupil(2 * (st.n_actuators - 1)), n_actuators=st.n_actuators)
            assert st.n_modes <= dm.n_act - 1


def test_overrides_replace_and_revalidate():
    c = load_case("bright1-best")
    c2 = apply_overrides(c, {"seeing": 0.6, "stage2.fs": 2000, "tau0": "5 ms"})
    assert (c2.atmosphere.seeing, c2.stage2.fs, c2.atmosphere.tau0) == (0.6, 2000.0, 0.005)
    assert c2.rate_ratio == 2 and c.stage2.fs == 3000.0
    with pytest.raises(CaseError, match="integer multiple"):
        apply_overrides(c, {"stage2.fs": 1500})
    with pytest.raises(CaseError, match="ambiguous or unknown"):
        apply_overrides(c, {"fs": 2000})  # in both stages
    assert isinstance(c2.to_dict()["stage1"]["fs"], float)


def test_unknown_case_lists_the_shipped_ones():
    with pytest.raises(ValueError, match="bright1-best"):
        load_case("bright9")


def _write(tmp_path: Path, edit) -> Path:
    text = case_path("bright1-best").read_text()
    text = edit(text)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    return path


def _sub(old: str, new: str):
    def edit(text: str) -> str:
        assert old in text, old
        return text.replace(old, new, 1)

    return edit


BAD = [
    ("unknown key", _sub("[star]\n", "[star]\nK = 4.0\n"), "star.K", "unknown key"),
    ("missing key", _sub('tau0 = "9 ms"', "# no tau0"), "atmosphere.tau0", "missing"),
    ("missing table", _sub("[star]\n", "[stars]\n"), "stars", "unknown key"),
    ("wrong type", _sub("n_modes = 1200", 'n_modes = "1200"'), "stage1.n_modes", "integer"),
    ("no unit", _sub('tau0 = "9 ms"', "tau0 = 0.009"), "atmosphere.tau0", "with a unit"),
    ("wrong unit", _sub('tau0 = "9 ms"', 'tau0 = "9 Hz"'), "atmosphere.tau0", "wrong unit"),
    ("implausible unit", _sub('tau0 = "9 ms"', 'tau0 = "9 s"'), "atmosphere.tau0", "wrong unit"),
    ("negative seeing", _sub('"0.4 arcsec"', '"-0.4 arcsec"'), "atmosphere.seeing", "non-phys"),
    ("negative tau0", _sub('"9 ms"', '"-9 ms"'), "atmosphere.tau0", "non-physical"),
    ("zero rate", _sub('fs = "1000 Hz"', 'fs = "0 Hz"'), "stage1.fs", "non-physical"),
    ("ratio", _sub('fs = "1000 Hz"', 'fs = "700 Hz"'), "stage2.fs", "integer multiple"),
    ("too many modes", _sub("n_modes = 400 ", "n_modes = 700 "), "stage2.n_modes", "exceed"),
    ("bad wfs", _sub('wfs = "pyramid"', 'wfs = "curvature"'), "stage2.wfs", "one of"),
    ("bad toml", _sub("[star]", "[star"), "<file>", "invalid TOML"),
]


@pytest.mark.parametrize(("label", "edit", "key", "reason"), BAD, ids=[b[0] for b in BAD])
def test_bad_case_file_names_file_key_and_reason(tmp_path, label, edit, key, reason):
    path = _write(tmp_path, edit)
    with pytest.raises(CaseError) as info:
        load_case(path)
    err = info.value
    assert err.source == str(path) and err.key == key, (label, str(err))
    assert reason in err.reason, (label, str(err))
    assert str(path) in str(err) and key in str(err)


def test_good_copy_loads(tmp_path):
    # Twin of the bad-file tests: the unedited copy loads, so the failures above come from
    # the edits.
    c = load_case(_write(tmp_path, lambda t: t))
    assert isinstance(c, Case) and c.stage1.n_modes == 1200
