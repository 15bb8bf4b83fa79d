"""Public API: every name in each public module's ``__all__`` exists and is documented.

The docstrings are parsed with ``numpydoc.docscrape`` (as python-control's docstring test
does): every parameter of every public function and class constructor must appear in its
``Parameters`` section (``Attributes`` also counts for a dataclass field). A word that merely
appears somewhere in the text does not count.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
import warnings

import pytest
from numpydoc.docscrape import ClassDoc, FunctionDoc

import aocontrol

# Modules that run something when imported (the command line entry point).
_SKIP_MODULES = {"aocontrol.__main__"}


def _public_modules() -> list[str]:
    """``aocontrol`` and every submodule whose dotted path has no private component."""
    names = ["aocontrol"]
    for info in pkgutil.walk_packages(aocontrol.__path__, prefix="aocontrol."):
        if info.name in _SKIP_MODULES or any(p.startswith("_") for p in info.name.split(".")):
            continue
        names.append(info.name)
    return names


def _cases() -> list[tuple[str, str, object]]:
    out = []
    for module_name in _public_modules():
        module = importlib.import_module(module_name)
        for name in getattr(module, "__all__", ()):
            out.append((module_name, name, getattr(module, name, _MISSING)))
    return out


_MISSING = object()
CASES = _cases()


def _documented_names(section) -> set[str]:
    """Names of a numpydoc section; ``"b, a : ..."`` documents both ``b`` and ``a``."""
    names = set()
    for item in section:
        for part in item.name.split(","):
            names.add(part.strip().lstrip("*"))
    return names


def _signature_params(obj) -> list[str]:
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):  # builtins without a signature
        return []
    return [p for p in sig.parameters if p not in ("self", "cls")]


def test_every_public_module_has_an_all():
    # A public module without __all__ would escape the documentation check below.
    for module_name in _public_modules():
        module = importlib.import_module(module_name)
        assert hasattr(module, "__all__"), f"{module_name} has no __all__"


@pytest.mark.parametrize(("module", "name", "obj"), CASES, ids=[f"{m}.{n}" for m, n, _ in CASES])
def test_public_name_exists_and_is_documented(module, name, obj):
    assert obj is not _MISSING, f"{module}.__all__ lists {name!r}, which does not exist"
    if not (inspect.isclass(obj) or inspect.isfunction(obj)):
        pytest.skip("constants are documented by a #: comment next to them")
    doc = inspect.getdoc(obj)
    assert doc and len(doc.strip()) > 20, f"{module}.{name} has no docstring"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numpydoc warns on unknown sections
        parsed = ClassDoc(obj) if inspect.isclass(obj) else FunctionDoc(obj)
    documented = _documented_names(parsed["Parameters"])
    if inspect.isclass(obj):
        if dataclasses.is_dataclass(obj):
            documented |= _documented_names(parsed["Attributes"])
        if issubclass(obj, BaseException) and obj.__init__ is BaseException.__init__:
            return  # no constructor of its own
    missing = [p for p in _signature_params(obj) if p not in documented]
    assert not missing, (
        f"{module}.{name}: parameters {missing} are not documented in a numpydoc "
        f"'Parameters' section (documented: {sorted(documented)})"
    )


def test_checker_flags_an_undocumented_parameter():
    # The check above can fail: a function that mentions its parameter only in prose.
    def f(alpha, beta):
        """Compute something from alpha and beta (both named here, neither documented).

        Parameters
        ----------
        alpha : float
            The first one.
        """

    documented = _documented_names(FunctionDoc(f)["Parameters"])
    assert [p for p in _signature_params(f) if p not in documented] == ["beta"]


def test_version_has_one_source():
    # pyproject.toml reads aocontrol._version.__version__ (no second literal to forget), the
    # package and the comparison's settings record the same value, and no module reads it
    # from elsewhere (the top package, the installed metadata).
    import pathlib

    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    from aocontrol._version import __version__

    meta = tomllib.loads((pathlib.Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert "version" not in meta["project"] and "version" in meta["project"]["dynamic"]
    assert meta["tool"]["setuptools"]["dynamic"]["version"] == {
        "attr": "aocontrol._version.__version__"
    }
    assert __version__ == aocontrol.__version__
    root = pathlib.Path(aocontrol.__file__).parent
    for path in root.rglob("*.py"):
        text = path.read_text()
        assert "from aocontrol import __version__" not in text, path
        assert 'version("aocontrol")' not in text, path


def test_pyproject_license_is_an_spdx_expression():
    # Issue 33: a license table ({ text = ... }) makes setuptools >= 77 warn three times per
    # install (deprecated, unsupported from 2027-02-18); an SPDX string needs setuptools >= 77.
    import pathlib
    import re

    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    meta = tomllib.loads((pathlib.Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert isinstance(meta["project"]["license"], str)
    (req,) = [r for r in meta["build-system"]["requires"] if r.startswith("setuptools")]
    assert int(re.search(r">=\s*(\d+)", req).group(1)) >= 77
