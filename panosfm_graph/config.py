"""Configuration: one frozen dataclass tree whose defaults are the paper's values unless a comment says otherwise.

Thresholds carry their unit in their name (``merge_angle_deg``,
``junction_dist_frac`` = a fraction of ``min(width, height)``). An ablation is
a list of configs: switch relation types and factor types here, never in code.
``dataclasses.replace`` (or :func:`with_overrides`) derives variants.
Each field's comment says what it is and why its default; the measurements behind
a default are in ``docs/decisions.md`` (the anchor after "see").
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class CaptureConfig:
    """How frames are taken from a capture."""

    every_k: int = 1  # take every k-th frame
    max_frames: int | None = None  # cap the number of frames (after every_k)
    scale: float = 1.0  # downscale factor applied to frames and intrinsics (0 < scale <= 1)
    min_imu_rate_hz: float = 5.0  # an IMU slower than this AND than half the frame rate is an error
    min_turn_deg: float = 90.0  # IMU yaw span over the frames below this: error (no spin to reconstruct)
    full_turn_deg: float = 300.0  # ... below this: a warning, the result covers part of the room
    max_gap_intervals: float = 3.0  # a frame gap longer than this many median intervals: "dropped frames" warning


@dataclass(frozen=True)
class DetectConfig:
    """Paper §3.1 'Line segment detection' (LSD + merging)."""

    merge_angle_deg: float = 1.0  # merge segments whose angles differ less than this
    merge_dist_frac: float = 0.05  # ... and whose closest endpoints are nearer than this * min(w, h)
    merge_offset_px: float = 1.5  # ... and that are colinear within this perpendicular offset
    min_length_frac: float = 0.05  # drop segments shorter than this * min(w, h) after merging
    workers: int = 2  # worker processes for per-frame detection


@dataclass(frozen=True)
class ManhattanConfig:
    """Paper §3.1 and supplement §1 (Manhattan frame extraction, Manhattan lines)."""

    sphere_bins: int = 10242  # near-uniform bins on the Gaussian sphere
    vote_band_rad: float = 0.03  # a bin gets a vote within this angle of the great circle
    label_angle_deg: float = 85.0  # Manhattan segment: plane normal >= this from one direction...
    # ... and < this from the other two (no segment compatible with two directions)
    iterations: int = 3  # alternate extraction / labelling / rotation refinement (10: 0.0764 -> 0.0757 deg only)
    vertical_search_deg: float = 10.0  # the vertical peak is searched this close to gravity
    vertical_max_deg: float = 5.0  # a refined vertical farther than this from gravity is replaced by it (0: off)
    # ... and in a streamed batch's warm start (lines.refine_warm); see docs/decisions.md#warm-vertical
    warm_vertical_max_deg: float = 0.25
    min_segments: int = 20  # fewer (Manhattan) segments than this: TooFewLinesError


@dataclass(frozen=True)
class FocalConfig:
    """Focal length from the Manhattan vanishing points (our addition): camera.json without one, or asked for."""

    estimate: bool = False  # estimate it even when camera.json gives one (panosfm run --estimate-focal)
    hfov_min_deg: float = 30.0  # the search's horizontal fields of view: from ...
    hfov_max_deg: float = 120.0  # ... to ...
    hfov_step_deg: float = 5.0  # ... in steps of this, then a bounded scalar refinement
    max_frames: int = 120  # evenly spread frames the search uses (all when fewer)
    gauss_newton_iterations: int = 4  # each frame's rotation re-fitted to its segments at every candidate
    gravity_sigma_deg: float = 0.5  # ... its tilt held to the IMU's gravity this tightly, the heading free
    huber_deg: float = 0.5  # ... Huber threshold on a segment's residual
    label_angle_deg: float = 85.0  # ... segments within 90 - this of a vanishing direction take part (the 85 degree rule)
    truncate_px: float = 2.0  # cost: each segment's end-point distance (px) from its vanishing point's line, truncated here
    min_sharpness: float = 1.01  # the cost 5 % off the estimate less than this many times higher: a warning
    # then the point tracks as bearings about one centre (points/stitch.py): their focal length is taken where they
    # fit within this (px, 90th percentile of the corners): a turn about the camera (0: off); see
    # docs/decisions.md#stitched-focal-length
    stitch_max_p90_px: float = 1.0
    # where they do not (parallax), the same tracks with the camera on the spin's circle, focal free, taken within
    # the same bound; see docs/decisions.md#focal-on-an-arm
    stitch_arm: bool = True


@dataclass(frozen=True)
class RotationConfig:
    """Supplement §2 (rotation refinement, Eq. 1)."""

    imu_weight: float = 1.0  # lambda of the IMU relative-rotation term (paper 0.1 with unweighted residuals)
    neighbour_angle_deg: float = 10.0  # frames whose optical axes differ less than this are neighbours
    max_neighbours: int = 8  # per frame, nearest in time first (keeps the graph sparse)
    max_iterations: int = 20  # Levenberg-Marquardt iterations of each refinement
    huber_deg: float = 0.5  # Huber threshold on the Eq. 1 data residual (0: plain least squares as in the paper)
    gravity_sigma_deg: float = 0.5  # prior on each frame's IMU gravity direction (0: off, as in the paper)
    # IMU heading drift (gyro bias) as a polynomial in time of this degree, removed before the IMU's relative rotations
    # are used (-1: off, the paper); see docs/decisions.md#imu-heading-drift-model
    drift_degree: int = 1
    # drift fit weighs each frame with horizontal lines alike ("frames"), not by line length ("length": one object's
    # lines bias its frames alike); see docs/decisions.md#heading-held-by-the-imu
    drift_weights: str = "frames"
    # option: frames with fewer horizontal Manhattan segments than this do not enter the drift fit (1: every frame
    # with one); brittle on the real cuts, see docs/decisions.md#drift-fit-without-feedback
    drift_min_horizontal: int = 1
    # the preprocessing iterations refine against the drift-corrected IMU (True) or the raw one, the correction used
    # only by the last refinement (False); see docs/decisions.md#drift-fit-without-feedback
    drift_feedback: bool = False
    # frames a turn apart whose optical axes lie within this (deg) give the drift between them (0: off); see
    # docs/decisions.md#drift-between-the-spins-ends
    drift_loop_deg: float = 3.0
    drift_loop_weight: float = 10.0  # ... the weight of those rows, relative to a frame's
    # the last refinement holds each frame to the drift-free IMU with this weight (as imu_weight; 0: off, the paper),
    # so lines that mislead the vanishing points do not carry the heading off; see
    # docs/decisions.md#heading-held-by-the-imu
    heading_weight: float = 10.0


@dataclass(frozen=True)
class TrackingConfig:
    """Supplement §3 (line tracking)."""

    axis_angle_deg: float = 2.0  # match frames whose optical axes are within this angle
    axis_angle_steps: float = 1.5  # ... or within this many median frame steps, if more (slow frame rates; 0: paper)
    match_dist_frac: float = 0.05  # smallest endpoint-to-line distance < this * min(w, h)
    match_angle_deg: float = 1.0  # angle difference between matched segments
    min_track_length: int = 2  # tracks with fewer segments are dropped (3: purer, worse end to end)
    # >0: also link track ENDS across frames whose axes are within this (0: paper); see
    # docs/decisions.md#tracking-settings-left-at-defaults
    bridge_angle_deg: float = 0.0
    # loop closure: frames a turn apart whose axes are within this (deg) are matched too (0: off, the paper); off:
    # the swaying spins got worse, see docs/decisions.md#loop-closure
    loop_angle_deg: float = 0.0
    match_angle_px: float = 1.0  # >0: angle tolerance max(match_angle_deg, atan(this / shorter length)) (0: paper)
    colinear_px: float = 1.0  # >0: colinear pieces of one frame (within this) are matched as one (0: paper)
    # matched segments overlap along the line up to a gap of this * min(w, h) (None: paper); see
    # docs/decisions.md#match-overlap
    match_gap_frac: float | None = 0.0
    # refine each frame pair's rotation homography by the image shift that best aligns at least this many first
    # matches, then match again (0: off); see docs/decisions.md#shift-refined-matching
    shift_min_matches: int = 4
    # segments whose polarities (grey levels) both exceed this and disagree never match (a trim's two sides; 0: off);
    # see docs/decisions.md#polarity-and-vanishing-point-grouping
    polarity_min: float = 8.0
    vp_colinear: bool = True  # group colinear pieces by their vanishing-point lines (False: by their own endpoints)
    # a match farther than this (px) from its partner's vanishing-point line, after the pair's common image shift, is a
    # jump to a neighbouring line and is dropped (0: off); see docs/decisions.md#line-jumps
    jump_px: float = 3.0
    jump_ref_deg: float = 2.0  # ... times a pair's turn / this where more (0: fixed); see docs/decisions.md#merge-gap-and-jump-threshold-in-degrees
    # option: that factor to the power 1 + this * |n_x| (upright lines keep parallax; 0: off); off: better at 60 frames per
    # turn, worse at 100, see docs/decisions.md#upright-lines-jump-further
    jump_across_power: float = 0.0
    # tracks of one axis that end and start at most this many frames apart are joined when their fits agree (0: off);
    # see docs/decisions.md#fragment-merging
    merge_gap_frames: int = 3
    merge_gap_deg: float = 5.5  # ... and no more median frame steps than fit this turn (deg; at least 1; 0: frames only)
    merge_tol_px: float = 2.0  # ... their interpretation-plane angles, fitted linearly over frames, agree within this
    merge_overlap: bool = False  # ... and tracks whose spans overlap (two pieces of one line followed side by side)
    merge_image_px: float = 3.0  # ... and each fit passes this close (px) to the other track's nearest segment (0: off)
    # ... or, across up to merge_gap_frames at any spin speed, one line through both seen from the spin's circle fits
    # within this RMS (px; 0: off); see docs/decisions.md#spin-line-fragment-joins
    merge_spin_px: float = 0.0
    min_longest_frac: float = 0.0  # drop tracks whose longest segment is below this * min(w, h) (texture; 0: off)


@dataclass(frozen=True)
class PointsConfig:
    """Point tracks (our addition, issue #40; points/tracking.py): corners followed by optical flow."""

    enabled: bool = True  # False: no point tracks (the motion model places frames by the spin and lines alone)
    # a zero-baseline spin: the point tracks join the rotations' adjustment as bearings (False: lines only); see
    # docs/decisions.md#zero-baseline-points
    zero_baseline: bool = True
    per_frame: int = 150  # corners kept per frame (tracked ones first, new ones seeded where none run)
    quality: float = 0.01  # goodFeaturesToTrack's qualityLevel
    min_distance_px: float = 12.0  # between corners
    min_eigen_ratio: float = 0.3  # a corner's smaller over larger structure-tensor eigenvalue (below: an edge)
    fb_px: float = 0.5  # forward-backward flow check
    max_parallax_px: float = 20.0  # a step departs from the rotation's prediction by at most this ...
    # ... where the spin's median step turns this much or less (240+ frames per turn); larger steps in proportion
    parallax_ref_step_deg: float = 1.5
    min_frames: int = 4  # shorter tracks are dropped
    loop_min_turn_deg: float = 270.0  # a frame this far into the turn past an earlier one may close the loop ...
    loop_max_deg: float = 15.0  # ... with the earlier frame closest in rotation, if within this
    loop_every: int = 2  # ... every this many frames (0: no loop closure)
    loop_parallax_px: float = 40.0  # ... its corners this far from the rotations' prediction at most
    anchor_sigma_rel: float = 0.01  # with points the line-fixed centres are anchors within this share of the diameter
    anchor_sigma_deg: float = 0.1  # ... and their rotations within this
    relative_sigma_deg: float = 0.05  # std of the refined rotations' relative rotation between neighbouring frames
    # each frame the points place is also held to its preprocessed (vanishing-point) rotation within this (deg; 0:
    # off), kept where the point tracks fit that placement within vp_fit_ratio times the free one's; see
    # docs/decisions.md#vanishing-point-rotations-in-the-placement
    vp_sigma_deg: float = 0.2
    vp_fit_ratio: float = 1.05
    vp_min_horizontal: int = 2  # ... only frames with this many horizontal Manhattan segments (they fix the heading)
    reject_px: float = 1.0  # a track whose RMS residual exceeds this after a solve is dropped and the graph solved again
    reject_rounds: int = 3  # ... at most this many times
    sigma_px: float = 0.3  # std of a point observation in the motion model's graph (Huber, robust_k)
    robust_k: float = 1.345
    max_error_px: float = 30.0  # a point triangulated more than this off a line-fixed frame's observation is dropped
    per_frame_graph: int = 40  # point observations per frame in the graph (the tracks spanning the most frames)
    # ... and in the bundle adjustment with the points joined (0: every observation); see
    # docs/decisions.md#every-point-in-the-joint-solve
    per_frame_joint: int = 0


@dataclass(frozen=True)
class NormalsConfig:
    """Paper §3.2: per-frame surface normals (model, orientation-map or oracle)."""

    # "orientation-map" | "model" | "oracle"; the shipped model is better on exact circles but worse on swaying spins,
    # see docs/decisions.md#normal-network
    source: str = "orientation-map"
    model_path: str | None = None  # a user's own ONNX model (see README)
    width: int = 256  # normal maps are computed at this width (aspect kept)
    # orientation map: the maps of the frames whose optical axes are within this (deg) are warped and vote (0: each
    # frame alone, Lee et al.); see docs/decisions.md#orientation-map-fusion
    fuse_deg: float = 10.0
    # ... the winning axis needs this share of the frames that label the pixel (0.8: within noise); see
    # docs/decisions.md#orientation-map-vote-share
    fuse_share: float = 0.6
    # ... on a slow spin only every k-th of those frames votes, k = round(this / the median step between frames, deg),
    # so that the work per frame stays that of a 300-frame spin (0: every frame); see
    # docs/decisions.md#orientation-map-fusion-stride
    fuse_step_deg: float = 1.25
    # streaming: an old frame's map is made again where its camera-frame Manhattan axes moved more than this (deg)
    # since it was made (its fusion neighbourhood grown or not); see docs/decisions.md#streamed-normals
    stream_keep_deg: float = 0.5


@dataclass(frozen=True)
class RelationsConfig:
    """Paper §3.2 'Geometric relationship detection'."""

    orthogonal: bool = True  # detect orthogonal coplanarities (paper)
    # parallel coplanarities off in the pipeline (our deviation; tools/bench_relations.py still measures them): the
    # solves do better without them, see docs/decisions.md#parallel-coplanarity
    parallel: bool = False
    junction: bool = True  # detect junctions (paper)
    floor: bool = True  # detect floor relations (paper)
    quad_normal_deg: float = 20.0  # mean normal in the quad within this of the expected direction
    quad_deviation_deg: float = 5.0  # mean deviation of the quad's normals below this
    junction_dist_frac: float = 0.1  # endpoints within this * min(w, h)
    floor_normal_deg: float = 25.0  # floor pixels: normal within this of vertical
    # candidate pairs for quad tests: midpoints within this * min(w, h); see docs/decisions.md#quad-settings
    max_pair_dist_frac: float = 0.5
    # a quad needs a normal on this share of its area; see docs/decisions.md#quad-settings
    quad_valid_share: float = 0.5
    # junction checks beyond the paper (0 / False: the paper's endpoint test only); see
    # docs/decisions.md#junction-corner-test
    junction_corner_frac: float = 0.03  # both endpoints within this * min(w, h) of the lines' intersection (an L)
    junction_normals: bool = True  # the quad inside the L passes the orthogonal normal test too
    # no Manhattan segment longer than this * min(w, h) may lie inside an orthogonal/parallel quad (0: paper); see
    # docs/decisions.md#crossed-quad
    quad_clear_frac: float = 0.05
    # points along each segment for that test (1: its mid-point only); see docs/decisions.md#quad-clear-samples
    quad_clear_samples: int = 9
    # junctions detected in fewer frames than this are dropped (1: the paper); see docs/decisions.md#junction-support
    junction_min_support: int = 2
    # option: drop an orthogonal/parallel pair whose face would run to the side its lines' L-junctions rule out (False:
    # the paper); off: worse on swaying spins, see docs/decisions.md#junction-sides
    junction_sides: bool = False
    # a junction's ends at the corner must lie more than this (px) inside the image: the frame's edge cuts lines, it
    # makes no corner (0: anywhere); see docs/decisions.md#junction-border
    junction_border_px: float = 2.0
    # option: coplanarities on a vertical plane must agree with where their segments meet the floor, within this *
    # min(w, h) (0: off, the paper); off: worse on swaying spins, see docs/decisions.md#floor-contacts
    floor_contact_frac: float = 0.0
    floor_contact_propagate: bool = False  # ... cannot-links also veto coplanarities joining their tracks' planes
    floor_contact_min_frames: int = 3  # ... a track pair contradicted in this many frames is a cannot-link
    floor_hanging_frac: float = 0.03  # ... no floor relation for a line a vertical this long hangs from (a cabinet top)
    t_junction_frac: float = 0.03  # ... a horizontal ending on the inside of a vertical (a T) is behind it


@dataclass(frozen=True)
class LinearConfig:
    """Paper §3.3 'Linear SfM formulation'."""

    colinearity_weight: float = 1.0  # weight of the colinearity rows (paper)
    coplanarity_weight: float = 1.0  # weight of the coplanarity rows (paper; 0: none)
    # option: solve from the tracks and the floor alone, coplanarities only where that registers fewer than
    # tracks_first_share of the frames they do (False: the paper); off: worse on kept-back bedrooms, see
    # docs/decisions.md#tracks-first
    tracks_first: bool = False
    tracks_first_share: float = 0.8
    floor_weight: float = 1.0  # weight of the floor rows (paper)
    min_depth_m: float = 0.3  # lower bound on every depth (lambda > 0)
    camera_height_m: float | None = None  # metric scale: floor this far below the mean camera height
    zero_translation: bool = False  # the paper's baseline: all camera centres fixed at the origin
    # zero baseline (our addition): below this median drift (px) of tracked segments off their track's plane through
    # the camera, the spin has no measurable parallax and is solved with one shared centre, every frame output (0:
    # never); see docs/decisions.md#zero-baseline
    zero_baseline_px: float = 3.0
    zero_baseline_min_turn_deg: float = 20.0  # ... only tracks seen over this much turn measure it
    # ... and not where the 90th percentile of the drift reaches this (the near lines of a big room show the arm); see
    # docs/decisions.md#zero-baseline-by-the-near-lines
    zero_baseline_p90_px: float = 8.0
    # register a frame only if its lines' interpretation-plane normals span 3D this well (smallest eigenvalue of their
    # scatter; the BA's determinacy test still applies); see docs/decisions.md#min-view-eigenvalue
    min_view_eig: float = 0.005
    # Cauchy IRLS rounds on the coplanarity rows against false relations (0: plain least squares, the paper); see
    # docs/decisions.md#robust-linear-solve
    robust_iterations: int = 3
    # relations whose IRLS weight ends below this (a residual over 7 robust sigmas) are not given to the bundle
    # adjustment (Solution.relations_kept; 0: all are); see docs/decisions.md#reject-weight
    reject_weight: float = 0.1
    # IRLS also downweights observations far off their track's line (impure tracks); see
    # docs/decisions.md#robust-observations
    robust_observations: bool = False
    robust_k: float = 2.385  # Cauchy constant, in robust sigmas (1.4826 * median |residual|)
    floor_tolerance: float = 0.0  # IRLS: floor lines this share of the camera-to-floor distance ABOVE the floor are downweighted (0: never)
    # body-motion prior on consecutive centres (rows in m, like colinearity; sigma_c / sigma_accel; 0: paper), for
    # fragmented tracks; see docs/decisions.md#motion-prior
    motion_weight: float = 0.3
    motion_order: int = 2  # 2: velocity constant in a frame turning with the camera heading (linear/priors.py); 1: T_a - T_b ~ 0
    motion_max_gap: int = 3  # frames: no motion row across a larger gap between registered frames
    # anchor frames (fixed on every axis by their own lines) this many degrees of turn apart or closer are linked by
    # the motion prior, the frames between them registered (0: off; the steady style uses 90); see
    # docs/decisions.md#motion-bridging and docs/decisions.md#steady-bridge
    motion_bridge_deg: float = 0.0
    # spin model rows (our addition): sigma of a colinearity row / sigma of a centre off the circle the phone describes
    # about a slowly wandering stand point (~2.5 mm / 1.2 cm; 0: off, the paper); see docs/decisions.md#spin-prior
    spin_weight: float = 0.2
    spin_vertical_ratio: float = 1.0  # ... the vertical row's weight relative to the horizontal ones
    spin_knot_deg: float = 90.0  # ... the stand point is interpolated between knots this turn apart (0: one stand point)
    spin_walk_ratio: float = 1.0  # ... rows tying neighbouring knots, weight relative to spin_weight
    # ... without a verified floor the solve is scaled so that the spin's arm is this long (m), so that the BA's
    # sigmas in metres hold (0: mean depth 1); see docs/decisions.md#arm-units
    spin_arm_m: float = 0.35
    # option: the spin model places a group of frames the lines link along one horizontal axis but not the other (use
    # with spin_knot_deg 0 here and in graph); off: worse on swaying spins, see docs/decisions.md#spin-links
    spin_links: bool = False
    # option: the spin model holds the height of a frame whose lines do not (with graph.spin_height); off: worse
    # worst captures, see docs/decisions.md#spin-height
    spin_height: bool = False
    # floor relations whose line lies less than this share as deep below the cameras as the deepest floor candidates
    # are furniture tops, dropped (0: keep all, the paper); see docs/decisions.md#floor-verification
    floor_verify_ratio: float = 0.85
    # fewer verified floor lines (distinct tracks) than this: they are dropped too, the scale reported arbitrary;
    # see docs/decisions.md#min-floor-lines
    min_floor_lines: int = 1


@dataclass(frozen=True)
class GraphConfig:
    """Paper §3.4 'Bundle adjustment' (three phases) in GTSAM."""

    colinearity: bool = True  # colinearity factors (switches: the factor ablation)
    coplanarity_orthogonal: bool = True  # orthogonal coplanarity factors
    coplanarity_parallel: bool = True  # parallel coplanarity factors (the relations stage detects none by default)
    coplanarity_junction: bool = True  # junction factors
    coplanarity_floor: bool = True  # floor factors
    reprojection: bool = True  # line reprojection factors (without them nothing registers)
    imu_prior: bool = True  # IMU relative-rotation factors
    # colinearity / coplanarity weight relative to reprojection (paper); see docs/decisions.md#relation-weight
    relation_weight: float = 1e4
    reprojection_sigma_px: float = 1.0  # std of a line observation's reprojection residual (px)
    # kernel on each line observation's reprojection residual ("none" | "huber" | "cauchy" | "geman_mcclure"; our
    # addition: a track jumping between two crossing edges bends the poses); see docs/decisions.md#reprojection-kernel
    reprojection_robust: str = "geman_mcclure"
    reprojection_robust_k: tuple[float, ...] = (3.0, 3.0, 3.0)  # ... threshold in sigmas in phases 1, 2, 3 (0: none)
    # ... in phase 1 this times the initial (linear solve's) RMS residual in sigmas, within [that threshold, k_max]:
    # graduated, the kernel starts as wide as the residuals are
    reprojection_robust_widen: float = 2.5
    reprojection_robust_k_max: float = 10.0
    imu_sigma_deg: float = 0.2  # relative-rotation prior between neighbouring frames
    # kernel on the relation factors ("none" | "huber" | "cauchy" | "geman_mcclure": caps a false relation's cost at
    # k^2/2); see docs/decisions.md#ba-relation-kernel
    robust: str = "geman_mcclure"
    robust_k: float = 1.345
    # scale gauge: the best-observed line's distance from the first camera is held (False: the floor height); the
    # result is rescaled to the linear solve's camera height either way; see docs/decisions.md#scale-line-gauge
    scale_line_gauge: bool = True
    support_weighting: bool = True  # relation sigma / sqrt(frames the relation was detected in)
    phases: tuple[int, ...] = (1, 2, 3)  # 1: lines+translations, 2: +rotations, 3: +intrinsics
    # phase 3 refines a focal length camera.json gives as well (False: only an estimated one; panosfm run
    # --refine-focal); see docs/decisions.md#a-given-focal-length-kept
    refine_given_focal: bool = False
    max_iterations: int = 30  # Levenberg-Marquardt iterations per solve
    # option: coplanarities checked against a first solve without them (False: off, worse on kept-back offices); see
    # docs/decisions.md#relation-check
    verify_relations: bool = False
    verify_sigma: float = 2.0  # ... dropped when their lines lie further apart than verify_sigma * std
    verify_tolerance: float = 0.0  # ... + verify_tolerance * median camera-to-line distance
    verify_start_share: float = 0.75  # ... and the BA starts from that solve if it fixes this share of the frames
    # spin prior (our addition; factors/spin_prior.py): std of a centre off the circle the phone describes about a
    # slowly wandering stand point, one arm for the whole sweep (m; 0: off, the paper); see
    # docs/decisions.md#ba-spin-prior-sigma
    spin_sigma_m: float = 0.02
    spin_vertical_ratio: float = 1.0  # ... the vertical std relative to the horizontal one
    spin_robust: str = "huber"  # ... its kernel (k = robust_k)
    spin_knot_deg: float = 90.0  # ... the stand point is interpolated between knots this turn apart (0: one stand point)
    spin_walk_sigma_m: float = 0.05  # ... std of the stand point's step between neighbouring knots (m)
    spin_height: bool = False  # ... holds the height of a frame whose lines do not (determinacy; see linear.spin_height)
    # ... holds every coordinate of a frame (determinacy), so a steady spin's bridged frames stay registered
    # (SPIN_STYLES 'steady'); see docs/decisions.md#steady-spin-style
    spin_position: bool = False
    # a steady solve whose centres lie further than this share of the arm off one circle (RMS) warns, and the auto
    # style rejects it; see docs/decisions.md#auto-spin-style
    steady_max_rms_arm: float = 0.022
    # auto spin style (our addition; graph.steady_or_hand_held): where the hand-held solve leaves frames unregistered,
    # solve again as a steady spin and keep it if its centres pass steady_max_rms_arm (False: the style as set); see
    # docs/decisions.md#auto-spin-style
    steady_auto: bool = True
    # motion model (our addition; graph.place_by_motion_model): frames the lines leave without a pose are placed by
    # the spin model and their own observations of the adjusted lines, kept where their centre's largest std is at
    # most motion_max_sigma_rel of the spin's diameter (False: line-fixed frames only, panosfm run --strict); see
    # docs/decisions.md#motion-model-placement
    motion_model: bool = True
    motion_max_sigma_rel: float = 0.025
    # with point tracks the spin is also placed by the points alone (the line-fixed frames' rotations as anchors);
    # where the line-fixed centres lie further than this share of the diameter (median, after a scale and a shift)
    # from the points', the points' poses are kept and the lines triangulated again at them (0: off); see
    # docs/decisions.md#lines-or-points
    motion_lines_points_max_rel: float = 0.01
    # ... unless the point tracks fit the line-fixed frames' poses within this ratio (or this many px more) of their fit
    # to their own placement on those frames: then the lines' poses are kept (0: off); see
    # docs/decisions.md#lines-checked-by-the-points
    motion_lines_points_fit_ratio: float = 1.5
    motion_lines_points_fit_slack_px: float = 0.3
    # ... and where they agree, the spin placed again anchored by the line-fixed frames (False: the points' own
    # placement, moved onto the line-fixed frames, wherever it places every frame: a streamed preview's, see
    # graph.incremental_anchored); see docs/decisions.md#lighter-previews
    motion_anchored: bool = True
    # where the point tracks placed the frames, the lines triangulated at those poses are then bundle-adjusted with
    # the poses held: reprojection, colinearity and the kept coplanarity relations (False: triangulated only); see
    # docs/decisions.md#lines-at-held-poses
    lines_held_poses: bool = True
    # the bundle adjustment solved once more with the point tracks joined (graph/joint_points.py), kept unless the
    # lines' RMS reprojection grows more than this ratio (0: off); see docs/decisions.md#points-in-the-bundle-adjustment
    points_joint_max_line_rms_ratio: float = 3.0
    # metric scale: the floor moves down to the deepest horizontal line seen in at least this many frames (0: off);
    # see docs/decisions.md#floor-below-lines
    floor_below_lines_min_obs: int = 3
    # metric scale checked against the spin's arm (m): outside this range the floor was a furniture top, and the model
    # is scaled to metric_arm_fallback_m and reported not metric ((0, 1e9): off); see docs/decisions.md#arm-check
    metric_arm_range_m: tuple[float, float] = (0.15, 0.55)
    metric_arm_fallback_m: float = 0.35  # ... the arm then (m; as linear.spin_arm_m)
    metric_arm_min_turn_deg: float = 90.0  # ... checked only where the registered frames span this much turn (deg)
    # the BA is solved again at the final scale where the scale checks rescaled it by more than this ratio either way,
    # kept where it fits the images no worse (0: off); see docs/decisions.md#resolve-at-final-scale
    resolve_scale_ratio: float = 1.25
    reject_sigma: float = 5.0  # drop relations whose residual exceeds this many sigmas, then resolve
    incremental_batch: int | None = None  # frames per batch for incremental solves
    # the last streamed batch solved as the one-shot run does, from the streamed segments, point tracks and normals
    # (False: the warm-started batch's estimate is the result); see docs/decisions.md#streaming-final-solve
    incremental_final_solve: bool = True
    # a streamed batch before the last runs the joint solve with the point tracks too (False: its estimate, a
    # preview, is the motion model's; the last batch runs it); see docs/decisions.md#previews-without-the-joint-solve
    incremental_joint: bool = False
    # ... and joins this many point observations per frame to it (0: all, as the last batch and one-shot do); see
    # docs/decisions.md#streamed-point-tracks
    incremental_points_per_frame: int = 40
    # ... tries the steady spin style (with point tracks; False: hand-held, the points place what the lines leave) and
    # places the spin anchored by the line-fixed frames (False: motion_anchored off); the last batch does both; see
    # docs/decisions.md#lighter-previews
    incremental_steady: bool = False
    incremental_anchored: bool = False
    # phases >= 2: absolute prior at the preprocessed (vanishing-point) rotations (deg; 0: off); see
    # docs/decisions.md#rotation-prior
    rotation_prior_sigma_deg: float = 0.1
    # a zero-baseline spin (linear.zero_baseline_px) adjusts its rotations and lines about the one shared centre
    # (graph/rotation_only.py; False: the linear solve's rotations, the preprocessed ones); see
    # docs/decisions.md#zero-baseline-rotations
    zero_baseline_rotations: bool = True
    # option: that prior turned by a heading-drift ramp the BA estimates, prior on the ramp's total (deg; 0: off);
    # off: the lines do not fix the slope, see docs/decisions.md#heading-drift-slope-in-the-ba
    heading_drift_sigma_deg: float = 0.0
    focal_max_sigma_frac: float = 0.002  # phase 3 refines the focal only if its marginal std is below this share of it
    max_line_sigma_m: float = 0.1  # lines whose position std (from their factors) exceeds this are marked invalid
    # ... and those whose far end lies beyond this times the median line's from the spin's centre (0: off); see
    # docs/decisions.md#lines-beyond-the-room
    max_line_distance_ratio: float = 4.0
    max_center_sigma_m: float = 0.1  # frames whose centre std (from their observations) exceeds this are unregistered


@dataclass(frozen=True)
class VerifyConfig:
    """Every result checked against independent evidence, with an honest std per frame (our addition, issue #63;
    graph.reliability). Stds are shares of the spin's diameter; the scales are calibrated on the procedural rooms
    (tools/calibrate_sigma.py, docs/decisions.md#honest-sigma)."""

    enabled: bool = True
    # a frame's std (graph.reliability.combine_evidence): each evidence scaled to a median predictor of its error
    # (the motion model's marginal times model_ratio; the distance to the nearest independent solution, the larger of
    # its own and its median over evidence_window of the frames about it, times gap_ratio; the distance to the one
    # independent of the frame's own source times other_ratio), the first two's geometric mean, never under the third,
    # times a scale per source so that 3 stds cover 96 % of that source's frames' errors on 50 procedural rooms
    model_ratio: float = 1.032
    gap_ratio: float = 0.748
    other_ratio: float = 0.598
    evidence_window: float = 0.05
    lines_scale: float = 1.353  # ... the line-fixed frames'
    points_scale: float = 1.022  # ... the frames the point tracks placed
    motion_scale: float = 1.817  # ... the motion model's and the steady circle's
    floor_sigma_rel: float = 0.002  # every frame's std is at least this
    fallback_sigma_rel: float = 0.01  # a frame without any evidence
    points_check: bool = True  # place the spin by the point tracks alone where the pipeline did not, to compare
    flag_sigma_rel: float = 0.05 / 3  # a frame whose std exceeds this is doubtful (3 stds within an accurate 5 %)
    max_sigma_rel: float = 0.10  # ... beyond this it is left out
    # a frame this far (share of the diameter) from the nearest independent solution is doubtful whatever its std (0:
    # off); see docs/decisions.md#a-frame-far-from-every-solution
    max_gap_rel: float = 0.04
    # where doubtful frames are at most this share of a run's frames and nothing else casts doubt on it, they are left
    # out and the run is trusted (a trusted run vouches for every frame it outputs); more: kept, flagged, run doubtful
    max_doubtful_share: float = 0.1
    # in a doubtful run, frames no solution independent of their own source places are doubtful too (False: only by
    # their std); see docs/decisions.md#a-doubtful-run-vouches-only-for-checked-frames
    doubt_unchecked: bool = True
    max_rotation_gap_deg: float = 1.0  # a rotation this far from every other estimate of it is doubtful
    max_lines_points_rel: float = 0.03  # the lines' and the points' solutions this far apart: the run is doubtful,
    # unless the point tracks refute the lines' solution (their residual at its poses over refute_ratio times theirs
    # at their own and refute_slack_px more: graph.motion_model.lines_fit_points); then it contradicts no frame
    refute_ratio: float = 1.5
    refute_slack_px: float = 0.3
    # a frame whose rotation relative to its neighbours (within imu_window_frames) departs from the IMU's by more than
    # this is doubtful: the IMU drifts over the spin, not over a few frames
    max_imu_gap_deg: float = 1.0
    imu_window_frames: int = 5
    # a focal length camera.json gives is checked against the vanishing points' (lines.focal, 0.2-1.4 s): where they
    # fix it (sharpness at least focal_min_sharpness) and it lies more than max_focal_gap off, the run is doubtful
    focal_check: bool = True
    focal_min_sharpness: float = 1.1
    max_focal_gap: float = 0.05
    # --strict: keep only frames that an independent solution confirms (within 3 of their stds)
    strict: bool = False


@dataclass(frozen=True)
class Config:
    """The whole pipeline's settings; ``summary.json`` records the exact config used."""

    capture: CaptureConfig = field(default_factory=CaptureConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    manhattan: ManhattanConfig = field(default_factory=ManhattanConfig)
    focal: FocalConfig = field(default_factory=FocalConfig)
    rotation: RotationConfig = field(default_factory=RotationConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    points: PointsConfig = field(default_factory=PointsConfig)
    normals: NormalsConfig = field(default_factory=NormalsConfig)
    relations: RelationsConfig = field(default_factory=RelationsConfig)
    linear: LinearConfig = field(default_factory=LinearConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    verify: VerifyConfig = field(default_factory=VerifyConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def with_overrides(config: Config, **sections: dict[str, Any]) -> Config:
    """Returns a copy of ``config`` with fields of its sections replaced.

    ``with_overrides(cfg, relations={"floor": False}, graph={"robust": "none"})``
    """
    changes = {}
    for name, values in sections.items():
        sub = getattr(config, name)
        changes[name] = dataclasses.replace(sub, **values)
    return dataclasses.replace(config, **changes)


# Spin styles (``panosfm run --spin``; our addition). "hand-held" places a frame only where its own lines fix it, the
# stand point wandering between knots 90 degrees of turn apart. "steady" has one stand point for the whole sweep and
# places the frames between two that their lines fix (at most 90 degrees apart) on its circle: for spins that really
# stay put (a rotating arm, a turntable); on a swaying spin it is wrong by the sway. See
# docs/decisions.md#steady-spin-style and docs/decisions.md#auto-spin-style.
SPIN_STYLES: dict[str, dict[str, dict[str, Any]]] = {
    "auto": {},  # the defaults: hand-held, and steady where the centres say so (graph.steady_auto)
    "hand-held": {"graph": {"steady_auto": False}},
    "steady": {
        "linear": {"spin_knot_deg": 0.0, "motion_bridge_deg": 90.0},
        "graph": {"spin_knot_deg": 0.0, "spin_position": True, "steady_auto": False},
    },
}


def with_spin_style(config: Config, style: str) -> Config:
    """Returns ``config`` set for a spin style of :data:`SPIN_STYLES` ("hand-held": unchanged, "steady")."""
    if style not in SPIN_STYLES:
        raise ValueError(f"unknown spin style {style!r} (one of {', '.join(SPIN_STYLES)})")
    return with_overrides(config, **SPIN_STYLES[style])
