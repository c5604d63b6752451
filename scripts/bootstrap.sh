#!/usr/bin/env bash
# Idempotent set-up on a Debian machine (run from anywhere; as root, or with sudo):
#  1. Debian packages for the C++ extension and Open3D, installed only when missing;
#  2. .venv with Python >= 3.11 (set PYTHON=/path/to/python3.x to choose the interpreter);
#  3. this package installed editable with its test and docs extras (pytest, pytest-xdist,
#     mkdocs), and `build` for scripts/check_wheel.sh. Skipped when pyproject.toml and
#     cpp_ext/ are unchanged since the last successful install and the extension loads.
set -euo pipefail
cd "$(dirname "$0")/.."

# libusb-1.0-0, libegl1, libgl1, libx11-6: what the open3d-cpu wheel links against.
# python3-dev: the headers the extension's build needs for Debian's own python3.
# proj-data: the worldwide EGM96 geoid (egm96_15.gtx) for GNSS heights where the national
# geoid grid of the city model's height system is missing.
APT_PACKAGES=(libceres-dev libeigen3-dev libgoogle-glog-dev libusb-1.0-0 libegl1 libgl1 libx11-6
  g++ cmake python3-venv python3-dev proj-data)

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$pkg")
  fi
done
if ((${#missing[@]})); then
  if [ "$(id -u)" -eq 0 ]; then
    SUDO=()
  elif command -v sudo >/dev/null 2>&1; then
    SUDO=(sudo)
  else
    echo "error: missing Debian packages (${missing[*]}) and not root; install them with" \
      "apt-get install ${missing[*]}" >&2
    exit 1
  fi
  echo "bootstrap: installing ${missing[*]}"
  "${SUDO[@]}" apt-get update
  "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
    "${missing[@]}"
fi

python_ok() { "$1" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; }

if [ ! -x .venv/bin/python ]; then
  PY="${PYTHON:-}"
  if [ -z "$PY" ]; then
    for candidate in python3 python3.13 python3.12 python3.11; do
      if command -v "$candidate" >/dev/null 2>&1 && python_ok "$candidate"; then
        PY="$candidate"
        break
      fi
    done
  fi
  if [ -z "$PY" ] || ! python_ok "$PY"; then
    echo "error: no Python >= 3.11 found (set PYTHON=/path/to/python3.11 or newer)" >&2
    exit 1
  fi
  echo "bootstrap: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
if ! python_ok .venv/bin/python; then
  echo "error: .venv/bin/python is older than 3.11; remove .venv and run again" >&2
  exit 1
fi

# Everything that changes the installed package or the compiled extension.
stamp_file=.venv/.colmap_citymodel-install-stamp
stamp="$(cat pyproject.toml cpp_ext/CMakeLists.txt $(find cpp_ext/include cpp_ext/src -type f | sort) \
  | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp_file" ] && [ "$(cat "$stamp_file")" = "$stamp" ] \
  && .venv/bin/python -c "from colmap_citymodel._ext import load_core; load_core()" >/dev/null 2>&1; then
  echo "bootstrap: .venv is up to date"
  exit 0
fi

echo "bootstrap: installing colmap-citymodel into .venv (builds the C++ extension)"
# Build requirements in the venv itself (pinned pybind11 3.0.x: shared internals with
# pycolmap/pyceres; ninja, which a bare Debian lacks as it lacks make), then build without
# isolation so the in-place CMake cache stays valid; `build` makes the sdist and wheel that
# scripts/check_wheel.sh installs.
.venv/bin/python -m pip install "scikit-build-core>=0.10" "pybind11>=3.0,<3.1" ninja build
.venv/bin/python -m pip install --no-build-isolation -e ".[test,docs]"
.venv/bin/python -c "from colmap_citymodel._ext import load_core; load_core()"
echo "$stamp" > "$stamp_file"
echo "bootstrap: done"
