"""The database: migrations, engine setup, and the repository's save/get round trips.

Tests that take ``db_url`` or ``engine`` (tests/conftest.py) run twice: on a new SQLite file
and on a new database of a real PostgreSQL server. Tests of SQLite's own set-up (WAL, busy
timeout, migrate on first use, file locking across processes) take ``sqlite_url``.
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import sqlite3
import threading
import time
from dataclasses import replace
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory

from pipescan.core.model import Defect, FrameQuality, InspectionMeta, SectionMeasures, SectionStatus
from pipescan.storage.database import db, repository
from pipescan.storage.database.models import Base, Inspection, Section
from tests.conftest import is_sqlite

TABLES = {"assets", "inspections", "sections", "defects", "frame_quality", "network_pipes"}
NOMINAL_DIAMETER_M = 0.6
NOMINAL_AREA_M2 = math.pi * NOMINAL_DIAMETER_M**2 / 4


# ---------------------------------------------------------------------------------------------
# Known data


def make_meta(asset_id: str = "MH1042-MH1043", **changes: object) -> InspectionMeta:
    meta = InspectionMeta(
        asset_id=asset_id,
        inspected_at=datetime(2026, 3, 4, 9, 30, tzinfo=timezone(timedelta(hours=2))),
        nominal_diameter_m=NOMINAL_DIAMETER_M,
        upstream_node="MH1042",
        downstream_node="MH1043",
        material="concrete",
    )
    return replace(meta, **changes)  # type: ignore[arg-type]


def make_sections(count: int = 5) -> list[SectionMeasures]:
    """``count`` sections of 0.1 m from 0; the last is unmeasured (no figures, no contour)."""
    angles = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    sections = []
    for i in range(count - 1):
        radius_m = 0.3 - 0.01 * i
        contour_m = np.column_stack([radius_m * np.cos(angles), radius_m * np.sin(angles)])
        open_area_m2 = math.pi * radius_m**2
        sections.append(
            SectionMeasures(
                chainage_start_m=i / 10,
                chainage_end_m=(i + 1) / 10,
                nominal_area_m2=NOMINAL_AREA_M2,
                status=SectionStatus.OK,
                point_count=1000 + i,
                coverage_ratio=0.95,
                open_area_m2=open_area_m2,
                blockage_ratio=1 - open_area_m2 / NOMINAL_AREA_M2,
                ovality_ratio=0.01 * i,
                deformation_ratio=0.005 * i,
                deposit_height_ratio=0.0 if i == 0 else 0.02 * i,
                grade=4 - i,
                contour_m=contour_m,
            )
        )
    sections.append(
        SectionMeasures(
            chainage_start_m=(count - 1) / 10,
            chainage_end_m=count / 10,
            nominal_area_m2=NOMINAL_AREA_M2,
            status=SectionStatus.TOO_FEW_POINTS,
            point_count=3,
            coverage_ratio=0.1,
        )
    )
    return sections


DEFECTS = [
    Defect(
        code="BBC",
        measure="deposit_height_ratio",
        chainage_start_m=0.2,
        chainage_end_m=0.4,
        peak_chainage_m=0.3,
        peak_value=0.06,
        peak_blockage_ratio=0.12,
        grade=2,
        clock_from_h=4.25,
        clock_to_h=7.75,
        lower_bound=True,  # storage keeps the flag whatever the code
    ),
    Defect(
        code="BAA",
        measure="deformation_ratio",
        chainage_start_m=0.1,
        chainage_end_m=0.2,
        peak_chainage_m=0.1,
        peak_value=0.05,
        peak_blockage_ratio=None,
        grade=None,
        characterisation="A",
    ),
]
FRAME_QUALITY = [
    FrameQuality(index=0, fitness=1.0, rmse_m=0.0, degenerate=False),
    FrameQuality(index=1, fitness=0.93, rmse_m=0.004, degenerate=True),
]
PARAMS = {"section_step_m": 0.1, "contour_method": "alpha_shape", "voxel_m": 0.01}


def _inspection_arguments() -> dict[str, object]:
    """What every saved test inspection has, for ``save`` and ``item``."""
    return {
        "meta": make_meta(),
        "archive_uri": "/scans/run1.zip",
        "content_hash": "sha256:aaaa",
        "params": PARAMS,
        "software_version": "0.1.0",
        "sections": make_sections(),
        "defects": DEFECTS,
        "frame_quality": FRAME_QUALITY,
    }


def save(engine: sa.Engine, **changes: object) -> int:
    arguments: dict[str, object] = {
        **_inspection_arguments(),
        "registration": {"mean_fitness": 0.965, "rmse_m": 0.002, "degenerate_frames": 1},
        "threshold_table": "vsa-2023",
        "point_count": 123_456,
        "frame_count": 2,
        "scanned_length_m": 0.5,
    }
    arguments.update(changes)
    return repository.save_inspection(engine, repository.InspectionToSave(**arguments))  # type: ignore[arg-type]


def count_rows(engine: sa.Engine, table: str) -> int:
    with engine.connect() as connection:
        return connection.exec_driver_sql(f"SELECT count(*) FROM {table}").scalar_one()


def summary_columns(engine: sa.Engine) -> list[tuple[object, ...]]:
    with engine.connect() as connection:
        return [
            tuple(row)
            for row in connection.exec_driver_sql(
                "SELECT id, measured_section_count, mean_blockage_ratio, peak_blockage_ratio,"
                " peak_chainage_start_mm FROM inspections ORDER BY id"
            )
        ]


@pytest.fixture
def sqlite_engine(sqlite_url: str):
    engine = db.connect(sqlite_url)
    yield engine
    engine.dispose()


# ---------------------------------------------------------------------------------------------
# Migrations


def test_one_head_in_a_date_prefixed_file() -> None:
    scripts = ScriptDirectory.from_config(db.alembic_config())
    assert len(scripts.get_heads()) == 1
    assert scripts.get_heads()[0] == db.head_revision()
    files = sorted(p.name for p in (db.MIGRATIONS_DIR / "versions").glob("2*.py"))
    assert files == [
        "2026_11_23_0001_initial_schema.py",
        "2026_11_23_1620_inspection_blockage_summary.py",
        "2026_12_01_1530_network_pipes_and_survey_geometry.py",
        "2026_12_01_1600_uncertainty_water_start_source.py",
        "2026_12_01_1700_section_chainage_uncertainty.py",
        "2026_12_01_1800_defect_clock_positions.py",
        "2026_12_07_1900_defect_lower_bound.py",
        "2026_12_07_2300_section_water_depth_uncertainty.py",
    ]
    assert scripts.get_revision(db.head_revision()).path.endswith(files[-1])
    # One line of revisions, oldest file first.
    chain = [r.revision for r in scripts.walk_revisions()][::-1]
    assert [scripts.get_revision(r).path.rsplit("/", 1)[-1] for r in chain] == files


def test_migration_matches_models(engine: sa.Engine) -> None:
    with engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        assert compare_metadata(context, Base.metadata) == []

        # The comparison does see a difference when there is one.
        changed = sa.MetaData(naming_convention=Base.metadata.naming_convention)
        for table in Base.metadata.tables.values():
            table.to_metadata(changed)
        sa.Table("sections", changed, sa.Column("extra_ratio", sa.Float()), extend_existing=True)
        changed.tables["inspections"].c.status.nullable = True
        diffs = compare_metadata(context, changed)
    kinds = sorted(str(d[0][0] if isinstance(d, list) else d[0]) for d in diffs)
    assert kinds == ["add_column", "modify_nullable"]


def test_connect_migrates_a_new_file_and_creates_its_folder(tmp_path: Path) -> None:
    path = tmp_path / "deep" / "er" / "pipescan.db"
    engine = db.connect(f"sqlite:///{path}")
    try:
        assert path.is_file()
        assert db.current_revision(engine) == db.head_revision()
        assert set(sa.inspect(engine).get_table_names()) >= TABLES
        # A second connect on a database at head changes nothing.
        save(engine)
        db.connect(f"sqlite:///{path}").dispose()
        assert count_rows(engine, "sections") == 5
    finally:
        engine.dispose()


def test_connect_migrates_an_outdated_sqlite_file(sqlite_url: str) -> None:
    engine = db.create_engine_for(sqlite_url)
    db.upgrade(engine)
    db.downgrade(engine, "base")
    assert db.current_revision(engine) is None
    engine.dispose()
    engine = db.connect(sqlite_url)
    assert db.current_revision(engine) == db.head_revision()
    engine.dispose()


def test_connect_on_an_outdated_database(db_url: str) -> None:
    # At the first revision: SQLite is brought to head on first use, PostgreSQL is left to
    # the operator and refused until then.
    first = ScriptDirectory.from_config(db.alembic_config()).get_base()
    assert first is not None and first != db.head_revision()
    db.upgrade(db_url, first)
    if is_sqlite(db_url):
        engine = db.connect(db_url)
        assert db.current_revision(engine) == db.head_revision()
        engine.dispose()
        return
    with pytest.raises(db.StorageError, match=rf"{first}.*pipescan db upgrade"):
        db.connect(db_url)
    engine = db.create_engine_for(db_url)
    try:
        assert db.current_revision(engine) == first  # nothing was migrated
    finally:
        engine.dispose()


def test_connect_refuses_a_revision_it_does_not_know(engine: sa.Engine, db_url: str) -> None:
    with engine.begin() as connection:
        connection.exec_driver_sql("UPDATE alembic_version SET version_num = 'ffffffffffff'")
    with pytest.raises(db.StorageError, match=r"ffffffffffff.*upgrade pipescan"):
        db.connect(db_url)


def test_connect_refuses_an_empty_postgres_database(postgres_url: str) -> None:
    with pytest.raises(db.StorageError, match=r"none \(empty database\).*pipescan db upgrade"):
        db.connect(postgres_url)
    db.upgrade(postgres_url)
    db.connect(postgres_url).dispose()


def test_unreachable_server_is_a_storage_error() -> None:
    from tests.pg_cluster import free_port

    url = f"postgresql+psycopg://nobody@127.0.0.1:{free_port()}/nothing?connect_timeout=2"
    with pytest.raises(db.StorageError, match=r"(?s)cannot open database.*server is running"):
        db.connect(url)


def test_upgrade_downgrade_upgrade_with_data(engine: sa.Engine) -> None:
    first = save(engine)
    save(engine, params={**PARAMS, "voxel_m": 0.02})
    assert count_rows(engine, "inspections") == 2

    db.downgrade(engine, "base")
    assert db.current_revision(engine) is None
    assert not TABLES & set(sa.inspect(engine).get_table_names())

    db.upgrade(engine, "head")
    assert db.current_revision(engine) == db.head_revision()
    second = save(engine)
    assert repository.list_sections(engine, second) == make_sections()
    # Ids are never reused: the sqlite_sequence restarts only with the table.
    assert second >= first
    if engine.dialect.name == "sqlite":
        # Foreign keys are back on after the migration switched them off.
        with engine.connect() as connection:
            assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar_one() == 1


def test_blockage_summary_migration_with_data(engine: sa.Engine) -> None:
    # Down below the summary and up again: the summary columns are dropped, then filled in from the
    # sections by the migration, to exactly what save_inspection wrote.
    measured = save(engine)
    unmeasured = save(
        engine, content_hash="sha256:none", sections=[make_sections()[-1]], defects=[]
    )
    written = summary_columns(engine)
    assert written[0][:2] == (measured, 4)
    assert written[1] == (unmeasured, 0, None, None, None)
    # Peak: the first section, the one with the smallest contour (radius 0.3 - 0.01 * 3).
    assert written[0][3] == pytest.approx(1 - (0.27 / 0.3) ** 2)
    assert written[0][4] == 300

    # To the revision before the summary (later migrations go down with it).
    db.downgrade(engine, "c5e1a9f40b21")
    columns = {c["name"] for c in sa.inspect(engine).get_columns("inspections")}
    assert "peak_blockage_ratio" not in columns
    assert count_rows(engine, "sections") == 6
    db.upgrade(engine)
    migrated = summary_columns(engine)
    assert [r[:2] for r in migrated] == [r[:2] for r in written]
    assert migrated[0][2] == pytest.approx(written[0][2], rel=1e-12)
    assert migrated[0][3:] == written[0][3:]
    assert migrated[1] == written[1]
    # A re-save of the same work keeps its id.
    replacement = save(
        engine, content_hash="sha256:none", sections=[make_sections()[-1]], defects=[]
    )
    assert replacement == unmeasured
    # SQLite's AUTOINCREMENT survived the table copy: the newest inspection's id, once it is
    # deleted, is not handed to the next one.
    with engine.begin() as connection:
        connection.execute(sa.text("DELETE FROM inspections WHERE id = :id"), {"id": unmeasured})
    later = save(engine, content_hash="sha256:later", sections=[make_sections()[-1]], defects=[])
    assert later > unmeasured


def test_uncertainty_and_water_migration_with_data(engine: sa.Engine) -> None:
    # Down one step: the uncertainty, water and start-source columns go, the sections stay;
    # up again: they come back empty for what was stored without them.
    inspection_id = save(engine)
    with engine.connect() as connection:
        before = connection.execute(
            sa.select(Section.chainage_start_mm, Section.blockage_ratio).order_by(
                Section.chainage_start_mm
            )
        ).all()
    db.downgrade(engine, "3f8a6c2d9e17")  # the revision before uncertainty and water
    columns = {c["name"] for c in sa.inspect(engine).get_columns("sections")}
    assert "blockage_uncertainty_ratio" not in columns
    assert "water_depth_ratio" not in columns
    inspection_columns = {c["name"] for c in sa.inspect(engine).get_columns("inspections")}
    assert "start_source" not in inspection_columns
    assert count_rows(engine, "sections") == len(before)
    db.upgrade(engine)
    with engine.connect() as connection:
        after = connection.execute(
            sa.select(
                Section.chainage_start_mm,
                Section.blockage_ratio,
                Section.blockage_uncertainty_ratio,
                Section.water_depth_ratio,
            ).order_by(Section.chainage_start_mm)
        ).all()
        source = connection.execute(
            sa.select(Inspection.start_source).where(Inspection.id == inspection_id)
        ).scalar_one()
    assert [tuple(r[:2]) for r in after] == [tuple(r) for r in before]
    assert all(r[2] is None and r[3] is None for r in after)
    assert source is None


def test_chainage_uncertainty_round_trip_and_migration(engine: sa.Engine) -> None:
    sections = [
        dataclasses.replace(s, chainage_uncertainty_m=0.01 * i)
        for i, s in enumerate(make_sections())
    ]
    sections[-1] = dataclasses.replace(sections[-1], chainage_uncertainty_m=None)
    inspection_id = save(engine, sections=sections)
    stored = repository.list_sections(engine, inspection_id)
    assert [s.chainage_uncertainty_m for s in stored] == [0.0, 0.01, 0.02, 0.03, None]
    # Down to the revision before it: the column goes, the sections stay; up again: it is
    # back, unknown (NULL).
    db.downgrade(engine, "a61c0e5d2b94")
    columns = {c["name"] for c in sa.inspect(engine).get_columns("sections")}
    assert "chainage_uncertainty_m" not in columns
    assert count_rows(engine, "sections") == 5
    db.upgrade(engine)
    again = repository.list_sections(engine, inspection_id)
    assert [s.chainage_uncertainty_m for s in again] == [None] * 5
    assert [s.blockage_ratio for s in again] == [s.blockage_ratio for s in stored]


def test_water_depth_uncertainty_round_trip_and_migration(engine: sa.Engine) -> None:
    sections = [
        dataclasses.replace(
            s,
            status=SectionStatus.INVERT_UNDER_WATER,
            water_depth_ratio=0.06,
            water_depth_uncertainty_ratio=0.008,
        )
        for s in make_sections()
    ]
    sections[-1] = dataclasses.replace(
        sections[-1], water_depth_ratio=None, water_depth_uncertainty_ratio=None
    )
    inspection_id = save(engine, sections=sections)
    stored = repository.list_sections(engine, inspection_id)
    assert [s.water_depth_uncertainty_ratio for s in stored] == [0.008] * 4 + [None]
    # Down to the revision before it: the column goes, the sections and their depths stay;
    # up again: it is back, unknown (NULL).
    db.downgrade(engine, "8b1e4c7d2a90")
    columns = {c["name"] for c in sa.inspect(engine).get_columns("sections")}
    assert "water_depth_uncertainty_ratio" not in columns
    db.upgrade(engine)
    again = repository.list_sections(engine, inspection_id)
    assert [s.water_depth_uncertainty_ratio for s in again] == [None] * 5
    assert [s.water_depth_ratio for s in again] == [s.water_depth_ratio for s in stored]


def test_defect_clock_positions_migration_with_data(engine: sa.Engine) -> None:
    # Down one step: the defects stay, without their clock positions; up again: they come
    # back empty (NULL: not coded), and new saves fill them in.
    first = save(engine)
    db.downgrade(engine, "3f8a61c2d7e4")  # the revision before the clock positions
    columns = {c["name"] for c in sa.inspect(engine).get_columns("defects")}
    assert {"clock_from_h", "clock_to_h", "characterisation"}.isdisjoint(columns)
    assert count_rows(engine, "defects") == 2
    db.upgrade(engine)
    before = repository.list_defects(engine, first)
    assert [(d.code, d.clock_from_h, d.clock_to_h, d.characterisation) for d in before] == [
        ("BAA", None, None, None),
        ("BBC", None, None, None),
    ]
    # Stored before the lower bound was recorded: none was one (water was never coded).
    assert [d.lower_bound for d in before] == [False, False]
    again = save(engine, content_hash="sha256:again")
    assert repository.list_defects(engine, again) == [DEFECTS[1], DEFECTS[0]]


def test_unknown_revision_raises_storage_error(engine: sa.Engine) -> None:
    with pytest.raises(db.StorageError, match="nonexistent"):
        db.upgrade(engine, "nonexistent")
    assert db.current_revision(engine) == db.head_revision()


# ---------------------------------------------------------------------------------------------
# Engine setup


def test_sqlite_pragmas(sqlite_engine: sa.Engine, sqlite_url: str) -> None:
    with sqlite_engine.connect() as connection:
        assert connection.exec_driver_sql("PRAGMA journal_mode").scalar_one() == "wal"
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar_one() == 1
        busy_ms = connection.exec_driver_sql("PRAGMA busy_timeout").scalar_one()
        assert busy_ms == db.SQLITE_BUSY_TIMEOUT_S * 1000
    # WAL is a property of the file: a plain sqlite3 connection sees it too.
    raw = sqlite3.connect(sqlite_url.removeprefix("sqlite:///"))
    try:
        assert raw.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    finally:
        raw.close()


def test_deleting_an_inspection_cascades(engine: sa.Engine) -> None:
    inspection_id = save(engine)
    with engine.begin() as connection:
        connection.execute(sa.text("DELETE FROM inspections WHERE id = :id"), {"id": inspection_id})
    for table in ("sections", "defects", "frame_quality"):
        assert count_rows(engine, table) == 0
    assert count_rows(engine, "assets") == 1


@pytest.mark.parametrize("url", ["not a url", "postgresql://h:port/db"])
def test_bad_url_raises_storage_error(url: str) -> None:
    from pipescan.flows.database import absolute_database_url

    with pytest.raises(db.StorageError, match="cannot parse"):
        db.create_engine_for(url)
    with pytest.raises(db.StorageError, match="cannot parse"):
        absolute_database_url(url)  # what a run checks first


def test_session_scope_rolls_back_on_error(engine: sa.Engine) -> None:
    save(engine)
    with pytest.raises(RuntimeError), db.session_scope(engine, write=True) as session:
        session.execute(sa.text("DELETE FROM sections"))
        raise RuntimeError("boom")
    assert count_rows(engine, "sections") == 5


# ---------------------------------------------------------------------------------------------
# Repository


def test_sections_round_trip(engine: sa.Engine) -> None:
    inspection_id = save(engine)
    expected = make_sections()
    stored = repository.list_sections(engine, inspection_id)
    # Dataclass equality compares every field but the contour.
    assert stored == expected
    unmeasured = stored[-1]
    assert unmeasured.status is SectionStatus.TOO_FEW_POINTS
    assert unmeasured.open_area_m2 is None
    assert unmeasured.blockage_ratio is None
    assert unmeasured.grade is None
    assert unmeasured.contour_m is None
    assert stored[0].deposit_height_ratio == 0.0  # a measured 0 stays 0, not None
    for got, want in zip(stored[:-1], expected[:-1], strict=True):
        assert got.contour_m is not None and want.contour_m is not None
        assert got.contour_m.shape == want.contour_m.shape == (36, 2)
        assert got.contour_m.dtype == np.float64
        # Stored to the millimetre.
        np.testing.assert_allclose(got.contour_m, want.contour_m, atol=0.0005 + 1e-12)
    assert [s.chainage_start_m for s in stored] == [0.0, 0.1, 0.2, 0.3, 0.4]


def test_chainages_are_keyed_to_the_millimetre(engine: sa.Engine) -> None:
    # Accumulated float error (0.1 * 3 != 0.3) does not survive: keys are whole millimetres.
    section = replace(make_sections(1)[0], chainage_start_m=0.1 * 3, chainage_end_m=0.1 * 4)
    assert section.chainage_start_m != 0.3
    stored = repository.list_sections(engine, save(engine, sections=[section]))[0]
    assert (stored.chainage_start_m, stored.chainage_end_m) == (0.3, 0.4)
    with engine.connect() as connection:
        keys = connection.exec_driver_sql("SELECT chainage_start_mm, chainage_end_mm FROM sections")
        assert keys.all() == [(300, 400)]


def test_inspection_record(engine: sa.Engine) -> None:
    inspection_id = save(engine)
    record = repository.get_inspection(engine, inspection_id)
    assert record.id == inspection_id
    assert record.asset_id == "MH1042-MH1043"
    # 09:30 at +02:00 is 07:30 UTC, and comes back aware.
    assert record.inspected_at == datetime(2026, 3, 4, 7, 30, tzinfo=UTC)
    assert record.inspected_at.utcoffset() == timedelta(0)
    assert record.created_at.tzinfo is not None
    assert abs(record.created_at - datetime.now(UTC)) < timedelta(minutes=1)
    assert record.params == PARAMS
    assert record.params_hash == repository.params_hash(PARAMS)
    assert record.registration == {
        "mean_fitness": 0.965,
        "rmse_m": 0.002,
        "degenerate_frames": 1,
    }
    assert (record.point_count, record.frame_count, record.scanned_length_m) == (123_456, 2, 0.5)
    assert (record.threshold_table, record.status, record.section_count) == ("vsa-2023", "ok", 5)
    assert (record.upstream_node, record.downstream_node) == ("MH1042", "MH1043")
    assert (record.nominal_diameter_m, record.pipe_shape, record.material) == (
        0.6,
        "circular",
        "concrete",
    )
    assert repository.list_inspections(engine) == [record]


def test_defects_and_frame_quality_round_trip(engine: sa.Engine) -> None:
    inspection_id = save(engine)
    # Ordered by start chainage.
    assert repository.list_defects(engine, inspection_id) == [DEFECTS[1], DEFECTS[0]]
    assert repository.list_frame_quality(engine, inspection_id) == FRAME_QUALITY


def test_params_hash_is_canonical() -> None:
    a = repository.params_hash({"b": (1, 2), "a": np.float64(0.5), "c": SectionStatus.OK})
    b = repository.params_hash({"a": 0.5, "c": "ok", "b": [1, 2]})
    assert a == b
    assert a != repository.params_hash({"a": 0.5, "c": "ok", "b": [1, 3]})
    with pytest.raises(db.StorageError, match="params"):
        repository.params_hash({"x": float("nan")})


def test_resaving_the_same_archive_and_params_replaces_under_the_same_id(
    engine: sa.Engine,
) -> None:
    first = save(engine)
    other = save(engine, content_hash="sha256:other")
    # Fewer sections the second time: leftovers of the first save would show.
    second = save(engine, sections=make_sections(3), archive_uri="/moved/run1.zip")
    assert count_rows(engine, "inspections") == 2
    assert count_rows(engine, "sections") == 3 + len(make_sections())
    assert count_rows(engine, "defects") == 2 * len(DEFECTS)
    assert count_rows(engine, "frame_quality") == 2 * len(FRAME_QUALITY)
    # Reports and exports quote the id: the re-saved inspection keeps it.
    assert second == first
    assert [r.id for r in repository.list_inspections(engine)] == [first, other]
    assert repository.get_inspection(engine, first).archive_uri == "/moved/run1.zip"
    assert repository.list_sections(engine, first) == make_sections(3)
    # A batch that re-saves one inspection and adds another: each gets its right id.
    ids = repository.save_inspections(
        engine,
        [
            item(content_hash="sha256:third"),
            item(content_hash="sha256:other", sections=make_sections(2)),
        ],
    )
    assert ids[1] == other and ids[0] > other
    assert repository.list_sections(engine, other) == make_sections(2)


def test_other_params_or_archive_add_an_inspection(engine: sa.Engine) -> None:
    first = save(engine)
    second = save(engine, params={**PARAMS, "contour_method": "paper"})
    third = save(engine, content_hash="sha256:bbbb")
    assert len({first, second, third}) == 3
    assert count_rows(engine, "inspections") == 3
    assert count_rows(engine, "sections") == 15
    assert count_rows(engine, "assets") == 1
    # Same inspection date: the last saved is the latest.
    assert repository.find_latest_inspection_id(engine) == third
    assert repository.find_latest_inspection_id(engine, "MH1042-MH1043") == third
    assert repository.find_latest_inspection_id(engine, "other") is None


def test_a_failure_after_the_sections_leaves_the_previous_save(
    engine: sa.Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    first = save(engine)

    def fail(*args: object) -> None:
        raise RuntimeError("disk full")

    monkeypatch.setattr(repository, "_insert_defects", fail)
    with pytest.raises(RuntimeError, match="disk full"):
        save(engine, sections=make_sections(2))
    assert [r.id for r in repository.list_inspections(engine)] == [first]
    assert repository.list_sections(engine, first) == make_sections()
    assert count_rows(engine, "defects") == len(DEFECTS)


def test_a_section_the_database_refuses_leaves_the_previous_save(
    engine: sa.Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    first = save(engine)
    # Bypass the Python-side checks so the database's CHECK constraint has to catch it.
    original = repository._section_row

    def bad_coverage(section: SectionMeasures) -> dict[str, object]:
        return {**original(section), "coverage_ratio": 1.5}

    monkeypatch.setattr(repository, "_section_row", bad_coverage)
    with pytest.raises(db.StorageError, match="coverage_range"):
        save(engine)
    assert [r.id for r in repository.list_inspections(engine)] == [first]
    assert repository.list_sections(engine, first) == make_sections()


def item(**changes: object) -> repository.InspectionToSave:
    arguments = _inspection_arguments()
    arguments.update(changes)
    return repository.InspectionToSave(**arguments)  # type: ignore[arg-type]


def test_save_inspections_in_one_transaction(engine: sa.Engine) -> None:
    replaced = save(engine, content_hash="sha256:b")
    batch = [
        item(content_hash="sha256:a", sections=make_sections(3)),
        item(meta=make_meta("OTHER", material=None), content_hash="sha256:o"),
        item(content_hash="sha256:b", sections=make_sections(2), defects=[]),  # replaces
        item(meta=make_meta("OTHER", material="PVC", upstream_node=None), content_hash="x"),
    ]
    ids = repository.save_inspections(engine, batch)
    assert len(set(ids)) == 4
    assert ids[2] == replaced  # a replaced save keeps its id
    # Each id holds its own item's rows.
    for inspection_id, it in zip(ids, batch, strict=True):
        record = repository.get_inspection(engine, inspection_id)
        assert (record.asset_id, record.content_hash) == (it.meta.asset_id, it.content_hash)
        assert repository.list_sections(engine, inspection_id) == list(it.sections)
        assert len(repository.list_defects(engine, inspection_id)) == len(it.defects)
        assert record.measured_section_count == sum(
            1 for x in it.sections if x.status is SectionStatus.OK
        )
    assert count_rows(engine, "inspections") == 4
    assert count_rows(engine, "sections") == 3 + 5 + 2 + 5
    # Asset attributes merge in order, as consecutive saves would.
    other = {a.asset_id: a for a in repository.list_assets(engine)}["OTHER"]
    assert (other.upstream_node, other.material) == ("MH1042", "PVC")
    assert repository.save_inspections(engine, []) == []


def test_a_repeated_item_in_a_batch_is_saved_once(engine: sa.Engine) -> None:
    ids = repository.save_inspections(
        engine, [item(sections=make_sections(2)), item(sections=make_sections(4))]
    )
    assert ids[0] == ids[1]  # the later replaced the earlier
    assert repository.list_sections(engine, ids[0]) == make_sections(4)
    assert count_rows(engine, "inspections") == 1


def test_a_failing_batch_writes_nothing(engine: sa.Engine, monkeypatch: pytest.MonkeyPatch) -> None:
    first = save(engine)
    # Validation: the bad item is found before anything is written.
    bad = item(content_hash="new", sections=[replace(make_sections(1)[0], coverage_ratio=2.0)])
    with pytest.raises(db.StorageError, match="coverage_ratio"):
        repository.save_inspections(engine, [item(content_hash="sha256:c"), bad])
    # The database: a CHECK fails in the middle of the batch.
    original = repository._section_row

    def bad_coverage(section: SectionMeasures) -> dict[str, object]:
        row = original(section)
        return {**row, "coverage_ratio": 1.5} if row["chainage_start_mm"] == 300 else row

    monkeypatch.setattr(repository, "_section_row", bad_coverage)
    with pytest.raises(db.StorageError, match="coverage_range"):
        repository.save_inspections(
            engine, [item(content_hash="sha256:d", sections=make_sections(2)), item()]
        )
    assert [r.id for r in repository.list_inspections(engine)] == [first]
    assert count_rows(engine, "sections") == 5


@pytest.mark.parametrize(
    ("sections", "match"),
    [
        (
            [*make_sections(2), replace(make_sections(2)[0], chainage_end_m=0.05)],
            "two sections share the key 0 mm",
        ),
        ([replace(make_sections(1)[0], chainage_end_m=0.0004)], "chainage_end_m"),
        ([replace(make_sections(1)[0], coverage_ratio=1.2)], "coverage_ratio"),
        ([replace(make_sections(1)[0], coverage_ratio=math.nan)], "coverage_ratio"),
        ([replace(make_sections(1)[0], status="melted")], "unknown status 'melted'"),
    ],
)
def test_invalid_sections_are_refused_before_writing(
    engine: sa.Engine, sections: list[SectionMeasures], match: str
) -> None:
    first = save(engine)
    with pytest.raises(db.StorageError, match=match):
        save(engine, sections=sections)
    assert repository.list_sections(engine, first) == make_sections()


def test_nan_figures_are_stored_as_null(engine: sa.Engine) -> None:
    section = replace(make_sections(1)[0], blockage_ratio=math.nan, open_area_m2=math.nan)
    inspection_id = save(engine, sections=[section])
    stored = repository.list_sections(engine, inspection_id)[0]
    assert stored.blockage_ratio is None
    assert stored.open_area_m2 is None


def test_naive_inspected_at_is_taken_as_utc(engine: sa.Engine) -> None:
    inspection_id = save(engine, meta=make_meta(inspected_at=datetime(2024, 5, 17)))
    record = repository.get_inspection(engine, inspection_id)
    assert record.inspected_at == datetime(2024, 5, 17, tzinfo=UTC)


def test_non_circular_pipe_without_diameter(engine: sa.Engine) -> None:
    meta = make_meta(nominal_diameter_m=math.nan, pipe_shape="egg")
    section = replace(make_sections(1)[0], nominal_area_m2=math.nan, blockage_ratio=None)
    inspection_id = save(engine, meta=meta, sections=[section])
    record = repository.get_inspection(engine, inspection_id)
    assert record.nominal_diameter_m is None
    assert record.pipe_shape == "egg"
    assert math.isnan(repository.list_sections(engine, inspection_id)[0].nominal_area_m2)


def test_assets_and_their_upsert(engine: sa.Engine) -> None:
    save(engine)
    later = datetime(2027, 1, 2, 3, 4, tzinfo=UTC)
    # A newer save without nodes keeps the known nodes but updates what it does give.
    save(
        engine,
        meta=make_meta(inspected_at=later, upstream_node=None, material="PVC"),
        content_hash="sha256:cccc",
    )
    save(engine, meta=make_meta("A0-A1", nominal_diameter_m=0.3))
    assets = repository.list_assets(engine)
    assert [a.asset_id for a in assets] == ["A0-A1", "MH1042-MH1043"]
    a0, mh = assets
    assert (a0.inspection_count, a0.nominal_diameter_m) == (1, 0.3)
    assert mh.inspection_count == 2
    assert mh.last_inspected_at == later
    assert (mh.upstream_node, mh.downstream_node, mh.material) == ("MH1042", "MH1043", "PVC")
    assert [r.asset_id for r in repository.list_inspections(engine, "A0-A1")] == ["A0-A1"]
    assert repository.get_asset(engine, "MH1042-MH1043") == mh
    with pytest.raises(db.StorageError, match="no asset 'NONE'"):
        repository.get_asset(engine, "NONE")
    assert repository.find_latest_inspection_id(engine, "NONE") is None


def test_section_trend(engine: sa.Engine) -> None:
    dates = [datetime(2024 + i, 6, 1, tzinfo=UTC) for i in range(3)]
    ids = []
    for i, inspected_at in enumerate(reversed(dates)):  # saved out of date order
        blocked = replace(make_sections()[2], blockage_ratio=0.1 * (2 - i))
        ids.append(
            save(
                engine,
                meta=make_meta(inspected_at=inspected_at),
                content_hash=f"sha256:{i}",
                sections=[*make_sections()[:2], blocked],
            )
        )
    trend = repository.list_section_trend(engine, "MH1042-MH1043", 0.25)
    assert [p.inspected_at for p in trend] == dates
    assert [p.inspection_id for p in trend] == ids[::-1]
    assert [p.section.chainage_start_m for p in trend] == [0.2] * 3
    assert [p.section.blockage_ratio for p in trend] == pytest.approx([0.0, 0.1, 0.2])
    assert repository.list_section_trend(engine, "MH1042-MH1043", 0.3) == []


def test_missing_inspection_is_named(engine: sa.Engine) -> None:
    for get in (
        repository.get_inspection,
        repository.list_sections,
        repository.list_defects,
        repository.list_frame_quality,
    ):
        with pytest.raises(db.StorageError, match="no inspection with id 4242"):
            get(engine, 4242)


# ---------------------------------------------------------------------------------------------
# Concurrency


def test_a_writer_waits_for_the_lock_instead_of_failing(
    sqlite_engine: sa.Engine, sqlite_url: str
) -> None:
    engine = sqlite_engine
    # Another process holds the write lock for 0.5 s.
    blocker = sqlite3.connect(sqlite_url.removeprefix("sqlite:///"), isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")
    outcome: dict[str, object] = {}

    def writer() -> None:
        started = time.monotonic()
        try:
            outcome["id"] = save(engine)
        except Exception as exc:  # reported below
            outcome["error"] = exc
        outcome["waited_s"] = time.monotonic() - started

    thread = threading.Thread(target=writer)
    thread.start()
    time.sleep(0.5)
    blocker.execute("COMMIT")
    blocker.close()
    thread.join(timeout=30)
    assert "error" not in outcome, outcome.get("error")
    assert isinstance(outcome["id"], int)
    assert outcome["waited_s"] >= 0.4  # it did have to wait
    assert count_rows(engine, "inspections") == 1


def _save_many(url: str, worker: int, count: int) -> list[int]:
    engine = db.connect(url)
    try:
        return [
            save(
                engine,
                meta=make_meta(f"W{worker}"),
                content_hash=f"sha256:{worker}-{i}",
                sections=make_sections(20),
            )
            for i in range(count)
        ]
    finally:
        engine.dispose()


def test_concurrent_writers_in_threads(db_url: str) -> None:
    # Separate engines, so separate connections, as in separate workers; on SQLite the first
    # connects race to create and migrate the file too.
    if not is_sqlite(db_url):
        db.upgrade(db_url)
    results: dict[int, list[int]] = {}
    errors: list[BaseException] = []

    def run(worker: int) -> None:
        try:
            results[worker] = _save_many(db_url, worker, 8)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(w,)) for w in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert errors == []
    engine = db.connect(db_url)
    ids = [i for worker_ids in results.values() for i in worker_ids]
    assert len(set(ids)) == 24
    assert count_rows(engine, "inspections") == 24
    assert count_rows(engine, "sections") == 24 * 20
    engine.dispose()


def test_concurrent_writers_in_processes(sqlite_url: str) -> None:
    context = multiprocessing.get_context("spawn")
    with context.Pool(2) as pool:
        results = pool.starmap(_save_many, [(sqlite_url, 0, 5), (sqlite_url, 1, 5)])
    engine = db.connect(sqlite_url)
    assert len({i for ids in results for i in ids}) == 10
    assert count_rows(engine, "inspections") == 10
    assert {a.asset_id: a.inspection_count for a in repository.list_assets(engine)} == {
        "W0": 5,
        "W1": 5,
    }
    engine.dispose()


def test_concurrent_writers_of_one_asset(db_url: str) -> None:
    if not is_sqlite(db_url):
        db.upgrade(db_url)
    errors: list[BaseException] = []

    def run(worker: int) -> None:
        engine = db.connect(db_url)
        try:
            for i in range(5):
                # Every worker saves the same new asset, and the same archive twice over.
                save(engine, content_hash=f"sha256:{i}", sections=make_sections(20))
        except BaseException as exc:
            errors.append(exc)
        finally:
            engine.dispose()

    threads = [threading.Thread(target=run, args=(w,)) for w in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert errors == []
    engine = db.connect(db_url)
    try:
        assert count_rows(engine, "assets") == 1
        assert count_rows(engine, "inspections") == 5
        assert count_rows(engine, "sections") == 5 * 20
    finally:
        engine.dispose()


# ---------------------------------------------------------------------------------------------
# PostgreSQL specifics


def test_postgres_sections_are_copied_and_typed(
    postgres_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    db.upgrade(postgres_url)
    engine = db.connect(postgres_url)
    calls: list[int] = []
    original = repository._copy_sections

    def counting(connection: sa.Connection, owned: list) -> None:
        calls.append(sum(len(rows) for _, rows in owned))
        original(connection, owned)

    monkeypatch.setattr(repository, "_copy_sections", counting)
    try:
        inspection_id = save(engine)
        assert calls == [5]  # the bulk path, not row-by-row INSERTs
        assert repository.list_sections(engine, inspection_id) == make_sections()
        with engine.connect() as connection:
            types = dict(
                connection.exec_driver_sql(
                    "SELECT column_name, data_type FROM information_schema.columns "
                    "WHERE table_name = 'inspections' AND table_schema = current_schema()"
                ).all()
            )
        assert types["inspected_at"] == "timestamp with time zone"
        assert types["params_json"] == "json"
    finally:
        engine.dispose()


def test_a_new_sqlite_file_opened_by_three_threads_at_once(tmp_path: Path) -> None:
    # Switching a new file to WAL fails at once ("database is locked", no busy wait) for all
    # but one of the connections racing to do it: 5 of 40 trials before the retry.
    errors: list[BaseException] = []

    def run(url: str, barrier: threading.Barrier) -> None:
        try:
            barrier.wait()
            db.connect(url).dispose()
        except BaseException as exc:
            errors.append(exc)

    for trial in range(30):
        url = f"sqlite:///{tmp_path / f'race-{trial}.db'}"
        barrier = threading.Barrier(3)
        threads = [threading.Thread(target=run, args=(url, barrier)) for _ in range(3)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
    assert errors == []
