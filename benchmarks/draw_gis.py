"""Draw pipescan's GIS export of a small simulated network, to look at it.

Simulates four pipe scans (the paper's scene, an obstacle alone, a clean pipe, a large
obstacle and a deposit),
inspects them with ``pipescan inspect-network``, lays a made-up network of lines out around
them (EPSG:25832), imports it with ``pipescan network import`` (three pipes; the fourth gets its
line from node positions in its ``inspection.toml``), exports the GeoPackage with ``pipescan
export gis`` and draws it with matplotlib: pipes coloured by condition class, defects on top.
One line is drawn 12 % longer than its scan reaches, so that the export's length note shows.

    python benchmarks/draw_gis.py                # writes benchmarks/out/gis/network-map.png

Also writes the ISYBAU XML of every inspection and the network report PDF next to it. Takes a
few minutes (four simulated scans).
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CRS = "EPSG:25832"
X0, Y0 = 512_300.0, 5_803_100.0
CLASS_COLOURS = {0: "#b2182b", 1: "#ef8a62", 2: "#fddb6d", 3: "#a6d96a", 4: "#1a9641"}


def pipescan(*args: str) -> str:
    env = {**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    result = subprocess.run(
        [sys.executable, "-m", "pipescan.cli", *args],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    if result.returncode != 0:
        raise SystemExit(f"pipescan {' '.join(args)} failed:\n{result.stderr[-2000:]}")
    return result.stdout + result.stderr


def simulate(store: Path) -> None:
    from pipescan.simulator.archive import dumps_toml, write_simulated_archive
    from pipescan.simulator.scan import BoxObstacle, DepositFill, get_scenario, simulate_scan

    obstacle = BoxObstacle(
        start_m=2.6, end_m=2.9, y_min_m=-0.14, y_max_m=0.14, z_min_m=0.1184, z_max_m=0.35
    )
    # Deposits stay under the sensor's path (0.05 m below the axis, with clearance).
    deep = DepositFill(start_m=3.2, end_m=4.0, ramp_m=0.25, peak_height_ratio=0.3)
    big = BoxObstacle(start_m=2.0, end_m=2.3, y_min_m=-0.2, y_max_m=0.2, z_min_m=0.02, z_max_m=0.35)
    pipes = {
        "MH101-MH102": get_scenario("paper", upstream_node="MH101", downstream_node="MH102"),
        "MH103-MH102": get_scenario(
            "paper", upstream_node="MH103", downstream_node="MH102", deformations=(),
            deposits=(), obstacles=(obstacle,),
        ),
        "MH102-MH104": get_scenario("clean", upstream_node="MH102", downstream_node="MH104"),
        "MH105-MH101": get_scenario(
            "paper", upstream_node="MH105", downstream_node="MH101", deformations=(),
            deposits=(deep,), obstacles=(big,),
        ),
    }  # fmt: skip
    for seed, (asset_id, scenario) in enumerate(pipes.items()):
        archive = store / asset_id
        if (archive / "inspection.toml").is_file():
            continue
        scan = simulate_scan(scenario, seed=seed)
        write_simulated_archive(scan, archive)
        doc = tomllib.loads((archive / "inspection.toml").read_text())
        doc["asset_id"] = asset_id
        (archive / "inspection.toml").write_text(dumps_toml(doc))
        print(f"simulated {asset_id}", flush=True)


def reaches(db_url: str) -> dict[str, float]:
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.queries import list_network_inspections, section_profiles

    engine = connect(db_url)
    try:
        records = list_network_inspections(engine)
        profiles = section_profiles(engine, [r.id for r in records])
    finally:
        engine.dispose()
    return {r.asset_id: max(s.chainage_end_m for s in profiles[r.id]) for r in records}


def polyline(start: np.ndarray, headings_deg: list[float], length_m: float) -> np.ndarray:
    """A line from ``start`` in equal legs along the headings (degrees from east)."""
    points = [start]
    leg = length_m / len(headings_deg)
    for heading in headings_deg:
        a = math.radians(heading)
        points.append(points[-1] + leg * np.array([math.cos(a), math.sin(a)]))
    return np.array(points)


def lay_out(reach: dict[str, float], layer_path: Path, store: Path) -> None:
    """The made-up network: lines digitised upstream to downstream (one the other way), one
    line 12 % longer than its scan reaches; MH102-MH104 only as node positions in its
    inspection.toml."""
    import shapely
    import tomli_w
    from pyogrio.raw import write

    mh101 = np.array([X0, Y0])
    p1 = polyline(mh101, [0.0, 10.0], reach["MH101-MH102"])
    mh102 = p1[-1]
    p2 = polyline(mh102, [80.0], reach["MH103-MH102"])[::-1]  # digitised MH103 -> MH102
    p4 = polyline(mh101, [200.0, 180.0], 1.12 * reach["MH105-MH101"])[::-1]
    lines = {"SW-1001": p1, "SW-1002": p2, "SW-1004": p4}
    nodes = {
        "SW-1001": ("MH101", "MH102"),
        "SW-1002": ("MH103", "MH102"),
        "SW-1004": ("MH105", "MH101"),
    }
    write(
        str(layer_path),
        np.array(shapely.to_wkb([shapely.LineString(c) for c in lines.values()]), dtype=object),
        [
            np.array(list(lines), dtype=object),
            np.array([nodes[k][0] for k in lines], dtype=object),
            np.array([nodes[k][1] for k in lines], dtype=object),
        ],
        ["FACILITYID", "UPNODE", "DOWNNODE"],
        layer="sewer_pipes",
        driver="GPKG",
        geometry_type="LineString",
        crs=CRS,
    )
    # The fourth pipe: its nodes' positions, in its archive's metadata.
    p3 = polyline(mh102, [-40.0], reach["MH102-MH104"])
    path = store / "MH102-MH104" / "inspection.toml"
    doc = tomllib.loads(path.read_text())
    doc |= {
        "upstream_node_xyz": [*p3[0].tolist(), 41.2],
        "downstream_node_xyz": [*p3[-1].tolist(), 41.16],
        "crs": CRS,
    }
    path.write_text(tomli_w.dumps(doc))


def _left(segment: np.ndarray) -> np.ndarray:
    """The unit normal to the left of a segment's direction, (2,)."""
    d = segment[-1] - segment[0]
    return np.array([-d[1], d[0]]) / np.linalg.norm(d)


