"""Stored inspections as ISYBAU XML 2013 condition data ("Zustandsdaten", format 2013-02).

ISYBAU is the exchange format of the German federal building authorities for sewer data; asset
systems in Germany import inspections in it. The schema (``isybau_xsd/``, unchanged, entry point
``1302-metadaten.xsd``) is shipped with pipescan, and every file is validated against it before
it is written: a file that does not validate is never written.

What a file holds (docs/exports.md has the whole mapping):

- one ``Zustandsdatenkollektiv`` per inspection, each with its order (``Auftrag``) and one
  inspected pipe (``InspizierteAbwassertechnischeAnlage``, Anlagentyp 1, a Haltung): its nodes,
  the survey's direction, the surveyed length, its observations (``RZustand``) and pipescan's
  condition class (``Bewertung``, Bewertungsverfahren 4, "another method");
- the observations: ``BCD`` at station 0 and ``BCE`` at the end of the survey, as every pipe
  in the published example starts and ends, and one per defect whose code's use in ISYBAU
  could be checked against the published example (:data:`EMITTED_CODES`); a defect spanning
  more than one section is a ``Streckenschaden``, an ``A`` observation at its start and a
  ``B`` at its end.

What pipescan cannot know is left out, never guessed, and said in words: the
characterisation (a material a LiDAR scan does not see), a clock position that was not
determined, a code whose use could not be checked (written to the remarks, ``Bemerkung``, with
its figures), the video reference (there is no video).
"""

from __future__ import annotations

import io
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, date, datetime, time
from functools import cache
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Engine

from pipescan.core.defaults import SECTION_STEP_M
from pipescan.core.errors import PipescanError
from pipescan.core.flags import DEFAULT_TABLE
from pipescan.core.model import Defect
from pipescan.core.summary import worst_grade
from pipescan.storage.atomic import atomic_file
from pipescan.storage.database.db import session_scope
from pipescan.storage.database.models import Inspection, Section
from pipescan.storage.database.network import gis_ids, resolve_asset
from pipescan.storage.database.queries import section_profiles
from pipescan.storage.database.repository import (
    InspectionRecord,
    get_inspection,
    list_defects,
    list_inspections,
    mm_to_m,
)

__all__ = [
    "EMITTED_CODES",
    "END_CODE",
    "NAMESPACE",
    "SCHEMA_ENTRY",
    "START_CODE",
    "IsybauError",
    "IsybauHeader",
    "IsybauInspection",
    "ObservationCode",
    "build_isybau",
    "export_isybau",
    "load_isybau_inspections",
    "validation_errors",
]

NAMESPACE = "http://www.ofd-hannover.la/Identifikation"
FORMAT_VERSION = "2013-02"
SCHEMA_ENTRY = Path(__file__).with_name("isybau_xsd") / "1302-metadaten.xsd"
"""The schema's entry point; it includes the other five files."""

ENCODING = "ISO-8859-1"
"""The encoding of the published schema and example; characters outside it are written as
character references."""


class IsybauError(PipescanError):
    """An inspection cannot be written as ISYBAU XML (a value outside what the format holds,
    a figure pipescan did not keep), or the file would not validate."""


@dataclass(frozen=True)
class ObservationCode:
    """An EN 13508-2 code pipescan writes as an ISYBAU observation.

    ``label`` names it in the observation's comment; ``evidence`` says where its use in ISYBAU
    was checked (in the published example file, ``sample-zustandsdaten-en13508-2.xml``).
    """

    code: str
    label: str
    evidence: str


