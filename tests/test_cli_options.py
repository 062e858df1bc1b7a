"""Options that name a registry entry, as a user meets them: the CLI run as a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipescan.core.contour import CONTOUR_METHODS


def run_cli(args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pipescan.cli", *args],
        cwd=cwd,
        env={**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false", **env},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.mark.parametrize("command", ["inspect", "inspect-network"])
def test_an_unknown_contour_method_is_one_line_and_nothing_runs(command, tmp_path):
    store = tmp_path / "store"
    store.mkdir()
    db = tmp_path / "p.db"
    known = ", ".join(CONTOUR_METHODS)
    given = run_cli([command, str(store), "--db", f"sqlite:///{db}", "--contour", "polr"], tmp_path)
    from_env = run_cli(
        [command, str(store), "--db", f"sqlite:///{db}"], tmp_path, PIPESCAN_CONTOUR_METHOD="polr"
    )
    for result, origin in ((given, "--contour 'polr'"), (from_env, "PIPESCAN_CONTOUR_METHOD")):
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1, result.stderr
        assert origin in lines[0] and known in lines[0]
    assert not db.exists()


def test_help_lists_the_registered_contour_methods(tmp_path):
    result = run_cli(["inspect", "--help"], tmp_path, COLUMNS="200")
    assert result.returncode == 0
    assert " or ".join(CONTOUR_METHODS) in result.stdout
