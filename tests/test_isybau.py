"""ISYBAU XML 2013 export: every document validates against the published schema, a broken
one does not, the observations say what the defects are, and the mapping's claims about the
published example hold."""

from __future__ import annotations

import gzip
import math
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import replace
from datetime import UTC, date, datetime
from pathlib import Path

import pytest
import sqlalchemy as sa
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.core.model import Defect, InspectionMeta, SectionMeasures, SectionStatus
from pipescan.exports import isybau
from pipescan.exports.isybau import (
    EMITTED_CODES,
    END_CODE,
    NAMESPACE,
    START_CODE,
    IsybauError,
    IsybauHeader,
    IsybauInspection,
    build_isybau,
    validation_errors,
)
from pipescan.storage.database import db, repository

SAMPLE = Path(__file__).parent / "data" / "isybau-sample-zustandsdaten-en13508-2.xml.gz"
NS = {"i": NAMESPACE}
HEADER = IsybauHeader(created_on=date(2026, 12, 1), property_number="1234567890")


def record(**changes: object) -> repository.InspectionRecord:
    base = repository.InspectionRecord(
        id=7,
        asset_id="MH1042-MH1043",
        inspected_at=datetime(2025, 3, 14, 9, 30, tzinfo=UTC),
        archive_uri="site7.zip",
        content_hash="sha256:a",
        params_hash="p",
        params={"step_m": 0.1},
        software_version="0.1.0",
        status="ok",
        created_at=datetime(2025, 3, 15, 8, 0, tzinfo=UTC),
        point_count=1000,
        frame_count=10,
        scanned_length_m=40.0,
        registration={},
        threshold_table="vsa-2023",
        upstream_node="MH1042",
        downstream_node="MH1043",
        nominal_diameter_m=0.5,
        pipe_shape="circular",
        material="concrete",
        section_count=400,
        direction="downstream",
        chainage_offset_m=0.0,
    )
    return replace(base, **changes)  # type: ignore[arg-type]


def defect(code: str, start_m: float, end_m: float, **changes: object) -> Defect:
    measure = {"BBC": "deposit_height_ratio", "BAA": "deformation_ratio"}.get(
        code, "blockage_ratio"
    )
    base = Defect(
        code=code,
        measure=measure,
        chainage_start_m=start_m,
        chainage_end_m=end_m,
        peak_chainage_m=start_m,
        peak_value=0.235,
        peak_blockage_ratio=0.2,
        grade=2,
        clock_from_h=4.6,
        clock_to_h=7.4,
    )
    return replace(base, **changes)  # type: ignore[arg-type]


DEFECTS = (
    defect("BBC", 3.5, 4.0),  # continuous: A/B pair
    defect("BBE", 2.6, 2.7, peak_value=0.175, clock_from_h=11.8, clock_to_h=0.3, grade=3),
    defect("BAA", 1.7, 2.0, peak_value=0.066, grade=1),  # to the remarks
    defect("BBB", 10.0, 12.0, clock_from_h=None, clock_to_h=None, grade=None),
)


def inspection(**changes: object) -> IsybauInspection:
    base = IsybauInspection(
        record=record(),
        defects=DEFECTS,
        first_chainage_m=0.4,
        last_chainage_m=40.0,
        worst_grade=1,
        step_m=0.1,
    )
    return replace(base, **changes)  # type: ignore[arg-type]


def parse(document: bytes) -> ET.Element:
    return ET.fromstring(document)


def observations(root: ET.Element) -> list[dict[str, str]]:
    return [
        {child.tag.split("}")[1]: (child.text or "") for child in state}
        for state in root.iterfind(".//i:RZustand", NS)
    ]


# ---------------------------------------------------------------------------------------------
# The schema check can fail, and does on what it should


def test_the_published_example_validates_with_the_shipped_schema() -> None:
    document = gzip.decompress(SAMPLE.read_bytes())
    assert validation_errors(document) == []


@pytest.mark.parametrize(
    ("old", "new", "where"),
    [
        (b"<Station>0.00</Station>", b"<Station>O.00</Station>", "Station"),
        (b"<Inspektionsrichtung>O</Inspektionsrichtung>", b"", "Rohrleitung"),
        (
            b"<InspektionsKode>BCD</InspektionsKode>",
            b"<InspektionsKode>BCD-START-1</InspektionsKode>",
            "InspektionsKode",
        ),
        (b"<PositionVon>05</PositionVon>", b"<PositionVon>105</PositionVon>", "PositionVon"),
        (b"<Kollektivart>2</Kollektivart>", b"<Kollektivart>9</Kollektivart>", "Kollektivart"),
    ],
    ids=[
        "station-not-a-number",
        "direction-missing",
        "code-too-long",
        "position-3-digits",
        "unknown-list-value",
    ],
)
def test_a_broken_field_fails_validation(old: bytes, new: bytes, where: str) -> None:
    document = build_isybau([inspection()], HEADER)
    assert validation_errors(document) == []
    assert old in document
    errors = validation_errors(document.replace(old, new, 1))
    assert errors, "the broken document validated"
    assert any(where in e for e in errors), errors