EMITTED_CODES: dict[str, ObservationCode] = {
    code.code: code
    for code in (
        ObservationCode(
            "BBB",
            "attached deposits",
            "1 pipe observation (RZustand) with InspektionsKode BBB: Charakterisierung1 A, "
            "Quantifizierung1Numerisch 1.00 (a percentage), PositionVon 08 to PositionBis 10 "
            "(on the wall)",
        ),
        ObservationCode(
            "BBC",
            "settled deposits",
            "5 pipe observations with BBC: Charakterisierung1 A or B, "
            "Quantifizierung1Numerisch 5.00 or 10.00, PositionVon 06 (the invert)",
        ),
        ObservationCode(
            "BBE",
            "obstacle",
            "11 pipe observations with BBE: Kommentar 'Eisenstange' (iron bar) and "
            "'Holzbrett' (wooden board), objects in the pipe; Quantifizierung1Numerisch 6.00 "
            "to 25.00, PositionVon 03 to 12",
        ),
    )
}
"""Defect codes written as observations. Any other code (BAA among them: it does not occur
in the published example) goes to the remarks with its figures."""

START_CODE = ObservationCode(
    "BCD",
    "start node",
    "the first observation of every one of the 133 pipe inspections, at Station 0.00",
)
END_CODE = ObservationCode(
    "BCE",
    "end node",
    "the last observation of the 123 pipe inspections that were not abandoned (the other 10 "
    "end with BDC), at the largest station of the survey in 122 of them",
)

_MEASURE_WORDS = {
    "deposit_height_ratio": "deposit height {} % of the pipe's height",
    "blockage_ratio": "cross-section lost {} %",
    "deformation_ratio": "diameter reduced by {} %",
    "ovality_ratio": "ovality {} %",
}

MAX_STATION_M = 999.99
"""Largest station (and surveyed length) the format holds: 5 digits, 2 after the point."""

MAX_CONTINUOUS_DEFECTS = 99
"""Continuous defects (Streckenschaden) are numbered 1-99 within one inspected pipe."""


@dataclass(frozen=True)
class IsybauHeader:
    """The file's administrative data (``Admindaten``).

    ``property_number`` and ``property_name`` are the ISYBAU Liegenschaftsnummer (at most 20
    characters) and Liegenschaftsbezeichnung (at most 255); pipescan does not know them, so
    they stay empty unless given.
    """

    created_on: date
    property_number: str = ""
    property_name: str = ""


@dataclass(frozen=True)
class IsybauInspection:
    """Everything one inspected pipe of the file needs.

    ``first_chainage_m`` and ``last_chainage_m`` are the scan's extent (start of its first
    section, end of its last), None without sections; ``step_m`` the section length, which
    sets what counts as a point defect; ``gis_id`` the pipe's id in an imported network
    layer, which then names the pipe.
    """

    record: InspectionRecord
    defects: Sequence[Defect]
    first_chainage_m: float | None
    last_chainage_m: float | None
    worst_grade: int | None
    step_m: float = SECTION_STEP_M
    gis_id: str | None = None


# --------------------------------------------------------------------------------------------
# Figures in the format's terms


def _hour(clock_h: float) -> int:
    """A clock position in hours as the whole hour the format holds: 1-12, 12 at the crown."""
    hour = math.floor(clock_h + 0.5) % 12
    return 12 if hour == 0 else hour


def _decimal(value: float, what: str, where: str, *, limit: float = MAX_STATION_M) -> str:
    text = f"{value:.2f}"
    if not math.isfinite(value) or not float(text) <= limit:
        raise IsybauError(
            f"{where}: {what} {value:.2f} is beyond {limit:g}, the largest the format holds",
            field=what,
            hint="ISYBAU holds pipes up to 999.99 m; split the survey",
        )
    return text


def _percent(ratio: float) -> str:
    return f"{100.0 * ratio:.1f}"


def _positions(defect: Defect) -> dict[str, Any]:
    """PositionVon and PositionBis of a defect's clock arc: whole hours, clockwise; one
    position for an arc within one hour, 12 to 12 style (equal hours) for a whole ring."""
    if defect.clock_from_h is None or defect.clock_to_h is None:
        return {}
    start, end = _hour(defect.clock_from_h), _hour(defect.clock_to_h)
    arc_h = (defect.clock_to_h - defect.clock_from_h) % 12.0
    if start == end and arc_h < 6.0:
        return {"position_from": start, "position_to": None}
    return {"position_from": start, "position_to": end}


