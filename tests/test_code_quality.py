"""The layering (import-linter contracts in pyproject.toml), the lint rules and the docs build
hold for the whole tree."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str:
    path = Path(sys.executable).parent / name
    found = str(path) if path.exists() else shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: run scripts/bootstrap.sh")
    return found


def test_import_layers_are_kept():
    result = subprocess.run(
        [_tool("lint-imports")], cwd=ROOT, capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stdout[-3000:]
    assert "0 broken" in result.stdout


def test_ruff_is_clean():
    result = subprocess.run(
        [
            _tool("ruff"),
            "check",
            "--output-format",
            "concise",
            "pipescan",
            "tests",
            "benchmarks",
            "docs",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stdout[-3000:]


def test_docs_build_makes_its_figures(tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "build.py"), "--out", str(tmp_path), "--dpi", "40"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    page = tmp_path / "report-page-1.png"
    assert page.read_bytes().startswith(b"\x89PNG")


def test_benchmarks_call_the_flows_with_their_parameters():
    """Benchmarks are not run by the tests: a flow parameter that moved (the database URL
    became a setting) must still not leave them calling the flow with it."""
    import ast
    import inspect

    from pipescan.flows.inspect import inspect_archive
    from pipescan.flows.network import inspect_network

    accepted = {
        flow.fn.__name__: set(inspect.signature(flow.fn).parameters)
        for flow in (inspect_archive, inspect_network)
    }
    wrong = []
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        # Calls of a flow by name, or of a name bound to flow.with_options(...).
        aliases = {name: name for name in accepted}
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Assign)
                and isinstance(node.value, ast.Call)
                and isinstance(node.value.func, ast.Attribute)
                and node.value.func.attr == "with_options"
                and isinstance(node.value.func.value, ast.Name)
                and node.value.func.value.id in accepted
            ):
                for target in node.targets:
                    if isinstance(target, ast.Name):
                        aliases[target.id] = node.value.func.value.id
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
                flow_name = aliases.get(node.func.id)
                if flow_name is None:
                    continue
                for kw in node.keywords:
                    if kw.arg is not None and kw.arg not in accepted[flow_name]:
                        wrong.append(f"{path.name}:{node.lineno}: {flow_name}({kw.arg}=...)")
    assert not wrong, wrong
