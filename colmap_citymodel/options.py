"""Options of the refine step as dataclasses, with the defaults of method.md (Unger 5.3).

Every number a user may want to change lives here, documented, in one place. `RefineOptions`
loads from and dumps to TOML-like dicts; unknown keys are rejected (like pycolmap's mergedict),
so a typo in an options file is an error, not a silently ignored setting.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InputError


@dataclass
class AssignmentOptions:
    """Assignment of tie points to model planes (method.md section 6, Unger 4.1 and 4.4).

    Defaults are Unger's (4.4 and the parameter table of 5.3) unless a docstring says otherwise.
    """

    method: str = "auto"
    """"direct" = method (a), closest plane; "msac" = (b), planes extracted from the whole tie
    point cloud and matched to the model; "roi_msac" = (c), one plane searched near each model
    plane; "auto" = `auto_indirect_method` while the threshold exceeds `auto_switch_threshold`,
    (a) below it (assign.schedule.ASSIGNERS, assign/indirect.py). Unger 6.5: (a) and (c) give
    similar results; (b) assigns far fewer planes but is meant for poor initial values. "auto":
    the first assignment takes only points that form a plane, not the clutter (a) takes at 2 m."""
    max_threshold: float = 2.0
    """(a): upper limit of the point-to-plane distance threshold in metres (first iteration)."""
    indirect_max_threshold: float = 3.0
    """Upper limit (m) of the threshold for (b) (distance of an extracted plane's boundary
    centroid to the model plane) and (c) (ROI search distance); Unger 5.3 sets it looser than
    (a)'s 2 m since these methods only take points that form a plane. The lower limit is the
    same 2 x sigma_dTP. The caller's schedule chooses the threshold passed to `assign`;
    assign.schedule.initial_threshold gives the upper limit of the configured method."""
    threshold_factor: float = 3.5
    """Later thresholds = factor x mean over planes of the per-plane mean distance."""
    min_threshold_sigmas: float = 2.0
    """Lower bound of the threshold in units of the sigma of a tie point's distance from its
    face's plane: sigma_dTP with every point alike (2 x 0.2 m = 0.4 m), with the faces' errors
    as unknowns also their offset's (sqrt(0.2^2 + 0.2^2): 0.57 m)."""
    min_points_per_plane: int = 15
    """Planes with fewer assigned tie points get none (5 for a detailed model)."""
    planarity_threshold: float = 0.001
    """(l2 - l3) / l1 of the assigned points' covariance must exceed this (not a line)."""
    face_hysteresis: float = 0.5
    """In the refine loop a face that held tie points in the previous iteration keeps them while
    they pass the planarity test at this fraction of its limit: a face whose points lie close to
    a line would otherwise come and go between iterations, moving the block each time. The
    minimum count is not relaxed, so that a wrong face loses its points as the block moves onto
    the model. 1: the same limit for every face."""
    point_normal_angle: float = 180.0
    """(a): a tie point whose neighbourhood is flat goes to a face only if its neighbourhood's
    normal is within this angle (deg) of the face's (30 is typical): eaves, window reveals and
    balcony slabs lie near a wall's plane but are not on it. 180 (default): no test, as sparse
    tie points can drop whole small faces with it (docs/method.md)."""
    point_normal_neighbours: int = 12
    """(a): tie points (the point itself included) whose plane gives a point's normal; the
    neighbourhood is flat where its smallest eigenvalue is below 5 % of their sum."""
    ambiguity_margin: float = 0.2
    """(a): a tie point goes to its nearest face only if every other face parallel to it (within
    30 deg) that contains its projection, off its plane, is at least this much (m) further away:
    a point between a facade and a set-back storey or an arcade goes to neither. sigma_dtp's
    size; 0: off."""
    window: str = "plane"
    """(a) in refine's loop: "plane", a tie point within the threshold of the face's plane;
    "centred", within it of the face's own surface (the median signed distance of the points
    within `window_reach` beyond the threshold), so that a face standing off its surface keeps
    its points from both sides instead of the side toward the plane, wherever the block is."""
    window_reach: float = 0.4
    """With `window` "centred": how far (m) beyond the threshold a face's points are looked for:
    twice a LOD2 face's generalisation sigma (0.2 m, Unger 5.3)."""
    polygon_margin: float = 0.1
    """A point's projection may lie this far (m) outside the face polygon and still count."""
    excluded_classes: tuple[str, ...] = ("GroundSurface", "ClosureSurface")
    """Faces no tie point can lie on: a building's ground is under it, closures are virtual."""
    roofs_seen_from_above: bool = True
    """A tie point goes to a roof face only when most of the images that observe it lie above the
    roof's plane: a surface is seen from its front only, and cameras below a roof see eaves,
    parapets and facade tops near its plane, never the roof. Applied from the first solve on;
    the first assignment and the similarity rounds before it, which bring the block from metres
    away, keep such points. Roofs only: their orientation is checked by class when the model is
    read, a wall ring's orientation often is not outward. Not in Unger (his images see roofs)."""
    msac_inlier_distance: float = 0.3
    """(b): MSAC inlier distance (m) of the plane extraction in the whole cloud (Unger 5.3:
    tighter than (c)'s because the search is not restricted to the model's vicinity)."""
    roi_inlier_distance: float = 0.4
    """(c): MSAC inlier distance (m) inside a model plane's ROI (Unger 5.3)."""
    alpha_radius: float = 1.0
    """(b): alpha shape radius (m) for the connected components of an extracted plane's points:
    gaps wider than two radii split it (a window is bridged, the gap to the next house is
    not; Unger 4.4, 5.3)."""
    max_normal_angle: float = 10.0
    """(b): largest angle (deg) between an extracted and a matched model plane's normal; (c):
    largest angle of the searched plane's normal from the model normal (Unger 5.3)."""
    msac_confidence: float = 0.99
    """Probability of drawing at least one all-inlier sample; sets the number of hypotheses
    from the best inlier fraction found so far (not from Unger). In (b), late planes hold a
    small fraction of the cloud and `msac_max_trials` decides."""
    msac_max_trials: int = 256
    """At most this many plane hypotheses per MSAC run (bounds the run time; not from Unger)."""
    msac_sample_points: int = 2048
    """Hypotheses are scored on a random subsample of at most this many points; the best few
    are scored again on four times as many (bounds the run time on 100k points; not from
    Unger)."""
    msac_sample_cell: float = 4.0
    """(b): half of the samples take their three points from one cube of this side (m), so
    that small planes of a large cloud get sampled at all (not from Unger)."""
    msac_point_normal_angle: float = 30.0
    """(b): an MSAC inlier also needs its point normal (from its nearest neighbours) within this
    angle (deg) of the plane's, as in Mulder's RANSAC (4.4.3); not in Unger. Without it, once
    the large planes are gone, a horizontal slab cutting every facade of a street holds more
    points than any one facade and is extracted as strips. 90 switches the test off."""
    msac_point_normal_neighbours: int = 10
    """(b): nearest neighbours (the point included) whose principal axes give a point's normal
    (Mulder: 6; more are steadier for noisy tie points)."""
    msac_max_planes: int = 1000
    """(b): at most this many planes are extracted (bounds the run time; not from Unger)."""
    msac_keep_segmentation: bool = True
    """(b): a call with the same tie points as the last extraction, moved by a solve, keeps that
    segmentation while no plane, refitted to its moved points, has lost more than 5 % of them
    from within `msac_inlier_distance` (assign.indirect.MAX_LOST_SHARE). A plane of the cloud
    stays one when the block bends by centimetres; a new random extraction splits the cloud
    differently and moves the block by decimetres. Not from Unger. False: extract every time."""
    msac_max_failures: int = 3
    """(b): the extraction stops after this many planes in a row whose largest connected
    component has fewer than `min_points_per_plane` points (Unger 4.3.1: "repeatedly
    smaller than a threshold")."""
    weighted_sampling: bool = False
    """Weighted RANSAC (Mulder 4.4): with per-point quality weights given to `assign`, (b) and
    (c) draw sample points with probability proportional to their weight and refit planes by
    weighted least squares. Off by default: Mulder found no gain over plain RANSAC."""
    auto_switch_threshold: float = 1.0
    """"auto": above this threshold (m) the block is still far from the model and an indirect
    method runs; at or below it, direct assignment (not from Unger)."""
    auto_indirect_method: str = "roi_msac"
    """The indirect method "auto" uses: "roi_msac" (fast, close to (a) in Unger 6.5) or
    "msac" (independent of the model's position, slower)."""
    random_seed: int = 0
    """Seed of MSAC's sampling: the same input gives the same assignment."""


