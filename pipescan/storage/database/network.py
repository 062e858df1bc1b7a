"""The network's geometry: an imported pipe layer, and which asset each of its pipes is.

An imported layer's pipes are stored as read (``network_pipes``); which asset a pipe stands
for is decided when it is read, by the rules of :func:`asset_geometries`, so that a layer
imported once also serves the assets inspected after it. Like the repository, every function
opens and closes its own session and returns core dataclasses.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import sqlalchemy as sa
from sqlalchemy.engine import Engine

from pipescan.core.network import (
    ORIENTED_BY_METADATA,
    NetworkLayer,
    PipeGeometry,
    PipeLine,
    length_note,
    orient,
)
from pipescan.storage.database.db import StorageError, session_scope
from pipescan.storage.database.models import Asset, Inspection, NetworkPipe

__all__ = [
    "NetworkImport",
    "Placement",
    "asset_geometries",
    "gis_ids",
    "import_network_layer",
    "placements",
    "resolve_asset",
]

_CHUNK = 500


@dataclass(frozen=True)
class NetworkImport:
    """What an import did: pipes stored (``replaced`` of them were stored before, by GIS id),
    and the stored assets that now have a pipe of the network (``matched``, by asset id) or
    still have none (``unmatched_assets``)."""

    stored: int
    replaced: int
    matched: tuple[str, ...]
    unmatched_assets: tuple[str, ...]


def _line_json(line: PipeLine) -> str:
    return json.dumps(line.coords.tolist(), separators=(",", ":"))


def import_network_layer(engine: Engine, layer: NetworkLayer) -> NetworkImport:
    """Store a network layer's pipes, replacing those stored before with the same GIS id.

    In one transaction; nothing is written when it fails.

    Raises
    ------
    StorageError
        When an asset id the layer names is already named by another stored pipe, or when the
        database holds assets and not one of them matches a pipe of the layer (the wrong id
        field, most likely).
    """
    ids = [p.gis_id for p in layer.pipes]
    refs = {p.asset_ref: p.gis_id for p in layer.pipes}
    with session_scope(engine, write=True) as session:
        replaced = 0
        for chunk in _chunks(ids):
            replaced += (
                session.scalar(sa.select(sa.func.count()).where(NetworkPipe.gis_id.in_(chunk))) or 0
            )
        mine = set(ids)
        for chunk in _chunks(list(refs)):
            # The layer's own ids are left out here, not in SQL: a NOT IN of every id of a
            # large layer passed SQLite's limit on variables.
            for gis_id, ref in session.execute(
                sa.select(NetworkPipe.gis_id, NetworkPipe.asset_ref).where(
                    NetworkPipe.asset_ref.in_(chunk)
                )
            ):
                if gis_id in mine:
                    continue
                raise StorageError(
                    f"pipe {refs[ref]} of {layer.source} names asset {ref}, which pipe "
                    f"{gis_id} (imported before) already names",
                    field="asset_ref",
                    hint="an asset is one pipe of the network; fix the layer or the earlier one",
                )
        for chunk in _chunks(ids):
            session.execute(sa.delete(NetworkPipe).where(NetworkPipe.gis_id.in_(chunk)))
        session.execute(
            sa.insert(NetworkPipe),
            [
                {
                    "gis_id": p.gis_id,
                    "asset_ref": p.asset_ref,
                    "from_node": p.from_node,
                    "to_node": p.to_node,
                    "crs": layer.crs,
                    "line_json": _line_json(p.line),
                    "length_m": p.line.length_m,
                    "source": layer.source,
                }
                for p in layer.pipes
            ],
        )
        session.flush()
        assets = list(session.scalars(sa.select(Asset.asset_id).order_by(Asset.asset_id)))
        matches = _matches(session, assets)
        matched = tuple(a for a in assets if a in matches and matches[a].gis_id in mine)
        if assets and not matched:
            sample_id = layer.pipes[0].asset_ref
            raise StorageError(
                f"none of the {len(layer.pipes)} pipes of {layer.source} matches one of the "
                f"{len(assets)} stored assets (the layer names pipes like {sample_id!r}, the "
                f"assets are like {assets[0]!r})",
                hint="name the field holding pipescan's asset ids with --asset-field, or the "
                "node fields with --from-node-field and --to-node-field; nothing was imported",
            )
        unmatched = tuple(a for a in assets if a not in matches)
    return NetworkImport(
        stored=len(ids), replaced=replaced, matched=matched, unmatched_assets=unmatched
    )


def _chunks(items: Sequence[Any]) -> Iterable[Sequence[Any]]:
    for start in range(0, len(items), _CHUNK):
        yield items[start : start + _CHUNK]


@dataclass(frozen=True)
class _Match:
    gis_id: str
    row: Any


def _matches(session: Any, asset_ids: Sequence[str]) -> dict[str, _Match]:
    """Each asset's pipe of the network: the pipe naming the asset's id; failing that, the one
    pipe between the asset's two nodes (either way round). Two pipes between the same nodes
    match neither."""
    found: dict[str, _Match] = {}
    for chunk in _chunks(list(asset_ids)):
        for asset_id, row in session.execute(
            sa.select(Asset.asset_id, NetworkPipe)
            .join(NetworkPipe, NetworkPipe.asset_ref == Asset.asset_id)
            .where(Asset.asset_id.in_(chunk))
        ):
            found[asset_id] = _Match(row.gis_id, row)
    rest = [a for a in asset_ids if a not in found]
    by_nodes: dict[str, list[Any]] = {}
    same = sa.and_(
        NetworkPipe.from_node == Asset.upstream_node, NetworkPipe.to_node == Asset.downstream_node
    )
    swapped = sa.and_(
        NetworkPipe.from_node == Asset.downstream_node, NetworkPipe.to_node == Asset.upstream_node
    )
    for chunk in _chunks(rest):
        for condition in (same, swapped):
            for asset_id, row in session.execute(
                sa.select(Asset.asset_id, NetworkPipe)
                .join(NetworkPipe, condition)
                .where(Asset.asset_id.in_(chunk))
            ):
                by_nodes.setdefault(asset_id, []).append(row)
    for asset_id, rows in by_nodes.items():
        distinct = {r.gis_id: r for r in rows}
        if len(distinct) == 1:
            row = next(iter(distinct.values()))
            found[asset_id] = _Match(row.gis_id, row)
    return found


def gis_ids(engine: Engine, asset_ids: Sequence[str] | None = None) -> dict[str, str]:
    """The GIS id of each asset that has a pipe in an imported layer (all assets by default);
    assets without one are left out."""
    with session_scope(engine) as session:
        if asset_ids is None:
            asset_ids = list(session.scalars(sa.select(Asset.asset_id)))
        return {a: m.gis_id for a, m in _matches(session, asset_ids).items()}


def asset_geometries(engine: Engine, asset_ids: Sequence[str]) -> dict[str, PipeGeometry]:
    """Where each asset's pipe lies, upstream node first.

    From the imported layer's pipe that stands for the asset (see :func:`_matches`),
    oriented by :func:`pipescan.core.network.orient`; failing that, the straight line between
    the node positions of the asset's metadata. Assets with neither are left out.
    """
    with session_scope(engine) as session:
        assets = {
            a.asset_id: a
            for chunk in _chunks(list(asset_ids))
            for a in session.scalars(sa.select(Asset).where(Asset.asset_id.in_(chunk)))
        }
        matches = _matches(session, list(assets))
        found: dict[str, PipeGeometry] = {}
        for asset_id, asset in assets.items():
            match = matches.get(asset_id)
            if match is not None:
                row = match.row
                same_crs = asset.crs is not None and asset.crs.upper() == row.crs.upper()
                line, oriented_by = orient(
                    np.asarray(json.loads(row.line_json), dtype=np.float64),
                    from_node=row.from_node,
                    to_node=row.to_node,
                    upstream_node=asset.upstream_node,
                    downstream_node=asset.downstream_node,
                    upstream_xyz=asset.upstream_node_xyz if same_crs else None,
                    downstream_xyz=asset.downstream_node_xyz if same_crs else None,
                )
                found[asset_id] = PipeGeometry(
                    asset_id=asset_id,
                    line=line,
                    crs=row.crs,
                    source=row.source,
                    oriented_by=oriented_by,
                    gis_id=row.gis_id,
                )
            elif (
                asset.upstream_node_xyz is not None
                and asset.downstream_node_xyz is not None
                and asset.crs is not None
            ):
                found[asset_id] = PipeGeometry(
                    asset_id=asset_id,
                    line=PipeLine(np.array([asset.upstream_node_xyz, asset.downstream_node_xyz])),
                    crs=asset.crs,
                    source="inspection.toml",
                    oriented_by=ORIENTED_BY_METADATA,
                )
        return found


@dataclass(frozen=True)
class Placement:
    """How a scan sits on its pipe's geometry, for reports: the pipe's GIS id (None without an
    imported layer's pipe) and the words saying that the scan's reach and the line's length
    disagree (:func:`pipescan.core.network.length_note`; None when they agree or there is no
    geometry)."""

    gis_id: str | None
    length_note: str | None


def placements(engine: Engine, reaches: dict[str, float | None]) -> dict[str, Placement]:
    """The placement of each asset's scan, given how far it reaches from the upstream node
    (the end of its last section; None when it has no sections). Assets without a geometry
    get ``Placement(None, None)``."""
    geometries = asset_geometries(engine, sorted(reaches))
    found = {}
    for asset_id, reach in reaches.items():
        geometry = geometries.get(asset_id)
        note = None
        if geometry is not None and reach is not None:
            note = length_note(reach, geometry.line.length_m)
        found[asset_id] = Placement(None if geometry is None else geometry.gis_id, note)
    return found


def resolve_asset(engine: Engine, name: str) -> str:
    """The asset a user names: an asset id with inspections, or the GIS id of an imported pipe
    that stands for one.

    Raises
    ------
    StorageError
        When it is neither.
    """
    with session_scope(engine) as session:
        if session.scalar(sa.select(sa.func.count()).where(Inspection.asset_id == name)):
            return name
        imported = session.scalar(sa.select(sa.func.count()).where(NetworkPipe.gis_id == name))
    if imported:
        named = sorted(a for a, gis_id in gis_ids(engine).items() if gis_id == name)
        if named:
            return named[0]
    raise StorageError(
        f"no inspection of asset {name!r}",
        field="asset",
        hint="list the assets with `pipescan assets` (a GIS id of an imported layer works too)",
    )
