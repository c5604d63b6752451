"""Finding a batch's workspaces on disk: nested directories, list files, the model COLMAP
registered most images in, and the GNSS source of each."""

from __future__ import annotations

import sqlite3
import struct
from pathlib import Path

import pytest

from colmap_citymodel.batch.workspaces import find_workspaces, pose_prior_count
from colmap_citymodel.errors import InputError


def make_model(directory: Path, num_images: int) -> None:
    directory.mkdir(parents=True)
    (directory / "cameras.bin").write_bytes(struct.pack("<Q", 1))
    (directory / "images.bin").write_bytes(struct.pack("<Q", num_images))


def make_database(path: Path, priors: int) -> None:
    connection = sqlite3.connect(path)
    connection.execute("CREATE TABLE pose_priors (pose_prior_id INTEGER, position BLOB)")
    connection.executemany("INSERT INTO pose_priors VALUES (?, ?)",
                           [(k, b"\0" * 24) for k in range(priors)] + [(99, None)])
    connection.commit()
    connection.close()


@pytest.fixture
def tree(tmp_path):
    root = tmp_path / "flights"
    make_model(root / "city" / "a" / "sparse" / "0", 20)
    make_database(root / "city" / "a" / "database.db", 20)
    # COLMAP split this block: sparse/1 holds more images than sparse/0
    make_model(root / "city" / "b" / "sparse" / "0", 5)
    make_model(root / "city" / "b" / "sparse" / "1", 30)
    make_database(root / "city" / "b" / "database.db", 0)  # no pose priors: gnss.txt is used
    (root / "city" / "b" / "gnss.txt").write_text("x.jpg 1 2 3\n")
    make_model(root / "c" / "sparse" / "0", 12)
    (root / "c" / "images").mkdir()
    make_model(root / "d" / "sparse", 3)  # the model directly in sparse/, and no GNSS
    make_model(root / ".trash" / "e" / "sparse" / "0", 9)  # hidden: not searched
    (root / "notes").mkdir()
    return root


def test_search_finds_nested_workspaces_and_their_inputs(tree):
    found = {ws.name: ws for ws in find_workspaces(tree)}
    assert sorted(found) == ["c", "city/a", "city/b", "d"]
    a, b, c, d = found["city/a"], found["city/b"], found["c"], found["d"]
    assert a.model == tree / "city" / "a" / "sparse" / "0" and a.gnss_source == "database"
    assert b.model.name == "1" and b.gnss_source == "gnss.txt"
    assert c.gnss_source == "exif" and c.exif == tree / "c" / "images"
    assert d.model == tree / "d" / "sparse" and d.gnss_source is None
    assert "no GNSS" in d.problem and a.problem is b.problem is c.problem is None
    assert pose_prior_count(tree / "city" / "a" / "database.db") == 20  # NULL position left out


def test_a_list_file_names_workspaces(tree, tmp_path):
    listing = tmp_path / "list.txt"
    listing.write_text(f"# two of them\nflights/city/b\n\n{tree / 'c'}  # absolute\n"
                       "flights/city/b\nflights/notes\n")
    found = find_workspaces(listing)
    assert [ws.name for ws in found] == ["city/b", "c", "notes"]  # duplicates once
    assert found[2].problem.startswith("no COLMAP model")
    # a single workspace is named after its directory
    (only,) = find_workspaces(tree / "city" / "a")
    assert only.name == "a"


def test_nothing_to_refine_is_an_error(tmp_path):
    with pytest.raises(InputError, match="no COLMAP workspace"):
        find_workspaces(tmp_path)
    with pytest.raises(InputError, match="no such workspace"):
        find_workspaces(tmp_path / "missing")
    listing = tmp_path / "list.txt"
    listing.write_text("missing_workspace\n")
    (ws,) = find_workspaces(listing)
    assert "no such directory" in ws.problem
