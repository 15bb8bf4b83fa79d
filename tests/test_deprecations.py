"""One deprecation mechanism, every deprecated name listed in the docs with its removal."""

import pathlib
import re
import warnings

import pytest

from aocontrol._deprecation import DEPRECATIONS, REMOVAL_RELEASE

DOCS = pathlib.Path(__file__).parents[1] / "docs" / "deprecations.md"


def import_all():
    """Import every module of the package: the registry is then complete."""
    import importlib
    import pkgutil

    import aocontrol

    for mod in pkgutil.walk_packages(aocontrol.__path__, "aocontrol."):
        if not mod.name.endswith("__main__"):
            importlib.import_module(mod.name)
    return list(DEPRECATIONS)


def _doc_rows():
    rows = set()
    for line in DOCS.read_text().splitlines():
        m = re.match(r"\| `([^`]+)` \| `([^`]+)` \| (.+) \| (\w+) \| ([\d.]+) \|$", line)
        if m:
            rows.add(m.groups())
    return rows


def test_every_deprecation_is_listed_with_its_removal_release():
    registry = {(d.old, d.where, d.new, d.kind, d.removed_in) for d in import_all()}
    assert registry, "the registry is empty: the declarations were not recorded"
    assert _doc_rows() == registry
    assert all(d.removed_in == REMOVAL_RELEASE for d in import_all())


def test_a_deprecated_name_warns_with_its_removal_release():
    import aocontrol
    from aocontrol.controllers import Integrator

    with pytest.warns(DeprecationWarning, match=f"removed in {REMOVAL_RELEASE}"):
        Integrator(0.5, fs=1000.0, stroke=10.0)
    with pytest.warns(DeprecationWarning, match=f"removed in {REMOVAL_RELEASE}"):
        loader = aocontrol.load_result
    from aocontrol.study.results import load_result

    assert loader is load_result


def test_no_deprecation_warning_is_raised_by_hand_outside_the_mechanism():
    # A DeprecationWarning written with warnings.warn elsewhere would bypass the registry.
    root = pathlib.Path(__file__).parents[1] / "aocontrol"
    offenders = [
        str(p.relative_to(root))
        for p in root.rglob("*.py")
        if p.name != "_deprecation.py" and re.search(r"DeprecationWarning,", p.read_text())
    ]
    assert offenders == []


def test_the_mechanism_catches_an_unlisted_deprecation():
    # Twin of the first test: a new declaration makes the registry differ from the docs.
    from aocontrol import _deprecation

    before = list(_deprecation.DEPRECATIONS)
    try:
        _deprecation.declare("aocontrol.example", "old", "new")
        registry = {(d.old, d.where, d.new, d.kind, d.removed_in) for d in import_all()}
        assert _doc_rows() != registry
    finally:
        _deprecation.DEPRECATIONS[:] = before
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _doc_rows() == {(d.old, d.where, d.new, d.kind, d.removed_in) for d in import_all()}
