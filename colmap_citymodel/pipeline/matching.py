"""COLMAP's feature matching of a run, the matcher chosen from the data, resumable.

`choose_matcher` ("auto", logged with its reason; RunOptions.matching):
1. a small set (at most `exhaustive_max_images`): every pair (exhaustive);
2. GNSS for every image: each with its nearest by position (spatial);
3. names of video frames (a prefix, a frame number, one extension; pipeline.options): each
   frame with the next ones (sequential);
4. otherwise every pair, slow for large sets (exhaustive, with a warning).

The pairs are those of COLMAP's own pair generators (`pycolmap.ExhaustivePairGenerator`,
`SpatialPairGenerator`, `SequentialPairGenerator` with COLMAP's pairing options); they are
matched and verified by COLMAP (`pycolmap.match_image_pairs`) in chunks, so that a progress bar
moves and an interrupted run keeps what it matched. Pairs the database holds already are not
matched again. The spatial matcher reads the database's pose priors: `sync_pose_priors` writes
the run's GNSS there first (model CRS, CARTESIAN, covariance from the sigmas).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from ..errors import InputError
from .features import colmap_warnings_only
from .options import MatchingChoiceOptions, RunOptions

logger = logging.getLogger(__name__)

MATCHERS = ("auto", "exhaustive", "spatial", "sequential")
_FRAME_NAME = re.compile(r"^(.*?)(\d+)(\.[A-Za-z0-9]+)$")


@dataclass
class MatcherChoice:
    """The matcher of a run and why; `pairing` COLMAP's pairing options for it."""

    matcher: str
    reason: str
    pairing: dict = field(default_factory=dict)

    def todict(self) -> dict:
        return {"matcher": self.matcher, "reason": self.reason, "pairing": self.pairing}


def frame_sequence(names: list[str], options: MatchingChoiceOptions) -> bool:
    """Whether `names` look like frames of a video: most of them one prefix, a number and one
    extension, the numbers rising by small steps in name order."""
    groups: dict[tuple[str, str], list[int]] = {}
    for name in names:
        found = _FRAME_NAME.match(name)
        if found:
            groups.setdefault((found.group(1), found.group(3).lower()), []).append(
                int(found.group(2)))
    if not groups or len(names) < 3:
        return False
    numbers = sorted(max(groups.values(), key=len))
    if len(numbers) < options.min_sequence_share * len(names):
        return False
    steps = np.diff(numbers)
    return bool(np.mean((steps >= 1) & (steps <= options.max_sequence_step))
                >= options.min_sequence_share)


def choose_matcher(names: list[str], gnss_xy: dict[str, np.ndarray],
                   options: MatchingChoiceOptions | None = None,
                   matcher: str = "auto") -> MatcherChoice:
    """The matcher for the images `names` (`gnss_xy`: name -> easting, northing of those with
    GNSS) by the rules of the module docstring, or the one the user named (`matcher`)."""
    options = options or MatchingChoiceOptions()
    if matcher not in MATCHERS:
        raise InputError(f"--matcher takes {', '.join(MATCHERS)}, got {matcher!r}")
    n, located = len(names), sum(name in gnss_xy for name in names)
    if matcher == "auto":
        if n <= options.exhaustive_max_images:
            matcher, reason = "exhaustive", (f"{n} images (at most "
                                             f"{options.exhaustive_max_images}): every pair")
        elif located == n:
            matcher, reason = "spatial", f"GNSS for all {n} images: each with its nearest"
        elif frame_sequence(names, options):
            matcher, reason = "sequential", (f"{n} images named as video frames, GNSS for "
                                             f"{located}: each with the next frames")
        else:
            matcher, reason = "exhaustive", (f"{n} images, GNSS for {located} only, names not "
                                             "of video frames: every pair (slow for many)")
            logger.warning("matching: %s", reason)
    else:
        reason = "--matcher"
        if matcher == "spatial" and located < n:
            logger.warning("spatial matching: %d of %d images have no GNSS and get no pairs",
                           n - located, n)
    return MatcherChoice(matcher, reason, pairing_options(matcher, gnss_xy, options))


def pairing_options(matcher: str, gnss_xy: dict[str, np.ndarray],
                    options: MatchingChoiceOptions) -> dict:
    """COLMAP's pairing options of `matcher` (spatial: the neighbours and the distance limit
    from the GNSS spacing, MatchingChoiceOptions)."""
    if matcher == "spatial":
        xy = np.array(list(gnss_xy.values()), dtype=np.float64).reshape(-1, 2)
        distance = options.spatial_max_distance
        if len(xy) > 1:
            from scipy.spatial import cKDTree

            spacing = float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1]))
            distance = max(distance, options.spatial_spacing_factor * spacing)
        return {"max_num_neighbors": options.spatial_neighbors, "max_distance": distance,
                "ignore_z": True}
    if matcher == "sequential":
        return {"overlap": options.sequential_overlap, "quadratic_overlap": True}
    return {}


# -- the database ---------------------------------------------------------------------------------

