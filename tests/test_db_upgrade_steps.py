"""``pipescan db upgrade`` lists the migrations it ran, and what each means for rows stored
before it (older defects have no clock positions)."""

from __future__ import annotations

from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.flows.database import migration_steps
from pipescan.storage.database.db import head_revision


def test_db_upgrade_lists_the_steps_it_ran(tmp_path):
    db = f"sqlite:///{tmp_path / 'u.db'}"
    first = CliRunner().invoke(app, ["db", "upgrade", "--db", db, "--revision", "3f8a61c2d7e4"])
    assert first.exit_code == 0, first.output
    lines = first.output.strip().splitlines()
    assert lines[0] == "database migrated from empty to revision 3f8a61c2d7e4:"
    assert [line.split()[0] for line in lines[1:]] == [
        "c5e1a9f40b21",
        "7d2b4e91c3a8",
        "3f8a6c2d9e17",
        "a61c0e5d2b94",
        "3f8a61c2d7e4",
    ]
    second = CliRunner().invoke(app, ["db", "upgrade", "--db", db])
    assert second.exit_code == 0, second.output
    assert second.output.splitlines()[:2] == [
        f"database migrated from 3f8a61c2d7e4 to revision {head_revision()}:",
        "  3f6c2d8a1b47 Clock positions and characterisation of each defect. All three are "
        "NULL for defects stored before: they were not coded.",
    ]
    assert second.output.splitlines()[2] == (
        "  8b1e4c7d2a90 Whether each defect's figure is a lower bound. NULL for defects "
        "stored before: sections with water in the invert were not coded then, so none of them "
        "is a lower bound."
    )
    assert second.output.splitlines()[3] == (
        "  5d2e8b7c4a16 The 95 % uncertainty of each section's water depth. NULL for sections "
        "stored before: their water depth was read without a stated ±, and from the axis "
        "rather than the wall's own circle."
    )
    again = CliRunner().invoke(app, ["db", "upgrade", "--db", db])
    assert again.output.strip() == f"database already at revision {head_revision()}"


def test_a_downgrade_lists_what_it_undid():
    assert migration_steps("3f6c2d8a1b47", "3f8a61c2d7e4") == [
        "undone 3f6c2d8a1b47 Clock positions and characterisation of each defect."
    ]
    assert migration_steps("x", "x") == []