def _clock_words(defect: Defect, *, coded: bool = True) -> str:
    if defect.clock_from_h is None or defect.clock_to_h is None:
        left_out = ", so PositionVon/PositionBis are left out" if coded else ""
        return "clock position not determined" + left_out
    return f"clock {defect.clock_from_h:.1f} to {defect.clock_to_h:.1f} h"


@dataclass(frozen=True)
class _Observation:
    station_m: float
    order: int  # ties: the start node first, the end node last, A before B
    code: str
    quantity: str | None = None
    continuous: str | None = None
    number: int | None = None
    position_from: int | None = None
    position_to: int | None = None
    comment: str | None = None


@dataclass
class _Pipe:
    """The observations and remarks of one inspected pipe, in the format's terms."""

    observations: list[_Observation] = field(default_factory=list)
    remarks: list[str] = field(default_factory=list)
    surveyed_length_m: float = 0.0
    governing: Defect | None = None


def _station(chainage_m: float, direction: str, offset_m: float) -> float:
    # Stations count in the survey's direction from its start node; chainage counts from the
    # upstream node. A downstream survey starts there; an upstream survey's start is taken to
    # be where the scan started (the downstream node is not known to pipescan).
    return chainage_m if direction == "downstream" else offset_m - chainage_m


def _describe(inspection: IsybauInspection) -> _Pipe:
    record = inspection.record
    direction, offset = record.direction, record.chainage_offset_m
    where = f"inspection {record.id}"
    if direction not in ("downstream", "upstream") or offset is None:
        raise IsybauError(
            f"{where} was stored before pipescan kept the survey's direction, which ISYBAU "
            "needs (Inspektionsrichtung)",
            field="direction",
            hint="inspect its archive again (pipescan inspect ARCHIVE) and export the new one",
        )
    pipe = _Pipe()
    pipe.remarks.append(
        f"Surveyed with a LiDAR scan, processed by pipescan {record.software_version} "
        f"(inspection {record.id}, asset {record.asset_id})"
    )
    if direction == "downstream":
        pipe.remarks.append("Stations count from the upstream node, where chainage starts")
    else:
        pipe.remarks.append(
            f"Upstream survey: stations count from the scan's start, {offset:.2f} m from the "
            "upstream node, taken as the start node"
        )
    pipe.remarks.append(
        f"Condition classes are pipescan's (0 worst, 4 best) under the threshold table "
        f"{record.threshold_table or DEFAULT_TABLE}, not an ISYBAU assessment; characterisations "
        "are left out: a LiDAR scan measures shape, not material"
    )

    if inspection.first_chainage_m is not None and inspection.last_chainage_m is not None:
        ends = sorted(
            _station(c, direction, offset)
            for c in (inspection.first_chainage_m, inspection.last_chainage_m)
        )
        pipe.surveyed_length_m = max(ends[1], 0.0)
    _decimal(pipe.surveyed_length_m, "Inspektionslaenge", where)
    pipe.observations.append(_Observation(0.0, 0, START_CODE.code))
    pipe.observations.append(_Observation(pipe.surveyed_length_m, 9, END_CODE.code))

    number = 0
    graded = [d for d in inspection.defects if d.grade is not None]
    for defect in inspection.defects:
        code = EMITTED_CODES.get(defect.code)
        a, b = sorted(
            _station(c, direction, offset) for c in (defect.chainage_start_m, defect.chainage_end_m)
        )
        words = _MEASURE_WORDS.get(defect.measure, defect.measure + " {} %")
        peak = words.format(_percent(defect.peak_value))
        rest = (
            f" at chainage {defect.peak_chainage_m:.2f} m"
            + (
                f", cross-section lost {_percent(defect.peak_blockage_ratio)} %"
                if defect.peak_blockage_ratio is not None and defect.measure != "blockage_ratio"
                else ""
            )
            + (f", condition class {defect.grade}" if defect.grade is not None else ", not graded")
            + (
                " or worse; at least this: part of it stood in water that returned nothing"
                if defect.lower_bound
                else ""
            )
        )
        if code is None:
            pipe.remarks.append(
                f"Not coded as an observation (EN 13508-2 {defect.code}: its use in ISYBAU "
                f"could not be checked against the published example): {peak}{rest}, chainage "
                f"{defect.chainage_start_m:.2f}-{defect.chainage_end_m:.2f} m (stations "
                f"{a:.2f}-{b:.2f}), {_clock_words(defect, coded=False)}"
            )
            continue
        if defect.peak_value < 0 or not math.isfinite(defect.peak_value):
            quantity = None
            figures = f"{peak}{rest}; Quantifizierung1 left out (the figure is not a loss)"
        else:
            quantity = _decimal(100.0 * defect.peak_value, "Quantifizierung1", where, limit=9999)
            quantity = f"{float(quantity):.1f}"
            figures = f"{peak} (Quantifizierung1){rest}"
        comment = f"pipescan: {code.label}, {figures}; {_clock_words(defect)}"
        positions = _positions(defect)
        length = defect.chainage_end_m - defect.chainage_start_m
        if length <= inspection.step_m * 1.5:
            pipe.observations.append(
                _Observation(
                    (a + b) / 2, 5, code.code, quantity=quantity, comment=comment, **positions
                )
            )
        else:
            number += 1
            if number > MAX_CONTINUOUS_DEFECTS:
                raise IsybauError(
                    f"{where} has more than {MAX_CONTINUOUS_DEFECTS} continuous defects, the "
                    "most the format numbers (StreckenschadenLfdNr)",
                    field="StreckenschadenLfdNr",
                )
            for station, order, mark in ((a, 3, "A"), (b, 7, "B")):
                pipe.observations.append(
                    _Observation(
                        station,
                        order,
                        code.code,
                        quantity=quantity,
                        continuous=mark,
                        number=number,
                        comment=comment if mark == "A" else None,
                        **positions,
                    )
                )
    for obs in pipe.observations:
        _decimal(obs.station_m, "Station", where)
    pipe.observations.sort(key=lambda o: (round(o.station_m, 2), o.order))
    if graded:
        pipe.governing = min(graded, key=lambda d: (d.grade, -d.peak_value))
    return pipe


