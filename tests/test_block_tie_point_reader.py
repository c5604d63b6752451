"""TiePointReader: the same ids and coordinates as tie_points, current after every change of
the reconstruction, looked up anew when its points change."""

import numpy as np
import pycolmap

from colmap_citymodel.block.reconstruction import TiePointReader, tie_points


def test_reader_follows_the_adjusted_points(street_scene):
    rec = pycolmap.Reconstruction(street_scene.sfm)
    all_ids = np.asarray(sorted(rec.point3D_ids()), np.int64)
    exclude = set(all_ids[::7].tolist())
    read = TiePointReader(exclude)
    ids, xyz = read(rec)
    expected_ids, expected_xyz = tie_points(rec, exclude)
    np.testing.assert_array_equal(ids, expected_ids)
    np.testing.assert_array_equal(xyz, expected_xyz)
    assert not exclude & set(ids.tolist())

    # Moving the block moves what the reader returns (views of COLMAP's points), and the
    # returned array is a copy that the next move leaves alone.
    move = pycolmap.Sim3d(1.5, pycolmap.Rotation3d(np.array([0.0, 0.0, 0.1, 0.995])),
                          np.array([10.0, -4.0, 2.0]))
    rec.transform(move)
    ids_after, moved = read(rec)
    np.testing.assert_array_equal(ids_after, ids)
    matrix = np.asarray(move.matrix())
    np.testing.assert_allclose(moved, xyz @ matrix[:, :3].T + matrix[:, 3], atol=1e-9)
    np.testing.assert_array_equal(moved, tie_points(rec, exclude)[1])

    # A deleted point: looked up anew, never a stale view.
    gone = int(ids[3])
    rec.delete_point3D(gone)
    ids_deleted, xyz_deleted = read(rec)
    assert gone not in set(ids_deleted.tolist())
    np.testing.assert_array_equal(xyz_deleted, tie_points(rec, exclude)[1])

    # Another reconstruction (a copy) is read from itself.
    other = pycolmap.Reconstruction(rec)
    other.transform(move)
    np.testing.assert_array_equal(read(other)[1], tie_points(other, exclude)[1])


def test_reader_of_a_subset_skips_missing_points(street_scene):
    rec = pycolmap.Reconstruction(street_scene.sfm)
    all_ids = np.asarray(sorted(rec.point3D_ids()), np.int64)
    wanted = np.array([all_ids[5], 10 ** 9, all_ids[2]], np.int64)  # order kept, one unknown
    ids, xyz = TiePointReader(ids=wanted)(rec)
    np.testing.assert_array_equal(ids, [all_ids[5], all_ids[2]])
    np.testing.assert_array_equal(xyz, [rec.point3D(int(all_ids[5])).xyz,
                                        rec.point3D(int(all_ids[2])).xyz])