#: sigma_generalisation (m) to use when the generalisation-aware model is switched on: Unger's
#: sigma_dTP "as this is the expected typical size of generalisation effects" (5.3).
GENERALISATION_SIGMA = 0.20


@dataclass
class AdjustmentOptions:
    """Stochastic model and solver settings of the hybrid bundle adjustment (Unger 3.2, 5.3)."""

    sigma_image: float = 1.0
    """A priori sigma of image coordinates (px) of tie points and check points."""
    sigma_gnss: tuple[float, float, float] = (3.0, 3.0, 5.0)
    """Default sigma of GNSS projection centres X, Y, Z (m) when the source gives none."""
    sigma_dtp: float = 0.20
    """Fictitious distance tie point -> assigned plane (m); 0.05 for a detailed model."""
    sigma_dvt: float = 0.01
    """Fictitious distance vertex -> each plane it belongs to (m)."""
    sigma_vt: float = 0.01
    """Direct observation of each model vertex (m): the model is "almost fixed" (Unger 3.2.3).
    With `correct_model` it stays so for every vertex the images do not correct."""
    correct_model: bool = False
    """Model correction (Unger 5.2.2, 6.7.3): after the assign/adjust loop, the vertices of the
    faces the images see well (`correction_max_sigma`) are observed with `sigma_vt_corrected`
    only, so their planes follow the tie points; the other vertices keep sigma_vt, a corrected
    vertex stays on the plane of every uncorrected face it belongs to, and f_dVT keeps every face
    planar (adjust.model_correction, adjust.correction_loop). Preset "correct_model"."""
    correction_moves_block: bool = False
    """False: the block's poses stay as the adjustment left them and the planes are fitted to its
    tie points (Unger's model correction likewise used a block's tie points as control points).
    True: block and model are estimated together; where the images have systematic errors the
    block bends back and the planes follow it. See adjust.correction_loop."""
    sigma_vt_corrected: float = 0.5
    """Direct observation (m) of the vertices of corrected faces: Unger's 0.5 m "to correct the
    model" (5.3)."""
    sigma_correction_datum: float | None = 0.05
    """Where block and model are estimated together (`correction_moves_block`, and the problem the
    corrected vertices' sigmas come from), the similarity that the corrected planes' moves imply
    is observed as zero with this sigma (m; rotation and scale as the displacement they cause),
    so the corrected model keeps the given one's datum (adjust.model_correction.datum_condition).
    0.05 m: a LOD2 model's per-plane error (~0.2 m, Unger 5.2.2) averaged over a dozen planes.
    None: no condition."""
    correction_max_sigma: float = 0.02
    """A face is corrected only where its assigned tie points determine its plane to this (m) at
    every vertex: the a posteriori sigma of a plane fitted to them (model_correction.
    plane_fit_sigma), which grows with few points, points bunched on part of the face and points
    of another surface among them. 0.02 m: a tenth of a LOD2 model's plane error (~0.2 m, Unger
    5.2.2). The sigma leaves out the block's own error normal to the face, which the corrected
    plane inherits: a larger limit lets in faces whose tie points lie off the true plane."""
    correction_iterations: int = 5
    """At most this many assign + correction solves after the loop (the planes move, so the
    tie points are assigned again to the corrected model)."""
    correction_significance: float = 3.0
    """A vertex shift counts as significant when |shift| / sigma (sigma of the corrected
    vertex along the shift, scaled by s0) exceeds this."""
    image_loss: str = "none"
    """How step 2 treats outliers among the image observations. "none": solve, eliminate
    observations beyond `elimination_threshold`, solve again, all with the original weights
    (Foerstner and Wrobel's scheme without its reweighting phase: COLMAP's mapper already drops
    observations beyond 4 px, `filter_max_reproj_error`). "huber" or "cauchy": solve with that
    robust loss, then eliminate (no second solve); their reweighting of the many residuals near
    1 px costs many more Ceres iterations than "none"."""
    image_loss_scale: float = 1.0
    """Scale (px) of the robust reprojection loss in step 2 ("huber", "cauchy")."""
    plane_loss_scale: float = 2.0
    """Huber scale (in units of sigma_dTP) of the robust f_dTP loss in step 4."""
    elimination_threshold: float = 3.0
    """Observations whose normalised residual |v| / sigma exceeds this are eliminated."""
    min_triangulation_angle: float = 1.5
    """Degrees; tie points below it are removed with the image outliers in step 2."""
    refine_intrinsics: bool = False
    """Refine each camera's focal length and distortion in every solve (the principal point
    held), as COLMAP's own bundle adjuster does. False: held as the reconstruction states them,
    unless the test below finds them off: free, a drive's focal length trades against its
    motion in depth and its block can land metres off."""
    intrinsics_test_alpha: float | None = 0.001
    """Significance level of step 2's test whether the images show the interior orientation
    off: the bundle adjustment without the model is solved again with focal length and
    distortion free, and where its chi-square drops by more than chance allows at this level
    (k1 off by 7e-4, 1.5 px in the corners, bends a long block by decimetres), they are refined
    from then on. None: no test."""
    max_solver_iterations: int = 300
    """Ceres iterations per solve (COLMAP: 100); a drifted block needs more to converge."""
    max_images_direct_solver: int = 4000
    """Up to this many images every solve (step 2 and the hybrid ones) uses Ceres' direct
    SPARSE_SCHUR solver, above it ITERATIVE_SCHUR (COLMAP's
    `max_num_images_direct_sparse_cpu_solver`, whose default 1,000 refine would otherwise
    inherit). The reduced camera system of a block, where each image shares points with its
    neighbours only, stays sparse: the direct solver stays far faster at thousands of images."""
    function_tolerance: float = 1e-6
    """A solve ends when a step lowers the cost by less than this fraction of it. The cost is
    half the chi-square of n normalised residuals, whose own spread is sqrt(2n): a 1e-6
    relative change (~0.1 at n = 4e5) is far below anything statistically visible. COLMAP
    leaves it at 0 and then crawls for 100+ iterations at that level."""
    initial_trust_region_radius: float = 1e8
    """Levenberg-Marquardt starts close to Gauss-Newton (Ceres: 1e4): the hybrid problem is nearly
    linear around SfM's block, so a large first radius saves iterations."""
    num_threads: int = -1
    """Threads of the Ceres solves and the nearest-plane searches; -1: all cores."""
    sigma_generalisation: float | None = None
    """None: the classical stochastic model only (independent f_dTP, as Unger). A value (m): also
    the generalisation-aware one, in which the f_dTP of one plane share an offset o_p ~ N(0,
    sigma^2) and a tilt (each vertex off by sigma), so that a plane's systematic error does not
    average out over its points (Unger 6.3, Table 12), as consider parameters (precision.estimate:
    the estimate stays classical, its covariance grows). Recommended: `GENERALISATION_SIGMA`.
    VCE ("gen"), or None with PrecisionOptions.generalisation_from_data, uses the data's value."""
    face_weighting: str = "offsets"
    """How a face's shared error enters. "offsets" (default): each face's offset and tilts
    unknowns with priors (sigma_face), GNSS's common bias one too (gnss_bias_share), in a
    second loop from where every point alike placed the block (adjust.staged); closer on
    generalised models (docs/method.md, "Faces as units"). "per_point": every f_dTP independent
    at sigma_dtp (Unger; the detailed preset). "face": each point at sigma^2 = sigma_dtp^2 +
    n sigma_face^2 (with `gnss_offset` "all")."""
    face_tilt_weights: bool = False
    """Each tie point's f_dTP also carries its model face's tilt error (each vertex off by
    sigma_face, adjust.faces.tilt_axes): a point far from the face's centroid, where a tilt of
    the model moves the surface most, weighs less. Off: every point of a face weighs alike
    (docs/method.md, "Faces as units")."""
    face_test_alpha: float | None = 0.001
    """Significance level (per face, two-sided) of the test that drops a face whose points the
    other faces place further off than the generalisation error explains (an arcade behind a
    facade, a set-back storey; adjust.faces.snooped_faces). None: no face is dropped."""
    sigma_face: float | None = None
    """With `face_weighting` "face" or "offsets": the sigma (m) of a face's offset error, shared
    by all its tie points. None: estimated from the faces' mean offsets after each solve
    (adjust.faces), starting from 0.20 m, Unger's typical size of a LOD2 model's generalisation
    effects (5.3)."""
    estimate_generalisation: bool = False
    """Experimental: also estimate the o_p (unknowns with that prior, f_dTP becomes
    (n.X + d + o_p) / sigma_dTP) in a re-solve after refine's assignment loop. Off: with the
    plane offsets free, shrinking the block about any point reduces the scatter of the tie
    points about their planes (their relief is real), and only the priors and GNSS resist it."""
    gnss_offset: str = "none"
    """A constant offset of all GNSS positions as unknowns, fixed by the model planes (roofs and
    eaves fix the height, walls of several orientations the plan position): "none"; "height"
    (`--gnss_height_offset auto`: heights in another system, e.g. ellipsoidal without the
    national geoid, EGM96 from a flight controller, above take-off); "all" (`--gnss_bias auto`:
    a constant 3D bias). Refused where the planes do not fix those directions
    (adjust.observability). With an offset the coarse search spans the model's height range."""
    gnss_bias_share: float = 1.0
    """The share of the GNSS positions' stated sigma that is a bias common to the block
    (receiver, multipath, datum), which no number of images averages out: every stage's error
    model holds it (errormodel.gnss), datum sigma sqrt(sigma^2 / n + (share sigma)^2). 1: a
    consumer receiver's stated accuracy may all be common to a block. 0: independent."""
    gnss_drift_share: float = 0.0
    """The share of the GNSS positions' stated sigma that varies slowly along the track (a
    first-order Gauss-Markov process with correlation length `gnss_drift_length`: multipath
    changing along a street canyon), in the error model every score and test uses
    (errormodel.gnss). 0: a bias and white noise only."""
    gnss_drift_length: float = 200.0
    """Correlation length (m along the camera path) of the slowly varying GNSS error: a block
    much shorter sees it as part of the bias, a much longer one as white noise."""
    sigma_model_datum: float = 0.03
    """Sigma (m, per axis) of an error all faces of the model share, which no number of faces
    averages out: its georeference, details that stand out of every facade the same way. Every
    stated datum sigma includes it (adjust.observability). 0.03: a few centimetres, below any
    LOD2 model's generalisation; a model's known georeference accuracy sets it."""
    sigma_gnss_offset: float = 3.0
    """A priori sigma (m) of the estimated offset about 0, i.e. about the positions as read and
    converted (national grid, or the fallback geoid EGM96, typically within 2 m of it, plus the
    GNSS's own bias). Dropped, leaving the offset free, when the coarse search finds the block
    further off than 3 of it (heights above take-off, another height system); 0: always free."""