# --------------------------------------------------------------------------------------------
# Writing the tree


def _sub(parent: ET.Element, tag: str, text: object = None) -> ET.Element:
    element = ET.SubElement(parent, f"{{{NAMESPACE}}}{tag}")
    if text is not None:
        element.text = str(text)
    return element


def _one_line(text: str) -> str:
    # xsd:token collapses whitespace anyway; keep what is written equal to what is read.
    return " ".join(text.split())


def _check_length(value: str, limit: int, what: str, where: str, hint: str) -> str:
    if len(value) > limit:
        raise IsybauError(
            f"{where}: {value!r} has {len(value)} characters; ISYBAU's {what} holds {limit}",
            field=what,
            hint=hint,
        )
    return value


def _kennung(index: int) -> str:
    return f"Z{index:04d}"


def _inspected_object(parent: ET.Element, inspection: IsybauInspection, pipe: _Pipe) -> None:
    record = inspection.record
    where = f"inspection {record.id}"
    name = inspection.gis_id or record.asset_id
    anlage = _sub(parent, "InspizierteAbwassertechnischeAnlage")
    _sub(
        anlage,
        "Objektbezeichnung",
        _check_length(
            name, 30, "Objektbezeichnung", where, "shorten the asset id (or the GIS id) to 30"
        ),
    )
    _sub(anlage, "Anlagentyp", 1)  # U103: Haltung
    optical = _sub(anlage, "OptischeInspektion")
    _sub(optical, "Auftragskennung", 1)
    inspected = record.inspected_at.astimezone(UTC)
    _sub(optical, "Inspektionsdatum", inspected.date().isoformat())
    _sub(optical, "Inspektionsverfahren", 3)  # U108: anderes Verfahren (a LiDAR scan)
    if inspected.time() != time(0, 0):
        _sub(optical, "Uhrzeit", inspected.strftime("%H:%M:%SZ"))
    _sub(optical, "Bemerkung", _one_line(". ".join(pipe.remarks) + "."))
    pipe_element = _sub(optical, "Rohrleitung")
    _sub(pipe_element, "Rohrleitungstyp", 0)  # U100: Haltung
    _sub(pipe_element, "Inspektionsrichtung", "O" if record.direction == "downstream" else "U")
    _sub(pipe_element, "Inspektionslaenge", f"{pipe.surveyed_length_m:.2f}")
    _sub(pipe_element, "ArtVideoreferenz", 4)  # U127: keine Videoreferenz vorhanden
    if record.upstream_node and record.downstream_node:
        basics = _sub(pipe_element, "RGrunddaten")
        hint = "node names hold 30 characters in ISYBAU"
        _sub(
            basics,
            "KnotenZulauf",
            _check_length(record.upstream_node, 30, "KnotenZulauf", where, hint),
        )
        _sub(basics, "KnotenZulaufTyp", 0)  # G300: Schacht (pipescan's nodes are manholes)
        _sub(
            basics,
            "KnotenAblauf",
            _check_length(record.downstream_node, 30, "KnotenAblauf", where, hint),
        )
        _sub(basics, "KnotenAblaufTyp", 0)
        if record.pipe_shape == "circular" and record.nominal_diameter_m:
            # The inner diameter the scan measured (U124 4: Querschnittsvermessung), else
            # the nominal one (2: aus Stammdaten).
            measured = (record.registration or {}).get("measured_inner_diameter_m")
            _sub(basics, "HerkunftProfilmasse", 2 if measured is None else 4)
            size_mm = round((record.nominal_diameter_m if measured is None else measured) * 1000)
            _sub(basics, "Profilhoehe", size_mm)
            _sub(basics, "Profilbreite", size_mm)
            _sub(basics, "Profilart", 0)  # G205: Kreisprofil
    data = _sub(pipe_element, "Inspektionsdaten")
    for obs in pipe.observations:
        state = _sub(data, "RZustand")
        _sub(state, "Station", f"{obs.station_m:.2f}")
        # The schema asks for one of Timecode, Frame, Videozaehler or Parameter; there is no
        # video (ArtVideoreferenz 4), so the free Parameter stays empty.
        _sub(state, "Parameter", "")
        _sub(state, "InspektionsKode", obs.code)
        if obs.quantity is not None:
            _sub(state, "Quantifizierung1Numerisch", obs.quantity)
        if obs.continuous is not None:
            _sub(state, "Streckenschaden", obs.continuous)
            _sub(state, "StreckenschadenLfdNr", obs.number)
        if obs.position_from is not None:
            _sub(state, "PositionVon", f"{obs.position_from:02d}")
            if obs.position_to is not None:
                _sub(state, "PositionBis", f"{obs.position_to:02d}")
        if obs.comment:
            _sub(state, "Kommentar", _one_line(obs.comment))
    if inspection.worst_grade is not None:
        rating = _sub(pipe_element, "Bewertung")
        _sub(rating, "Bewertungsverfahren", 4)  # U112: anderes Verfahren
        _sub(rating, "Bewertungsdatum", record.created_at.astimezone(UTC).date().isoformat())
        governing = pipe.governing
        if governing is not None and governing.code in EMITTED_CODES:
            _sub(rating, "MassgebenderSchaden", governing.code)
            if governing.peak_value >= 0:
                _sub(rating, "MassgebendeQuantifizierung", f"{100 * governing.peak_value:.1f}")
        _sub(rating, "KlasseAutomatisch", inspection.worst_grade)


