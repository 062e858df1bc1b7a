"""GIS: linear referencing, the network layer import, and the GeoPackage/GeoJSON export read
back with pyogrio (keys, CRS, where the events are)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pyogrio
import pytest
import shapely
import sqlalchemy as sa
from hypothesis import given, settings
from hypothesis import strategies as st
from pyogrio.raw import read, write
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.core.errors import LayerError
from pipescan.core.model import Defect, InspectionMeta, SectionMeasures, SectionStatus
from pipescan.core.network import (
    ORIENTED_BY_DIGITISING,
    ORIENTED_BY_METADATA,
    ORIENTED_BY_NODE_NAMES,
    ORIENTED_BY_NODE_POSITIONS,
    PipeLine,
    length_note,
    orient,
)
from pipescan.exports.gis import GisError, export_gis
from pipescan.storage.database import db, repository
from pipescan.storage.database.network import (
    asset_geometries,
    gis_ids,
    import_network_layer,
    placements,
)
from pipescan.storage.input.network_layer import read_network_layer

CRS = "EPSG:25832"
X0, Y0 = 512_000.0, 5_800_000.0

# ---------------------------------------------------------------------------------------------
# Linear referencing


def test_points_and_cuts_along_a_bent_line() -> None:
    line = PipeLine(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]]))
    assert line.length_m == 7.0
    assert line.point_at(1.5).tolist() == [1.5, 0.0]
    assert line.point_at(3.0).tolist() == [3.0, 0.0]
    assert line.point_at(-1.0).tolist() == [0.0, 0.0]  # clamped
    cut = line.cut(2.0, 5.0)
    assert cut.coords.tolist() == [[2.0, 0.0], [3.0, 0.0], [3.0, 2.0]]
    assert cut.beyond_m == 0.0
    # Past the end: cut there, and the part that did not fit is measured, never stretched.
    cut = line.cut(6.5, 7.4)
    assert cut.coords.tolist() == [[3.0, 3.5], [3.0, 4.0]]
    assert cut.beyond_m == pytest.approx(0.4)
    cut = line.cut(8.0, 9.0)
    assert cut.coords.tolist() == [[3.0, 4.0], [3.0, 4.0]] and cut.beyond_m == 1.0
    with pytest.raises(ValueError, match="length"):
        PipeLine(np.array([[1.0, 1.0], [1.0, 1.0]]))
    with pytest.raises(ValueError, match="finite"):
        PipeLine(np.array([[1.0, 1.0], [np.nan, 1.0]]))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-2, 2)),
        min_size=2,
        max_size=6,
        unique=True,
    ),
    st.floats(0, 1),
    st.floats(0, 1),
)
def test_a_cut_inside_the_line_is_as_long_as_its_span(vertices, a, b) -> None:
    coords = np.array(vertices)
    if np.linalg.norm(np.diff(coords, axis=0), axis=1).min() < 1e-3:
        return
    line = PipeLine(coords)
    start, end = sorted((a * line.length_m, b * line.length_m))
    cut = line.cut(start, end)
    along = np.linalg.norm(np.diff(cut.coords, axis=0), axis=1).sum()
    assert along == pytest.approx(end - start, abs=1e-6)
    assert cut.beyond_m == 0.0
    assert np.allclose(cut.coords[0], line.point_at(start))
    assert np.allclose(cut.coords[-1], line.point_at(end))


def test_orientation_by_names_then_positions_then_digitising() -> None:
    coords = np.array([[0.0, 0.0], [10.0, 0.0]])
    names = {"upstream_node": "A", "downstream_node": "B"}
    line, why = orient(coords, from_node="A", to_node="B", **names)
    assert line.coords[0].tolist() == [0.0, 0.0] and why == ORIENTED_BY_NODE_NAMES
    line, why = orient(coords, from_node="B", to_node="A", **names)
    assert line.coords[0].tolist() == [10.0, 0.0] and why == ORIENTED_BY_NODE_NAMES
    line, why = orient(
        coords,
        from_node=None,
        to_node=None,
        **names,
        upstream_xyz=(9.5, 0.2, 3.0),
        downstream_xyz=(0.1, 0.0, 2.0),
    )
    assert line.coords[0].tolist() == [10.0, 0.0] and why == ORIENTED_BY_NODE_POSITIONS
    line, why = orient(coords, from_node=None, to_node=None, **names)
    assert line.coords[0].tolist() == [0.0, 0.0] and why == ORIENTED_BY_DIGITISING


def test_length_note_only_beyond_two_percent() -> None:
    assert length_note(40.79, 40.0) is None
    assert length_note(39.21, 40.0) is None
    assert "+2.5 %" in length_note(41.0, 40.0)
    assert "not stretched" in length_note(30.0, 40.0)


# ---------------------------------------------------------------------------------------------
# Layers on disk


def write_layer(
    path: Path,
    lines: list[list[tuple[float, ...]]],
    fields: dict[str, list[object]],
    *,
    crs: str | None = CRS,
    layer: str = "pipes",
    geometry_type: str = "LineString",
    driver: str = "GPKG",
    geometries: list[object] | None = None,
) -> Path:
    geoms = geometries if geometries is not None else [shapely.LineString(c) for c in lines]
    write(
        str(path),
        np.array(shapely.to_wkb(geoms), dtype=object),
        [np.array(v, dtype=object) for v in fields.values()],
        list(fields),
        layer=layer,
        driver=driver,
        geometry_type=geometry_type,
        crs=crs,
        append=path.exists() and driver == "GPKG",
    )
    return path


def network_lines() -> list[list[tuple[float, float]]]:
    # SW-1 digitised downstream (MH1 -> MH2), 10 m with a bend; SW-2 digitised upstream
    # (MH3 -> MH2), 20 m; SW-3 not inspected.
    return [
        [(X0, Y0), (X0 + 6.0, Y0), (X0 + 6.0, Y0 + 4.0)],
        [(X0 + 26.0, Y0 + 4.0), (X0 + 6.0, Y0 + 4.0)],
        [(X0 + 26.0, Y0 + 4.0), (X0 + 26.0, Y0 + 40.0)],
    ]


def network_fields() -> dict[str, list[object]]:
    return {
        "FACILITYID": ["SW-1", "SW-2", "SW-3"],
        "UPNODE": ["MH1", "MH3", "MH3"],
        "DOWNNODE": ["MH2", "MH2", "MH4"],
    }


def test_reading_a_layer(tmp_path: Path) -> None:
    path = write_layer(tmp_path / "net.gpkg", network_lines(), network_fields())
    layer = read_network_layer(
        path, id_field="FACILITYID", from_field="UPNODE", to_field="DOWNNODE"
    )
    assert layer.crs == CRS and "net.gpkg" in layer.source
    assert [p.gis_id for p in layer.pipes] == ["SW-1", "SW-2", "SW-3"]
    assert [p.asset_ref for p in layer.pipes] == ["SW-1", "SW-2", "SW-3"]
    assert [(p.from_node, p.to_node) for p in layer.pipes][1] == ("MH3", "MH2")
    assert [p.line.length_m for p in layer.pipes] == [10.0, 20.0, 36.0]
    # Integer ids are read as their digits; a MultiLineString of one part is one line.
    path = write_layer(
        tmp_path / "ints.gpkg",
        [],
        {"ID": [1042, 1043]},
        geometries=[
            shapely.MultiLineString([[(0, 0), (1, 0)]]),
            shapely.MultiLineString([[(1, 0), (2, 0)]]),
        ],
        geometry_type="MultiLineString",
    )
    assert [p.gis_id for p in read_network_layer(path, id_field="ID").pipes] == ["1042", "1043"]


@pytest.mark.parametrize(
    ("case", "field", "message"),
    [
        ("missing-id-field", "FACILITY", "no field 'FACILITY'"),
        ("missing-node-field", "UP", "no field 'UP'"),
        ("one-node-field", "--to-node-field", "given as a pair"),
        ("duplicate-id", "FACILITYID", "id 'SW-1' is on feature 0 and on feature 1"),
        ("empty-id", "FACILITYID", "feature 1 has no value"),
        ("point", "geometry", "feature 0 (SW-1): is a Point, not one line"),
        ("two-parts", "geometry", "MultiLineString of 2 parts"),
        ("no-crs", "crs", "no coordinate reference system"),
        ("geographic", "crs", "geographic CRS"),
        ("degrees", "crs", "looks like degrees"),
        ("two-layers", "layer", "2 layers"),
    ],
)
def test_a_bad_layer_is_refused_naming_file_and_field(
    tmp_path: Path, case: str, field: str, message: str
) -> None:
    path = tmp_path / "net.gpkg"
    lines, fields = network_lines(), network_fields()
    options: dict[str, object] = {"id_field": "FACILITYID"}
    if case == "missing-id-field":
        options["id_field"] = "FACILITY"
    elif case == "missing-node-field":
        options |= {"from_field": "UP", "to_field": "DOWNNODE"}
    elif case == "one-node-field":
        options |= {"from_field": "UPNODE"}
    elif case == "duplicate-id":
        fields["FACILITYID"][1] = "SW-1"
    elif case == "empty-id":
        fields["FACILITYID"][1] = " "
    if case == "point":
        write_layer(
            path,
            [],
            {"FACILITYID": ["SW-1"]},
            geometries=[shapely.Point(X0, Y0)],
            geometry_type="Point",
        )
    elif case == "two-parts":
        write_layer(
            path,
            [],
            {"FACILITYID": ["SW-1"]},
            geometries=[shapely.MultiLineString([[(0, 0), (1, 0)], [(2, 0), (3, 0)]])],
            geometry_type="MultiLineString",
        )
    elif case == "geographic":
        write_layer(path, lines, fields, crs="EPSG:4326")
    elif case == "degrees":
        small = [[(7.0 + x * 1e-5, 52.0 + y * 1e-5) for x, y in [(0, 0), (3, 4)]]]
        write_layer(path, small, {"FACILITYID": ["SW-1"]}, crs="EPSG:3857")
    elif case == "no-crs":
        with pytest.warns(UserWarning, match="crs"):
            write_layer(path, lines, fields, crs=None)
    elif case == "two-layers":
        write_layer(path, lines, fields)
        write_layer(path, lines, fields, layer="copy")
    else:
        write_layer(path, lines, fields)
    with pytest.raises(LayerError) as info:
        read_network_layer(path, **options)  # type: ignore[arg-type]
    assert message in str(info.value)
    assert info.value.field == field
    assert info.value.file == str(path)


# ---------------------------------------------------------------------------------------------
# The database: import, matching, geometry


def meta(asset_id: str, up: str, down: str, **changes: object) -> InspectionMeta:
    base = InspectionMeta(
        asset_id=asset_id,
        inspected_at=datetime(2025, 3, 14, 9, 30, tzinfo=UTC),
        nominal_diameter_m=0.5,
        upstream_node=up,
        downstream_node=down,
    )
    return replace(base, **changes)  # type: ignore[arg-type]


def sections(length_m: float, *, grade_at: float | None = None) -> list[SectionMeasures]:
    count = round(length_m / 0.1)
    return [
        SectionMeasures(
            chainage_start_m=round(i / 10, 3),
            chainage_end_m=round((i + 1) / 10, 3),
            nominal_area_m2=math.pi * 0.25**2,
            status=SectionStatus.OK,
            point_count=900,
            coverage_ratio=1.0,
            open_area_m2=0.18,
            blockage_ratio=0.05 + 0.001 * i,
            grade=1 if grade_at is not None and abs(i / 10 - grade_at) < 1e-9 else 4,
        )
        for i in range(count)
    ]


def save(engine: sa.Engine, m: InspectionMeta, length_m: float, defects=(), **changes) -> int:
    arguments: dict[str, object] = {
        "meta": m,
        "archive_uri": f"{m.asset_id}.zip",
        "content_hash": f"sha256:{m.asset_id}:{m.inspected_at.isoformat()}",
        "params": {"step_m": 0.1},
        "software_version": "0.1.0",
        "sections": sections(length_m, grade_at=defects[0].chainage_start_m if defects else None),
        "defects": list(defects),
        "threshold_table": "vsa-2023",
        "scanned_length_m": length_m,
    }
    arguments.update(changes)
    return repository.save_inspection(engine, repository.InspectionToSave(**arguments))  # type: ignore[arg-type]


def deposit(start_m: float, end_m: float) -> Defect:
    return Defect(
        code="BBC",
        measure="deposit_height_ratio",
        chainage_start_m=start_m,
        chainage_end_m=end_m,
        peak_chainage_m=start_m,
        peak_value=0.3,
        peak_blockage_ratio=0.25,
        grade=1,
        clock_from_h=4.5,
        clock_to_h=7.5,
    )


def test_import_matches_by_nodes_and_orients_by_them(engine: sa.Engine, tmp_path: Path) -> None:
    save(engine, meta("MH1-MH2", "MH1", "MH2"), 10.0)
    save(engine, meta("MH2-MH3", "MH3", "MH2"), 20.0)  # flows MH3 -> MH2
    path = write_layer(tmp_path / "net.gpkg", network_lines(), network_fields())
    layer = read_network_layer(
        path, id_field="FACILITYID", from_field="UPNODE", to_field="DOWNNODE"
    )
    result = import_network_layer(engine, layer)
    assert (result.stored, result.replaced) == (3, 0)
    assert result.matched == ("MH1-MH2", "MH2-MH3") and result.unmatched_assets == ()
    assert gis_ids(engine) == {"MH1-MH2": "SW-1", "MH2-MH3": "SW-2"}
    geometries = asset_geometries(engine, ["MH1-MH2", "MH2-MH3"])
    first, second = geometries["MH1-MH2"], geometries["MH2-MH3"]
    assert first.line.coords[0].tolist() == [X0, Y0]
    assert second.line.coords[0].tolist() == [X0 + 26.0, Y0 + 4.0]  # MH3 end first
    assert {first.oriented_by, second.oriented_by} == {ORIENTED_BY_NODE_NAMES}
    assert (first.crs, first.gis_id) == (CRS, "SW-1")

    # Imported again: replaced, not doubled.
    again = import_network_layer(engine, layer)
    assert again.replaced == 3
    with engine.connect() as connection:
        assert connection.exec_driver_sql("SELECT count(*) FROM network_pipes").scalar() == 3


def test_a_layer_imported_first_serves_later_inspections(engine: sa.Engine, tmp_path) -> None:
    path = write_layer(tmp_path / "net.gpkg", network_lines(), network_fields())
    layer = read_network_layer(path, id_field="FACILITYID")  # ids are the asset ids
    result = import_network_layer(engine, layer)  # no assets yet: nothing to match
    assert result.matched == ()
    save(engine, meta("SW-3", "MH3", "MH4"), 36.0)
    assert gis_ids(engine) == {"SW-3": "SW-3"}
    assert asset_geometries(engine, ["SW-3"])["SW-3"].oriented_by == ORIENTED_BY_DIGITISING


def test_a_layer_that_names_no_stored_asset_is_refused(engine: sa.Engine, tmp_path) -> None:
    save(engine, meta("MH1-MH2", "MH1", "MH2"), 10.0)
    path = write_layer(tmp_path / "net.gpkg", network_lines(), network_fields())
    layer = read_network_layer(path, id_field="FACILITYID")
    with pytest.raises(db.StorageError, match=r"none of the 3 pipes.*matches one of the 1 stored"):
        import_network_layer(engine, layer)
    with engine.connect() as connection:
        assert connection.exec_driver_sql("SELECT count(*) FROM network_pipes").scalar() == 0


def test_an_asset_named_by_two_imports_is_refused(engine: sa.Engine, tmp_path: Path) -> None:
    save(engine, meta("MH1-MH2", "MH1", "MH2"), 10.0)
    fields = network_fields() | {"ASSET": ["MH1-MH2", "X", "Y"]}
    path = write_layer(tmp_path / "a.gpkg", network_lines(), fields)
    import_network_layer(
        engine, read_network_layer(path, id_field="FACILITYID", asset_field="ASSET")
    )
    fields["FACILITYID"] = ["SW-9", "SW-8", "SW-7"]
    path = write_layer(tmp_path / "b.gpkg", network_lines(), fields)
    with pytest.raises(db.StorageError, match="names asset MH1-MH2, which pipe SW-1"):
        import_network_layer(
            engine, read_network_layer(path, id_field="FACILITYID", asset_field="ASSET")
        )


def test_metadata_positions_give_a_geometry_and_orient_a_layer(engine: sa.Engine, tmp_path) -> None:
    positioned = meta(
        "MH1-MH2",
        "MH1",
        "MH2",
        upstream_node_xyz=(X0 + 6.0, Y0 + 4.0, 40.0),  # at the line's digitised end
        downstream_node_xyz=(X0, Y0, 39.9),
        crs=CRS,
    )
    save(engine, positioned, 10.0)
    geometry = asset_geometries(engine, ["MH1-MH2"])["MH1-MH2"]
    assert geometry.source == "inspection.toml" and geometry.oriented_by == ORIENTED_BY_METADATA
    assert geometry.line.coords.tolist() == [[X0 + 6.0, Y0 + 4.0, 40.0], [X0, Y0, 39.9]]
    # A later inspection without positions keeps them.
    save(engine, meta("MH1-MH2", "MH1", "MH2", inspected_at=datetime(2026, 1, 1, tzinfo=UTC)), 10.0)
    assert asset_geometries(engine, ["MH1-MH2"])["MH1-MH2"].source == "inspection.toml"
    # With a layer, the layer's line, turned by the metadata's positions (no node fields).
    fields = {"FACILITYID": ["SW-1"], "ASSET": ["MH1-MH2"]}
    path = write_layer(tmp_path / "net.gpkg", network_lines()[:1], fields)
    import_network_layer(
        engine, read_network_layer(path, id_field="FACILITYID", asset_field="ASSET")
    )
    geometry = asset_geometries(engine, ["MH1-MH2"])["MH1-MH2"]
    assert geometry.gis_id == "SW-1" and geometry.oriented_by == ORIENTED_BY_NODE_POSITIONS
    assert geometry.line.coords[0].tolist() == [X0 + 6.0, Y0 + 4.0]


def test_the_new_columns_survive_a_downgrade_and_upgrade(engine: sa.Engine) -> None:
    save(engine, meta("MH1-MH2", "MH1", "MH2", direction="upstream", chainage_offset_m=12.0), 1.0)
    record = repository.list_inspections(engine)[0]
    assert (record.direction, record.chainage_offset_m) == ("upstream", 12.0)
    db.downgrade(engine, "7d2b4e91c3a8")
    with engine.connect() as connection:
        assert connection.exec_driver_sql("SELECT count(*) FROM inspections").scalar() == 1
        assert connection.exec_driver_sql("SELECT count(*) FROM sections").scalar() == 10
    assert "network_pipes" not in sa.inspect(engine).get_table_names()
    db.upgrade(engine)
    record = repository.list_inspections(engine)[0]
    # Inspections stored before the columns existed say "unknown", never a guess.
    assert (record.direction, record.chainage_offset_m) == (None, None)
    assert len(repository.list_sections(engine, record.id)) == 10


# ---------------------------------------------------------------------------------------------
# The export, read back


@pytest.fixture
def network(tmp_path: Path):
    """A SQLite database with two pipes on an imported layer, one inspected twice."""
    url = f"sqlite:///{tmp_path / 'gis.db'}"
    engine = db.connect(url)
    save(
        engine,
        meta("MH1-MH2", "MH1", "MH2"),
        10.0,
        defects=[deposit(6.5, 7.5)],
        registration={"measured_inner_diameter_m": 0.4912},
    )
    save(
        engine,
        meta("MH2-MH3", "MH3", "MH2", inspected_at=datetime(2023, 3, 1, tzinfo=UTC)),
        18.0,
        sections=sections(18.0),
    )
    save(engine, meta("MH2-MH3", "MH3", "MH2"), 18.0, defects=[deposit(17.5, 18.0)])
    path = write_layer(tmp_path / "net.gpkg", network_lines(), network_fields())
    import_network_layer(
        engine,
        read_network_layer(path, id_field="FACILITYID", from_field="UPNODE", to_field="DOWNNODE"),
    )
    yield engine, url
    engine.dispose()


def read_layer(path: Path, layer: str | None = None) -> tuple[dict, list, dict[str, np.ndarray]]:
    meta_, _, geometry, values = read(str(path), layer=layer)
    fields = dict(zip(meta_["fields"], values, strict=True))
    return meta_, [shapely.from_wkb(g) for g in geometry], fields


def test_geopackage_round_trip(network, tmp_path: Path) -> None:
    engine, _ = network
    out = tmp_path / "network.gpkg"
    result = export_gis(engine, out, with_sections=True)
    assert result.paths == (out,) and result.crs == CRS
    assert result.counts == {"pipes": 2, "defects": 2, "sections": 280}
    assert [name for name, _ in pyogrio.list_layers(out)] == ["pipes", "defects", "sections"]

    info, lines, pipes = read_layer(out, "pipes")
    assert info["crs"] == CRS
    assert list(pipes) == [
        "asset_id", "gis_id", "inspection_id", "inspected_at", "inspection_count",
        "condition_class", "peak_blockage_ratio", "peak_chainage_m",
        "measured_inner_diameter_m", "growth_per_year_ratio",
        "defect_count", "scan_end_chainage_m", "gis_length_m", "length_difference_ratio",
        "length_note", "geometry_source", "oriented_by",
    ]  # fmt: skip
    by_asset = {a: i for i, a in enumerate(pipes["asset_id"])}
    first, second = by_asset["MH1-MH2"], by_asset["MH2-MH3"]
    # The wall's measured inner diameter, where the run measured it (none before it did).
    assert pipes["measured_inner_diameter_m"][first] == pytest.approx(0.4912)
    assert np.isnan(pipes["measured_inner_diameter_m"][second])
    assert pipes["gis_id"][first] == "SW-1" and pipes["gis_id"][second] == "SW-2"
    assert pipes["condition_class"][first] == 1  # the graded section at 6.5 m
    assert pipes["inspection_count"][second] == 2
    # Growth of the peak: 0.05 + 0.001 * 179 in both scans, two years apart: zero.
    assert pipes["growth_per_year_ratio"][second] == pytest.approx(0.0, abs=1e-12)
    assert math.isnan(pipes["growth_per_year_ratio"][first])  # one scan: null
    # 18 m scanned on a 20 m line: said, not stretched; 10 m on 10 m: nothing to say.
    assert pipes["length_note"][first] is None
    assert "-10.0 %" in pipes["length_note"][second]
    assert pipes["length_difference_ratio"][second] == pytest.approx(-0.1)
    assert set(result.length_notes) == {"MH2-MH3"}
    assert lines[second].coords[0] == (X0 + 26.0, Y0 + 4.0)  # upstream first

    _, events, defects = read_layer(out, "defects")
    assert set(defects) >= {
        *("code", "condition_class", "chainage_start_m", "chainage_end_m", "peak_value"),
        *("clock_from_h", "clock_to_h", "beyond_line_m", "position_note"),
    }
    d1 = list(defects["asset_id"]).index("MH1-MH2")
    # 6.5-7.5 m along SW-1: 6 m east, then north: from (6.0, 0.5) to (6.0, 1.5).
    assert events[d1].coords[0] == pytest.approx((X0 + 6.0, Y0 + 0.5))
    assert events[d1].coords[-1] == pytest.approx((X0 + 6.0, Y0 + 1.5))
    assert events[d1].length == pytest.approx(1.0)
    assert defects["condition_class"][d1] == 1
    # Clock positions come through once the database keeps them (the defect-coding work adds
    # the columns); until then they are null, never made up.
    kept = {c["name"] for c in sa.inspect(engine).get_columns("defects")}
    expected_clock = 4.5 if "clock_from_h" in kept else None
    got = defects["clock_from_h"][d1]
    assert (None if got is None or math.isnan(got) else got) == expected_clock
    # 17.5-18.0 m along SW-2 from MH3, 20 m long: measured chainage, not scaled by 20/18.
    d2 = list(defects["asset_id"]).index("MH2-MH3")
    assert events[d2].coords[0] == pytest.approx((X0 + 26.0 - 17.5, Y0 + 4.0))
    assert defects["beyond_line_m"][d2] == 0.0

    _, points, cut = read_layer(out, "sections")
    s0 = list(zip(cut["asset_id"], cut["chainage_start_m"], strict=True)).index(("MH1-MH2", 0.0))
    assert (points[s0].x, points[s0].y) == pytest.approx((X0 + 0.05, Y0))


def test_events_past_the_line_are_cut_and_say_so(network, tmp_path: Path) -> None:
    engine, _ = network
    save(engine, meta("MH1-MH2", "MH1", "MH2", inspected_at=datetime(2026, 1, 1, tzinfo=UTC)),
         11.0, defects=[deposit(9.8, 10.6)])  # fmt: skip
    result = export_gis(engine, tmp_path / "one.gpkg", asset_id="SW-1")  # by its GIS id
    assert result.counts == {"pipes": 1, "defects": 1}
    _, events, defects = read_layer(tmp_path / "one.gpkg", "defects")
    assert defects["beyond_line_m"][0] == pytest.approx(0.6)
    assert "past the end of the GIS line" in defects["position_note"][0]
    assert events[0].coords[-1] == pytest.approx((X0 + 6.0, Y0 + 4.0))
    assert "+10.0 %" in result.length_notes["MH1-MH2"]


def test_geojson_writes_a_file_per_layer(network, tmp_path: Path) -> None:
    engine, _ = network
    result = export_gis(engine, tmp_path / "gj", fmt="geojson")
    assert [p.name for p in result.paths] == ["pipes.geojson", "defects.geojson"]
    doc = json.loads((tmp_path / "gj" / "defects.geojson").read_text())
    assert "25832" in doc["crs"]["properties"]["name"]
    info, _, fields = read_layer(tmp_path / "gj" / "pipes.geojson")
    assert info["crs"] == CRS and sorted(fields["gis_id"]) == ["SW-1", "SW-2"]
    assert sorted(p.name for p in (tmp_path / "gj").iterdir()) == [
        "defects.geojson",
        "pipes.geojson",
    ]


def test_what_cannot_be_exported(network, tmp_path: Path) -> None:
    engine, _ = network
    save(engine, meta("LOOSE", "X1", "X2"), 3.0)
    result = export_gis(engine, tmp_path / "all.gpkg")
    assert result.without_geometry == ("LOOSE",) and result.counts["pipes"] == 2
    with pytest.raises(GisError, match="asset LOOSE has no geometry"):
        export_gis(engine, tmp_path / "x.gpkg", asset_id="LOOSE")
    elsewhere = meta(
        "FAR", "F1", "F2", upstream_node_xyz=(1.0, 2.0), downstream_node_xyz=(5.0, 2.0),
        crs="EPSG:31467",
    )  # fmt: skip
    save(engine, elsewhere, 4.0)
    with pytest.raises(GisError, match="2 coordinate reference systems"):
        export_gis(engine, tmp_path / "x.gpkg")
    with pytest.raises(db.StorageError, match="no inspection of asset 'NOPE'"):
        export_gis(engine, tmp_path / "x.gpkg", asset_id="NOPE")
    assert not (tmp_path / "x.gpkg").exists()
    with pytest.raises(GisError, match="its folder does not exist"):
        export_gis(engine, tmp_path / "missing" / "x.gpkg", asset_id="SW-1")
    (tmp_path / "afile").write_text("")
    with pytest.raises(GisError, match="is a file"):
        export_gis(engine, tmp_path / "afile", asset_id="SW-1", fmt="geojson")


def test_reports_name_pipes_by_gis_id_and_note_lengths(network) -> None:
    engine, url = network
    from pipescan.reports.network import build_network_context
    from pipescan.tasks.reporting import load_network_input, load_report_input

    ctx = build_network_context(load_network_input(url))
    rows = {r["asset_id"]: r for r in ctx["by_grade"]}
    assert rows["MH1-MH2"]["pipe"] == "SW-1" and rows["MH1-MH2"]["asset_note"] == "asset MH1-MH2"
    assert [n["pipe"] for n in ctx["length_notes"]] == ["SW-2"]
    inspection_id = repository.find_latest_inspection_id(engine, "MH2-MH3")
    report = load_report_input(url, inspection_id)
    assert report.gis_id == "SW-2" and "-10.0 %" in report.length_note
    assert placements(engine, {"MH1-MH2": 10.0})["MH1-MH2"].length_note is None


# ---------------------------------------------------------------------------------------------
# The command line


def test_cli_network_import_and_export(network, tmp_path: Path) -> None:
    _, url = network
    runner = CliRunner()
    result = runner.invoke(app, ["assets", "--db", url])
    assert result.exit_code == 0 and "SW-1 (asset MH1-MH2)" in result.output
    result = runner.invoke(app, ["worst", "--by", "current", "--db", url])
    assert "SW-2 (asset MH2-MH3)" in result.output
    out = tmp_path / "cli.gpkg"
    result = runner.invoke(app, ["export", "gis", "--format", "gpkg", "-o", str(out), "--db", url])
    assert result.exit_code == 0, result.output
    assert "2 pipes, 2 defects" in result.output and "-10.0 %" in result.output
    assert read_layer(out, "pipes")[0]["crs"] == CRS

    path = write_layer(tmp_path / "more.gpkg", network_lines(), network_fields())
    for args, message in [
        (["network", "import", str(path), "--id-field", "NOPE"], "no field 'NOPE'"),
        (["network", "import", str(tmp_path / "missing.gpkg"), "--id-field", "ID"], "cannot read"),
        (["network", "import", str(path), "--id-field", "UPNODE"], "id 'MH3' is on feature 1"),
        (["export", "gis", "-o", str(tmp_path / "x.gpkg"), "--inspection", "99"], "no inspection"),
        (["export", "gis", "-o", str(tmp_path / "x.gpkg"), "--asset", "NOPE"], "NOPE"),
    ]:
        result = runner.invoke(app, [*args, "--db", url])
        assert result.exit_code == 2, result.output
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0]


def test_isybau_names_an_imported_pipe_by_its_gis_id(network, tmp_path: Path) -> None:
    from datetime import date

    from pipescan.exports.isybau import IsybauHeader, export_isybau, validation_errors

    engine, _ = network
    out = tmp_path / "sw2.xml"
    result = export_isybau(engine, out, IsybauHeader(date(2026, 12, 1)), asset_id="SW-2")
    assert len(result.inspection_ids) == 2  # both scans of MH2-MH3
    document = out.read_bytes()
    assert validation_errors(document) == []
    assert document.count(b"<Objektbezeichnung>SW-2</Objektbezeichnung>") == 2
    assert b"asset MH2-MH3" in document  # the remarks keep pipescan's asset id
