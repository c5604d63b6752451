"""Options files: method.md's defaults, presets, and one clear error per bad entry."""

import ast
import re
from pathlib import Path

import pytest

import colmap_citymodel
from colmap_citymodel.errors import InputError
from colmap_citymodel.options import RefineOptions


def test_presets_set_method_values():
    generalised = RefineOptions.preset("generalised")
    detailed = RefineOptions.preset("detailed")
    assert generalised.adjustment.sigma_dtp == pytest.approx(0.20)
    assert generalised.assignment.min_points_per_plane == 15
    assert detailed.adjustment.sigma_dtp == pytest.approx(0.05)
    assert detailed.assignment.min_points_per_plane == 5
    with pytest.raises(InputError, match="unknown preset"):
        RefineOptions.preset("fine")


def test_toml_file_overrides_the_preset(tmp_path):
    path = tmp_path / "options.toml"
    path.write_text('[adjustment]\nsigma_dtp = 1\nimage_loss = "cauchy"\n'
                    "[workflow]\nmax_iterations = 3\n")
    options = RefineOptions.from_toml(path, preset="detailed")
    assert options.adjustment.sigma_dtp == 1.0 and isinstance(options.adjustment.sigma_dtp, float)
    assert options.adjustment.image_loss == "cauchy"
    assert options.workflow.max_iterations == 3
    assert options.assignment.min_points_per_plane == 5  # from the preset, untouched


@pytest.mark.parametrize("text, message", [
    ("[adjustment]\nsigma_dpt = 0.1\n", "unknown option adjustment.sigma_dpt"),
    ("[adjustmnet]\nsigma_dtp = 0.1\n", "unknown options section"),
    ('[adjustment]\nsigma_dtp = "big"\n', "must be float"),
    ('[adjustment]\nimage_loss = "tukey"\n', "must be one of none, huber, cauchy"),
    ("[adjustment\n", "not a valid TOML file"),
])
def test_bad_options_file_names_the_file_and_entry(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as error:
        RefineOptions.from_toml(path)
    assert str(path) in str(error.value.path)


def test_missing_options_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        RefineOptions.from_toml(tmp_path / "none.toml")


# -- docstrings: what an option means and why, not which run set it -------------------------

OPTION_MODULES = {
    "options.py": None,  # every dataclass
    "precision/quality.py": ("QualityThresholds",),
}
MAX_DOC_LINES = 6
#: A run's or the development's story: scenario names, figures before -> after, sessions, issues,
#: single runs, the benchmark blocks. The measurements behind defaults live in docs/defaults.md.
STORY = re.compile(r"\bScn\d|\bsession\b|\bissue\b|\b(?:one|a|in one) run\b|\d\s*->\s*[-\d]"
                   r"|\bsimulated\b|\bdemo street\b|\breal drive\b|\bbenchmarks/results\b",
                   re.IGNORECASE)


def field_docstrings(source: str, classes=None):
    """(class, field, lines, text) of every dataclass field (text None without a docstring),
    and (class, None, lines, text) of the class docstrings."""
    out = []
    for node in ast.parse(source).body:
        if not isinstance(node, ast.ClassDef) \
                or not any("dataclass" in ast.unparse(d) for d in node.decorator_list) \
                or (classes is not None and node.name not in classes):
            continue
        docstring = ast.get_docstring(node, clean=False)
        if docstring is not None:
            first = node.body[0]
            out.append((node.name, None, first.end_lineno - first.lineno + 1, docstring))
        for stmt, after in zip(node.body, node.body[1:] + [None]):
            if not isinstance(stmt, ast.AnnAssign):
                continue
            doc = (after if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                   and isinstance(after.value.value, str) else None)
            out.append((node.name, stmt.target.id,
                         doc.end_lineno - doc.lineno + 1 if doc else 0,
                         doc.value.value if doc else None))
    return out


def docstring_problems(source: str, classes=None) -> list[str]:
    problems = []
    for cls, name, lines, text in field_docstrings(source, classes):
        where = f"{cls}.{name}" if name else cls
        if text is None:
            problems.append(f"{where}: no docstring")
            continue
        if lines > MAX_DOC_LINES:
            problems.append(f"{where}: {lines} lines")
        story = STORY.search(" ".join(text.split()))
        if story:
            problems.append(f"{where}: tells a story ({story.group(0)!r})")
    return problems


@pytest.mark.parametrize("module", sorted(OPTION_MODULES))
def test_option_docstrings_say_what_and_why_in_a_few_lines(module):
    path = Path(colmap_citymodel.__file__).parent / module
    source = path.read_text()
    fields = field_docstrings(source, OPTION_MODULES[module])
    # The parser found the fields (the verdict keeps a handful of constants).
    assert len([f for f in fields if f[1]]) >= (10 if OPTION_MODULES[module] is None else 4)
    assert docstring_problems(source, OPTION_MODULES[module]) == []


def test_docstring_check_catches_long_and_story_docstrings():
    source = ('from dataclasses import dataclass\n\n\n@dataclass\nclass X:\n'
              '    """Options."""\n\n'
              '    short: int = 1\n    """One line."""\n'
              '    long: int = 2\n    """' + "\n    ".join(f"line {i}" for i in range(7)) + '"""\n'
              '    story: float = 0.1\n    """Threshold (m); short Scn3: 0.25 -> 0.26 m."""\n'
              '    bare: int = 3\n')
    assert docstring_problems(source) == [
        "X.long: 7 lines", "X.story: tells a story ('Scn3')", "X.bare: no docstring"]
