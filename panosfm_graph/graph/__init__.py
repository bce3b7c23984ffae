"""Bundle adjustment as a GTSAM factor graph (paper §3.4), solved in three phases.

Variables (keys made by :func:`center_key`, :func:`rotation_key`, ...):

* ``c<i>``  ``gtsam.Point3`` centre of registered frame i (world, m) — every
  registered frame that observes at least one optimised line;
* ``r<i>``  ``gtsam.Rot3`` R_wc of registered frame i (phases >= 2; in phase 1
  the rotations are constants bound into the reprojection factors);
* ``l<t>``  ``gtsam.Point3`` Taylor vector Lambda_t of track t (valid tracks
  seen in >= 2 registered frames);
* ``h0``    1-vector floor height (the floor plane is ``z . X = h``), present
  when floor relations are used;
* ``f0``    1-vector focal length fx in pixels (phase 3; fy keeps the aspect);
* ``s<j>``  ``gtsam.Point3`` stand-point knot j, ``a0`` 2-vector arm (the spin prior, below);
* ``d0``    1-vector heading-drift slope (rad over the capture) of the rotation prior (phases >= 2, optional, below);
* ``p<k>``  ``gtsam.Point3`` point track k (only in :func:`place_by_motion_model`'s graph).

Factors (``factors`` package), switched by :class:`GraphConfig`:
line reprojection (one factor per chunk of a track's observations, sigma
``reprojection_sigma_px``; our addition: a Geman-McClure kernel on each observation,
``reprojection_robust``, graduated over the phases by ``reprojection_robust_k``, so that a track
that jumps between two edges fits the one most of its segments follow), colinearity and
coplanarity/floor (sigma ``reprojection_sigma_px / sqrt(relation_weight)``: the paper's weights 1 and
1e4; coplanarity and floor additionally divided by sqrt(support) when
``support_weighting`` and robustified with ``robust`` — Geman-McClure by default:
measured on synthetic problems with 10 % injected false relations, Huber lets
them drag weakly observed line depths by metres; Cauchy's cost still grows with a
false relation's residual, and on the pipeline's output (a quarter of the
relations false) their sum made a collapsed sweep cheaper than the true one;
Geman-McClure caps each at ``k^2 / 2``), IMU relative
rotations between consecutive registered frames (``imu_sigma_deg``, scaled by
sqrt of the frame gap).

Rotation prior (ours, phases >= 2, ``rotation_prior_sigma_deg``): each frame held to its preprocessed
(vanishing-point) rotation; optionally (``heading_drift_sigma_deg`` > 0, off by default) turned about up
by ``d0 * tau`` (``factors.heading_drift``; ``tau`` the frame's time in [-1/2, 1/2]), ``d0`` with a prior
of that sigma: the drift fit of the preprocessing can leave part of the IMU's heading drift where few
horizontal lines fix the heading, a ramp per-frame priors hold. Measured: on one bedroom spin its
-0.14 .. +0.16 degree ramp goes (rotation error 0.115 -> 0.072 degrees), on another a -0.57 degree ramp
comes in (0.070 -> 0.170): the lines do not determine the slope reliably (``config.py``).

Spin prior (our addition, ``spin_sigma_m``; ``factors.spin_prior``): every centre lies on the circle
the phone describes about the person's stand point (knots ``s<j>`` every ``spin_knot_deg`` of turn, a
random walk of ``spin_walk_sigma_m`` between them) with one arm ``a0`` (2-vector) for the whole sweep,
Huber-robust. Without it, tracks of a few frames leave the parts of a sweep free to take their own
scale, which reprojection cannot see (measured: from a linear solve 0.5 % off, 3-frame tracks drift to
48 % of the trajectory's diameter; with it 0.6 %).
Which frames stay registered (:func:`determinacy`) counts the prior only where asked: ``spin_height``
(the height) or ``spin_position`` (every coordinate: a steady spin, ``config.SPIN_STYLES``, whose frames
between two that their lines fix the linear solve placed on the circle).

Gauge: a tight prior holds the first registered camera centre at its initial
position; the world orientation is fixed by the Manhattan directions of the
lines. Scale: the distance of the best-observed line from the first camera
centre (along its initial normal) is held (``scale_line_gauge``; False: a tight
prior on the floor height ``h``, which a floor made of robustly down-weighted
furniture tops does not hold); with floor relations the result is then rescaled
about the origin so the MEAN camera-to-floor distance equals the initial one (a
metric initial solution stays metric even when its first frame is misplaced). Phase 3 adds a weak prior (10 % of the calibrated focal) on the
focal length.

Floor relations are used only where the linear solve's scale rests on them (:func:`floor_held_scale`):
where it dropped every one of them (no floor verified), so does the bundle adjustment.

Relations checked against the tracks (our addition, ``verify_relations``, off by default: measured
better on the captures it was developed on, worse on kept-back office captures): phase 1 is first solved
without any coplanarity; coplanarities whose lines that solve puts further apart than
``verify_sigma`` of their std are dropped, and the phases start from that solve when it fixes at
least ``verify_start_share`` of the frames (:func:`_verify_relations`).

Zero baseline (ours, :func:`rotation_bundle_adjust`, ``graph/rotation_only.py``): a spin without parallax
adjusts only rotations and lines about one fixed centre (the lines at an assumed distance of 1 unit).

Solver: our own Levenberg-Marquardt loop over ``graph.linearize`` /
``GaussianFactorGraph.optimize`` / ``Values.retract`` with isotropic damping
(``notes/gtsam-python-performance.md``: GTSAM's optimizers are slow with many
Python factors). The line reprojection terms, most of the cost, are linearised by one vectorised
call (:class:`factors.LineReprojectionSet`: the same residuals and Jacobians as the factors, one
``JacobianFactor`` per observation; with the focal length free in phase 3 its column as cross-term
``HessianFactor`` s per variable) instead of one Python callback per factor; the factors themselves
remain where a graph must hold them (the focal's marginal). Measured (``tools/bench_ba.py --frames 300 --clutter 60 --fragment 6``, 2,287-2,774
tracks): 23.1/22.5/18.5 s -> 10.3/11.4/9.8 s for living/bedroom/office, results equal to 1e-5.
After the last phase relations whose whitened residual
exceeds ``reject_sigma`` are dropped and the last phase is solved again
(up to 3 rounds).

Layout (one job per module; the package re-exports the names other modules use):

* :mod:`.problem`       the variables' keys, the selected problem (:class:`_Problem`), relation sigmas and residuals;
* :mod:`.factor_graph`  the factor graph of one phase (:func:`_build_graph`);
* :mod:`.lm`            the Levenberg-Marquardt loop (:func:`levenberg_marquardt`);
* :mod:`.readout`       the Solution read from the optimised values (extents, focal, RMS reprojection);
* :mod:`.determinacy`   line / centre stds, undetermined lines and frames, relations checked, the focal's marginal;
* :mod:`.scale`         the gauge constants and the floor's scale checks (camera height, floor below lines);
* :mod:`.spin`          the spin model: circle fit, arm length, the steady and arm checks;
* :mod:`.solve`         :func:`bundle_adjust` (the phases, rejection rounds, solved again at scale) and
  :func:`bundle_adjust_incremental`;
* :mod:`.style`         :func:`steady_or_hand_held`, the spin style chosen after the hand-held solve;
* :mod:`.motion_model`  :func:`place_by_motion_model`, the frames the lines leave without a pose placed by the spin
  model and the point tracks (:mod:`panosfm_graph.points`), with their std (issue #40);
* :mod:`.held_poses`    :func:`adjust_lines_at_poses`, the lines adjusted with the poses held and the relations;
* :mod:`.joint_points`  :func:`adjust_with_points`, the bundle adjustment solved again with the point tracks joined;
* :mod:`.reliability`   :func:`verify_solution`, the result checked against the lines' and the points' own solutions:
  every frame's honest std, the doubtful frames and the run's verdict (issue #63).
"""
from __future__ import annotations