def build_isybau(inspections: Sequence[IsybauInspection], header: IsybauHeader) -> bytes:
    """The ISYBAU XML document of some inspections, encoded in ISO-8859-1.

    One ``Zustandsdatenkollektiv`` per inspection: the format keys an inspected pipe by its
    name, type and direction within a collective, so two inspections of one pipe need two.

    Raises
    ------
    IsybauError
        When a value does not fit the format (see :class:`IsybauError`); nothing is built.
    """
    if not inspections:
        raise IsybauError("no inspection to export", hint="list them with `pipescan inspections`")
    pipes = [_describe(i) for i in inspections]
    ET.register_namespace("", NAMESPACE)
    root = ET.Element(f"{{{NAMESPACE}}}Identifikation")
    _sub(root, "Version", FORMAT_VERSION)
    admin = _sub(root, "Admindaten")
    estate = _sub(admin, "Liegenschaft")
    _sub(estate, "Liegenschaftsnummer", header.property_number)
    _sub(estate, "Liegenschaftsbezeichnung", header.property_name)
    collectives = _sub(root, "Datenkollektive")
    _sub(collectives, "Datenstatus", 1)  # M100: Bestandsdaten, as in the published example
    _sub(collectives, "Erstellungsdatum", header.created_on.isoformat())
    _sub(collectives, "Kommentar", "LiDAR condition data exported by pipescan")
    keys = _sub(collectives, "Kennungen")
    for index, _ in enumerate(inspections, start=1):
        collective = _sub(keys, "Kollektiv")
        _sub(collective, "Kennung", _kennung(index))
        _sub(collective, "Kollektivart", 2)  # M101: Zustandsdaten
        kind = _sub(_sub(collective, "Kollektiveigenschaft"), "Zustandsdaten")
        _sub(kind, "Inspektion", 1)
        _sub(kind, "Dichtheit", 0)
        _sub(kind, "Film", 0)
        _sub(collective, "Regelwerk", 5)  # M104: Arbeitshilfen Abwasser (ISYBAU 2013)
        _sub(collective, "Bearbeitungsstand", header.created_on.isoformat())
    for index, (inspection, pipe) in enumerate(zip(inspections, pipes, strict=True), start=1):
        record = inspection.record
        data = _sub(collectives, "Zustandsdatenkollektiv")
        _sub(data, "Kennung", _kennung(index))
        _sub(data, "Beschreibung", f"pipescan inspection {record.id}"[:100])
        order = _sub(_sub(data, "Auftraege"), "Auftrag")
        _sub(order, "Auftragsbezeichnung", f"pipescan inspection {record.id}"[:60])
        _sub(order, "Auftragskennung", 1)
        _sub(order, "Auftragsart", 1)  # U119: Inspektionsauftrag
        _sub(order, "Kodiersystem", 8)  # U102: DIN EN 13508-2:2011, no national rules
        _sub(order, "Systemname", "pipescan")
        _sub(order, "Version", record.software_version[:10])
        _inspected_object(data, inspection, pipe)
    ET.indent(root, space="  ")
    return ET.tostring(root, encoding=ENCODING, xml_declaration=True) + b"\n"