#: Largest magnitude of a float option: beyond any setting that means something.
MAX_OPTION_VALUE = 1e15
#: Options whose value is a probability, strictly between 0 and 1.
PROBABILITIES = ("assignment.msac_confidence", "precision.alpha", "marks.blunder_alpha",
                 "adjustment.intrinsics_test_alpha", "workflow.divergence_alpha")


def _as_float(value, name: str, source) -> float:
    try:
        return float(value)
    except OverflowError:
        raise InputError(f"option {name}: {value} is too large", source) from None


def _as_tuple(value, current: tuple, name: str, source) -> tuple:
    """A list from the file as a tuple of the default's element type (floats or strings)."""
    kind = type(current[0]) if current else str
    if not isinstance(value, (list, tuple)):
        raise InputError(f"option {name} must be a list, got {value!r}", source)
    out = []
    for v in value:
        if kind is float and isinstance(v, (int, float)) and not isinstance(v, bool):
            out.append(_as_float(v, name, source))
        elif isinstance(v, kind) and not isinstance(v, bool):
            out.append(v)
        else:
            raise InputError(f"option {name} must be a list of {kind.__name__}, got {value!r}",
                             source)
    if kind is float and len(out) != len(current):
        raise InputError(f"option {name} needs {len(current)} numbers, got {len(out)}", source)
    return tuple(out)


