"""Options files: method.md's defaults, presets, and one clear error per bad entry."""

import pytest

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
