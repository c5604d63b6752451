"""Damaged copies of every input the CLI reads end with exit 0 or 2 and one clean message naming
the file, never a traceback, a crash or a hang (the harness is fuzz_inputs.py).

The normal suite runs a small seeded set; `pytest -m fuzz` runs 10,000 cases and prints the
seed, the count, the wall time and the outcomes (FUZZ_SEED and FUZZ_CASES override the seed and
the count; FUZZ_KEEP names a directory that receives the damaged inputs of failing cases).
"""

from __future__ import annotations

import os
import random
from pathlib import Path

import pytest
from fuzz_inputs import (
    KINDS,
    Case,
    Runner,
    _selftest_worker,
    build_corpus,
    classify,
    damage,
    make_case,
    run_fuzz,
)

QUICK_SEED = 20240917
QUICK_CASES = 800


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    return build_corpus(tmp_path_factory.mktemp("fuzz_corpus"))


@pytest.fixture(scope="module")
def runner():
    with Runner() as r:
        yield r


def test_damage_is_seeded():
    data = b"<gml:posList>691000.125 5335000.5 12.0 691001.0 5335000.5 12.0</gml:posList>\n" * 20
    first = damage(data, random.Random("7:3"))
    assert first == damage(data, random.Random("7:3"))
    assert first[0] != data
    assert len({damage(data, random.Random(f"7:{i}"))[0] for i in range(20)}) > 15


def _case(names=("/x/file.gml",)) -> Case:
    return Case(0, "citygml", [], [], list(names), "test")


def test_classify_accepts_only_clean_endings():
    ok = {"status": 2, "stderr": "error: /x/file.gml: malformed XML\n", "seconds": 0.1}
    assert classify(_case(), ok) == ("exit 2", None)
    assert classify(_case(), {"status": 0, "stderr": "", "seconds": 0.1}) == ("exit 0", None)
    bad = [
        {"status": None, "stderr": "", "traceback": "Traceback ...\nValueError: x\n"},
        {"status": 2, "stderr": "error: /x/file.gml: a\nmore\n"},
        {"status": 2, "stderr": "error: /y/other.gml: malformed XML\n"},
        {"status": 1, "stderr": "error: /x/file.gml: x\n"},
        {"status": 0, "stderr": "", "shown_warnings": ["RuntimeWarning: overflow"]},
        {"status": "hang", "seconds": 10.0},
        {"status": "crash", "exitcode": -11, "seconds": 0.5},
    ]
    for result in bad:
        outcome, problem = classify(_case(), {"seconds": 0.0, **result})
        assert problem, result


def test_runner_reports_hangs_and_crashes():
    with Runner(timeout=2.0, target=_selftest_worker) as runner:
        assert runner.run(["ok"])["status"] == 0
        assert runner.run(["hang"])["status"] == "hang"
        assert runner.run(["ok"])["status"] == 0  # a new worker after the hang
        assert runner.run(["crash"])["status"] == "crash"
        assert runner.run(["ok"])["status"] == 0
        assert runner.restarts == 2


@pytest.mark.parametrize("kind", [k for k, _ in KINDS])
def test_undamaged_inputs_are_read(corpus, runner, tmp_path, kind):
    """Every kind of case reaches the end when nothing is damaged, so damage is what fails."""
    for index in range(4):
        case = make_case(corpus, QUICK_SEED, index, tmp_path, kind=kind, undamaged=True)
        result = runner.run(case.argv)
        outcome, problem = classify(case, result)
        assert problem is None and outcome in ("exit 0", "inputs read"), (case.argv, result)


def test_fuzz_quick(corpus, runner, tmp_path):
    report = run_fuzz(corpus, QUICK_SEED, QUICK_CASES, tmp_path / "cases", runner=runner)
    print(report.summary())
    assert not report.problems, report.summary()
    assert report.cases == QUICK_CASES
    assert set(report.by_kind) >= {k for k, _ in KINDS}
    # the damage is not all fatal, nor all harmless
    assert report.outcomes["exit 2"] > QUICK_CASES // 2
    assert report.outcomes["exit 0"] + report.outcomes["inputs read"] > QUICK_CASES // 20


@pytest.mark.fuzz
def test_fuzz_full(corpus, tmp_path):
    seed = int(os.environ.get("FUZZ_SEED", "20250101"))
    count = int(os.environ.get("FUZZ_CASES", "10000"))
    keep = Path(os.environ["FUZZ_KEEP"]) if os.environ.get("FUZZ_KEEP") else tmp_path / "failures"
    keep.mkdir(parents=True, exist_ok=True)
    report = run_fuzz(corpus, seed, count, tmp_path / "cases", keep_failures=keep, progress=print)
    print(report.summary())
    assert report.cases == count
    assert not report.problems, report.summary() + f"\ndamaged inputs of the failures: {keep}"
