#!/usr/bin/env bash
# Set up (scripts/bootstrap.sh), then run the test suite: every test not marked `slow`, plus
# slow tests also marked `ci`, but not the `fuzz` run of 10,000 damaged inputs (pytest -m fuzz).
# Extra arguments go to pytest. "No tests collected" is a failure.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
status=0
.venv/bin/pytest -m "(not slow or ci) and not fuzz" "$@" || status=$?
if [ "$status" -eq 5 ]; then
  echo "error: pytest collected no tests" >&2
  exit 1
fi
exit "$status"
