"""Public API: every name in each package's ``__all__`` exists and is documented."""

import importlib
import inspect

import pytest

PACKAGES = [
    "aocontrol",
    "aocontrol.plant",
    "aocontrol.controllers",
    "aocontrol.analysis",
    "aocontrol.synthesis",
    "aocontrol.disturbance",
    "aocontrol.sim",
    "aocontrol.sim.wfs",
    "aocontrol.sim.atmosphere",
    "aocontrol.sim.profiles",
    "aocontrol.sim.dm",
    "aocontrol.sim.modes",
    "aocontrol.sim.noise",
    "aocontrol.sim.science",
    "aocontrol.sim.turbulence",
    "aocontrol.sim.loop",
    "aocontrol.study.plot",
]


def _public(module_name):
    module = importlib.import_module(module_name)
    assert hasattr(module, "__all__"), f"{module_name} has no __all__"
    for name in module.__all__:
        yield module_name, name, getattr(module, name)


CASES = [c for m in PACKAGES for c in _public(m)]


@pytest.mark.parametrize(("module", "name", "obj"), CASES, ids=[f"{m}.{n}" for m, n, _ in CASES])
def test_public_name_is_documented(module, name, obj):
    if not (inspect.isclass(obj) or inspect.isfunction(obj)):
        return  # constants are documented by a #: comment next to them
    doc = inspect.getdoc(obj)
    assert doc and len(doc.strip()) > 20, f"{module}.{name} has no docstring"
    if inspect.isfunction(obj):
        params = [p for p in inspect.signature(obj).parameters if p not in ("self", "cls")]
        if len(params) >= 3:
            assert "Parameters" in doc or all(p in doc for p in params), (
                f"{module}.{name}: document its parameters ({params})"
            )