def test_an_invalid_document_is_never_written(
    tmp_path: Path, engine_with_inspection: tuple[object, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    engine, inspection_id = engine_with_inspection
    good = isybau.build_isybau

    def broken(*args: object, **kwargs: object) -> bytes:
        return good(*args, **kwargs).replace(b"<Anlagentyp>1</Anlagentyp>", b"")  # type: ignore[arg-type]

    monkeypatch.setattr(isybau, "build_isybau", broken)
    out = tmp_path / "out" / "x.xml"
    out.parent.mkdir()
    with pytest.raises(IsybauError, match=r"does not validate.*Anlagentyp"):
        isybau.export_isybau(engine, out, HEADER, inspection_id=inspection_id)  # type: ignore[arg-type]
    assert list(out.parent.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# Every export validates


CASES = {
    "downstream": [inspection()],
    "upstream": [inspection(record=record(direction="upstream", chainage_offset_m=40.4))],
    "no-defects-no-nodes": [
        inspection(defects=(), record=record(upstream_node=None, downstream_node=None))
    ],
    "no-sections": [
        inspection(defects=(), first_chainage_m=None, last_chainage_m=None, worst_grade=None)
    ],
    "two-inspections-of-one-pipe": [
        inspection(),
        inspection(record=record(id=8, inspected_at=datetime(2026, 3, 1, tzinfo=UTC))),
    ],
    "names-beyond-latin-1": [inspection(record=record(asset_id="Kanal-Müller-管道"))],
    "gis-name": [inspection(gis_id="SW-0042")],
    "egg-shaped": [inspection(record=record(pipe_shape="egg", nominal_diameter_m=None))],
}


@pytest.mark.parametrize("inspections", list(CASES.values()), ids=list(CASES))
def test_every_export_validates(inspections: list[IsybauInspection]) -> None:
    document = build_isybau(inspections, HEADER)
    assert document.startswith(b"<?xml version='1.0' encoding='ISO-8859-1'?>")
    assert validation_errors(document) == []
    root = parse(document)
    assert len(root.findall(".//i:InspizierteAbwassertechnischeAnlage", NS)) == len(inspections)


def test_names_outside_latin_1_survive_as_character_references() -> None:
    document = build_isybau(CASES["names-beyond-latin-1"], HEADER)
    assert b"M\xfcller" in document  # Latin-1 itself
    assert b"&#31649;&#36947;" in document  # the rest as references
    assert parse(document).find(".//i:Objektbezeichnung", NS).text == "Kanal-Müller-管道"


# ---------------------------------------------------------------------------------------------
# What the observations say


def test_observations_of_a_downstream_survey() -> None:
    root = parse(build_isybau([inspection()], HEADER))
    obs = observations(root)
    codes = [o["InspektionsKode"] for o in obs]
    # Start and end node first and last; BAA is not coded (its use was not checked).
    assert codes[0] == START_CODE.code and obs[0]["Station"] == "0.00"
    assert codes[-1] == END_CODE.code and obs[-1]["Station"] == "40.00"
    assert "BAA" not in codes
    assert [float(o["Station"]) for o in obs] == sorted(float(o["Station"]) for o in obs)
    pipe = root.find(".//i:Rohrleitung", NS)
    assert pipe.find("i:Inspektionsrichtung", NS).text == "O"
    assert pipe.find("i:Inspektionslaenge", NS).text == "40.00"

    # A single-section obstacle is one point observation, at its middle.
    (bbe,) = [o for o in obs if o["InspektionsKode"] == "BBE"]
    assert bbe["Station"] == "2.65" and "Streckenschaden" not in bbe
    assert bbe["Quantifizierung1Numerisch"] == "17.5"
    # 11.8 h to 0.3 h: 12 to 12 rounds to one position, over the crown.
    assert bbe["PositionVon"] == "12" and "PositionBis" not in bbe
    assert "Charakterisierung1" not in bbe  # a LiDAR scan does not see what it is made of

    # Longer defects are a Streckenschaden: A at the start, B at the end, same number.
    bbc = [o for o in obs if o["InspektionsKode"] == "BBC"]
    assert [(o["Station"], o["Streckenschaden"], o["StreckenschadenLfdNr"]) for o in bbc] == [
        ("3.50", "A", "1"),
        ("4.00", "B", "1"),
    ]
    assert all(o["Quantifizierung1Numerisch"] == "23.5" for o in bbc)
    assert all((o["PositionVon"], o["PositionBis"]) == ("05", "07") for o in bbc)
    assert "deposit height 23.5 % of the pipe's height" in bbc[0]["Kommentar"]
    assert "condition class 2" in bbc[0]["Kommentar"]

    # No clock position: left out, and said.
    bbb = [o for o in obs if o["InspektionsKode"] == "BBB"]
    assert [o["StreckenschadenLfdNr"] for o in bbb] == ["2", "2"]
    assert all("PositionVon" not in o for o in bbb)
    assert "clock position not determined" in bbb[0]["Kommentar"]

    # BAA goes to the remarks, with its figures.
    remarks = root.find(".//i:OptischeInspektion/i:Bemerkung", NS).text
    assert "EN 13508-2 BAA" in remarks and "diameter reduced by 6.6 %" in remarks
    assert "chainage 1.70-2.00 m" in remarks

    # pipescan's class, under "another method"; the governing defect is a coded one.
    rating = root.find(".//i:Bewertung", NS)
    assert rating.find("i:Bewertungsverfahren", NS).text == "4"
    assert rating.find("i:KlasseAutomatisch", NS).text == "1"
    assert rating.find("i:MassgebenderSchaden", NS) is None  # the class-1 defect is BAA


def test_a_lower_bound_is_said_in_the_observation_and_still_validates() -> None:
    defects = [replace(d, lower_bound=d.code == "BBE") for d in DEFECTS]
    document = build_isybau([inspection(defects=defects)], HEADER)
    assert validation_errors(document) == []
    (bbe,) = [o for o in observations(parse(document)) if o["InspektionsKode"] == "BBE"]
    assert bbe["Quantifizierung1Numerisch"] == "17.5"
    assert "or worse; at least this: part of it stood in water" in bbe["Kommentar"]
    others = [o for o in observations(parse(document)) if o["InspektionsKode"] == "BBC"]
    assert not any("at least" in o.get("Kommentar", "") for o in others)


def test_stations_of_an_upstream_survey_count_from_its_start() -> None:
    offset = 40.4
    root = parse(
        build_isybau(
            [inspection(record=record(direction="upstream", chainage_offset_m=offset))], HEADER
        )
    )
    obs = observations(root)
    assert root.find(".//i:Inspektionsrichtung", NS).text == "U"
    assert obs[-1]["InspektionsKode"] == "BCE"
    assert float(obs[-1]["Station"]) == pytest.approx(offset - 0.4)
    bbc = [o for o in obs if o["InspektionsKode"] == "BBC"]
    # Chainage 3.5-4.0 m from the upstream node is met first at 4.0 m: A at 36.40.
    assert [(o["Station"], o["Streckenschaden"]) for o in bbc] == [("36.40", "A"), ("36.90", "B")]
    assert "stations count from the scan's start" in root.find(".//i:Bemerkung", NS).text


@pytest.mark.parametrize(
    ("clock_from_h", "clock_to_h", "expected"),
    [
        (4.6, 7.4, (5, 7)),
        (3.0, 9.0, (3, 9)),
        (9.0, 3.0, (9, 3)),  # clockwise over the crown
        (11.6, 0.4, (12, None)),  # within one hour at the crown: one position
        (2.5, 3.49, (3, None)),
        (0.4, 12.0, (12, 12)),  # 11.6 h of arc: a whole ring, both given
    ],
)
def test_clock_positions_are_whole_hours(
    clock_from_h: float, clock_to_h: float, expected: tuple[int, int | None]
) -> None:
    got = isybau._positions(
        defect("BBC", 1.0, 1.1, clock_from_h=clock_from_h, clock_to_h=clock_to_h)
    )
    assert (got["position_from"], got["position_to"]) == expected


def test_what_does_not_fit_the_format_is_refused() -> None:
    with pytest.raises(IsybauError, match=r"Objektbezeichnung.*30"):
        build_isybau([inspection(record=record(asset_id="A" * 31))], HEADER)
    with pytest.raises(IsybauError, match="Inspektionslaenge"):
        build_isybau([inspection(last_chainage_m=1000.0)], HEADER)
    with pytest.raises(IsybauError, match="direction"):
        build_isybau([inspection(record=record(direction=None, chainage_offset_m=None))], HEADER)
    many = tuple(defect("BBC", 2.0 * i, 2.0 * i + 0.5) for i in range(100))
    with pytest.raises(IsybauError, match="99"):
        build_isybau([inspection(defects=many, last_chainage_m=300.0)], HEADER)


# ---------------------------------------------------------------------------------------------
# The mapping's claims about the published example


def _sample_pipe_observations() -> list[list[dict[str, str]]]:
    root = ET.fromstring(gzip.decompress(SAMPLE.read_bytes()))
    return [
        [
            {c.tag.split("}")[1]: (c.text or "") for c in z}
            for z in pipe.iterfind(".//i:RZustand", NS)
        ]
        for pipe in root.iterfind(".//i:Rohrleitung", NS)
    ]


def test_the_evidence_for_each_emitted_code_is_in_the_published_example() -> None:
    pipes = _sample_pipe_observations()
    flat = [o for pipe in pipes for o in pipe]
    by_code = Counter(o["InspektionsKode"] for o in flat)
    # BAA, the code pipescan leaves to the remarks, is not in the example.
    assert by_code["BAA"] == 0
    expected_counts = {"BBB": 1, "BBC": 5, "BBE": 11}
    assert set(EMITTED_CODES) == set(expected_counts)
    for code, count in expected_counts.items():
        assert by_code[code] == count
        assert f"{count} pipe observation" in EMITTED_CODES[code].evidence
        uses = [o for o in flat if o["InspektionsKode"] == code]
        # Quantified as a percentage, with a clock position, like pipescan writes them.
        assert all(0 < float(o["Quantifizierung1Numerisch"]) <= 100 for o in uses)
        assert all("PositionVon" in o for o in uses)
    assert {o["PositionVon"] for o in flat if o["InspektionsKode"] == "BBC"} == {"06"}
    bbb = next(o for o in flat if o["InspektionsKode"] == "BBB")
    assert (bbb["PositionVon"], bbb["PositionBis"]) == ("08", "10")
    comments = {o.get("Kommentar") for o in flat if o["InspektionsKode"] == "BBE"}
    assert {"Eisenstange", "Holzbrett"} <= comments

    # Every pipe inspection starts with BCD at 0.00 and ends with BCE, or BDC when abandoned.
    assert len(pipes) == 133
    assert all(p[0]["InspektionsKode"] == "BCD" and p[0]["Station"] == "0.00" for p in pipes)
    ends = Counter(p[-1]["InspektionsKode"] for p in pipes)
    assert ends == {"BCE": 123, "BDC": 10}
    assert "133 pipe inspections" in START_CODE.evidence
    assert "123 pipe inspections" in END_CODE.evidence
    at_the_end = sum(
        float(p[-1]["Station"]) == max(float(o["Station"]) for o in p)
        for p in pipes
        if p[-1]["InspektionsKode"] == "BCE"
    )
    assert at_the_end == 122
    assert "in 122 of them" in END_CODE.evidence


# ---------------------------------------------------------------------------------------------
# From the database and the command line


def _sections(count: int) -> list[SectionMeasures]:
    return [
        SectionMeasures(
            chainage_start_m=round(0.4 + i / 10, 3),
            chainage_end_m=round(0.5 + i / 10, 3),
            nominal_area_m2=math.pi * 0.25**2,
            status=SectionStatus.OK,
            point_count=900,
            coverage_ratio=1.0,
            open_area_m2=0.19,
            blockage_ratio=0.03,
            grade=4 if i != 5 else 2,
        )
        for i in range(count)
    ]


@pytest.fixture
def engine_with_inspection(tmp_path: Path):
    engine = db.connect(f"sqlite:///{tmp_path / 'isybau.db'}")
    meta = InspectionMeta(
        asset_id="MH1042-MH1043",
        inspected_at=datetime(2025, 3, 14, 9, 30, tzinfo=UTC),
        nominal_diameter_m=0.5,
        upstream_node="MH1042",
        downstream_node="MH1043",
        direction="upstream",
        chainage_offset_m=6.0,
    )
    inspection_id = repository.save_inspection(
        engine,
        repository.InspectionToSave(
            meta=meta,
            archive_uri="site7.zip",
            content_hash="sha256:a",
            params={"step_m": 0.1},
            software_version="0.1.0",
            sections=_sections(50),
            defects=list(DEFECTS[:3]),
            threshold_table="vsa-2023",
        ),
    )
    yield engine, inspection_id
    engine.dispose()


def test_export_from_the_database(engine_with_inspection, tmp_path: Path) -> None:
    engine, inspection_id = engine_with_inspection
    out = tmp_path / "pipe.xml"
    result = isybau.export_isybau(engine, out, HEADER, asset_id="MH1042-MH1043")
    assert result.inspection_ids == (inspection_id,)
    assert result.defects_in_remarks == 1
    document = out.read_bytes()
    assert validation_errors(document) == []
    root = parse(document)
    assert root.find(".//i:Inspektionsrichtung", NS).text == "U"
    # Sections 0.4-5.4 m of an upstream survey that started 6.0 m from the upstream node.
    assert root.find(".//i:Inspektionslaenge", NS).text == "5.60"
    assert root.find(".//i:KlasseAutomatisch", NS).text == "2"  # worst section class
    # The clock positions come through once the database keeps them (the defect-coding
    # work adds the columns); until then they are left out, and the comment says so.
    bbc = [o for o in observations(root) if o["InspektionsKode"] == "BBC"]
    kept = {c["name"] for c in sa.inspect(engine).get_columns("defects")}
    if "clock_from_h" in kept:
        assert (bbc[0]["PositionVon"], bbc[0]["PositionBis"]) == ("05", "07")
    else:
        assert "PositionVon" not in bbc[0]
        assert "clock position not determined" in bbc[0]["Kommentar"]


def test_cli_export_isybau(engine_with_inspection, tmp_path: Path) -> None:
    engine, inspection_id = engine_with_inspection
    url = str(engine.url)
    out = tmp_path / "demo.xml"
    runner = CliRunner()
    result = runner.invoke(
        app, ["export", "isybau", "--inspection", str(inspection_id), "-o", str(out), "--db", url]
    )
    assert result.exit_code == 0, result.output
    assert "validated against the ISYBAU XML 2013 schema" in result.output
    assert "described in the remarks" in result.output
    assert validation_errors(out.read_bytes()) == []

    for args, message in [
        (["--inspection", "999"], "no inspection with id 999"),
        (["--asset", "NOPE"], "no inspection of asset 'NOPE'"),
        ([], "give --inspection ID or --asset ID"),
        (["--inspection", str(inspection_id), "--property-number", "x" * 21], "--property-number"),
    ]:
        target = tmp_path / "bad.xml"
        result = runner.invoke(app, ["export", "isybau", *args, "-o", str(target), "--db", url])
        assert result.exit_code == 2, result.output
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0]
        assert not target.exists()


def test_an_unwritable_target_is_one_line(engine_with_inspection, tmp_path: Path) -> None:
    engine, inspection_id = engine_with_inspection
    blocker = tmp_path / "a-file"  # a missing folder is made; a file on the way is refused
    blocker.write_text("")
    target = blocker / "x.xml"
    result = CliRunner().invoke(
        app,
        ["export", "isybau", "--inspection", str(inspection_id), "-o", str(target),
         "--db", str(engine.url)],
    )  # fmt: skip
    assert result.exit_code == 2
    assert result.output.strip().startswith("error: file") and "cannot write" in result.output


def test_an_inspection_stored_without_its_direction(engine_with_inspection, tmp_path) -> None:
    engine, inspection_id = engine_with_inspection
    with engine.begin() as connection:
        connection.exec_driver_sql("UPDATE inspections SET direction = NULL")
    result = CliRunner().invoke(
        app,
        [
            "export",
            "isybau",
            "--inspection",
            str(inspection_id),
            "-o",
            str(tmp_path / "x.xml"),
            "--db",
            str(engine.url),
        ],
    )
    assert result.exit_code == 2
    assert "inspect its archive again" in result.output


def test_the_profile_is_the_measured_one_where_the_scan_measured_it() -> None:
    """U124: 4 (Querschnittsvermessung) with the inner diameter the wall measured, else 2 (aus
    Stammdaten) with the nominal one; both validate."""

    def profile(rec) -> tuple[str, str, str]:
        document = build_isybau([inspection(record=rec)], HEADER)
        assert validation_errors(document) == []
        basics = parse(document).find(".//i:RGrunddaten", NS)
        return tuple(
            basics.find(f"i:{name}", NS).text
            for name in ("HerkunftProfilmasse", "Profilhoehe", "Profilbreite")
        )

    assert profile(record()) == ("2", "500", "500")
    measured = record(registration={"measured_inner_diameter_m": 0.4872})
    assert profile(measured) == ("4", "487", "487")
