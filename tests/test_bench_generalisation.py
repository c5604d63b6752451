"""The generalisation benchmark's blocks: drawn deterministically, split by a hash of each
block's seed about half and half, both splits with the same mix."""

import json
import sys
from collections import Counter
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import generalisation_blocks as gb  # noqa: E402


@pytest.fixture(scope="module")
def drawn():
    return gb.draw_blocks(200, 1)


def test_drawing_is_deterministic_and_a_prefix(drawn):
    again = gb.draw_blocks(200, 1)
    assert json.dumps(drawn, sort_keys=True) == json.dumps(again, sort_keys=True)
    # a shorter run's blocks are the first of each split of a longer one's
    quick = gb.draw_blocks(20, 1)
    for split in gb.SPLITS:
        mine = [b for b in drawn if b["split"] == split][:10]
        assert [b for b in quick if b["split"] == split] == mine
    other = gb.draw_blocks(20, 2)
    assert {b["sim_seed"] for b in other}.isdisjoint({b["sim_seed"] for b in quick})


def test_split_by_the_seeds_hash_about_half(drawn):
    assert Counter(b["split"] for b in drawn) == {"dev": 100, "held_out": 100}
    assert all(gb.split_of(b["sim_seed"]) == b["split"] for b in drawn)
    # the hash splits the candidates about half and half: few are passed over
    assert max(b["index"] for b in drawn) < 240
    assert len({b["name"] for b in drawn}) == 200


def test_both_splits_hold_the_same_mix(drawn):
    for split in gb.SPLITS:
        mine = [b for b in drawn if b["split"] == split]
        families = Counter(b["family"] for b in mine)
        assert set(families) == set(gb.FAMILIES) and min(families.values()) >= 13
        cities = Counter(b["city"] for b in mine)
        assert len(cities) >= 8 and {b["format"] for b in mine} >= {"CityGML", "CityJSON"}
        assert set(Counter(b["gnss_model"] for b in mine)) == set(gb.GNSS_MODELS)
        assert Counter(b["model"] for b in mine) == {m: 25 for m in gb.MODEL_LEVELS}
        assert sum(b["terrain"] for b in mine) == 50
        wrong = [b for b in mine if b["wrong_model"]]
        assert len(wrong) >= 15 and all(b["gnss_model"] != "none" for b in wrong)
        assert {b["wrong"]["kind"] for b in wrong} == {"shifted", "rotated", "neighbour"}
        for b in mine:
            assert b["family"] in gb.TILES[b["tile"]].families
            if b["gnss_model"] == "none":
                assert gb.HINT_RANGE[0] <= b["hint"]["distance_m"] <= gb.HINT_RANGE[1]
            frames = b["toml"]["flight"]["num_key_frames"]
            assert (20 <= frames <= 40) if b["family"] == "video" else (30 <= frames <= 80)