# --------------------------------------------------------------------------------------------
# Validation


@cache
def _schema() -> Any:
    import xmlschema

    return xmlschema.XMLSchema(str(SCHEMA_ENTRY))


def validation_errors(document: bytes, *, limit: int = 20) -> list[str]:
    """What is wrong with an ISYBAU XML document against the schema: ``path: reason`` lines
    (at most ``limit``); empty when it validates. The schema is parsed once per process."""
    errors = []
    for error in _schema().iter_errors(io.BytesIO(document)):
        reason = (error.reason or str(error)).strip().splitlines()[0]
        errors.append(f"{error.path}: {reason}")
        if len(errors) >= limit:
            break
    return errors


# --------------------------------------------------------------------------------------------
# From the database


def _extents(engine: Engine, ids: Sequence[int]) -> dict[int, tuple[float, float]]:
    statement = (
        sa.select(
            Section.inspection_id,
            sa.func.min(Section.chainage_start_mm),
            sa.func.max(Section.chainage_end_mm),
        )
        .where(Section.inspection_id.in_(list(ids)))
        .group_by(Section.inspection_id)
    )
    with session_scope(engine) as session:
        return {i: (mm_to_m(a), mm_to_m(b)) for i, a, b in session.execute(statement)}


def load_isybau_inspections(
    engine: Engine, *, inspection_id: int | None = None, asset_id: str | None = None
) -> list[IsybauInspection]:
    """One inspection, or every inspection of an asset (by date), ready for
    :func:`build_isybau`.

    ``asset_id`` may be the GIS id of an imported pipe.

    Raises
    ------
    StorageError
        For an unknown inspection id, or an asset without inspections.
    IsybauError
        Neither, or an inspection of another asset than the one given.
    """
    if inspection_id is not None:
        records = [get_inspection(engine, inspection_id)]
        if asset_id is not None and records[0].asset_id != asset_id:
            raise IsybauError(
                f"inspection {inspection_id} is of asset {records[0].asset_id}, not {asset_id}",
                field="asset",
                hint="give --inspection or --asset, or both of the same pipe",
            )
    elif asset_id is not None:
        records = list_inspections(engine, resolve_asset(engine, asset_id))
    else:
        raise IsybauError(
            "say which inspection to export", hint="give --inspection ID or --asset ID"
        )
    ids = [r.id for r in records]
    extents = _extents(engine, ids)
    profiles = section_profiles(engine, ids)
    names = gis_ids(engine, sorted({r.asset_id for r in records}))
    with session_scope(engine) as session:
        steps = {
            i: float((params or {}).get("step_m", SECTION_STEP_M))
            for i, params in session.execute(
                sa.select(Inspection.id, Inspection.params_json).where(Inspection.id.in_(ids))
            )
        }
        return [
            IsybauInspection(
                record=r,
                defects=list_defects(session, r.id),
                first_chainage_m=extents.get(r.id, (None, None))[0],
                last_chainage_m=extents.get(r.id, (None, None))[1],
                worst_grade=worst_grade(profiles[r.id]),
                step_m=steps.get(r.id, SECTION_STEP_M),
                gis_id=names.get(r.asset_id),
            )
            for r in records
        ]