from .determinacy import determinacy, focal_sigma
from .held_poses import adjust_lines_at_poses
from .joint_points import adjust_with_points
from .factor_graph import CHUNK_OBS, FOCAL_PRIOR_FRAC, GAUGE_SIGMA
from .lm import levenberg_marquardt
from .motion_model import compares_points, place_by_motion_model, place_by_points_alone, points_replace_lines
from .problem import (ARM_KEY, DRIFT_KEY, FLOOR_KEY, FOCAL_KEY, center_key, floor_held_scale, line_key, relation_residuals,
                      relation_sigmas, rotation_key, stand_key)
from .readout import drop_lines_beyond_room, line_extents
from .reliability import Evidence, honest_sigma, verify_solution
from .rotation_only import rotation_bundle_adjust
from .scale import _scaled
from .solve import MAX_REJECT_ROUNDS, bundle_adjust, bundle_adjust_incremental, solve_at_final_scale
from .spin import circle_rms_arm, fit_spin, spin_arm_length, spin_fit
from .style import steady_or_hand_held, steady_tried

__all__ = [
    "ARM_KEY", "CHUNK_OBS", "DRIFT_KEY", "FLOOR_KEY", "FOCAL_KEY", "FOCAL_PRIOR_FRAC", "GAUGE_SIGMA", "MAX_REJECT_ROUNDS",
    "Evidence", "compares_points", "honest_sigma", "verify_solution",
    "adjust_lines_at_poses", "adjust_with_points", "bundle_adjust", "bundle_adjust_incremental", "center_key", "circle_rms_arm", "determinacy", "drop_lines_beyond_room",
    "fit_spin", "floor_held_scale",
    "focal_sigma", "levenberg_marquardt", "line_extents", "line_key", "place_by_motion_model", "place_by_points_alone", "points_replace_lines", "relation_residuals", "relation_sigmas",
    "rotation_bundle_adjust", "rotation_key", "solve_at_final_scale", "spin_arm_length", "spin_fit", "stand_key",
    "steady_or_hand_held", "steady_tried",
    "_scaled",  # tests/test_graph.py
]
