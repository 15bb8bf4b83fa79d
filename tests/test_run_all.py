"""``make bench`` runs every command the README's benchmark table quotes (issue 19)."""

from __future__ import annotations

import importlib.util
import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run_all():
    spec = importlib.util.spec_from_file_location("run_all", ROOT / "benchmarks" / "run_all.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["run_all"] = module
    spec.loader.exec_module(module)
    return module


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Benchmarks", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ") and "---" not in line]
    commands = []
    for row in rows[1:]:  # the header first
        cell = row.rstrip(" |").rsplit("|", 1)[-1]
        commands += [c for c in re.findall(r"`([^`]+)`", cell) if c.startswith("bench_")]
    return commands


def test_every_readme_command_is_run_by_make_bench():
    run_all = _run_all()
    run = {" ".join([e.script, *e.full]) for e in run_all.BENCHMARKS.values()}
    run |= {f"{e.script} {c}" for e in run_all.BENCHMARKS.values() for c in e.covers}
    commands = _readme_commands()
    assert len(commands) >= 15, commands
    for cmd in commands:
        # Optional parts the README shows in brackets, and the OOPAO python, are not settings.
        plain = re.sub(r"\s*\[[^\]]*\]", "", cmd).replace(" --oopao-python PY", "").strip()
        assert plain in run, f"README command {cmd!r} is not in run_all.BENCHMARKS"


def test_every_entry_names_an_existing_script_and_lists(capsys):
    run_all = _run_all()
    for entry in run_all.BENCHMARKS.values():
        assert (ROOT / "benchmarks" / entry.script).is_file(), entry.script
    assert run_all.main(["--list", "--only", "bench_cascade.py"]) == 0
    out = capsys.readouterr().out
    assert "bench_cascade.py --repeat 2" in out
    assert "diffractive" in out  # both entries of the script


def test_a_run_prints_the_machine_and_each_commands_load_and_cpu(capsys, monkeypatch):
    run_all = _run_all()
    calls = []

    def fake_call(cmd):
        calls.append(cmd)
        return 3  # a failing benchmark: the run's exit code says so

    monkeypatch.setattr(run_all.subprocess, "call", fake_call)
    assert run_all.main(["--only", "lqg"]) == 1
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith("machine: ") and " cores, " in out
    assert "commit " in out.splitlines()[0]
    (line,) = [ln for ln in out.splitlines() if ln.startswith("lqg ")]
    assert re.search(r"exit\s+3\s+[\d.]+ s wall\s+[\d.]+ s CPU\s+load \S+ -> \S+$", line), line
    assert len(calls) == 1 and calls[0][1].endswith("bench_lqg.py")


def test_every_name_a_benchmark_imports_from_aocontrol_exists():
    # The benchmarks import some names inside their functions (a part run on demand) and reach
    # private ones through a module (``dd._design_chunk``): a name moved by a refactoring
    # breaks only that part, at run time (bench_sweep's and bench_synthesis's did, 3 Dec).
    import ast
    import importlib
    import types

    missing = []
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        tree = ast.parse(path.read_text())
        modules = {}  # local name -> aocontrol module
        for node in ast.walk(tree):
            if not isinstance(node, ast.ImportFrom):
                continue
            if not (node.module or "").startswith("aocontrol"):
                continue
            module = importlib.import_module(node.module)
            for alias in node.names:
                value = getattr(module, alias.name, None)
                if value is None:
                    try:
                        value = importlib.import_module(f"{node.module}.{alias.name}")
                    except ImportError:
                        missing.append(f"{path.name}:{node.lineno} {node.module}.{alias.name}")
                        continue
                if isinstance(value, types.ModuleType):
                    modules[alias.asname or alias.name] = value
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in modules
                and not hasattr(modules[node.value.id], node.attr)
            ):
                name = modules[node.value.id].__name__
                missing.append(f"{path.name}:{node.lineno} {name}.{node.attr}")
    assert not missing, missing
