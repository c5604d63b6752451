#!/usr/bin/env bash
# Check the package as a user installs it, not as the editable checkout imports it:
#  1. `python -m build`: the sdist, then the wheel built from that sdist (the C++ extension
#     compiles in an isolated build environment with the build requirements from PyPI);
#  2. the wheel installed into a fresh temporary venv (pycolmap, open3d, ... from PyPI);
#  3. from a directory outside the checkout, so that nothing imports the source tree:
#     `colmap-citymodel refine --help` and `colmap-citymodel demo --output_path <tmp>`.
# Exits non-zero when any step fails. KEEP_WHEEL_CHECK=1 keeps the temporary directory.
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$(pwd)"
bash scripts/bootstrap.sh

tmp="$(mktemp -d -t colmap-citymodel-wheel.XXXXXX)"
cleanup() {
  if [ "${KEEP_WHEEL_CHECK:-0}" = 1 ]; then
    echo "check_wheel: kept $tmp"
  else
    rm -rf "$tmp"
  fi
}
trap cleanup EXIT
start=$SECONDS

echo "check_wheel: building the sdist and, from it, the wheel"
.venv/bin/python -m build --outdir "$tmp/dist" "$repo" >"$tmp/build.log" 2>&1 || {
  tail -n 40 "$tmp/build.log" >&2
  echo "error: python -m build failed (log above)" >&2
  exit 1
}
sdist=("$tmp"/dist/*.tar.gz)
wheel=("$tmp"/dist/*.whl)
if [ ! -f "${sdist[0]}" ] || [ ! -f "${wheel[0]}" ]; then
  echo "error: python -m build wrote no sdist or no wheel into $tmp/dist" >&2
  exit 1
fi
echo "check_wheel: $(basename "${sdist[0]}") and $(basename "${wheel[0]}")" \
  "($((SECONDS - start)) s)"

echo "check_wheel: installing the wheel into a fresh venv"
.venv/bin/python -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install --quiet "${wheel[0]}" >"$tmp/install.log" 2>&1 || {
  tail -n 40 "$tmp/install.log" >&2
  echo "error: installing ${wheel[0]} failed (log above)" >&2
  exit 1
}

# Outside the checkout: the installed package, not the source tree, answers the import.
mkdir -p "$tmp/run"
cd "$tmp/run"
cli="$tmp/venv/bin/colmap-citymodel"
location="$("$tmp/venv/bin/python" -c 'import colmap_citymodel; print(colmap_citymodel.__file__)')"
case "$location" in
  "$tmp/venv/"*) ;;
  *) echo "error: colmap_citymodel imported from $location, not from the wheel" >&2; exit 1 ;;
esac

echo "check_wheel: colmap-citymodel refine --help"
"$cli" refine --help >"$tmp/help.txt" || { echo "error: refine --help failed" >&2; exit 1; }
grep -q -- "--citymodel" "$tmp/help.txt" || {
  echo "error: refine --help does not list --citymodel" >&2
  exit 1
}

echo "check_wheel: colmap-citymodel demo --output_path $tmp/demo"
"$cli" demo --output_path "$tmp/demo" || { echo "error: the demo failed from the wheel" >&2; exit 1; }

echo "check_wheel: passed in $((SECONDS - start)) s"
