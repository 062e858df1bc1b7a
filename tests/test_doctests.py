"""The examples in pipescan's docstrings run, and say what they show."""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pipescan"


def _modules_with_examples() -> list[str]:
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if ">>>" in path.read_text(encoding="utf-8"):
            relative = path.relative_to(PACKAGE.parent).with_suffix("")
            names.append(".".join(relative.parts).removesuffix(".__init__"))
    return names


MODULES = _modules_with_examples()


def test_examples_are_found():
    assert "pipescan.core.grading" in MODULES and "pipescan.core.contour" in MODULES
    # The whole package is searched, not only the core: every layer with examples runs them.
    layers = {name.split(".")[1] for name in MODULES}
    assert {"core", "storage", "exports", "reports", "tasks", "flows", "cli", "web"} <= layers
    # Examples marked ``doctest: +SKIP`` (they need files) are found but not run.
    assert doctest.testmod(importlib.import_module("pipescan.core.summary")).attempted >= 5


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name: str) -> None:
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS, verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
