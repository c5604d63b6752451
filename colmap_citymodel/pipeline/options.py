"""Options of `colmap-citymodel run` that are not COLMAP's own (COLMAP's stay pycolmap's option
objects, set with `--extraction_options`, `--matching_options`, `--mapper_options`)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class MatchingChoiceOptions:
    """How `--matcher auto` picks COLMAP's matcher from the images (matching.choose_matcher),
    and the pairing it then uses."""

    exhaustive_max_images: int = 30
    """Up to this many images every pair is matched: 30 images are 435 pairs, about as many as
    the spatial matcher's `spatial_neighbors` nearest would give, and no image pair that
    overlaps is missed."""
    spatial_neighbors: int = 20
    """With GNSS for every image, each image is matched with this many nearest by position
    (COLMAP's SpatialPairingOptions.max_num_neighbors; COLMAP's default 50 is meant for GPU
    matching): +-10 images along a street drive or a strip, a sixth of a 60-image orbit."""
    spatial_max_distance: float = 100.0
    """Metres: no pair of images farther apart than this (COLMAP's default), unless the block
    is sparser: then `spatial_spacing_factor` times its median distance to the nearest image."""
    spatial_spacing_factor: float = 10.0
    """See `spatial_max_distance`: a block of photos 30 m apart still finds neighbours within
    300 m."""
    sequential_overlap: int = 10
    """Video frames in name order: each is matched with the next this many frames, and with
    quadratically farther ones (COLMAP's SequentialPairingOptions, overlap 10 and
    quadratic_overlap)."""
    min_sequence_share: float = 0.9
    """Images are taken for video frames when at least this share of their names is one
    prefix, a frame number and one extension, the numbers rising by at most
    `max_sequence_step` from one name to the next."""
    max_sequence_step: int = 10
    """See `min_sequence_share`: frames exported every 10th are still a sequence."""


@dataclass
class RunOptions:
    """`colmap-citymodel run` (pipeline.run)."""

    matching: MatchingChoiceOptions = field(default_factory=MatchingChoiceOptions)
    extraction_chunk: int = 8
    """Images handed to COLMAP's feature extraction at once: the progress bar moves and the
    database is written after each chunk (an interrupted run loses at most one chunk), while
    COLMAP's threads still have several images to share."""
    matching_chunk: int = 50
    """Image pairs handed to COLMAP's matching and geometric verification at once (the same
    reasons)."""
    remap_below: float = 0.5
    """When mapping registers less than this share of the images, it runs again (at most
    `remap_attempts` times, until one registers this share), and the largest block is kept."""
    remap_attempts: int = 3
    """Further mappings after one that registered too few, each with another COLMAP random
    seed, every other one with the small-parallax settings below (those `--mapper_options`
    does not set). Photos taken walking or driving along a street move along their viewing
    direction: their image pairs see little parallax, COLMAP's initial pair of two images
    triangulates too few points at its 1.5 deg to register a third, and its RANSAC and initial
    pair differ from seed to seed. The Lund street photos of tests/data, matched
    exhaustively: COLMAP's settings register 28-29 of the 29 images with 5 of 7 seeds, 2-3
    with the others; the small-parallax settings 29 with 2 of 3 seeds where COLMAP's failed
    (4 and 13 images with the others)."""
    remap_init_min_tri_angle: float = 2.0
    """Small parallax: the smallest triangulation angle of COLMAP's initial image pair, degrees
    (COLMAP's `mapper.init_min_tri_angle` 16, relaxed to 4 when no pair is found)."""
    remap_min_tri_angle: float = 0.5
    """Small parallax: the smallest triangulation angle of a tie point, degrees (COLMAP's
    `triangulation.min_angle` and `mapper.filter_min_tri_angle` 1.5)."""
    remap_abs_pose_min_num_inliers: int = 15
    """Small parallax: the 2D-3D inliers that register an image (COLMAP's
    `mapper.abs_pose_min_num_inliers` 30)."""

    def small_parallax(self) -> dict:
        """The small-parallax settings as `--mapper_options` values."""
        return {"mapper": {"init_min_tri_angle": self.remap_init_min_tri_angle,
                           "filter_min_tri_angle": self.remap_min_tri_angle,
                           "abs_pose_min_num_inliers": self.remap_abs_pose_min_num_inliers},
                "triangulation": {"min_angle": self.remap_min_tri_angle}}