@dataclass(frozen=True)
class IsybauExport:
    """What :func:`export_isybau` wrote: the file, its inspections, the observations and the
    defects left to the remarks."""

    path: Path
    inspection_ids: tuple[int, ...]
    observations: int
    defects_in_remarks: int


def export_isybau(
    engine: Engine,
    out_path: Path,
    header: IsybauHeader,
    *,
    inspection_id: int | None = None,
    asset_id: str | None = None,
) -> IsybauExport:
    """Write an inspection (or every inspection of an asset) as an ISYBAU XML file.

    The document is validated against the shipped schema first; only a valid document is
    written, through a temporary file in the same folder, so a failed export leaves nothing.

    Raises
    ------
    IsybauError
        The document would not validate (its first errors are named), or a value does not fit.
    StorageError
        Unknown ids.
    """
    inspections = load_isybau_inspections(engine, inspection_id=inspection_id, asset_id=asset_id)
    document = build_isybau(inspections, header)
    errors = validation_errors(document)
    if errors:
        raise IsybauError(
            f"the document does not validate against the ISYBAU 2013 schema: {errors[0]}"
            + (f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""),
            hint="nothing was written; this is a bug in pipescan, please report it",
        )
    try:
        with atomic_file(out_path) as fh:  # a new file of a random name: no link followed
            fh.write(document)
    except OSError as exc:
        raise IsybauError(
            f"cannot write: {exc.strerror or exc}",
            file=str(out_path),
            hint="give a file in an existing folder you may write to; nothing was written",
        ) from exc
    pipes = [_describe(i) for i in inspections]
    return IsybauExport(
        path=out_path,
        inspection_ids=tuple(i.record.id for i in inspections),
        observations=sum(len(p.observations) for p in pipes),
        defects_in_remarks=sum(
            1 for i in inspections for d in i.defects if d.code not in EMITTED_CODES
        ),
    )


def created_today() -> date:
    """Today's date in UTC (the file's creation date)."""
    return datetime.now(UTC).date()