def _check_number(name: str, value, source) -> None:
    """Numbers no setting can take: not finite, negative, beyond MAX_OPTION_VALUE or 2**31 - 1;
    zero for a sigma, scale, radius, distance or factor; a probability outside (0, 1); an angle
    beyond 180 degrees."""
    values = value if isinstance(value, tuple) else (value,)
    key = name.rpartition(".")[2]
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        if isinstance(v, int):
            lowest = -1 if key == "num_threads" else 0
            if not lowest <= v <= 2**31 - 1:
                raise InputError(f"option {name} must be an integer in [{lowest}, 2147483647], "
                                 f"got {v}", source)
            continue
        if not math.isfinite(v) or abs(v) > MAX_OPTION_VALUE or v < 0:
            raise InputError(f"option {name} must be a finite number >= 0, got {v}", source)
        positive = key.startswith("sigma_") or key.endswith(
            ("_scale", "_radius", "_distance", "_factor"))
        if positive and v == 0:
            raise InputError(f"option {name} must be > 0, got {v}", source)
        if name in PROBABILITIES and not 0 < v < 1:
            raise InputError(f"option {name} must lie between 0 and 1, got {v}", source)
        if key.endswith("_angle") and v > 180:
            raise InputError(f"option {name} is an angle in degrees (at most 180), got {v}",
                             source)


