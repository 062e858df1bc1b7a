#!/usr/bin/env bash
# Set up pipescan on a fresh Debian/Ubuntu machine: system libraries, a virtualenv in .venv,
# and the package with its test tools. Safe to run again: it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

# open3d needs libusb; WeasyPrint subsets fonts with HarfBuzz; poppler-utils renders report PDFs
# to PNG (tests, docs); postgresql runs the storage tests against a real server; chromium runs
# the web view's browser tests (driven by Playwright, which downloads no browser of its own).
debs=(libusb-1.0-0 libharfbuzz-subset0 poppler-utils postgresql chromium)
missing=()
for pkg in "${debs[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
    echo "bootstrap: installing Debian packages: ${missing[*]}"
    sudo_cmd=()
    [[ $(id -u) -ne 0 ]] && sudo_cmd=(sudo)
    "${sudo_cmd[@]}" apt-get update -qq
    DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

python=${PYTHON:-python3}
if [[ ! -x .venv/bin/python ]]; then
    echo "bootstrap: creating .venv with $($python --version)"
    "$python" -m venv .venv
fi
echo "bootstrap: installing pipescan and its test tools into .venv"
.venv/bin/python -m pip install -q --upgrade pip
# setuptools says "Editable installation" as a warning on every editable install: information
# only (pypa/packaging-problems#558), so it is filtered out here.
PYTHONWARNINGS="ignore:Editable installation" .venv/bin/python -m pip install -q -e '.[test]'
echo "bootstrap: ready"
