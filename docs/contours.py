"""Draw a few measured contours of the real S3DSS scan for the README.

    python docs/contours.py [--out docs/img/contours-real459.png]

Each panel shows one 0.1 m section: its points, the nominal 800 mm circle, and the polar contour
pipescan measured (drawn dashed where the section is not ``ok``), with its status and blockage.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from pipescan.core.axis import fit_axis
from pipescan.core.measures import measure_section
from pipescan.core.sections import iter_section_points, plan_windows
from pipescan.storage.input.pointfiles import read_points

ROOT = Path(__file__).resolve().parents[1]
SCAN = (
    Path(os.environ.get("PIPESCAN_REALDATA_DIR") or ROOT.parent / "shared" / "realdata")
    / "s3dss-real459-16k"
    / "real_459_full.txt"
)
# x (m) of the sections to draw: clean wall, the intrusion, the data gap, the joint.
PICKS_X_M = (-0.57, 0.62, -0.07, 0.82)


def draw(out: Path) -> Path:
    points = read_points(SCAN, kind="cloud")
    axis = fit_axis(points)
    chain = axis.chainage(points)
    sections = {}
    for w in plan_windows(chain.min(), chain.max(), step_m=0.1, window_m=3.0):
        for start_mm, local, count in iter_section_points(points, axis, w):
            x = float(axis.point_at(start_mm / 1000 + 0.05, 0.0, 0.0)[0])
            m = measure_section(
                local,
                chainage_start_m=start_mm / 1000,
                chainage_end_m=start_mm / 1000 + 0.1,
                nominal_diameter_m=0.8,
                point_count=count,
            )
            sections[x] = (local, m)
    fig, axes = plt.subplots(1, len(PICKS_X_M), figsize=(4 * len(PICKS_X_M), 4.3))
    theta = np.linspace(0, 2 * np.pi, 361)
    for ax, want in zip(axes, PICKS_X_M, strict=True):
        x = min(sections, key=lambda k: abs(k - want))
        local, m = sections[x]
        ax.plot(local[:, 0], local[:, 1], ".", ms=3, color="0.3", label="points")
        ax.plot(0.4 * np.cos(theta), 0.4 * np.sin(theta), ":", color="tab:blue", label="nominal")
        if m.contour_m is not None:
            c = np.vstack((m.contour_m, m.contour_m[:1]))
            ax.plot(
                c[:, 0],
                c[:, 1],
                "-" if m.is_ok else "--",
                color="tab:red",
                lw=0.9,
                label="contour" if m.is_ok else "contour (not trusted)",
            )
        figure = "not measured" if not m.is_ok else f"blockage {100 * m.blockage_ratio:.1f} %"
        ax.set_title(
            f"x = {x:+.2f} m: {m.status.value}\n{figure}, coverage {100 * m.coverage_ratio:.0f} %",
            fontsize=10,
        )
        ax.set_aspect("equal")
        ax.set_xlim(-0.47, 0.47)
        ax.set_ylim(-0.47, 0.47)
        ax.tick_params(labelsize=8)
        ax.set_xlabel("across (m)", fontsize=8)
        ax.set_ylabel("up, the file's +z (m)", fontsize=8)
    axes[0].legend(loc="lower left", fontsize=8)
    fig.suptitle(
        "S3DSS real_459 (800 mm concrete pipe): 0.1 m sections, polar contour", fontsize=11
    )
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "contours-real459.png")
    print(draw(parser.parse_args().out))


if __name__ == "__main__":
    main()
