"""Configuration: one frozen dataclass tree whose defaults are the paper's values.

Thresholds carry their unit in their name (``merge_angle_deg``,
``junction_dist_frac`` = a fraction of ``min(width, height)``). An ablation is
a list of configs: switch relation types and factor types here, never in code.
``dataclasses.replace`` (or :func:`with_overrides`) derives variants.
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
    iterations: int = 3  # alternate extraction / labelling / rotation refinement
    vertical_search_deg: float = 10.0  # the vertical peak is searched this close to gravity
    min_segments: int = 20  # fewer (Manhattan) segments than this: TooFewLinesError


@dataclass(frozen=True)
class RotationConfig:
    """Supplement §2 (rotation refinement, Eq. 1)."""

    imu_weight: float = 1.0  # lambda of the IMU relative-rotation term (paper 0.1 with unweighted residuals)
    neighbour_angle_deg: float = 10.0  # frames whose optical axes differ less than this are neighbours
    max_neighbours: int = 8  # per frame, nearest in time first (keeps the graph sparse)
    max_iterations: int = 20
    huber_deg: float = 0.5  # Huber threshold on the Eq. 1 data residual (0: plain least squares as in the paper)
    gravity_sigma_deg: float = 0.5  # prior on each frame's IMU gravity direction (0: off, as in the paper)
    # IMU heading drift (a gyro bias) modelled as a polynomial in time of this degree, fitted to the
    # heading corrections of the frames with horizontal Manhattan lines and removed from the IMU
    # before its relative rotations are used (-1: off, as in the paper)
    drift_degree: int = 1
    # ... fitted with each frame that has horizontal Manhattan lines weighing one ("frames") or by their total
    # length ("length"): frames crowded with one object's lines, biased alike, would carry the fit
    drift_weights: str = "frames"
    # ... and frames a turn apart whose optical axes lie within this (deg; a spin's two ends) give the drift between
    # them directly, rows of this weight (relative to a frame's): the lines both see bias both alike (0: off).
    # Measured (refined rotations of the 45 benchmark captures, mean of their median errors): off 0.087, 1 deg
    # 0.081, 2 deg 0.080, 3 deg 0.080 deg; through the pipeline see README (status)
    drift_loop_deg: float = 3.0
    drift_loop_weight: float = 10.0
    # in the last refinement each frame is held to the IMU with that drift removed, with this weight (as
    # imu_weight; 0: off, the paper): once its gyro bias is removed the IMU's attitude is good to about its
    # noise; where the lines' vanishing points mislead (a wardrobe's thin top, its two edges fitted as one line
    # 1-4 degrees off, over 60 frames of a bedroom) the heading is not carried off along the relative rotations.
    # Measured (tools/bench.py --seeds 5, with drift_weights "frames"; rotation medians living/bedroom/office):
    # selection 0.069/0.117/0.096 -> 0.064/0.072/0.068 deg, kept back 0.083/0.088/0.108 -> 0.061/0.077/0.082,
    # swaying 0.069/0.079/0.100 -> 0.062/0.072/0.065, none of the 45 captures worse (other weights, measured
    # on the preprocessing alone: README, status)
    heading_weight: float = 10.0


@dataclass(frozen=True)
class TrackingConfig:
    """Supplement §3 (line tracking)."""

    axis_angle_deg: float = 2.0  # match frames whose optical axes are within this angle
    match_dist_frac: float = 0.05  # smallest endpoint-to-line distance < this * min(w, h)
    match_angle_deg: float = 1.0  # angle difference between matched segments
    min_track_length: int = 2  # tracks with fewer segments are dropped
    bridge_angle_deg: float = 0.0  # >0: also link track ENDS across frames whose axes are within this (0: paper)
    # loop closure (tracking.loop_pairs): frames a turn (180 degrees or more) apart whose axes are within this are
    # matched too, so that a line both ends of the spin see is one track (0: off, the paper). Off: measured at 6
    # (tools/bench.py --seeds 5, living/bedroom/office): ideal circles registered 97/23/85 -> 97/23/87 %, centre
    # err. 1.16/0.65/1.11 -> 0.95/0.56/1.00 %, worst 2.4 -> 1.7 %; but on spins swaying 5 cm 96/31/57 -> 97/35/81 %,
    # 1.18/1.03/1.57 -> 1.49/1.03/1.43 %, living capture 3 0.57 -> 2.71 % at 2.3 px: the loop registers its first
    # frames, and the linear solve places frame 0 (the gauge, held by the BA) 0.5 m from frame 1
    loop_angle_deg: float = 0.0
    match_angle_px: float = 1.0  # >0: angle tolerance max(match_angle_deg, atan(this / shorter length)) (0: paper)
    colinear_px: float = 1.0  # >0: colinear pieces of one frame (within this) are matched as one (0: paper)
    match_gap_frac: float | None = 0.0  # matched segments overlap along the line up to a gap of this * min(w, h) (None: paper)
    # refine each frame pair's rotation homography by the image shift that best aligns its first matches,
    # then match again (the paper refines its homography by image features); 0: off
    shift_min_matches: int = 4
    # segments whose polarities (grey levels, Segments.contrast) both exceed this and disagree never
    # match: a trim's two sides, 2-4 px apart, are as close as neighbouring frames' parallax; 0: off
    polarity_min: float = 8.0
    # colinear pieces of one frame are grouped by their vanishing-point lines (colinear_groups), not by their
    # own endpoints (whose angle is ~1 degree off on a 60 px piece); False: the endpoint test
    vp_colinear: bool = True
    # a match whose mid-point, after the image shift that best aligns the pair's matches, is farther than this (px)
    # from the other segment's vanishing-point line is a jump to a neighbouring line, not kept (tracking.line_jumps;
    # needs the Manhattan directions; 0: off). Measured: README (status)
    jump_px: float = 3.0
    # tracks of one axis that end and start at most this many frames apart are joined when their
    # interpretation-plane angles, fitted linearly over frames, agree within merge_tol_px (0: off). Measured
    # with the spin prior (tools/bench.py --seeds 5, registered living/bedroom/office, centre err. medians):
    # 96/18/50 % at 1.53/0.70/0.61 % -> 96/23/78 % at 1.46/0.69/1.65 %; kept-back seeds 94/41/78 % ->
    # 94/41/82 %, swaying spins 95/16/51 % -> 95/29/52 %, no capture worse than 10 % (tolerance 3 px: one)
    merge_gap_frames: int = 3
    merge_tol_px: float = 2.0
    merge_overlap: bool = False  # ... and tracks whose spans overlap (two pieces of one line followed side by side)
    merge_image_px: float = 3.0  # ... and each fit passes this close (px) to the other track's nearest segment (0: off)
    # tracks whose longest segment is shorter than this * min(w, h) are dropped (surface texture); 0: off
    min_longest_frac: float = 0.0


@dataclass(frozen=True)
class NormalsConfig:
    """Paper §3.2: per-frame surface normals (model, orientation-map or oracle)."""

    # "orientation-map" | "model" | "oracle". The shipped model is right on more pixels (tools/bench_normals.py:
    # 77 % of all pixels within 20 deg vs the orientation map's 44 %, which labels only half). Through the
    # pipeline it wins on the exact-circle spins (kept back: centres 0.57/0.47/0.49 -> 0.49/0.45/0.46 %, living 1
    # 60 -> 100 % registered) and loses on the swaying ones (tools/bench.py --sway 0.05: 1.03/0.88/1.16 ->
    # 1.62/1.05/1.29 %), which are what people film, so it is not the default.
    source: str = "orientation-map"
    model_path: str | None = None  # a user's own ONNX model (see README)
    width: int = 256  # normal maps are computed at this width (aspect kept)
    # orientation-map: fuse the maps of the frames whose optical axes are within this angle (rotation
    # homography, majority vote); 0: each frame alone (Lee et al.). Measured (tools/bench.py --seeds 3,
    # medians living/bedroom/office): centre error 12.0/1.4/0.6 -> 7.9/1.1/0.5 % (5 deg: coverage
    # 0.50 -> 0.57; 15 and 20 deg: worse reprojection on living)
    fuse_deg: float = 10.0
    # ... the winning axis needs this share of the frames that label the pixel. 0.8 (measured 2026-12-04): relation
    # precision orthogonal .75/.73/.76 -> .76/.76/.77, junction .83/.92/.83 -> .84/.96/.84, recall up 0.01-0.04;
    # end to end within noise (tools/bench.py --seeds 5, medians selection 0.46/0.46/0.44 -> 0.43/0.46/0.44 %,
    # kept back 0.57/0.47/0.49 -> 0.55/0.46/0.50, swaying 1.03/0.88/1.16 -> 1.02/0.68/1.22; swaying bedroom 4
    # 0.97 -> 1.92 %, living 2 1.79 -> 1.09 %), so unchanged
    fuse_share: float = 0.6


@dataclass(frozen=True)
class RelationsConfig:
    """Paper §3.2 'Geometric relationship detection'."""

    orthogonal: bool = True
    # parallel coplanarity is off in the pipeline (tools/bench_relations.py still detects and measures it), our
    # deviation: with orientation-map normals 69-72 % of the pairs are true (a wall line and the parallel
    # edge of furniture in front of it), and the solves do better without them. Measured (tools/bench.py
    # --seeds 5, medians living/bedroom/office): centre err. 1.46/0.69/1.65 -> 1.15/0.66/1.37 %, worst
    # capture 6.7 -> 3.6 %; kept-back seeds (--seed 50) 1.98/0.69/1.92 -> 1.06/0.71/1.50 %; registration
    # unchanged within 1 %; swaying spins (--sway 0.05) about even: 1.26/1.12/1.90 -> 1.05/1.18/1.93 %,
    # registered office 52 -> 49 %. A tiny spin (100 frames at 320x180) registers 2 frames with them, 0 without
    parallel: bool = False
    junction: bool = True
    floor: bool = True
    quad_normal_deg: float = 20.0  # mean normal in the quad within this of the expected direction
    quad_deviation_deg: float = 5.0  # mean deviation of the quad's normals below this
    junction_dist_frac: float = 0.1  # endpoints within this * min(w, h)
    floor_normal_deg: float = 25.0  # floor pixels: normal within this of vertical
    max_pair_dist_frac: float = 0.5  # candidate pairs for quad tests: midpoints within this * min(w, h)
    quad_valid_share: float = 0.5  # a quad needs a normal on this share of its area (0.95: orientation-map
    # orthogonal precision 0.45-0.55 -> 0.73-0.84, but end to end fewer frames register)
    # junction checks beyond the paper (0 / False: the paper's endpoint test only)
    junction_corner_frac: float = 0.03  # both endpoints within this * min(w, h) of the lines' intersection (an L)
    junction_normals: bool = True  # the quad inside the L passes the orthogonal normal test too
    # no Manhattan segment longer than this * min(w, h) may lie inside an orthogonal/parallel quad (0: paper)
    quad_clear_frac: float = 0.05
    # points along each segment for that test (1: its mid-point only). 9: a line running through the quad with
    # its mid-point outside counts too; oracle precision orthogonal .90/.83/.85 -> .92/.90/.86, parallel
    # .88/.84/.73 -> .94/.84/.74; end to end (tools/bench.py --seeds 5) corner reprojection 1.13/0.71/0.92 ->
    # 0.82/0.71/0.90 px (kept-back --seed 50: 0.88/0.89/0.85, unchanged)
    quad_clear_samples: int = 9
    # junctions detected in fewer frames than this are dropped (1: the paper). Measured 2026-12-04 (pooled over 9
    # captures, tools/bench_relations.py --seeds 3 --no-solve): junction precision oracle .959 -> .975, orientation
    # map .884 -> .929, model .922 -> .941, recall .45/.49/.26 -> .37/.40/.19; end to end (tools/bench.py --seeds 5,
    # medians living/bedroom/office) selection 0.46/0.46/0.44 -> 0.45/0.46/0.44 %, kept back 0.58/0.47/0.49 ->
    # 0.58/0.46/0.50 % (living 1 60 -> 100 % registered), swaying 1.03/0.88/1.16 -> 0.99/0.64/1.15 %. (An earlier
    # pipeline, 2026-11: worse end to end, 10.7/1.2/1.2 -> 11.1/1.2/3.8 %.)
    junction_min_support: int = 2
    # Option (False: the paper): an orthogonal/parallel pair whose face would run from one of its lines to the side
    # opposite the one that line's junctions show (relations.face_sides, junction_sided) is dropped. Measured
    # 2026-12-04 (tools/bench_relations.py --seeds 3, pooled over 9 captures): detected precision orthogonal oracle
    # .867 -> .898, orientation map .729 -> .766, model .863 -> .888 (recall .45/.46/.27 -> .44/.45/.27), parallel
    # .841/.704/.797 -> .941/.777/.818; kept by the pipeline, orthogonal .874/.775/.880 -> .907/.800/.897 (recall
    # .39/.43/.22 -> .40/.43/.24), floor .52/.27 -> .65/.31. End to end (tools/bench.py --seeds 5, medians living /
    # bedroom / office) selection 0.45/0.46/0.44 -> 0.49/0.45/0.42 %, kept back 0.58/0.46/0.50 % either way but
    # living 1 100 -> 60 % registered (three true sofa-arm-top pairs, the vertical link of 114 frames, vetoed
    # by doubtful junctions), swaying 0.99/0.64/1.15 -> 1.53/0.92/1.21 % (living 4 1.2 -> 6.1 %): off
    junction_sides: bool = False
    # ... and their ends at the corner must lie more than this inside the image (0: anywhere): the frame's edge
    # cuts lines, it makes no corner. tools/bench_relations.py --no-solve: junction precision, oracle
    # .95/.95/.94 -> .95/1.0/.94, orientation map .83/.92/.83 -> .86/.96/.83, model .92/.92/.86 -> .96/1.0/.86,
    # recall unchanged; end to end (tools/bench.py, 45 captures) unchanged within 0.06 % centre error
    junction_border_px: float = 2.0
    # Option (0: off, the paper): coplanarities on a vertical plane must agree with where their segments meet the
    # floor (relations.floor_consistent: verticals standing on the floor stand on the plane's one floor line, none
    # reaches below it), within this * min(w, h); the track pairs contradicted in floor_contact_min_frames frames
    # are cannot-links, and with floor_contact_propagate no coplanarity may join two cannot-linked tracks' planes
    # (relations.consistent_planes). Measured (0.01, T 0.03, hanging 0.03; README status): propagated from one frame,
    # oracle precision orthogonal .91/.88/.87 -> .93/.91/.88, parallel .96/.81/.64 -> .98/.84/.72, kept-back
    # captures 0.57/0.47/0.49 -> 0.50/0.46/0.51 %, but swaying ones 1.03/0.88/1.16 -> 1.43/0.91/1.20 % (9 of the 16
    # relations it dropped on swaying living 0 were true); direct only, from 3 frames: selection and kept back about
    # even, swaying bedroom 0.88 -> 0.64 %, but the swaying living room's lines 0.032 -> 0.048 m from the surfaces
    floor_contact_frac: float = 0.0
    floor_contact_propagate: bool = False
    floor_contact_min_frames: int = 3
    floor_hanging_frac: float = 0.03  # ... no floor relation for a line a vertical this long hangs from (a cabinet top)
    t_junction_frac: float = 0.03  # ... a horizontal ending on the inside of a vertical (a T) is behind it


@dataclass(frozen=True)
class LinearConfig:
    """Paper §3.3 'Linear SfM formulation'."""

    colinearity_weight: float = 1.0
    coplanarity_weight: float = 1.0
    # Option (off: the paper): solve from the tracks (colinearity, the body-motion prior) and the floor
    # alone, and use the coplanarities only when that registers fewer than ``tracks_first_share`` of the
    # frames they do; the bundle adjustment adds them in any case. A false coplanarity is satisfied here
    # by shrinking the camera motion that would show the depth difference (parts of the sweep collapsed
    # onto a point: living capture 30, 35 % centre error). Measured, with the BA's Geman-McClure kernel
    # (tools/bench.py --seeds 5, medians living/bedroom/office, captures worse than 10 %): selection seeds
    # 2.5/0.7/13.3 % (3 of 14) -> 4.3/0.8/1.0 % (3); unseen seeds (--seed 50) 1.8/5.3/1.9 % (2) ->
    # 1.4/12.2/2.0 % (6): worse on the bedroom, so off. With true relations (tools/bench_linear.py) the
    # paper's solve is far better (lines 0.1-0.3 cm vs 6-44 cm)
    tracks_first: bool = False
    tracks_first_share: float = 0.8
    floor_weight: float = 1.0
    min_depth_m: float = 0.3  # lower bound on every depth (lambda > 0)
    camera_height_m: float | None = None  # metric scale: floor this far below the mean camera height
    zero_translation: bool = False  # the paper's baseline: all camera centres fixed at the origin
    # register a frame only if its lines' interpretation-plane normals span 3D this well (smallest eigenvalue of their
    # scatter; the BA's 10 cm determinacy test still applies). 0.02 -> 0.005, measured (tools/bench.py --seeds 5,
    # registered living/bedroom/office, centre err. medians): selection 96/22/77 -> 97/23/85 %, 1.15/0.66/1.37 ->
    # 1.16/0.68/1.59 %; kept back 94/41/82 -> 96/44/85 %, 1.06/0.71/1.50 -> 1.20/0.71/1.34 %; swaying 95/31/49 ->
    # 96/33/57 %, 1.05/1.18/1.93 -> 1.05/1.27/2.10 %; no capture registers fewer, worst 5.5 % (was 5.5)
    min_view_eig: float = 0.005
    # IRLS rounds (Cauchy) on coplanarity rows against wrong relations; 0 = paper (plain LS). On an image-free problem
    # (tests/test_linear.py, 10 % false relations) 183 -> 40 mm (10 rounds: 8 mm, but swaying living 1.11 -> 1.99 %). On the pipeline's output (tools/bench_ba.py --real, seed 0, the linear
    # solve the result rests on, living/bedroom/office): oracle normals lines 2.0/3.1/11.4 -> 0.5/3.1/1.3 cm from the
    # surfaces, centres 0.39/0.46/1.82 -> 0.30/0.46/0.39 %; default normals 27/9.9/17.5 -> 1.9/3.0/2.2 cm, 3.1/0.9/4.7
    # -> 1.0/0.5/0.5 % (one false orthogonal pair bends the whole solve). Through the pipeline: README (status)
    robust_iterations: int = 3
    # relations whose IRLS weight ends below this (0.1: a residual over 7 robust sigmas) are not given to the bundle
    # adjustment (Solution.relations_kept; 0: all are). Measured: README (status)
    reject_weight: float = 0.1
    robust_observations: bool = False  # IRLS also downweights observations far off their track's line (impure tracks)
    robust_k: float = 2.385  # Cauchy constant, in robust sigmas (1.4826 * median |residual|)
    floor_tolerance: float = 0.0  # IRLS: floor lines this share of the camera-to-floor distance ABOVE the floor are downweighted (0: never)
    motion_weight: float = 0.3  # body-motion prior on consecutive centres (rows in m, like colinearity; sigma_c / sigma_accel); 0 = paper
    motion_order: int = 2  # 2: velocity constant in a frame turning with the camera heading (linear.py); 1: T_a - T_b ~ 0
    motion_max_gap: int = 3  # frames: no motion row across a larger gap between registered frames
    # anchor frames (fixed along every axis by their own lines) this many degrees of turn apart or closer are
    # linked by the motion prior, the frames between them registered (linear.py: Bridging; 0: off). Off: with
    # true tracks the bedroom registers 49 -> 100 % at 0.8 % error, but on the pipeline's tracks (bedroom capture 1)
    # the linear solve went 66 -> 300 frames and 2.2 -> 13 % centre error (26 % even with oracle normals)
    motion_bridge_deg: float = 0.0
    # spin model (our addition; linear.py _spin_rows): every centre on the circle the phone describes about a
    # (slowly wandering) stand point, one arm for the whole sweep. Weight: sigma of a colinearity row / sigma of a
    # centre off the circle (rows in m; ~2.5 mm / 1.2 cm); 0: off (the paper). Measured (tools/bench.py --seeds 5,
    # medians living/bedroom/office centre err., captures worse than 10 %): ideal circles 2.41/0.70/2.93 % (3 of 15)
    # -> 1.53/0.70/0.61 % (0); spins swaying 5 cm (--sway 0.05) 1.88/0.75/22.7 % (4) -> 1.52/0.68/1.90 % (0)
    spin_weight: float = 0.2
    spin_vertical_ratio: float = 1.0  # ... the vertical row's weight relative to the horizontal ones
    spin_knot_deg: float = 90.0  # ... the stand point is interpolated between knots this turn apart (0: one stand point)
    spin_walk_ratio: float = 1.0  # ... rows tying neighbouring knots, weight relative to spin_weight
    # ... and without a metric scale (no floor line verified) the solve is scaled so that the spin's arm is this
    # long: units about metres, so that the bundle adjustment's sigmas in metres hold (linear.py; 0: mean depth 1)
    spin_arm_m: float = 0.35
    # ... and it places a group of frames their own lines fix that the lines link to the rest along one
    # horizontal axis but not another (register_frames; a group sharing no line stays unregistered). Use it
    # with spin_knot_deg 0 here and in graph (a wandering stand point lets such a group slide). Off: on ideal
    # circles (tools/bench.py --seeds 5, registered and centre err. living/bedroom/office) 96/22/77 ->
    # 96/46/81 %, 1.15/0.66/1.37 -> 0.85/0.66/0.74 % (kept back 94/41/82 -> 95/67/85 %, 1.06/0.71/1.50 ->
    # 1.26/0.61/0.78 %), but on spins that sway 5 cm 1.05/1.18/1.93 -> 2.78/3.28/4.64 %, 1.1 -> 1.3-1.4 px.
    # Re-measured with the BA's reprojection kernel: ideal circles 97/23/85 -> 97/49/87 %, 1.47/0.66/1.25 ->
    # 0.81/0.64/0.71 %; swaying 96/33/57 -> 97/47/88 %, 0.92/0.93/2.03 -> 2.38/3.52/4.65 % (worst 2.4 -> 26 %);
    # with the stand point wandering (knots 90 deg here and in graph) swaying 1.36/2.16/1.98 %, worst 26 %
    spin_links: bool = False
    # ... and it holds the height of a frame whose lines do not (register_frames; with graph.spin_height). Off:
    # registered bedroom/office 23/78 -> 40/84 % (swaying spins 29/52 -> 35/84 %, kept-back seeds 41/82 ->
    # 65/88 %), but on the kept-back captures three of fifteen end worse than 10 % (none without)
    # Re-measured on this round's defaults (kernel BA, 2 cm spin prior), registered selection/kept back/swaying
    # office 85/87/57 -> 92/92/91 %, bedroom 23/44/31 -> 42/68/35 %; mean centre err. 1.10/1.26/1.23 ->
    # 1.52/1.74/1.77 %, worst 2.2/3.1/2.2 -> 7.2/4.6/4.8 % (selection office capture 22: the lifted frames bend
    # the rest): still off
    spin_height: bool = False
    # floor relations whose line lies less than this share as deep below the cameras as the deepest floor
    # candidates (a first solve without them tells) are furniture tops, dropped (0: keep all, the paper)
    floor_verify_ratio: float = 0.85
    # ... and fewer verified floor lines than this (distinct tracks) are dropped too: one or two lines
    # cannot hold the metric scale (measured: with a single floor line the 'metric' result came out
    # 1.5-2x too large on most synthetic captures); the scale is then reported arbitrary
    min_floor_lines: int = 1


@dataclass(frozen=True)
class GraphConfig:
    """Paper §3.4 'Bundle adjustment' (three phases) in GTSAM."""

    colinearity: bool = True
    coplanarity_orthogonal: bool = True
    coplanarity_parallel: bool = True
    coplanarity_junction: bool = True
    coplanarity_floor: bool = True
    reprojection: bool = True
    imu_prior: bool = True
    relation_weight: float = 1e4  # colinearity / coplanarity weight relative to reprojection (paper)
    reprojection_sigma_px: float = 1.0
    # kernel on each line observation's reprojection residual ("none" | "huber" | "cauchy" | "geman_mcclure"),
    # threshold in sigmas per phase 1, 2, 3 (0: none in that phase); in phase 1 reprojection_robust_widen times
    # the initial (linear solve's) RMS residual in sigmas, within [that threshold, reprojection_robust_k_max]:
    # graduated, the kernel starts as wide as the residuals are. Our addition: a track that jumps between two
    # edges where they cross in the image (measured, a swaying living capture: 20 of 87 tracks hold segments of
    # two true edges, 5 of them 81 % of the squared residual) is otherwise averaged into a line that fits
    # neither, and the poses bend to it. Measured (tools/bench.py --seeds 5 [--seed 50 | --sway 0.05], medians
    # living/bedroom/office, against "none"): corner reprojection selection 0.77/0.72/0.82 -> 0.72/0.72/0.76 px, kept back
    # 0.82/0.74/0.75 -> 0.71/0.72/0.72, swaying 1.13/0.75/1.19 -> 0.72/0.68/0.91 (captures above 1 px of 45:
    # 15 -> 6); centre err. 1.16/0.68/1.59 -> 1.47/0.66/1.25 %, 1.20/0.71/1.34 -> 1.01/0.70/1.34 %,
    # 1.05/1.27/2.10 -> 0.92/0.93/2.03 %; worst capture 5.5 -> 3.5 % (kept-back bedroom 81: 5.5 -> 0.4 %,
    # 6.9 -> 0.8 px). At 3 from phase 1 on: selection living 30 went 1.6 -> 5.4 %; at 10 in phase 1 kept-back
    # bedroom 81 stayed at 6.4 %; from phase 2 on it misses tracks that break phase 1 (tests/test_graph.py)
    reprojection_robust: str = "geman_mcclure"
    reprojection_robust_k: tuple[float, ...] = (3.0, 3.0, 3.0)
    reprojection_robust_widen: float = 2.5
    reprojection_robust_k_max: float = 10.0
    imu_sigma_deg: float = 0.2  # relative-rotation prior between neighbouring frames
    # "none" | "huber" | "cauchy" | "geman_mcclure" (relations only). Measured: huber lets false coplanarities
    # drag lines; Cauchy's cost keeps growing (log) with a false relation's residual, and a quarter of the
    # relations false outweighed the reprojection of a collapsing sweep (office capture 2: linear 2.9 %,
    # BA 33 %); Geman-McClure caps each at k^2/2. Five captures per scene, medians living/bedroom/office
    # (captures worse than 10 %): 3.4/1.1/14.1 % (5 of 15) -> 2.5/0.7/13.3 % (3 of 14); unseen seeds
    # (--seed 50) with this round's tracking and the Cauchy/floor-gauge BA 8.1/5.5/2.8 % (3) -> 1.8/5.3/1.9 % (2)
    robust: str = "geman_mcclure"
    robust_k: float = 1.345
    # scale gauge: the distance of the best-observed line from the first camera is held (True) instead of
    # the floor height (False: a floor made of furniture tops, robustly down-weighted, held nothing and
    # the sweep shrank; five captures per scene 2.4/1.1/33.6 -> 3.4/1.1/14.1 %); the result is rescaled
    # to the linear solve's camera height above the floor either way
    scale_line_gauge: bool = True
    support_weighting: bool = True  # relation sigma / sqrt(frames the relation was detected in)
    phases: tuple[int, ...] = (1, 2, 3)  # 1: lines+translations, 2: +rotations, 3: +intrinsics
    max_iterations: int = 30
    # coplanarities are checked against a first solve without them (graph.py _verify_relations): dropped when
    # their lines lie further apart than verify_sigma * std + verify_tolerance * median line distance. Off:
    # five captures per scene, living/bedroom/office centre err. 2.48/0.70/1.89 -> 1.52/0.70/1.47 %, corner
    # reprojection 1.13/0.71/0.92 -> 0.73/0.76/0.75 px (office capture 2: 25.9 -> 1.5 %), but on the kept-back
    # captures (--seed 50) 1.79/5.28/1.89 -> 1.21/5.26/4.41 %, captures worse than 10 % 2 -> 4 (two offices)
    verify_relations: bool = False
    verify_sigma: float = 2.0
    verify_tolerance: float = 0.0
    verify_start_share: float = 0.75  # ... and the BA starts from that solve if it fixes this share of the frames
    # spin prior (our addition; factors/spin_prior.py): std of a centre off the circle the phone describes about a
    # (slowly wandering) stand point, one arm for the whole sweep (m); 0: off (the paper). Without it, parts of
    # the sweep joined by few tracks take their own scale (measured: office capture 12, the middle of the
    # sweep at 1/100 of the ends' scale, 36 % centre error); with it 0.6 % (linear.spin_weight on, see there).
    # 5 -> 2 cm (the linear solve's rows weigh about 1.2 cm; swaying 5 cm RMS, the true centres lie 0.4-2 cm RMS
    # off the knotted circle): the arm's angle, which the lines barely see, drifted (office seed 0 of
    # tools/bench_ba.py --real: the sweep turned 9 deg against the cameras, 6.1 -> 2.9 % centre err.). Measured
    # (tools/bench.py --seeds 5, mean centre err. of the 15 captures, worst): selection 1.20 -> 1.10 % (2.4 ->
    # 2.2), kept back 1.26 -> 1.26 % (3.5 -> 3.1; medians bedroom/office 0.70/1.34 -> 0.84/1.50), swaying
    # 1.36 -> 1.23 % (2.4 -> 2.2); 3 cm on the swaying ones 1.27 %
    spin_sigma_m: float = 0.02
    spin_vertical_ratio: float = 1.0  # ... the vertical std relative to the horizontal one
    spin_robust: str = "huber"  # ... its kernel (k = robust_k)
    spin_knot_deg: float = 90.0  # ... the stand point is interpolated between knots this turn apart (0: one stand point)
    spin_walk_sigma_m: float = 0.05  # ... std of the stand point's step between neighbouring knots (m)
    spin_height: bool = False  # ... holds the height of a frame whose lines do not (determinacy; see linear.spin_height)
    # ... holds every coordinate of a frame (determinacy): a steady spin's frames the linear solve placed between two
    # that their lines fix (linear.motion_bridge_deg) stay registered (SPIN_STYLES 'steady')
    spin_position: bool = False
    # ... and with it on, a warning where the centres lie further than this share of the arm off one circle (RMS;
    # graph.py _check_steady). Measured with the steady style: 0.009-0.019 on the 15 ideal selection circles, 0.009-
    # 0.026 on 14 kept-back ones (the 15th 0.093, at 1.8 % centre err.), 0.025-18 on the 15 swaying spins (3.3-46 %)
    steady_max_rms_arm: float = 0.022
    # auto spin style (our addition; graph.steady_or_hand_held): where the hand-held solve left frames
    # unregistered, the capture is solved again as a steady spin (SPIN_STYLES 'steady') and that result kept
    # when its centres lie on one circle within steady_max_rms_arm (and it registers more): the circle the
    # lines' frames trace says whether the blank-wall frames may be placed on it (in incremental mode after the
    # final solve; the batches' estimates stay hand-held).
    # False: the style as set. Measured: see README (status)
    steady_auto: bool = True
    # metric scale: no horizontal line seen in at least this many frames may lie below the floor; the floor is
    # moved down to the deepest (graph.py _floor_below_lines; 0: off). Measured (tools/bench.py --seeds 5, the
    # similarity's scale to the truth within 10 %): selection captures 2 -> 11 of 15, kept-back 1 -> 13,
    # swaying 3 -> 10 (5 frames: kept-back 14, swaying 9; 8 frames: selection 10)
    floor_below_lines_min_obs: int = 3
    # ... and the metric scale is checked against the spin's arm (graph.py _check_arm): where the floor puts the
    # arm outside this range (m; a phone held out in front is 0.3-0.45 m from the body's axis) the floor was
    # not in view, and the model is scaled so that the arm is metric_arm_fallback_m (as linear.spin_arm_m) and
    # reported as not metric ((0, 1e9): off). Measured (tools/bench.py --seeds 5, the 44 of 45 captures with a
    # metric scale): it flags the 6 whose scale was more than 25 % off (0.44-0.60 and 4.3 x the truth; arms
    # 0.59-0.74 m and 0.07 m) and none of the other 38 (arms 0.29-0.45 m); the arm gives them 0.82-1.10 x
    metric_arm_range_m: tuple[float, float] = (0.15, 0.55)
    metric_arm_fallback_m: float = 0.35
    # ... checked only where the registered frames span this much turn (measured: arms over 104-150 deg of the
    # bedrooms right to 5-18 %; a 60-deg batch of an incremental solve is not checked)
    metric_arm_min_turn_deg: float = 90.0
    # the BA is solved again from the initial solution rescaled where the scale checks after it (floor kept,
    # floor below lines, arm) rescaled the result by more than this ratio either way (graph.bundle_adjust; 0: off),
    # kept where it fits the images no worse: its sigmas in metres then apply at the final scale. Measured
    # (tools/bench.py --seeds 5 after the heading prior, mean centre err. living/bedroom/office): selection
    # 0.44/0.56/0.41 -> 0.46/0.57/0.43 %, kept back 0.54/0.53/1.09 -> 0.55/0.46/0.96 % (office 2 and bedroom 3
    # then pass the steady check: 79 -> 100 % and 25 -> 98 % registered), swaying 1.37/1.03/1.33 ->
    # 1.34/1.01/1.20 %; tools/bench_ba.py --real office (the floor's scale 3.2 x too small): 4.9 -> 0.6 %, 2.1 -> 0.7 px
    resolve_scale_ratio: float = 1.25
    reject_sigma: float = 5.0  # drop relations whose residual exceeds this many sigmas, then resolve
    incremental_batch: int | None = None  # frames per batch for incremental solves
    incremental_final_solve: bool = True  # after the last batch, solve everything once from the linear solution
    # phases >= 2: absolute prior at the preprocessed (vanishing-point) R_wc; 0 = off. 0.03 -> 0.1, measured
    # (tools/bench.py --seeds 5, auto spin style, medians living/bedroom/office): rotation err. 0.074/0.124/0.105 ->
    # 0.069/0.117/0.096 deg, corner reproj. 0.71/0.84/0.76 -> 0.69/0.84/0.75 px (kept back 0.71/0.73/0.78 ->
    # 0.70/0.72/0.76, swaying 0.74/0.70/0.88 -> 0.72/0.69/0.88); centre err. means 0.52/0.58/0.49 -> 0.47/0.56/0.47 %
    # (kept back 0.64/0.50/1.20 -> 0.66/0.48/1.12, swaying 1.14/0.96/1.56 -> 1.15/0.97/1.49). Off: 0.13/0.26/0.21 deg
    rotation_prior_sigma_deg: float = 0.1
    # Option (off): the prior about the preprocessed rotations turned by a heading-drift ramp the BA estimates (one
    # slope over the capture, factors.heading_drift; this: the prior on the slope's total, deg; 0: off, the plain
    # prior). The drift fit can leave part of the IMU's drift where few horizontal lines fix the heading. Measured at
    # 1.0 (tools/bench.py --seeds 5, 15 captures each): selection bedroom 0 rotation err. 0.115 -> 0.072 deg (its
    # -0.14..+0.16 deg ramp gone), but bedroom 1 0.070 -> 0.170 deg, 0.93 -> 1.11 px (a -0.57 deg ramp put in;
    # at 0.3 / 0.1: 0.127 / 0.076 deg); rotation medians 0.062/0.070/0.067 -> 0.062/0.074/0.069, swaying
    # 0.061/0.070/0.063 -> 0.064/0.074/0.067: the lines do not determine the slope reliably
    heading_drift_sigma_deg: float = 0.0
    focal_max_sigma_frac: float = 0.002  # phase 3 refines the focal only if its marginal std is below this share of it
    max_line_sigma_m: float = 0.1  # lines whose position std (from their factors) exceeds this are marked invalid
    max_center_sigma_m: float = 0.1  # frames whose centre std (from their observations) exceeds this are unregistered


@dataclass(frozen=True)
class Config:
    """The whole pipeline's settings; ``summary.json`` records the exact config used."""

    capture: CaptureConfig = field(default_factory=CaptureConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    manhattan: ManhattanConfig = field(default_factory=ManhattanConfig)
    rotation: RotationConfig = field(default_factory=RotationConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    normals: NormalsConfig = field(default_factory=NormalsConfig)
    relations: RelationsConfig = field(default_factory=RelationsConfig)
    linear: LinearConfig = field(default_factory=LinearConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)

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


# Spin styles (``panosfm run --spin``). Our addition to the paper: the spin model (linear.spin_weight,
# graph.spin_sigma_m) ties every camera centre to the circle the phone describes about the person's stand point.
# "hand-held" (the defaults): the stand point wanders, interpolated between knots 90 degrees of turn apart, and a
# frame is placed only where its own lines fix it. "steady": the stand point stays put (a phone on a rotating arm
# or turntable, or a spin that keeps the feet and the elbow still), so one stand point serves the whole sweep, and
# the frames between two frames their lines fix (at most 45 degrees of turn apart) are placed on that circle
# (linear.motion_bridge_deg: they see a blank wall) and kept (graph.spin_position). Measured (tools/bench.py
# --seeds 5 [--seed 50 | --sway 0.05], medians living/bedroom/office): ideal circles registered 97/23/85 ->
# 100/96/100 %, centre err. 1.19/0.65/1.11 -> 0.52/0.55/0.52 %, worst 2.2 -> 0.8 %; kept back 96/44/87 ->
# 100/97/100 %, 1.01/0.84/1.50 -> 0.60/0.51/0.72 %, worst 3.1 -> 1.8 %; but on spins whose stand point sways
# 5 cm 1.15/1.03/1.57 -> 43.4/5.9/4.8 %, worst 46 %: only for spins that really are steady (graph.steady_max_rms_arm
# warns where the centres say otherwise).
SPIN_STYLES: dict[str, dict[str, dict[str, Any]]] = {
    "auto": {},  # the defaults: hand-held, and steady where the centres say so (graph.steady_auto)
    "hand-held": {"graph": {"steady_auto": False}},
    "steady": {
        "linear": {"spin_knot_deg": 0.0, "motion_bridge_deg": 45.0},
        "graph": {"spin_knot_deg": 0.0, "spin_position": True, "steady_auto": False},
    },
}


def with_spin_style(config: Config, style: str) -> Config:
    """Returns ``config`` set for a spin style of :data:`SPIN_STYLES` ("hand-held": unchanged, "steady")."""
    if style not in SPIN_STYLES:
        raise ValueError(f"unknown spin style {style!r} (one of {', '.join(SPIN_STYLES)})")
    return with_overrides(config, **SPIN_STYLES[style])
