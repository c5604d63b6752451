"""What the planes say about the datum must hold against what the model's errors do: a face's
tie points share its offset and its tilt, so many points on a few faces fix the block's
rotations only as well as those faces' orientations are known."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from colmap_citymodel.adjust.observability import face_tilts, observability
from colmap_citymodel.align.initial_alignment import similarity_to_planes
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.citymodel.read import read_city_model
from data_paths import CITYGML

GENERALISATION = 0.2
BERLIN = CITYGML / "berlin" / "3910_5819.gml"


def street_store():
    """Two rows of four 25 m houses (walls 15 m high, flat roofs) along x, closed at both ends
    by lower walls."""
    return store_from_polygons(street_rings(), origin=np.zeros(3))


def street_rings():
    """The rings of `street_store`."""
    rings = []
    for x0 in (-50.0, -25.0, 0.0, 25.0):
        x1 = x0 + 25.0
        rings.append([(x0, 10, 0), (x0, 10, 15), (x1, 10, 15), (x1, 10, 0)])
        rings.append([(x1, -10, 0), (x1, -10, 15), (x0, -10, 15), (x0, -10, 0)])
        rings.append([(x0, 10, 15), (x0, 20, 15), (x1, 20, 15), (x1, 10, 15)])
        rings.append([(x0, -20, 15), (x0, -10, 15), (x1, -10, 15), (x1, -20, 15)])
    rings.append([(-50, -10, 0), (-50, 10, 0), (-50, 10, 8), (-50, -10, 8)])
    rings.append([(75, 10, 0), (75, -10, 0), (75, -10, 8), (75, 10, 8)])
    return [np.array(r, float) for r in rings]


def tie_points_on(store, per_face, rng):
    points, faces = [], []
    for face in range(store.num_faces):
        corners = store.vertices[store.face_vertex_ids(face)]
        points.append(rng.uniform(corners.min(0), corners.max(0), (per_face, 3)))
        faces.append(np.full(per_face, face))
    return np.vstack(points), np.concatenate(faces)


def test_a_face_tilts_by_its_vertex_error_over_its_extent():
    """A 25 x 15 m wall whose four corners are each off by g: tilts of g / 25 and g / 15 rad
    about its two in-plane axes."""
    store = street_store()
    tilt = face_tilts(store, [0], GENERALISATION)[0]
    sigmas = np.sort(np.sqrt(np.linalg.eigvalsh(tilt.covariance)))
    assert sigmas == pytest.approx([GENERALISATION / 25, GENERALISATION / 15], rel=1e-6)
    assert np.abs(tilt.axes @ store.normals[0]).max() < 1e-9  # axes lie in the face
    assert tilt.centroid == pytest.approx([-37.5, 10.0, 7.5])


def test_rotation_sigmas_cover_what_tilted_faces_do_to_the_block():
    """Tie points exactly on a street's true planes, fitted (7 parameters, every point alike,
    as the adjustment weighs them) onto model planes with random offsets (g) and tilts (from
    their vertices off by g): the spread of the fitted rotations over many such models is what
    the stated sigmas must describe. With the tilts they do (the least-squares fit is a little
    less precise than the bound); with offsets alone they are 3.5-5x too small."""
    store = street_store()
    rng = np.random.default_rng(3)
    points, faces = tie_points_on(store, 200, rng)
    normals = store.normals[faces]
    tilts = face_tilts(store, faces, GENERALISATION)
    with_tilts = observability(points, normals, faces, None, None, 0.2, GENERALISATION,
                               tilts=tilts)
    offsets_only = observability(points, normals, faces, None, None, 0.2, GENERALISATION)

    rotations = []
    for _ in range(150):
        model_normals = np.empty((store.num_faces, 3))
        model_offsets = np.empty(store.num_faces)
        for face, tilt in tilts.items():
            normal = store.normals[face] + rng.multivariate_normal(np.zeros(2),
                                                                   tilt.covariance) @ tilt.axes
            normal /= np.linalg.norm(normal)
            model_normals[face] = normal
            model_offsets[face] = -normal @ (tilt.centroid + rng.normal(0, GENERALISATION)
                                             * store.normals[face])
        fit = similarity_to_planes(points, model_normals[faces], model_offsets[faces], 0.2,
                                   loss_scale=1e6)
        rotations.append(Rotation.from_matrix(fit.sim3.rotation.matrix()).as_rotvec())
    spread = np.degrees(np.std(rotations, axis=0))
    for axis, name in enumerate(("rotation_E", "rotation_N", "rotation_U")):
        stated = with_tilts[name]["sigma_planes"]
        assert 0.8 < spread[axis] / stated < 1.6, (name, spread[axis], stated)
        assert spread[axis] / offsets_only[name]["sigma_planes"] > 3.0
    # The positions hardly depend on the tilts: the offsets fix them.
    for name in ("E", "N", "U"):
        assert with_tilts[name]["sigma_planes"] == pytest.approx(
            offsets_only[name]["sigma_planes"], rel=0.05)


def test_the_walls_of_a_real_tile_tilt_by_the_generalisation_over_their_length():
    """Berlin's official LoD2 tile (867 walls): every face gets a finite tilt about in-plane
    axes; a wall's azimuth (its tilt about the vertical) is uncertain by about g over its
    length, so long facades are known to tenths of a degree and short segments by degrees."""
    store = read_city_model(BERLIN)
    faces = np.arange(store.num_faces)
    tilts = face_tilts(store, faces, GENERALISATION)
    assert set(tilts) == set(faces.tolist())
    ratios, sigmas, lengths = [], [], []
    for face, tilt in tilts.items():
        assert np.all(np.isfinite(tilt.covariance))
        assert np.abs(tilt.axes @ store.normals[face]).max() < 1e-6
        normal = store.normals[face]
        if abs(normal[2]) > 0.05:
            continue  # not a wall
        vertical = np.array([0.0, 0.0, 1.0])
        # The azimuth tilt turns the wall about the vertical: its lever runs along the wall.
        along = np.cross(vertical, normal)
        along /= np.linalg.norm(along)
        in_plane = tilt.axes @ along
        azimuth_sigma = float(np.sqrt(in_plane @ tilt.covariance @ in_plane))
        corners = store.vertices[store.face_vertex_ids(face)]
        length = np.ptp(corners @ along)
        ratios.append(azimuth_sigma * length / GENERALISATION)
        sigmas.append(np.degrees(azimuth_sigma))
        lengths.append(length)
    assert len(ratios) > 800
    # g / L for a rectangle (most walls), sqrt(2) g / L for a gable triangle.
    assert np.median(ratios) == pytest.approx(1.0, abs=0.1)
    assert np.percentile(ratios, 95) < 1.5
    lengths = np.array(lengths)
    sigmas = np.array(sigmas)
    # Median wall 6 m: 2.1 deg; facades over 20 m to 0.2-0.75 deg, short segments by degrees.
    assert np.all(sigmas[lengths > 20.0] < 0.9)
    assert np.all(sigmas[lengths < 2.0] > 5.0)


def test_a_gnss_bias_common_to_the_block_does_not_average_out():
    """Where GNSS alone fixes a direction, its datum sigma is sqrt(sigma^2 / n + b^2) with a
    bias b common to all positions (plus what the block's scale and tilts add at its images),
    not sigma / sqrt(n); where planes fix it, the bias hardly
    matters; `sigma_gnss` (refined against GNSS-only, which share the bias) stays without it."""
    from colmap_citymodel.adjust.observability import observability

    rng = np.random.default_rng(4)
    # Facades facing +-y only: they fix N, nothing fixes E or U but GNSS.
    left = np.column_stack([rng.uniform(-50, 50, 400), np.full(400, 10.0),
                            rng.uniform(0, 15, 400)])
    points = np.vstack([left, left * [1, -1, 1]])
    normals = np.repeat([[0, 1.0, 0], [0, -1.0, 0]], 400, axis=0)
    groups = np.repeat([0, 1], 400)
    cams = np.column_stack([np.linspace(-50, 50, 40), np.zeros(40), np.full(40, 2.0)])
    sigmas = np.tile([3.0, 3.0, 5.0], (40, 1))
    bias = np.array([1.5, 1.5, 2.5])
    plain = observability(points, normals, groups, cams, sigmas, 0.2, 0.2)
    biased = observability(points, normals, groups, cams, sigmas, 0.2, 0.2,
                           gnss_bias_sigmas=bias)
    for axis, k in (("E", 0), ("U", 2)):
        # The images' centres: the line's scale (E) and its tilt (U) about its middle, which
        # GNSS fixes as well as its mean, move them by as much again (sigma^2 / n).
        expected = np.sqrt(2 * sigmas[0, k] ** 2 / 40 + bias[k] ** 2)
        assert biased[axis]["sigma_gnss_with_bias"] == pytest.approx(expected, rel=1e-6)
        assert biased[axis]["sigma"] == pytest.approx(expected, rel=0.05)
        # Without the bias: the mean's sigma / sqrt(n) and the scale and tilt, which the
        # facades' distance helps fix (E).
        assert (sigmas[0, k] / np.sqrt(40) < plain[axis]["sigma"]
                <= sigmas[0, k] * np.sqrt(2 / 40) * 1.01)
        assert biased[axis]["sigma_gnss"] == pytest.approx(plain[axis]["sigma_gnss"])
        assert biased[axis]["source"] == plain[axis]["source"] == "gnss"
    assert biased["N"]["sigma"] == pytest.approx(plain["N"]["sigma"], rel=0.05)


def _weighted_fit_spread(points, normals, groups, shared, weights_sigmas, noise, trials, rng):
    """Spread (std per datum parameter) of the 7-parameter weighted least-squares fit of
    tie points whose distances to their planes are each group's shared error plus noise."""
    from colmap_citymodel.errormodel.gnss import datum_jacobian

    jac = datum_jacobian(points, normals, points.mean(0))
    w = 1.0 / weights_sigmas ** 2
    solve = np.linalg.solve(jac.T @ (w[:, None] * jac), (w[:, None] * jac).T)
    keys, slots = np.unique(groups, return_inverse=True)
    fits = [solve @ (rng.normal(0.0, shared[keys])[slots] + rng.normal(0.0, noise, len(points)))
            for _ in range(trials)]
    return np.std(fits, axis=0)


def test_the_stated_sigma_is_that_of_the_weights_refine_gives_a_terrain_unit():
    """Refine weighs a terrain unit's points as one observation of its offset (sigma
    sqrt(s^2 + n s_u^2) each): the stated height sigma is that weighting's, as a Monte Carlo
    of such fits spreads, not the far larger one of every ground point weighed like a roof
    point (2000 ground points with a 0.5 m unit error would then carry the height)."""
    rng = np.random.default_rng(7)
    store = street_store()
    points, faces = tie_points_on(store, 20, rng)
    ground = np.column_stack([rng.uniform(-50, 75, 2000), rng.uniform(-9, 9, 2000),
                              np.zeros(2000)])
    ground_face = store.num_faces
    points = np.vstack([points, ground])
    normals = np.vstack([store.normals[faces], np.tile([0.0, 0.0, 1.0], (2000, 1))])
    groups = np.concatenate([faces, np.full(2000, ground_face)])
    noise, unit_sigma = 0.05, 0.5
    weights_sigmas = np.where(groups == ground_face, np.sqrt(noise ** 2 + 2000 * unit_sigma ** 2),
                              noise)
    terrain = {ground_face: (0, unit_sigma)}
    stated = observability(points, normals, groups, None, None, noise, GENERALISATION,
                           terrain=terrain, per_point=True, weights_sigmas=weights_sigmas)
    alike = observability(points, normals, groups, None, None, noise, GENERALISATION,
                          terrain=terrain, per_point=True)
    shared = np.full(ground_face + 1, GENERALISATION)
    shared[ground_face] = unit_sigma
    spread = _weighted_fit_spread(points, normals, groups, shared, weights_sigmas, noise, 400,
                                  rng)
    assert stated["U"]["sigma"] == pytest.approx(spread[2], rel=0.15)
    assert stated["E"]["sigma"] == pytest.approx(spread[0], rel=0.15)
    assert alike["U"]["sigma"] > 2.0 * stated["U"]["sigma"]


def test_the_generalisation_sigma_comes_from_the_model_faces_not_the_terrain():
    """A corrected model (faces 2 cm off) beside a terrain half a metre off: the faces'
    generalisation sigma is the model's 2 cm, no terrain cell is called an outlier face, and the
    model-fit test counts the model's faces only (the terrain has its own sigma)."""
    from colmap_citymodel.adjust.observability import face_fit
    from colmap_citymodel.precision.quality import fit_statistics

    rng = np.random.default_rng(11)
    rings = street_rings()
    cells = [np.array([(x, -9, 0), (x + 10, -9, 0), (x + 10, 9, 0), (x, 9, 0)], float)
             for x in range(-50, 70, 10)]
    store = store_from_polygons(rings + cells, origin=np.zeros(3),
                                semantics=["Unknown"] * len(rings)
                                + ["TerrainSurface"] * len(cells),
                                building_ids=[f"b{k}" for k in range(len(rings))]
                                + ["terrain"] * len(cells))
    points, faces = tie_points_on(store, 40, rng)
    offsets = np.where(np.arange(store.num_faces) < len(rings), 0.02, 0.5) * rng.standard_normal(
        store.num_faces)
    points += store.normals[faces] * (offsets[faces] + rng.normal(0, 0.01, len(faces)))[:, None]
    fit = face_fit(points, faces, store, GENERALISATION)
    assert fit.estimated
    assert 0.01 < fit.sigma_generalisation < 0.04
    assert not np.isin(fit.outlier_faces, np.arange(len(rings), store.num_faces)).any()
    stats = fit_statistics(fit, GENERALISATION, 0.2, 2.5)
    assert stats["faces_dof"] == len(rings) - len(fit.outlier_faces) - 7


def test_gnss_whose_residuals_exceed_its_sigma_is_weighed_by_them():
    """The GNSS residuals of the block, their common mean (a bias) removed, against the stated
    sigmas: twice as large gives a factor of about 2 on every sigma GNSS gives; smaller than
    stated leaves the stated sigmas (never sharper); a bias alone changes nothing."""
    from colmap_citymodel.adjust.observability import gnss_variance_factor

    rng = np.random.default_rng(3)
    observed = rng.uniform(-50, 50, (200, 3))
    sigmas = np.tile([3.0, 3.0, 5.0], (200, 1))
    worse = observed + rng.normal(0.0, 2.0 * sigmas)
    assert gnss_variance_factor(worse, observed, sigmas) == pytest.approx(2.0, rel=0.1)
    better = observed + rng.normal(0.0, 0.5 * sigmas) + [4.0, -3.0, 6.0]
    assert gnss_variance_factor(better, observed, sigmas) == 1.0
    assert gnss_variance_factor(observed[:2] + 9.0, observed[:2], sigmas[:2]) == 1.0


def test_without_gnss_the_images_sigmas_carry_the_blocks_rotation():
    """Without GNSS the shifts' sigmas are still those of the images' centres: a street's walls
    and roofs hold the block's tilt only so well, which moves images 50 m along the street by
    more than the tie points' centroid."""
    rng = np.random.default_rng(5)
    store = street_store()
    points, faces = tie_points_on(store, 60, rng)
    cameras = np.column_stack([np.linspace(-50, 75, 40), np.zeros(40), np.full(40, 20.0)])
    at_centroid = observability(points, store.normals[faces], faces, None, None, 0.2,
                                GENERALISATION, tilts=face_tilts(store, faces, GENERALISATION))
    at_images = observability(points, store.normals[faces], faces, None, None, 0.2,
                              GENERALISATION, tilts=face_tilts(store, faces, GENERALISATION),
                              image_positions=cameras)
    for axis in ("E", "N", "U"):
        assert at_images[axis]["sigma"] >= at_centroid[axis]["sigma"]
    assert at_images["U"]["sigma"] > 1.2 * at_centroid["U"]["sigma"]


def test_a_loop_still_moving_the_block_states_that_move_in_its_sigma():
    """A loop out of iterations that would still move the block 0.6 m along E states E's sigma
    with that move (0.2 m settled); a move GNSS bounds better states GNSS's, source "gnss";
    a creep without bound and without GNSS leaves the shift without a sigma."""
    from colmap_citymodel.adjust.observability import unsettled_observability

    rows = {axis: {"source": "both", "one_plane": False, "sigma": 0.2,
                   "sigma_gnss_with_bias": 2.5} for axis in "ENU"}
    rows["scale"] = {"source": "planes", "sigma": 1e-3}
    out = unsettled_observability(rows, np.array([0.6, np.inf, 0.0]))
    assert out["E"]["sigma"] == pytest.approx(np.hypot(0.2, 0.6))
    assert out["E"]["source"] == "both" and out["E"]["remaining_move_m"] == 0.6
    assert out["N"]["sigma"] == 2.5 and out["N"]["source"] == "gnss"
    assert out["U"] == rows["U"] and out["scale"] == rows["scale"]
    assert unsettled_observability(rows, None) is rows
    no_gnss = {"E": {"source": "planes", "sigma": 0.2, "sigma_gnss_with_bias": None}}
    assert unsettled_observability(no_gnss, np.array([np.inf, 0, 0]))["E"]["sigma"] is None


def test_weighting_the_faces_that_moves_the_block_beyond_its_sigma_is_in_the_sigma():
    """The faces' errors as unknowns moved the block 0.28 m in U from where every tie point
    alike had placed it, against a stated 0.085 m: U's sigma is at least that move; E, moved
    less than its sigma, keeps it; a move beyond GNSS's sigma with its bias states GNSS's."""
    from colmap_citymodel.adjust.observability import weighting_observability

    rows = {"E": {"source": "planes", "sigma": 0.067, "sigma_gnss_with_bias": 1.6},
            "N": {"source": "planes", "sigma": 0.058, "sigma_gnss_with_bias": 1.6},
            "U": {"source": "planes", "sigma": 0.085, "sigma_gnss_with_bias": 2.8}}
    out = weighting_observability(rows, np.array([0.05, -2.0, -0.278]))
    assert out["E"] == rows["E"]
    assert out["U"]["sigma"] == pytest.approx(0.278) and out["U"]["source"] == "planes"
    assert out["U"]["sigma_one_weighting"] == 0.085
    assert out["N"]["sigma"] == 1.6 and out["N"]["source"] == "gnss"
    assert weighting_observability(rows, None) is rows


def test_a_shift_widened_to_gnss_s_sigma_goes_back_to_gnss():
    """An RTK block (GNSS 0.03 m with its bias) that the faces' weighting moved 0.09 m in U
    against a stated 0.04 m: U's sigma is GNSS's, so the block's U is GNSS's too (held back);
    E, moved within its sigma, stays the planes'; a shift GNSS fixes alone while one plane
    seems to (source "gnss", the planes' sigma small) is not held by the widening rule."""
    from colmap_citymodel.adjust.observability import left_to_gnss, weighting_observability

    rows = {"E": {"source": "both", "sigma": 0.02, "sigma_planes": 0.03, "sigma_gnss": 0.03,
                  "sigma_gnss_with_bias": 0.03},
            "N": {"source": "gnss", "sigma": 0.03, "sigma_planes": 0.04, "sigma_gnss": 0.03,
                  "sigma_gnss_with_bias": 0.03},
            "U": {"source": "both", "sigma": 0.04, "sigma_planes": 0.05, "sigma_gnss": 0.03,
                  "sigma_gnss_with_bias": 0.035}}
    assert not left_to_gnss(rows).any()
    out = weighting_observability(rows, np.array([0.01, 0.0, 0.09]))
    assert out["U"]["source"] == "gnss" and out["U"]["sigma"] == 0.04
    assert left_to_gnss(out).tolist() == [False, False, True]