def draw(gpkg: Path, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import shapely
    from matplotlib.lines import Line2D
    from pyogrio.raw import read

    def layer(name: str):
        meta, _, geometry, values = read(str(gpkg), layer=name)
        return (
            meta,
            [shapely.from_wkb(g) for g in geometry],
            dict(zip(meta["fields"], values, strict=True)),
        )

    meta, pipes, pf = layer("pipes")
    _, defects, df = layer("defects")
    fig, ax = plt.subplots(figsize=(11, 6.2), dpi=130)
    for i, line in enumerate(pipes):
        xy = np.asarray(line.coords)[:, :2] - (X0, Y0)
        grade = pf["condition_class"][i]
        colour = "#999999" if math.isnan(grade) else CLASS_COLOURS[int(grade)]
        ax.plot(*xy.T, color=colour, lw=9, solid_capstyle="round", zorder=1)
        # Flow direction: an arrowhead at the middle of the line's last leg.
        tail, head = xy[-2] + 0.45 * (xy[-1] - xy[-2]), xy[-2] + 0.55 * (xy[-1] - xy[-2])
        ax.annotate(
            "", xy=head, xytext=tail, zorder=2,
            arrowprops={"arrowstyle": "-|>", "color": "#333333", "lw": 1.2, "mutation_scale": 16},
        )  # fmt: skip
        leg = xy[len(xy) // 2 - 1 : len(xy) // 2 + 1]
        middle = leg.mean(axis=0)
        name = pf["gis_id"][i] or f"{pf['asset_id'][i]} (inspection.toml)"
        peak = pf["peak_blockage_ratio"][i]
        label = f"{name}\nclass {'–' if math.isnan(grade) else int(grade)}, peak {100 * peak:.1f} %"
        if pf["length_note"][i]:
            gis_m, scan_m = pf["gis_length_m"][i], pf["scan_end_chainage_m"][i]
            label += f"\nGIS {gis_m:.2f} m, scan {scan_m:.2f} m: not stretched"
        box = {"boxstyle": "round,pad=0.25", "fc": "white", "ec": "#cccccc", "alpha": 0.9}
        # Pipe labels to the left of the flow, defect labels to the right.
        ax.text(
            *(middle + 1.4 * _left(leg)), label, fontsize=7.5, zorder=4, bbox=box,
            ha="center", va="center",
        )  # fmt: skip
        for end in (xy[0], xy[-1]):
            ax.plot(*end, "o", ms=9, mfc="white", mec="#333333", zorder=3)
    for i, event in enumerate(defects):
        xy = np.asarray(event.coords)[:, :2] - (X0, Y0)
        ax.plot(*xy.T, color="#111111", lw=3.2, solid_capstyle="butt", zorder=5)
        grade = df["condition_class"][i]
        text = f"{df['code'][i]} {'' if math.isnan(grade) else int(grade)}"
        # Alternately nearer and further, so that neighbours do not overlap.
        away = -(0.45 if i % 2 == 0 else 0.85) * _left(xy[[0, -1]])
        ax.text(
            *(xy.mean(axis=0) + away), text, fontsize=7, color="#111111", zorder=6,
            ha="center", va="center",
        )  # fmt: skip
    handles = [
        Line2D([], [], color=c, lw=6, label=f"class {g}") for g, c in CLASS_COLOURS.items()
    ] + [
        Line2D([], [], color="#111111", lw=3, label="defect (code, class)"),
        Line2D([], [], color="#333333", marker=">", lw=0, label="flow direction"),
    ]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel(f"easting − {X0:.0f} (m)")
    ax.set_ylabel(f"northing − {Y0:.0f} (m)")
    ax.set_title(f"pipescan export gis: pipes by condition class, defects on top ({meta['crs']})")
    ax.grid(True, lw=0.3, color="#dddddd")
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" / "gis")
    parser.add_argument("--fresh", action="store_true", help="simulate and inspect again")
    args = parser.parse_args()
    out: Path = args.out
    if args.fresh and out.exists():
        shutil.rmtree(out)
    store = out / "store"
    store.mkdir(parents=True, exist_ok=True)
    db_url = f"sqlite:///{(out / 'network.db').resolve()}"
    simulate(store)
    if not (out / "network.db").exists():
        # First without node positions, to learn how far each scan reaches; the layer is laid
        # out to fit, then the clean pipe is inspected again with its positions.
        pipescan("inspect-network", str(store), "--db", db_url, "--no-network-report")
        lay_out(reaches(db_url), out / "pipes.gpkg", store)
        pipescan("inspect", str(store / "MH102-MH104"), "--db", db_url)
        print(
            pipescan(
                "network", "import", str(out / "pipes.gpkg"), "--id-field", "FACILITYID",
                "--from-node-field", "UPNODE", "--to-node-field", "DOWNNODE", "--db", db_url,
            )
        )  # fmt: skip
    gpkg = out / "network.gpkg"
    print(pipescan("export", "gis", "--format", "gpkg", "-o", str(gpkg), "--db", db_url))
    print(pipescan("assets", "--db", db_url))
    print(pipescan("report", "--network", "-o", str(out / "network-report.pdf"), "--db", db_url))
    for asset_id in ("MH101-MH102", "MH103-MH102", "MH102-MH104", "MH105-MH101"):
        xml = out / f"{asset_id}.xml"
        print(pipescan("export", "isybau", "--asset", asset_id, "-o", str(xml), "--db", db_url))
    png = out / "network-map.png"
    draw(gpkg, png)
    print(f"drew {png}")


if __name__ == "__main__":
    main()
