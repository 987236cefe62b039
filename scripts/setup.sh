#!/usr/bin/env bash
# Set up forestreg on a fresh Debian machine with Python 3.11 (idempotent; run from anywhere):
# the system libraries open3d, Qt and the GUI tests need, a virtual environment in .venv, and the
# package with its GUI, test and docs extras; where apt has them, the real plugin hosts (QGIS's
# Python bindings, CloudCompare) for the plugin tests.
set -euo pipefail
cd "$(dirname "$0")/.."

system_packages=(
  libusb-1.0-0 libgl1 libegl1 libgl1-mesa-dri libgomp1     # open3d, VTK (pyvista; Mesa renders offscreen)
  libglib2.0-0 libdbus-1-3 libfontconfig1 libxkbcommon-x11-0 # Qt
  libxcb-cursor0 libxcb-icccm4 libxcb-image0 libxcb-keysyms1 libxcb-randr0
  libxcb-render-util0 libxcb-shape0 libxcb-xinerama0
  xvfb xauth                                                 # GUI tests under a virtual X server
)
missing=()
for p in "${system_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  sudo_cmd=""
  [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  echo "setup: installing system packages: ${missing[*]}" >&2
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# The real plugin hosts, for tests/test_plugin.py and tests/test_qgis_real.py: Debian's QGIS Python
# bindings (the QGIS provider runs headless in /usr/bin/python3), QGIS itself for its qgis_process
# (the algorithms and the model run headless; package qgis) and CloudCompare (run under xvfb-run,
# installed above). Where apt has no such package (another distribution or release) the tests that
# need it are skipped; this says so and goes on.
host_packages=(python3-qgis qgis cloudcompare)
host_missing=()
for p in "${host_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || host_missing+=("$p")
done
if [ ${#host_missing[@]} -gt 0 ]; then
  if command -v apt-get >/dev/null 2>&1; then
    sudo_cmd=""
    [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq || true
    available=()
    for p in "${host_missing[@]}"; do
      if apt-cache policy "$p" 2>/dev/null | grep -q "Candidate: [0-9]"; then
        available+=("$p")
      else
        echo "setup: $p is not available from apt here: its plugin tests will be skipped" >&2
      fi
    done
    if [ ${#available[@]} -gt 0 ]; then
      echo "setup: installing the plugin hosts: ${available[*]}" >&2
      DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${available[@]}" >/dev/null \
        || echo "setup: installing ${available[*]} failed: the plugin tests that need them will be skipped" >&2
    fi
  else
    echo "setup: no apt-get here: ${host_missing[*]} not installed, their plugin tests will be skipped" >&2
  fi
fi

python=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($python --version)" >&2
  $python -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
# the newest versions the requirements allow, every time (--upgrade-strategy eager also moves the
# dependencies of dependencies): the tests run against what a new user installs today
.venv/bin/python -m pip install -q --upgrade --upgrade-strategy eager -e ".[gui,test,docs]"
# the package's modules compiled to bytecode now, as pip does when it installs a package: an editable
# install leaves that to the first import, and where PYTHONDONTWRITEBYTECODE is set (CI machines,
# containers) no import ever writes it, so every command compiled each of its modules anew (~0.07 s)
.venv/bin/python -m compileall -q -j 0 __init__.py client.py app cli engine plugin service ui >/dev/null
# the numerical kernels compiled now, into the per-version cache (~45 s on 2 cores, once): otherwise
# the first command after an install compiles those it needs
.venv/bin/forestreg warmup
.venv/bin/python -m pip list --format=freeze 2>/dev/null | grep -iE '^(numpy|scipy|open3d|hdbscan|scikit-learn|laspy|pyproj|matplotlib)==' | tr '\n' ' ' | sed 's/^/setup: versions: /' >&2 || true
echo >&2
echo "setup: ready (.venv/bin/forestreg)" >&2
