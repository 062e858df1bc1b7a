"""Build the documentation's figures: a sample condition report, one page of it as PNG, and
measured contours of the real scan.

    python docs/build.py            # writes docs/img/sample-report.pdf, report-page-1.png and
                                    # contours-real459.png
    python docs/build.py --page 3   # another page as the PNG (still report-page-1.png's name
                                    # is kept for page 1; other pages get their own number)

The report is rendered from synthetic data with known defects (pipescan.reports.sample: a
60 m DN 500 pipe with a deformation, an obstacle and settled deposits, two stretches not
measured, and two earlier inspections for the trend page). The PNGs are build products: they
are ignored by git (.gitignore: docs/img/*.png) and the README refers to them as made here.
Needs poppler's ``pdftoppm`` on the PATH.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

DOCS = Path(__file__).resolve().parent


def main() -> int:
    parser = argparse.ArgumentParser(description="Render the sample report and its page PNGs.")
    parser.add_argument("--page", type=int, action="append", help="page(s) to write as PNG")
    parser.add_argument("--dpi", type=int, default=110, help="PNG resolution")
    parser.add_argument("--out", type=Path, default=DOCS / "img", help="output folder")
    args = parser.parse_args()
    pages = args.page or [1]

    from pipescan.reports.render import render_pdf
    from pipescan.reports.sample import sample_input

    pdftoppm = shutil.which("pdftoppm")
    if pdftoppm is None:
        print("error: pdftoppm not found (install poppler-utils)", file=sys.stderr)
        return 2
    img = args.out
    img.mkdir(parents=True, exist_ok=True)
    pdf = render_pdf(sample_input(60.0), img / "sample-report.pdf")
    for page in pages:
        stem = img / f"report-page-{page}"
        subprocess.run(
            [pdftoppm, "-png", "-r", str(args.dpi), "-f", str(page), "-l", str(page),
             "-singlefile", str(pdf), str(stem)],
            check=True,
        )  # fmt: skip
        print(f"wrote {stem.with_suffix('.png')}")
    print(f"wrote {pdf}")
    sys.path.insert(0, str(DOCS))
    from contours import SCAN, draw

    if SCAN.exists():
        print(f"wrote {draw(img / 'contours-real459.png')}")
    else:
        print(f"skipped the contour figure: {SCAN} is not there")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