def sync_pose_priors(database_path: Path, gnss) -> int:
    """Make `gnss` (block.gnss.GNSSObservations, model CRS) the database's pose priors
    (CARTESIAN, covariance diag(sigma^2)), keeping the gravity COLMAP wrote. COLMAP's own
    priors from EXIF (WGS84, no covariance) go, also those of images the GNSS does not hold:
    the spatial matcher must not mix the two systems. Returns the priors written."""
    index = {name: k for k, name in enumerate(gnss.image_names)}
    written = 0
    with pycolmap.Database.open(str(database_path)) as db:
        existing = {_key(p.corr_data_id): p for p in db.read_all_pose_priors()}
        db.clear_pose_priors()
        for image in db.read_all_images():
            if image.name not in index:
                continue
            k, prior = index[image.name], pycolmap.PosePrior()
            before = existing.get(_key(image.data_id))
            if before is not None and before.has_gravity():
                prior.gravity = before.gravity
            prior.corr_data_id = image.data_id
            prior.position = gnss.positions[k].astype(np.float64)
            prior.position_covariance = np.diag(gnss.sigmas[k] ** 2)
            prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
            db.write_pose_prior(prior)
            written += 1
    return written


def _key(data_id) -> tuple:
    return (int(data_id.sensor_id.type.value), int(data_id.sensor_id.id), int(data_id.id))


def candidate_pairs(database_path: Path, choice: MatcherChoice) -> list[tuple[str, str]]:
    """The image pairs COLMAP's pair generator of `choice` gives, each once, by name."""
    generator, options = {
        "exhaustive": (pycolmap.ExhaustivePairGenerator, pycolmap.ExhaustivePairingOptions),
        "spatial": (pycolmap.SpatialPairGenerator, pycolmap.SpatialPairingOptions),
        "sequential": (pycolmap.SequentialPairGenerator, pycolmap.SequentialPairingOptions),
    }[choice.matcher]
    pairing = options()
    for key, value in choice.pairing.items():
        setattr(pairing, key, value)
    with colmap_warnings_only(), pycolmap.Database.open(str(database_path)) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        found = generator(pairing, db).all_pairs()
    unique = sorted({tuple(sorted((names[a], names[b]))) for a, b in found if a != b})
    return [(a, b) for a, b in unique]


def pairs_to_match(database_path: Path, pairs: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """The pairs whose matching the database does not hold yet."""
    with pycolmap.Database.open(str(database_path)) as db:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        return [(a, b) for a, b in pairs if not db.exists_two_view_geometry(ids[a], ids[b])]


# -- matching -------------------------------------------------------------------------------------

def match(database_path: Path, choice: MatcherChoice, work_dir: Path, *,
          matching: pycolmap.FeatureMatchingOptions | None = None,
          options: RunOptions | None = None, progress: bool = True) -> dict:
    """Match and verify the pairs of `choice` the database lacks (module docstring). Returns
    the step's details."""
    options = options or RunOptions()
    matching = matching or pycolmap.FeatureMatchingOptions()
    pairs = candidate_pairs(database_path, choice)
    todo = pairs_to_match(database_path, pairs)
    logger.info("matching: %s (%s): %d pairs, %d of them in the database already",
                choice.matcher, choice.reason, len(pairs), len(pairs) - len(todo))
    if any(" " in name for pair in todo for name in pair):  # COLMAP's pair lists split at spaces
        _match_whole(database_path, choice, matching)
    else:
        _match_chunks(database_path, todo, work_dir / ".match_pairs.txt", matching,
                      options.matching_chunk, progress)
    with pycolmap.Database.open(str(database_path)) as db:
        verified = int(db.num_verified_image_pairs())
    return {**choice.todict(), "pairs": len(pairs), "matched": len(todo),
            "reused": len(pairs) - len(todo), "verified_pairs": verified,
            "summary": f"{choice.matcher}: {len(todo)} of {len(pairs)} pairs matched, "
                       f"{verified} verified"}


def _match_chunks(database_path: Path, todo: list[tuple[str, str]], pair_file: Path,
                  matching, chunk: int, progress: bool) -> None:
    bar = tqdm(total=len(todo), desc="matches", unit="pair", disable=not progress or not todo)
    try:
        with colmap_warnings_only():
            for start in range(0, len(todo), chunk):
                part = todo[start:start + chunk]
                pair_file.write_text("".join(f"{a} {b}\n" for a, b in part), encoding="utf-8")
                pycolmap.match_image_pairs(
                    database_path, matching_options=matching,
                    pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pair_file),
                    device=pycolmap.Device.cpu)
                bar.update(len(part))
    finally:
        bar.close()
        pair_file.unlink(missing_ok=True)


def _match_whole(database_path: Path, choice: MatcherChoice, matching) -> None:
    """COLMAP's matcher function in one call (no progress): for image names with spaces."""
    function, options = {
        "exhaustive": (pycolmap.match_exhaustive, pycolmap.ExhaustivePairingOptions),
        "spatial": (pycolmap.match_spatial, pycolmap.SpatialPairingOptions),
        "sequential": (pycolmap.match_sequential, pycolmap.SequentialPairingOptions),
    }[choice.matcher]
    pairing = options()
    for key, value in choice.pairing.items():
        setattr(pairing, key, value)
    with colmap_warnings_only():
        function(database_path, matching_options=matching, pairing_options=pairing,
                 device=pycolmap.Device.cpu)