#: Options that take one of a few words.
CHOICES = {"adjustment.image_loss": ("none", "huber", "cauchy"),
           "adjustment.gnss_offset": ("none", "height", "all"),
           "adjustment.face_weighting": ("per_point", "face", "offsets"),
           "assignment.method": ("direct", "msac", "roi_msac", "auto"),
           "assignment.window": ("plane", "centred"),
           "assignment.auto_indirect_method": ("msac", "roi_msac"),
           "workflow.mode": ("global", "sliding_window"),
           "terrain.source": ("auto", "none")}


@dataclass
class WorkflowOptions:
    """The workflow: global (Unger Table 3: steps 3-4 repeated until convergence) or a sliding
    window along the sequence followed by the global adjustment (Unger 3.3.2, Tables 4-5;
    adjust.sliding_window)."""

    mode: str = "global"
    """"global": assignment and hybrid adjustment of the whole block at once; "sliding_window":
    first windows of `window_size` images in capture order (image name order), each adjusted
    with the model, the window moved on by `window_new` images; then the global adjustment of
    everything, starting from the windows' result (Unger's final global hybrid adjustment)."""
    window_size: int = 100
    """N_ws: images per window (Unger Table 4 / 5.3: 100 key frames; windows of fewer than about 50
    key frames see too few planes to hold them)."""
    window_new: int = 33
    """N_new: images each window adds; the N_ws - N_new most recent adjusted ones are kept
    (Unger 5.3: 33)."""
    window_held_images: int = 3
    """The oldest kept images at this many camera stations (distinct projection centres; all
    cameras of a station) enter the next window with pose priors at their adjusted poses
    (Unger 3.3.2: the poses of at least three of the oldest images, as direct observations;
    the other kept images are estimated again). Stations, not images: three cameras at one
    spot would leave the window's scale free."""
    sigma_window_position: float = 0.05
    """A priori sigma (m) of a held image's position in the next window. Unger takes the
    previous window's estimated covariances; a fixed sigma of the size of a window's a
    posteriori position sigma (a few centimetres with the model) avoids a covariance
    computation per window."""
    sigma_window_rotation: float = 0.05
    """A priori sigma (degrees) of a held image's rotation in the next window."""

    max_iterations: int = 10
    """At most this many assign + hybrid BA iterations."""
    convergence_rms_change: float = 1e-5
    """Stop when the relative change of the RMS of normalised residuals is below this."""
    convergence_camera_shift: float = 0.005
    """Stop when two iterations in a row (after the first) move no camera centre by more than this
    (m): late iterations move the cameras by millimetres, each at the cost of a hybrid solve,
    while one small move alone can be a pause in a slow swing. The floor of the tolerance:
    `convergence_sigma_share` of the block's stated sigma can be larger. 0 (with
    convergence_sigma_share 0) runs until the RMS settles."""
    convergence_sigma_share: float = 0.1
    """The cameras have settled (convergence_camera_shift's two iterations, and the assignment
    rule after one) once they move by less than this share of the block's stated position
    sigma at the first assignment (the smallest of E, N, U, planes and GNSS together), where
    that is more than convergence_camera_shift: a step a tenth of what the block is known to
    adds 1 % to its mean square error (0.1^2), while each further iteration costs a hybrid
    solve or two. 0: convergence_camera_shift alone."""
    convergence_assignment_change: float | None = 0.002
    """Stop before solving when the last solve (after the second iteration) moved no camera centre
    by more than convergence_camera_shift and the new assignment keeps the same planes and
    changes the plane of at most this share of the tie points: the solve would start close to
    its own solution. 0 stops only on an unchanged assignment, None never."""
    robust_second_iteration: bool = True
    """The second iteration, whose threshold falls from the upper limit to one from the data, goes
    straight to the robust solve: coming from the loose first threshold, its f_dTP hold
    outliers as a rule. Later iterations first solve with the original weights and solve
    robustly only if some |v| / sigma exceeds the elimination threshold. On a block without
    such outliers it costs one solve more."""
    keep_eliminated: bool = True
    """An f_dTP eliminated as an outlier (|v| / sigma above the elimination threshold after the
    robust solve) stays eliminated: later assignments do not give its tie point to that face
    again (another face may take it), so the same points do not come back to be eliminated with
    three solves per iteration. Eliminations of the first iteration are not kept: the block
    still moves by decimetres there."""
    solve_again_after_elimination: bool = False
    """True: an iteration whose robust solve eliminated f_dTP solves again at once with the original
    weights (the source's order), and the next iteration assigns from that solution. False (with
    keep_eliminated): the next iteration's assignment, which leaves those f_dTP out, is solved
    with the original weights instead, one solve fewer per eliminating iteration; the loop never
    ends on a robust solve. The sliding window (its windows and the global loop after them)
    always solves again at once."""
    alignment_rounds: int = 20
    """At most this many rounds of similarity fit + assignment before the first hybrid
    adjustment (initial_alignment; ICP-like)."""
    alignment_tolerance: float = 0.01
    """The rounds stop when a fit moves the tie points by less than this on average (m)."""
    overlap_margin: float = 30.0
    """Metres around the reconstruction's footprint in which model buildings are kept."""
    coarse_search_sigmas: float = 8.0
    """Before the first assignment the block's shift (and, along a straight flight line, its roll)
    is searched within +- this many GNSS sigmas of the GNSS-only position (align.coarse): GNSS
    errors are mostly a bias of metres, in a street often beyond the stated sigma, which a 2 m
    assignment threshold cannot bridge; a heavy-tailed penalty weighs the wide box. With an
    initial transform only the shift is searched (the GNSS-only adjustment has moved the block
    onto the GNSS). 0 switches the search off."""
    reuse_problem: bool = True
    """Keep one hybrid problem across the assign/adjust iterations: only the f_dTP blocks of
    tie points whose plane changed are exchanged (HybridProblem.reassign); a new problem is
    built when the set of planes, the loss or the priors change. An iteration whose
    assignment is the one the last solve used ends the loop without solving it again. False:
    a new problem every iteration (the same solution, set-up repeated)."""
    hold_gnss_height: bool = True
    """Where the planes know the block's height far worse than GNSS (observability.left_to_gnss),
    it is held where the coarse search and the first assignment put it (GNSS's level where GNSS
    is more precise than they; adjust.scale.level_prior) until the planes get a say: per tie
    point, walls tilted by a fraction of a degree can seem to fix the height. False: the planes
    decide there, as their f_dTP weigh."""
    alternating_planes_shift: float = 0.1
    """Stop when the last four iterations alternated between two sets of planes (a face at the
    minimum number of points coming and going) and none of the last three moved a camera by more
    than this (m); the best iterate by the block objective is the result. Such a loop would
    otherwise swing back and forth until `max_iterations`. 0: never."""
    divergence_alpha: float = 0.001
    """Significance level of the test that calls an iteration a divergence: its placement's
    log-likelihood (align.objective.BlockObjective: the tie points on faces and terrain, GNSS
    with its bias) lies below the best iterate's by more than chi-square(7) at this level
    allows (a likelihood ratio over the seven datum parameters). The loop then ends and the best
    iterate is kept."""


