#!/usr/bin/env bash
# Set up (scripts/bootstrap.sh), then run the test suite: every test not marked `slow`, plus
# slow tests also marked `ci`, but not the `fuzz` run of 10,000 damaged inputs (pytest -m fuzz),
# spread over one worker per core (pytest-xdist `-n auto`; the tests share nothing but the
# simulated-workspace cache, whose builds appear by one rename). Extra arguments go to pytest
# (`-n 0` runs them in this process). "No tests collected" is a failure. Then build the
# documentation site with `mkdocs build --strict` (a broken link, page or CLI reference fails
# the run).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
status=0
.venv/bin/pytest -n auto -m "(not slow or ci) and not fuzz" "$@" || status=$?
if [ "$status" -eq 5 ]; then
  echo "error: pytest collected no tests" >&2
  exit 1
fi
echo "run_tests: mkdocs build --strict"
docs_status=0
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict || docs_status=$?
if [ "$docs_status" -ne 0 ]; then
  echo "error: the documentation does not build (mkdocs build --strict)" >&2
  [ "$status" -ne 0 ] || status=$docs_status
fi
exit "$status"
