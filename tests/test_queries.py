"""The queries that pick "the latest inspection of each asset" and "the earlier scans of a pipe"
in SQL, against a plain Python reading of their rules, on SQLite and PostgreSQL.

The stored inspections are drawn at random (seeded): several assets, surveys on the same date,
archives processed more than once under other parameters, saved in a shuffled order.
"""

from __future__ import annotations

import random
from datetime import UTC, datetime, timedelta

import pytest
import sqlalchemy as sa

from pipescan.core.model import InspectionMeta, SectionMeasures, SectionStatus
from pipescan.storage.database import db, repository
from pipescan.storage.database.queries import (
    find_previous_scans,
    list_earlier_inspections,
    list_earlier_scans,
    list_network_inspections,
    scans_statement,
)

T0 = datetime(2021, 3, 1, 8, 0, tzinfo=UTC)


def _sections(count: int, blockage: float) -> list[SectionMeasures]:
    return [
        SectionMeasures(k / 10, (k + 1) / 10, 0.28, SectionStatus.OK, 900, 1.0,
                        open_area_m2=0.28 * (1 - blockage), blockage_ratio=blockage)
        for k in range(count)
    ]  # fmt: skip


@pytest.fixture
def stored(engine: sa.Engine) -> list[repository.InspectionRecord]:
    """About 25 inspections of 6 assets, saved in a shuffled order; returns their records."""
    rng = random.Random(14)
    plans = []
    for a in range(6):
        scans = rng.randint(1, 5)
        for k in range(scans):
            # Every other asset has two scans on the same date.
            day = k if a % 2 or k < 2 else k - 1
            when = T0 + timedelta(days=200 * day)
            for params in range(rng.choice([1, 1, 2, 3])):  # processed once or more
                plans.append((f"A{a}", when, f"sha256:A{a}-{k}", {"v": params}))
    rng.shuffle(plans)
    for asset_id, when, content, params in plans:
        repository.save_inspection(
            engine,
            repository.InspectionToSave(
                meta=InspectionMeta(asset_id=asset_id, inspected_at=when, nominal_diameter_m=0.6),
                archive_uri=f"/scans/{content}.zip",
                content_hash=content,
                params=params,
                software_version="0.1.0",
                sections=_sections(rng.randint(1, 4), rng.uniform(0.0, 0.3)),
                defects=[],
            ),
        )
    return repository.list_inspections(engine)


def _order(r: repository.InspectionRecord) -> tuple[datetime, int]:
    return (r.inspected_at, r.id)


def reference_earlier(
    records: list[repository.InspectionRecord], of: repository.InspectionRecord
) -> list[int]:
    """The rule in Python: the asset's inspections before ``of`` holding another archive, the
    latest save of each archive, newest first."""
    before = [
        r
        for r in records
        if r.asset_id == of.asset_id
        and r.content_hash != of.content_hash
        and _order(r) < _order(of)
    ]
    latest: dict[str, repository.InspectionRecord] = {}
    for r in before:
        if r.content_hash not in latest or r.id > latest[r.content_hash].id:
            latest[r.content_hash] = r
    return [r.id for r in sorted(latest.values(), key=_order, reverse=True)]


def test_latest_per_asset_and_earlier_scans_follow_their_rules(
    engine: sa.Engine, stored: list[repository.InspectionRecord]
) -> None:
    assert len(stored) > 20
    by_asset: dict[str, list[repository.InspectionRecord]] = {}
    for r in stored:
        by_asset.setdefault(r.asset_id, []).append(r)
    latest = list_network_inspections(engine)
    assert [r.id for r in latest] == [max(rs, key=_order).id for _, rs in sorted(by_asset.items())]
    assert latest == [r for r in stored if r.id in {x.id for x in latest}]  # whole records

    every = list_earlier_scans(engine, [r.id for r in stored])
    assert {i: [e.id for e in scans] for i, scans in every.items()} == {
        r.id: reference_earlier(stored, r) for r in stored
    }
    assert any(len(scans) >= 3 for scans in every.values())
    two = list_earlier_scans(engine, [r.id for r in stored], limit=2)
    assert {i: [e.id for e in s] for i, s in two.items()} == {
        i: [e.id for e in s][:2] for i, s in every.items()
    }
    previous = find_previous_scans(engine, latest)
    assert {i: p.id for i, p in previous.items()} == {
        r.id: reference_earlier(stored, r)[0] for r in latest if reference_earlier(stored, r)
    }
    one = stored[len(stored) // 2]
    assert [e.id for e in list_earlier_inspections(engine, one.id)] == reference_earlier(
        stored, one
    )
    with pytest.raises(db.StorageError, match="no inspection with id 99999"):
        list_earlier_inspections(engine, 99999)


def test_one_row_per_scan_for_trends(
    engine: sa.Engine, stored: list[repository.InspectionRecord]
) -> None:
    latest_save: dict[tuple[str, str], repository.InspectionRecord] = {}
    for r in stored:
        key = (r.asset_id, r.content_hash)
        if key not in latest_save or r.id > latest_save[key].id:
            latest_save[key] = r
    expected = sorted(latest_save.values(), key=lambda r: (r.asset_id, r.inspected_at, r.id))
    with engine.connect() as connection:
        rows = connection.execute(scans_statement()).all()
    assert [row.id for row in rows] == [r.id for r in expected]
    assert [row.peak_blockage_ratio for row in rows] == [r.peak_blockage_ratio for r in expected]


def test_network_selection_filters(
    engine: sa.Engine, stored: list[repository.InspectionRecord]
) -> None:
    since = T0 + timedelta(days=300)
    assert all(r.inspected_at >= since for r in list_network_inspections(engine, since=since))
    chosen = [stored[0].id, stored[-1].id]
    picked = list_network_inspections(engine, inspection_ids=chosen)
    assert {r.id for r in picked} <= set(chosen) and picked
    with pytest.raises(db.StorageError, match="no inspection with id 99999"):
        list_network_inspections(engine, inspection_ids=[stored[0].id, 99999])