@dataclass
class MapperOptions:
    """`colmap-citymodel map`: COLMAP's incremental mapping with the model in its global
    bundle adjustments (mapper.py). COLMAP's own mapper options stay pycolmap's
    IncrementalPipelineOptions (`--mapper_options KEY=VALUE`)."""

    min_gnss_images: int = 10
    """The block is georegistered (7-parameter fit to GNSS, then the coarse search onto the
    model) at the first global bundle adjustment at which at least this many registered images
    have GNSS; from then on every global bundle adjustment is the hybrid one with the model.
    Ten positions spread over a few stations give the similarity's seven parameters with
    redundancy; fewer would let single GNSS errors tilt the young block."""
    start_at_gnss: bool = False
    """Seek COLMAP's initial image pair among the images with GNSS (those with the most
    correspondences first), unless the pipeline names one. COLMAP otherwise starts where the
    matches are densest, possibly far from the images with GNSS: the block is then georegistered
    and held by the model only once it has grown back to them. Off by default: a block held on
    the model from its first few images can settle at a wrong scale."""
    hybrid_iterations: int = 3
    """At most this many assign + hybrid adjustment iterations in each global bundle adjustment
    during mapping (the block is still growing: the next one follows soon); the final refine
    after mapping runs `workflow.max_iterations`."""


