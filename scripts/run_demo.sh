#!/usr/bin/env bash
# Set up (scripts/bootstrap.sh), then run the built-in demo end to end into ./demo_output.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
.venv/bin/colmap-citymodel demo --output_path demo_output "$@"