@dataclass
class PrecisionOptions:
    """A posteriori precision after the last solve (method.md 7 and 9; precision.py)."""

    covariances: str = "auto"
    """"on", "off" or "auto": covariances of images and tie points (Schur elimination; the
    camera-side inverse dense, or selected where large) only for blocks of fewer than
    `max_images_auto` images. Without them s0 and the global test are still reported, with
    proportional group redundancies."""
    max_images_auto: int = 2500
    """Image count up to which "auto" computes covariances. Above 1,000 camera-side unknowns the
    inverse is selected (only where sigmas need it), whose cost grows about linearly along a
    street: at 2,000 images about 0.6 of the refine's own time; memory grows with images x
    planes."""
    alpha: float = 0.05
    """Significance level of the global model test (two-sided chi-square)."""
    tolerance: float = 0.25
    """The position tolerance (m) of the verdict (`--tolerance`): a result that its stated sigmas
    do not place within it with 95 % probability is "weak". Default 0.25: one face's generalisation
    in a LOD2 model (0.2 m, Unger 5.3) with the model's common error; a block placed that well
    is placed as well as the model is drawn."""
    generalisation_from_data: bool = True
    """Without an a priori `AdjustmentOptions.sigma_generalisation`, the covariances are also given
    under the generalisation-aware stochastic model, with the sigma the planes' mean f_dTP
    residuals give (a variance component by moments, precision.generalisation_effects; no
    re-solve, the estimate is unchanged). The classical covariances treat a plane's thousands of
    f_dTP as independent and state check points too precise (Unger Table 12: 3-19x). False: the
    classical covariances only, as Unger."""
    variance_components: bool = False
    """Iterated variance component estimation (Foerstner) of `variance_component_groups` after
    the last iteration, re-solving with the estimated sigmas; the covariances are those of that
    re-weighted final solve. Off by default: each VCE iteration is one more hybrid solve."""
    variance_component_groups: tuple[str, ...] = ("image", "dTP", "gen")
    """Groups whose sigma VCE estimates: image and f_dTP iterated with re-weighted solves;
    "gen" (the per-plane generalisation offsets) once at the end from the planes' mean f_dTP
    residuals (moments, precision.generalisation_effects), also without an a priori
    sigma_generalisation. GNSS is left out by default: its errors are time-correlated (a bias
    along the flight), which white-noise VCE would read as precision and then let the bias
    pull the datum."""
    variance_component_iterations: int = 10
    """At most this many re-weighted solves."""
    variance_component_tolerance: float = 0.02
    """Stop when no group factor changes by more than this (relative)."""


@dataclass
class TerrainOptions:
    """The ground beside the buildings as control (citymodel.terrain, citymodel.ground_faces):
    ground tie points held to a terrain surface from DTM files (`--terrain FILE ...`), the
    model files' TIN relief, or the buildings' feet."""

    source: str = "auto"
    """"auto": the DTM files given, else the model's relief, else the buildings' feet; "none":
    no terrain (`--terrain none`): the ground tie points stay unused."""
    files: tuple[str, ...] = ()
    """DTM rasters (GeoTIFF / COG tiles, any CRS, heights in the model's height system) to
    take the terrain from (`--terrain FILE ...`); empty: the model's relief or feet."""
    sigma: float = 0.15
    """The DTM's (or relief's) stated height accuracy (m), taken as one offset per tile: a
    tile's ground points together weigh as one observation of it (`--terrain_sigma`). DGM1 and
    AHN state 0.05-0.15 m on open ground."""
    feet_sigma: float = 0.30
    """Sigma (m) of one building's ground height, which the terrain interpolated from its feet
    shares (one offset per building), where the ground's tie points beside it and at least two
    other buildings' feet agree with it (citymodel.terrain_check): a LOD2 model's ground
    heights are its generalised outline's, decimetres off."""
    feet_spread: float = 1.5
    """Sigma (m) of a building's ground height that nothing checks (too few buildings beside
    the ground's tie points): official LoD2 takes a building's walls down to the lowest ground
    of its footprint, metres below a street on a slope, a ramp or a courtyard."""
    feet_sigma_growth: float = 0.02
    """Metres the feet terrain's local sigma (beyond its building's offset) grows per metre
    from the nearest foot: a street's cross slope and camber (2 %) are not in the feet."""
    cell: float = 6.0
    """Side (m) of the square terrain cells that become planar faces: a few metres, so that a
    cell takes enough tie points, and its plane follows the slope of the street."""


@dataclass
class MarkOptions:
    """Ground marks measured in the images (block.marks, adjust.marks): control marks
    (`--gcp`) in the adjustment, check marks (`--checkpoints` in gcp_list format) only
    compared with the block."""

    sigma_horizontal: float = 0.02
    """Sigma (m) of a mark's surveyed easting and northing where its line states none
    (`--gcp_sigma H V`): survey-grade RTK or total station, 1-2 cm."""
    sigma_vertical: float = 0.03
    """Sigma (m) of a mark's surveyed height where its line states none: RTK heights are about
    1.5 times worse than positions."""
    sigma_pixel: float = 1.0
    """Sigma (pixels) of a mark measured by hand in an image: the centre of a painted or
    printed target is found to about a pixel, a natural point (a manhole corner) worse."""
    blunder_alpha: float = 0.001
    """Significance level of the test that names a control mark a blunder (its surveyed
    position against where the other marks put it in the block, chi-square with 3 degrees of
    freedom, one mark at a time, the worst first) and a check mark a blunder (its error
    against the others' mean and both sigmas): a sound mark is named with this
    probability."""


@dataclass
class RefineOptions:
    """All options of refine, one dataclass per section of an options file."""

    assignment: AssignmentOptions = field(default_factory=AssignmentOptions)
    """Tie points to model planes (`[assignment]`)."""
    adjustment: AdjustmentOptions = field(default_factory=AdjustmentOptions)
    """Stochastic model and solver of the hybrid adjustment (`[adjustment]`)."""
    workflow: WorkflowOptions = field(default_factory=WorkflowOptions)
    """Global or sliding-window loop and its stopping rules (`[workflow]`)."""
    precision: PrecisionOptions = field(default_factory=PrecisionOptions)
    """A posteriori precision and the global test (`[precision]`)."""
    terrain: TerrainOptions = field(default_factory=TerrainOptions)
    """The ground as control: terrain source and sigma (`[terrain]`)."""
    marks: MarkOptions = field(default_factory=MarkOptions)
    """Control and check marks: their default sigmas and blunder test (`[marks]`)."""

    @classmethod
    def preset(cls, name: str) -> "RefineOptions":
        """`generalised` (default, LOD2 as published), `detailed` (LOD3 / detailed LOD2: its
        faces are the surfaces themselves, every tie point weighs alike) or `correct_model`
        (generalised, then the faces the images see are corrected)."""
        options = cls()
        if name in ("generalised", "generalized", "default"):
            return options
        if name == "detailed":
            options.adjustment.sigma_dtp = 0.05
            options.assignment.min_points_per_plane = 5
            options.adjustment.face_weighting = "per_point"
            return options
        if name == "correct_model":
            options.adjustment.correct_model = True
            return options
        raise InputError(f"unknown preset {name!r}; use generalised, detailed or correct_model")

    def todict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def mergedict(self, values: dict[str, Any], source: str = "options") -> "RefineOptions":
        """Overwrite fields from a nested dict; unknown sections or keys are an InputError."""
        for section, entries in values.items():
            target = getattr(self, section, None)
            if not dataclasses.is_dataclass(target) or not isinstance(entries, dict):
                raise InputError(f"unknown options section {section!r}", source)
            known = {f.name: f for f in dataclasses.fields(target)}
            for key, value in entries.items():
                if key not in known:
                    raise InputError(f"unknown option {section}.{key}", source)
                current = getattr(target, key)
                number = isinstance(value, (int, float)) and not isinstance(value, bool)
                if current is None and number:
                    value = _as_float(value, f"{section}.{key}", source)  # optional floats
                elif isinstance(current, tuple):
                    value = _as_tuple(value, current, f"{section}.{key}", source)
                elif isinstance(current, float) and number:
                    value = _as_float(value, f"{section}.{key}", source)
                elif not isinstance(value, type(current)) or (
                        isinstance(value, bool) and not isinstance(current, bool)):
                    raise InputError(
                        f"option {section}.{key} must be {type(current).__name__}, got {value!r}",
                        source,
                    )
                _check_number(f"{section}.{key}", value, source)
                choices = CHOICES.get(f"{section}.{key}")
                if choices is not None and value not in choices:
                    raise InputError(f"option {section}.{key} must be one of "
                                     f"{', '.join(choices)}, got {value!r}", source)
                setattr(target, key, value)
        return self

    @classmethod
    def from_toml(cls, path: str | Path, preset: str = "generalised") -> "RefineOptions":
        path = Path(path)
        try:
            values = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise InputError("options file does not exist", path) from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
            raise InputError(f"not a valid TOML file: {error}", path) from None
        return cls.preset(preset).mergedict(values, source=str(path))
