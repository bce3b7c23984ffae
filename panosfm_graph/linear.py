"""Linear SfM (paper §3.3): camera translations and line depths from colinearity and coplanarity.

Unknowns (paper §3.3 "Model"): the camera centres ``T_i`` and one depth ``lambda`` per line
observation -- the segment mid-point ``P = T_i + lambda D`` along its unit world viewing ray
``D = R_wc K^-1 x~`` (normalised). Rotations (``pre.R_wc``) and the Manhattan directions are known.

Formulation choices (documented deviations are marked *):

* Coordinates are taken in the Manhattan frame: ``tau_i[k] = T_i . N_k`` (``N_k`` = the
  Manhattan directions). A line of axis ``a`` is fixed by its two coordinates ``u[k] = P . N_k``,
  ``k != a`` (its position in the plane orthogonal to its direction).
* Colinearity (paper: ``(P_i - P_j) . N = 0`` for every pair of a track's observations) is
  written* with the per-track offsets ``u`` as extra unknowns: ``(T_i + lambda D) . N_k - u[k] = 0``
  for each observation and both ``k != a``. Minimising over ``u`` gives exactly the paper's
  all-pairs sum divided by the track length, with 2 rows per observation instead of O(n^2).
* A coplanarity with normal axis ``k`` (orthogonal, parallel, junction) is ``(P_l - P_m) . N_k = 0``;
  since ``N_k`` is orthogonal to both lines this equals ``u_l[k] - u_m[k] = 0`` for every choice
  of observations once colinearity holds, so it is written on the offsets. Relations whose normal
  axis is one of the tracks' own axes are impossible and skipped.
* Floor coplanarity: every floor track's vertical offset equals one floor height ``h``.
* The depths are eliminated per observation (each appears only in its two colinearity rows),
  leaving a small sparse least-squares problem in ``tau, u`` that is solved directly (sparse
  normal equations, Jacobi-scaled); the depths follow by back-substitution. The bound
  ``lambda >= min_depth`` is enforced by a primal active set: violating depths are pinned at the
  bound (their two rows kept explicitly) and released when their multiplier changes sign.
* Body-motion prior* (``motion_weight`` > 0, off in the paper): the phone is held out from the
  body and turns with it, so the centres' velocity is nearly constant in a frame turning with the
  camera's heading: rows ``w (Q_b (T_c - T_b) - Q_a (T_b - T_a)) = 0`` on consecutive registered
  frames (``Q = Rz(-yaw)``, exact for a uniform turn on a circle). It regularises the weak
  depth/translation modes of short tracks (measured: fragmented 4-frame tracks, office, 120
  frames: 48 % -> 0.7 % of the trajectory diameter) but never registers a frame (below).
* Spin model* (``spin_weight`` > 0, on by default; off in the paper): the person turns about a stand
  point and holds the phone out in front, so every centre lies on a circle in the direction the camera
  looks: ``T_i = S_i + a h_i + b h_i^perp`` (``h_i`` the horizontal viewing direction, ``(a, b)`` the arm,
  one for the whole sweep; the stand point ``S_i`` interpolated between knots ``spin_knot_deg`` of turn
  apart, neighbouring knots tied), linear in ``T, S, a, b`` (:func:`_spin_rows`). Parts of the sweep joined
  by few tracks otherwise take their own scale (measured, office capture 12: the ends of the sweep at 25-70
  times the middle's scale, 36 % centre error; with the model 3.4 %, 0.6 % after bundle adjustment,
  which carries the same model as a factor). It does not register a frame.
* Tracks first* (``tracks_first``, off by default: measured worse on the bedroom): the solve uses
  the tracks (colinearity, the body-motion prior) and the floor alone, and the coplanarity rows
  only when that registers fewer than ``tracks_first_share`` of the frames they register. A false
  coplanarity is satisfied here by shrinking the camera motion that would show the depth
  difference, so it leaves no residual to find it by (measured: parts of the sweep collapsed onto
  a point); the bundle adjustment brings the coplanarities in with a redescending kernel.
* Robust coplanarities* (``robust_iterations`` rounds, 3 by default; the paper: plain least squares): the
  coplanarity rows are reweighted by a Cauchy kernel on their residuals (scale: the residuals' robust
  spread, at least half a pixel at the median depth) and the system solved again. A false coplanarity
  (a cabinet front 7-9 cm before the wall, normals alike) otherwise bends the whole solve: measured
  (``tools/bench_ba.py --real``, office, oracle normals) lines 11.4 -> 1.3 cm from the surfaces.
  The relations left below ``reject_weight`` (0.1: a residual over 7 robust sigmas) are not handed
  on: the bundle adjustment would take them in again (measured, default normals, living: its lines
  2.3 -> 0.7 cm from the surfaces).
* Floor outliers* (``floor_tolerance`` > 0, with ``robust_iterations``): a floor relation whose line
  ends up above the floor (a furniture top: upward normals too) is downweighted, one-sided.
* Gauge: the first registered camera's centre is the origin. Scale, in this order:
  floor relations and ``camera_height_m`` -> the floor lies ``camera_height_m`` below the mean
  camera height (metric); floor relations only -> mean camera-to-floor distance = 1; otherwise
  the mean depth = 1 (solved with one depth fixed at 1, then rescaled) -- or*, with the spin model on,
  the spin's arm ``spin_arm_m`` long (about 0.35 m for a phone held out at eye height), so that the bundle
  adjustment's sigmas and determinacy thresholds in metres are about right (measured, the only two of
  45 captures with no floor verified: kept-back bedroom capture 81, 7.4 -> 5.5 % centre error and
  9.2 -> 6.9 px corner reprojection; bedroom capture 1 unchanged but 2 frames fewer registered). The
  arm does not check a metric scale: measured, a distorted linear solve's arm came out 0.06-0.09 m
  where the floor's scale was right (the BA then keeps it). ``min_depth_m`` is applied during the solve
  (with the floor ``camera_height_m`` -- or 1 -- below the FIRST camera, or the reference depth = 1) and
  is thus in approximately those units.
* Registration: a frame is solved only if (1) it lies in the largest group of frames that are
  connected, separately along each Manhattan axis ``k``, through observations of tracks that carry
  a ``k`` coordinate, relations of normal ``k`` and (``k`` vertical) the floor -- a frame linked
  to the rest only through vertical lines cannot have its height fixed -- where a track links frames
  only if it adds information (observations + relations >= 3); and (2) the interpretation-plane
  normals of its informative observations span 3D (smallest eigenvalue of their scatter >=
  ``min_view_eig``): each observation of a known line constrains the centre to one plane.
  (1) and (2) are iterated to a fixed point. Other frames get NaN centres and ``registered=False``.
* Spin links* (``spin_links``, with the spin model): a group of anchor frames (fixed along every axis by
  their own lines) that the lines link to the main group along a horizontal axis but not along another
  (a blank wall between, only lines along x in view) is placed along the missing axes by the spin model,
  with one stand point (``spin_knot_deg`` 0: a wandering stand point lets such a group slide). A group
  the lines link along no horizontal axis -- a part of the sweep that shares no line with the rest --
  stays unregistered: the floor alone links heights, not positions or scale.
* Bridging* (``motion_bridge_deg`` > 0 with the motion prior on; off by default): anchor frames
  (fixed along every axis by their own lines) that follow each other within that many degrees of
  turn are linked along every axis by the motion prior (:func:`motion_links`): it joins groups of
  frames no track or relation links (a stretch of blank wall between them), and the frames
  between two anchors are registered, their missing coordinates interpolated. It never
  extrapolates past an anchor, so a part of the sweep beyond a wider stretch stays unregistered.
  Measured: with true tracks and relations (``tools/bench_linear.py --bridge-deg 45``) the
  bedroom registers 49 -> 100 % at 0.77 % centre error; on the pipeline's own tracks it registered
  the bedroom (capture 1) 66 -> 300 frames but at 13 % instead of 2.2 % (26 % with oracle normals):
  off.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import spsolve

from .config import LinearConfig
from .data import (
    FLOOR,
    JUNCTION,
    ORTHOGONAL,
    PARALLEL,
    RELATION_NAMES,
    Camera,
    LineModel,
    Preprocessed,
    Relations,
    Solution,
    Tracks,
)
from .geometry import closest_on_lines, turned_degrees, world_rays

log = logging.getLogger("panosfm.linear")

_OTHER = np.array([[1, 2], [0, 2], [0, 1]])  # the two Manhattan axes orthogonal to axis a
_VERTICAL = 2


def observation_rays(pre: Preprocessed, camera: Camera, segments: np.ndarray | None = None,
                     which: str = "mid") -> np.ndarray:
    """Returns (N, 3) unit WORLD viewing rays ``D = R_wc K^-1 x~`` of segment mid-points (or end points).

    ``which`` is ``"mid"``, ``"start"`` (x1, y1) or ``"end"`` (x2, y2). Paper §3.3, "Model".
    """
    seg = pre.segments
    idx = np.arange(seg.n) if segments is None else np.asarray(segments)
    ep = seg.endpoints[idx].astype(np.float64)
    pts = {"mid": 0.5 * (ep[:, :2] + ep[:, 2:]), "start": ep[:, :2], "end": ep[:, 2:]}[which]
    return world_rays(camera.K, pre.R_wc[seg.frame[idx]], pts)


def _valid_relations(relations: Relations, axis: np.ndarray, config: LinearConfig) -> tuple[np.ndarray, np.ndarray]:
    """Returns (pair relation mask, floor relation mask) of relations the linear solve can use."""
    T = len(axis)
    kind = relations.kind
    a, b, k = relations.track_a, relations.track_b, relations.normal_axis.astype(int)
    in_a = (a >= 0) & (a < T)
    in_b = (b >= 0) & (b < T)
    ax_a = np.where(in_a, axis[np.clip(a, 0, max(T - 1, 0))], -1) if T else np.full(len(a), -1)
    ax_b = np.where(in_b, axis[np.clip(b, 0, max(T - 1, 0))], -1) if T else np.full(len(a), -1)
    pair = (np.isin(kind, (ORTHOGONAL, PARALLEL, JUNCTION)) & in_a & in_b & (a != b)
            & (k != ax_a) & (k != ax_b) & (k >= 0) & (k < 3) & (config.coplanarity_weight > 0))
    floor = (kind == FLOOR) & in_a & (ax_a != _VERTICAL) & (ax_a >= 0) & (config.floor_weight > 0)
    n_bad = int(np.sum(np.isin(kind, (ORTHOGONAL, PARALLEL, JUNCTION)) & ~pair)) if config.coplanarity_weight > 0 else 0
    if n_bad:
        log.warning("linear: skipped %d coplanarities whose normal axis is a line's own axis", n_bad)
    return pair, floor


def motion_links(anchor: np.ndarray, turned_deg: np.ndarray, bridge_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns (a, b): consecutive anchor frames (a < b) at most ``bridge_deg`` of turn apart.

    ``anchor`` (F,): frames whose own lines fix their centre along every axis. The body-motion
    prior links each such pair along every axis and interpolates the frames between them: it
    never extrapolates past an anchor, and a stretch without anchors wider than ``bridge_deg``
    breaks the sweep as before.
    """
    idx = np.flatnonzero(anchor)
    if bridge_deg <= 0 or len(idx) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    turned = np.asarray(turned_deg, dtype=np.float64)
    a, b = idx[:-1], idx[1:]
    ok = np.abs(turned[b] - turned[a]) <= bridge_deg
    return a[ok], b[ok]


def bridged_frames(a: np.ndarray, b: np.ndarray, n_frames: int) -> np.ndarray:
    """Returns (F,) bool: frames strictly between a linked pair ``a[j] < f < b[j]``."""
    d = np.zeros(n_frames + 1, int)
    inner = b - a > 1
    np.add.at(d, a[inner] + 1, 1)
    np.add.at(d, b[inner], -1)
    return np.cumsum(d)[:n_frames] > 0


def register_frames(n_frames: int, obs_frame: np.ndarray, obs_track: np.ndarray, obs_normal: np.ndarray,
                    track_axis: np.ndarray, rel_a: np.ndarray, rel_b: np.ndarray, rel_axis: np.ndarray,
                    floor_track: np.ndarray, min_view_eig: float, max_iterations: int = 10,
                    turned_deg: np.ndarray | None = None, bridge_deg: float = 0.0,
                    manhattan: np.ndarray = np.eye(3), spin_links: bool = False,
                    spin_height: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((F,) bool frames whose translation the linear solve can determine, (F,) int8 reasons) (paper §3.3).

    ``reasons`` index :data:`UNREGISTERED_REASONS` (0 for a registered frame): the first
    criterion a frame fails when it drops out, so that users see why (at the fixed point a
    dropped frame's lines have lost their other frames, and it is unlinked along every axis).

    ``obs_*`` describe the tracked observations (frame, track, unit interpretation-plane normal
    ``N_axis x D``); ``rel_*`` the usable pair coplanarities (tracks, normal axis);
    ``floor_track`` the tracks on the floor. See the module docstring for the two criteria. With
    ``bridge_deg`` > 0 (the body-motion prior is on) consecutive anchor frames (fixed along every
    axis by their own lines) within that turn are linked along every axis (:func:`motion_links`)
    and the frames between them registered; ``manhattan`` (rows: the axes) maps the weak
    directions of criterion (2) onto axes. With ``spin_links`` anchor groups linked to the main
    group along a horizontal axis are linked along the others too (module docstring: Spin links).
    """
    F, T = n_frames, len(track_axis)
    kept = np.zeros(F, bool)
    kept[obs_frame] = True
    has_obs = kept.copy()
    dropped_why = np.zeros(F, np.int8)  # the reason a frame left ``kept`` for, when it did (0: never left)
    linked = np.zeros((F, 3), bool)
    weak = np.zeros((F, 3), bool)
    turned = np.zeros(F) if turned_deg is None else np.asarray(turned_deg, dtype=np.float64)
    for _ in range(max_iterations):
        o = kept[obs_frame]
        n_obs = np.bincount(obs_track[o], minlength=T)
        live = n_obs > 0
        ra = live[rel_a] & live[rel_b]
        n_rel = (np.bincount(rel_a[ra], minlength=T) + np.bincount(rel_b[ra], minlength=T)
                 + np.bincount(floor_track[live[floor_track]], minlength=T))
        informative = (n_obs + n_rel >= 3) & live
        oi = o & informative[obs_track]
        # (2) the interpretation planes of the frame's informative observations span 3D
        scatter = np.zeros((F, 3, 3))
        np.add.at(scatter, obs_frame[oi], obs_normal[oi, :, None] * obs_normal[oi, None, :])
        weak = weak_axes(scatter, min_view_eig, manhattan)
        if spin_height:  # the spin model holds the phone's height: the vertical needs no line
            weak[:, _VERTICAL] = False
        anchor = kept & (np.bincount(obs_frame[oi], minlength=F) > 0) & ~weak.any(axis=1)
        link_a, link_b = motion_links(anchor, turned, bridge_deg)

        def axis_labels(hub):
            """(F, 3) connected-component label of each frame along each axis (``hub``: spin-linked frames)."""
            out = []
            for k in range(3):
                e_obs = oi & (track_axis[obs_track] != k)
                rows = [obs_frame[e_obs], F + obs_track[e_obs], link_a, hub]
                cols = [F + obs_track[e_obs], obs_frame[e_obs], link_b, np.full(len(hub), F + T + 1)]
                er = ra & (rel_axis == k) & informative[rel_a] & informative[rel_b]
                rows += [F + rel_a[er]]
                cols += [F + rel_b[er]]
                if k == _VERTICAL:
                    fl = floor_track[live[floor_track] & informative[floor_track]]
                    rows += [F + fl]
                    cols += [np.full(len(fl), F + T)]
                    if spin_height:
                        up = np.flatnonzero(kept)
                        rows += [up]
                        cols += [np.full(len(up), F + T + 1)]
                r = np.concatenate(rows)
                c = np.concatenate(cols)
                g = sp.coo_matrix((np.ones(len(r)), (r, c)), shape=(F + T + 2, F + T + 2))
                out.append(connected_components(g, directed=False)[1][:F])
            return np.stack(out, axis=1)

        def main_class(lab):
            """The label triple shared by the most kept frames (first on ties), or None."""
            cls_id, inv = np.unique(lab[kept], axis=0, return_inverse=True)
            return cls_id[np.argmax(np.bincount(np.ravel(inv)))] if len(cls_id) else None

        lab = axis_labels(np.zeros(0, int))
        best = main_class(lab)
        if spin_links and best is not None:
            # the spin model places a group of anchors along the axes no line links it by, but only a
            # group its lines link to the main one along a horizontal axis (that shares its scale):
            # a part of the sweep that shares no line with the rest stays unregistered
            hub = np.zeros(0, int)
            horizontal = [k for k in range(3) if k != _VERTICAL]
            for _ in range(F):
                new_hub = np.flatnonzero(anchor & np.any(lab[:, horizontal] == best[horizontal], axis=1))
                if np.array_equal(new_hub, hub):
                    break
                hub = new_hub
                lab = axis_labels(hub)
                best = main_class(lab)
        if best is None:
            none = np.zeros((F, 3), bool)
            return np.zeros(F, bool), _reasons(has_obs, ~none, none, np.zeros(F, bool))
        linked = lab == best[None]
        determined = linked & kept[:, None] & ~weak
        main = linked.all(axis=1)
        in_main = main[link_a] & main[link_b]
        new = determined.all(axis=1) | bridged_frames(link_a[in_main], link_b[in_main], F)
        # a frame dropped now is reported by the criterion it fails now, not by what the cascade leaves it
        # (its lines lose their other frames once it is gone, so at the fixed point it is unlinked along every axis)
        left = kept & ~new & (dropped_why == 0)
        dropped_why[left] = _reasons(has_obs, ~linked, weak, new)[left]
        if np.array_equal(new, kept):
            break
        kept = new
    codes = _reasons(has_obs, ~linked, weak, kept)
    return kept, np.where(~kept & (dropped_why > 0), dropped_why, codes).astype(np.int8)


UNREGISTERED_REASONS = (
    "registered",
    "no tracked Manhattan line",
    "not linked to the other frames along Manhattan axis x",
    "not linked to the other frames along Manhattan axis y",
    "not linked to the other frames along the vertical",
    "its lines do not fix its position along Manhattan axis x",
    "its lines do not fix its position along Manhattan axis y",
    "its lines do not fix its height",
    "bundle adjustment could not determine its position",
)
REASON_BUNDLE_ADJUST = len(UNREGISTERED_REASONS) - 1


def _reasons(has_obs: np.ndarray, unlinked: np.ndarray, weak: np.ndarray, registered: np.ndarray) -> np.ndarray:
    """Returns (F,) int8 codes into :data:`UNREGISTERED_REASONS`: the first criterion each frame fails."""
    code = np.zeros(len(has_obs), np.int8)
    first_unlinked = np.argmax(unlinked, axis=1)
    first_weak = np.argmax(weak, axis=1)
    code = np.where(weak.any(axis=1), 5 + first_weak, code)
    code = np.where(unlinked.any(axis=1), 2 + first_unlinked, code)
    code = np.where(has_obs, code, 1)
    code = np.where(registered, 0, code)
    return np.where(~registered & (code == 0), 2, code).astype(np.int8)  # fails only in the cascade: unlinked


def reason_counts(codes: np.ndarray, registered: np.ndarray) -> dict[str, int]:
    """Returns {reason: number of frames} of the unregistered frames (see :data:`UNREGISTERED_REASONS`)."""
    c = np.bincount(np.asarray(codes)[~np.asarray(registered, bool)], minlength=len(UNREGISTERED_REASONS))
    return {UNREGISTERED_REASONS[i]: int(n) for i, n in enumerate(c) if n and i}


def weak_axes(information: np.ndarray, min_eig: float, manhattan: np.ndarray = np.eye(3)) -> np.ndarray:
    """Returns (F, 3) bool: the Manhattan axes along which each (3, 3) information matrix is weak.

    Eigenvectors with eigenvalue below ``min_eig`` are weak directions; each is charged to the
    Manhattan axis (rows of ``manhattan``) it is closest to, or to all three axes when it is not
    within 25 degrees of any (a weak diagonal direction cannot be bridged axis by axis).
    """
    ev, evec = np.linalg.eigh(information)
    weak = np.zeros((len(ev), 3), bool)
    for j in range(3):  # eigenvalues in ascending order
        low = ev[:, j] < min_eig
        comp = np.abs(evec[:, :, j] @ np.asarray(manhattan, dtype=np.float64).T)  # (F, 3)
        k = np.argmax(comp, axis=1)
        aligned = comp[np.arange(len(ev)), k] >= np.cos(np.radians(25.0))
        weak[low & aligned, k[low & aligned]] = True
        weak[low & ~aligned] = True
    return weak


def floor_verified(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                   config: LinearConfig) -> np.ndarray:
    """Returns (R,) bool: every relation but the floor relations that are not on the floor.

    A deviation from the paper: surface normals cannot tell the floor from the tops of tables,
    beds and sofa seats (all horizontal), and one furniture top taken for the floor makes the
    metric scale wrong. The floor is the LOWEST horizontal plane, which a first solve without the
    floor relations shows: each floor candidate line's depth below the mean camera height is
    compared with the deepest horizontal lines' (the 90th percentile, or the deepest candidate when it
    lies deeper: with little floor in view most lines below the cameras are furniture); lines less than
    ``floor_verify_ratio`` of that deep (a desk top 0.7 m below a 1.45 m camera: 0.48) are no floor.
    With fewer than 5 horizontal lines below the cameras the candidates are compared among
    themselves, and with fewer than 3 candidates nothing can be verified: all are dropped (the
    scale is then reported arbitrary rather than metric on a guess), as are candidates whose line
    the first solve does not determine.
    """
    is_floor = relations.kind == FLOOR
    first = solve_linear(pre, tracks, relations.subset(~is_floor), camera,
                         dataclasses.replace(config, floor_verify_ratio=0.0, camera_height_m=None))
    up = pre.manhattan.directions[_VERTICAL]
    reg = first.registered
    cand = np.flatnonzero(is_floor)
    t = relations.track_a[cand].astype(int)
    known = first.lines.valid[t] & np.any(reg)  # the others cannot be checked: they are dropped too
    if not np.any(known):
        log.info("linear: none of the %d floor relations can be verified, dropped", len(cand))
        return ~is_floor
    cam_h = float(np.mean(first.centers[reg] @ up))
    depth = cam_h - first.lines.taylor[t[known]] @ up  # how far below the cameras each candidate line lies
    # the reference: the deepest horizontal lines of the model (floor candidates or not: a floor-wall
    # line need not have been detected as floor), or the candidates when fewer than 5 lie below
    horizontal = first.lines.valid & (tracks.axis != _VERTICAL)
    below = cam_h - first.lines.taylor[horizontal] @ up
    below = below[below > 0]
    if len(below) >= 5:
        # the floor is the lowest plane: a candidate deeper than most horizontal lines (when few floor
        # lines are in view, most lines below the cameras are furniture) raises the reference. Known
        # weakness: one misplaced deep candidate (living capture 0: 2.2x the others) then leaves the
        # scale on that single line (summary.json says how many floor lines hold it)
        ref = float(max(np.percentile(below, 90), depth.max()))
    elif len(depth) >= 3:
        ref = float(np.percentile(depth, 90))
    else:  # nothing to compare with: one or two floor lines may as well be a bed top; the scale stays arbitrary
        ref = np.inf
    drop = np.concatenate([cand[~known], cand[known][~(depth >= config.floor_verify_ratio * ref)]])
    kept = np.setdiff1d(cand, drop)
    if len(np.unique(relations.track_a[kept])) < config.min_floor_lines:
        drop = cand  # too few floor lines to hold the scale: arbitrary rather than wrong
    keep = np.ones(relations.n, bool)
    keep[drop] = False
    log.info("linear: %d of %d floor relations are above the floor (furniture tops), dropped", len(drop), len(cand))
    return keep


def _group_median(values: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """Returns (G,) the median of ``values`` per group id (NaN for empty groups), vectorised."""
    out = np.full(n_groups, np.nan)
    if len(values) == 0:
        return out
    order = np.lexsort((values, groups))
    v, g = values[order], groups[order]
    counts = np.bincount(g, minlength=n_groups)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts > 0
    lo = start[has] + (counts[has] - 1) // 2
    hi = start[has] + counts[has] // 2
    out[has] = 0.5 * (v[lo] + v[hi])
    return out


def _solve_normal(A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
    """Returns argmin |A x - b| by Jacobi-scaled sparse normal equations (a tiny ridge guards empty columns)."""
    N = (A.T @ A).tocsc()
    diag = N.diagonal()
    s = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    S = sp.diags(s)
    Ns = (S @ N @ S + 1e-12 * sp.identity(N.shape[0])).tocsc()
    y = spsolve(Ns, s * (A.T @ b))
    return s * np.atleast_1d(y)


def solve_linear(pre: Preprocessed, tracks: Tracks, relations: Relations, camera: Camera,
                 config: LinearConfig = LinearConfig()) -> Solution:
    """Returns the linear SfM solution (paper §3.3): camera centres and one 3D line per track.

    Solves colinearity + coplanarity + floor constraints for the translations and the line depths
    (``lambda >= min_depth_m``) of the registered frames (module docstring: formulation, gauge,
    scale, registration). Lines: direction = the track's Manhattan direction, position = the median
    of its observations' points (orthogonal to the direction), extent = the closest points on the
    line to its segments' end-point rays. ``R_wc`` is ``pre.R_wc`` passed through.
    With ``floor_verify_ratio`` > 0 the floor relations are verified first (:func:`floor_verified`);
    ``relations_kept`` of the result: all relations but the floor relations it found above the floor
    and those the robust solve left below ``reject_weight`` (the bundle adjustment leaves them out:
    :func:`~panosfm_graph.graph.bundle_adjust`).
    """
    if config.tracks_first and config.coplanarity_weight > 0:
        paper = dataclasses.replace(config, tracks_first=False)
        with_rel = solve_linear(pre, tracks, relations, camera, paper)
        alone = solve_linear(pre, tracks, relations, camera, dataclasses.replace(paper, coplanarity_weight=0.0))
        use_alone = alone.registered.sum() >= config.tracks_first_share * with_rel.registered.sum()
        sol = alone if use_alone else with_rel
        sol.residuals["coplanarities_in_linear"] = not use_alone
        log.info("linear: %s (tracks alone register %d frames, with the coplanarities %d)",
                 "from the tracks alone" if use_alone else "with the coplanarities",
                 int(alone.registered.sum()), int(with_rel.registered.sum()))
        return sol
    if config.floor_verify_ratio > 0 and np.any(relations.kind == FLOOR):
        keep = floor_verified(pre, tracks, relations, camera, config)
        sol = solve_linear(pre, tracks, relations.subset(keep), camera, dataclasses.replace(config, floor_verify_ratio=0.0))
        sol.residuals["floor_relations_rejected"] = int(np.sum(~keep))
        kept = keep.copy()
        kept[np.flatnonzero(keep)] = sol.relations_kept  # and of the verified ones, those the solve kept
        return dataclasses.replace(sol, relations_kept=kept)
    t_start = time.perf_counter()
    seg = pre.segments
    F = len(pre.R_wc)
    M = np.asarray(pre.manhattan.directions, dtype=np.float64)  # rows N_0, N_1, N_2
    T = tracks.n
    axis = tracks.axis.astype(int)
    w_c, w_p, w_f = config.colinearity_weight, config.coplanarity_weight, config.floor_weight

    obs = np.flatnonzero(tracks.track_of >= 0)
    obs = obs[(tracks.track_of[obs] < T)]
    o_frame = seg.frame[obs].astype(int)
    o_track = tracks.track_of[obs].astype(int)
    o_axis = axis[o_track]
    D = observation_rays(pre, camera, obs)  # (O, 3) world
    Dm = D @ M.T  # ray coordinates along the Manhattan axes
    k1 = _OTHER[o_axis, 0]
    k2 = _OTHER[o_axis, 1]
    O = np.arange(len(obs))
    d1, d2 = Dm[O, k1], Dm[O, k2]
    dn = np.hypot(d1, d2)
    ok = dn > 1e-6  # a ray along its own line fixes nothing
    obs, o_frame, o_track, o_axis, D, Dm, k1, k2, d1, d2, dn = (
        x[ok] for x in (obs, o_frame, o_track, o_axis, D, Dm, k1, k2, d1, d2, dn))

    pair, floor = _valid_relations(relations, axis, config)
    r_a = relations.track_a[pair].astype(int)
    r_b = relations.track_b[pair].astype(int)
    r_k = relations.normal_axis[pair].astype(int)
    r_kind = relations.kind[pair].astype(int)
    f_t = relations.track_a[floor].astype(int)

    n_int = np.cross(M[o_axis], D)
    n_int /= np.maximum(np.linalg.norm(n_int, axis=1, keepdims=True), 1e-12)
    if config.zero_translation:
        registered = np.zeros(F, bool)
        registered[o_frame] = True
        reasons = np.where(registered, 0, 1).astype(np.int8)
    else:
        bridge = config.motion_bridge_deg if config.motion_weight > 0 else 0.0
        registered, reasons = register_frames(F, o_frame, o_track, n_int, axis, r_a, r_b, r_k, f_t,
                                              config.min_view_eig, turned_deg=turned_degrees(pre.R_wc),
                                              bridge_deg=bridge, manhattan=M,
                                              spin_links=config.spin_links and config.spin_weight > 0,
                                              spin_height=config.spin_height and config.spin_weight > 0)

    # --- the system over the registered frames (the only unknowns) -------------------------
    o_sel = registered[o_frame]
    n_obs = np.bincount(o_track[o_sel], minlength=T)
    live = n_obs > 0
    rs = live[r_a] & live[r_b]
    fs = live[f_t]
    n_rel = np.bincount(r_a[rs], minlength=T) + np.bincount(r_b[rs], minlength=T) + np.bincount(f_t[fs], minlength=T)
    in_sys = live & (n_obs + n_rel >= 2)
    rs &= in_sys[r_a] & in_sys[r_b]
    fs &= in_sys[f_t]
    o_sel &= in_sys[o_track]
    frames = np.flatnonzero(registered)
    Fk = len(frames)
    frame_col = np.full(F, -1)
    frame_col[frames] = np.arange(Fk)
    tq = np.flatnonzero(in_sys)
    track_col = np.full(T, -1)
    track_col[tq] = np.arange(len(tq))
    n_u = 2 * len(tq)
    col_h = 3 * Fk + n_u
    use_spin = config.spin_weight > 0 and Fk >= 3 and not config.zero_translation
    col_spin = col_h + 1  # spin model: stand-point knots (3 Manhattan coordinates each), a, b (_spin_rows)
    fwd = np.asarray(pre.R_wc, dtype=np.float64)[:, :, 2] @ M.T  # optical axes in Manhattan coordinates
    if use_spin:
        spin_c, spin_v, n_spin = _spin_rows(frames, fwd, turned_degrees(pre.R_wc), col_spin, config)
    n_cols = col_h + 1 + (n_spin if use_spin else 0)
    col_arm = n_cols - 2  # the spin model's arm (a, b): its last two unknowns (_spin_rows)

    def tau_col(frame, k):
        return 3 * frame_col[frame] + k

    def u_col(track, k):
        slot = (k == _OTHER[axis[track], 1]).astype(int)
        return 3 * Fk + 2 * track_col[track] + slot

    use_floor = bool(np.any(fs))
    H = config.camera_height_m
    if use_floor:
        h0 = -(H if H is not None else 1.0)
        scale_mode = "metric" if H is not None else "camera_to_floor"
    else:
        h0 = 0.0
        scale_mode = "mean_depth"
        if H is not None:
            log.warning("linear: camera_height_m given but no floor relations among registered frames; "
                        "the scale is arbitrary")
    ob = np.flatnonzero(o_sel)
    fixed_val = np.full(n_cols, np.nan)
    fixed_val[col_h] = h0
    if Fk:
        if config.zero_translation:
            fixed_val[:3 * Fk] = 0.0
        else:
            fixed_val[tau_col(frames[0], np.arange(3))] = 0.0
    ref_obs = -1
    if not use_floor and len(ob):
        # fix one depth: an observation in the first registered frame of its most observed track
        cand = ob[o_frame[ob] == o_frame[ob].min()]
        ref_obs = int(cand[np.argmax(n_obs[o_track[cand]])])
        t0 = o_track[ref_obs]
        tau0 = np.zeros(3)  # the reference frame's centre is the origin
        for kk, dd in ((k1[ref_obs], d1[ref_obs]), (k2[ref_obs], d2[ref_obs])):
            fixed_val[u_col(np.array([t0]), np.array([kk]))[0]] = tau0[kk] + 1.0 * dd
    fixed = ~np.isnan(fixed_val)
    free_idx = np.flatnonzero(~fixed)

    # relation rows (coplanarity, floor): w * (x[rel_c0] - x[rel_c1]) = 0, reweighted by IRLS
    rel_c0 = np.concatenate([u_col(r_a[rs], r_k[rs]), u_col(f_t[fs], np.full(int(fs.sum()), _VERTICAL))])
    rel_c1 = np.concatenate([u_col(r_b[rs], r_k[rs]), np.full(int(fs.sum()), col_h)])
    rel_w = np.concatenate([np.full(int(rs.sum()), w_p), np.full(int(fs.sum()), w_f)])
    n_const_rows = len(rel_c0)
    n_pair_rows = int(rs.sum())

    # body-motion prior rows: w_m * (second or first difference of consecutive registered centres) = 0
    mot_c, mot_v = _motion_rows(frames, np.arctan2(fwd[:, 1], fwd[:, 0]), config)
    if use_spin:
        width = max(mot_c.shape[1], spin_c.shape[1])
        pad = lambda a, v: np.pad(a, ((0, 0), (0, width - a.shape[1])), constant_values=v)  # noqa: E731
        mot_c = np.concatenate([pad(mot_c, 0), pad(spin_c, 0)])
        mot_v = np.concatenate([pad(mot_v, 0.0), pad(spin_v, 0.0)])
    n_mot_rows = len(mot_c)

    o_f, o_t = o_frame[ob], o_track[ob]
    c_t1, c_t2 = tau_col(o_f, k1[ob]), tau_col(o_f, k2[ob])
    c_u1, c_u2 = u_col(o_t, k1[ob]), u_col(o_t, k2[ob])
    e1, e2, en = d1[ob], d2[ob], dn[ob]
    not_ref = ob != ref_obs
    lam_min = config.min_depth_m

    def assemble(pinned, robust_w):
        """Returns (A_free, b) for the depths pinned at the bound and the relations' IRLS weights."""
        free_o = ~pinned & not_ref
        nf, npn = int(free_o.sum()), int(pinned.sum())
        r0 = n_const_rows
        rr = r0 + np.arange(nf)
        wo = np.sqrt(robust_w[r0:])  # observations' IRLS weights (ones unless robust_observations)
        c1, c2 = wo[free_o] * e2[free_o] / en[free_o], wo[free_o] * e1[free_o] / en[free_o]
        rc = np.arange(r0)
        wr = rel_w * np.sqrt(robust_w[:r0])
        rows = [rc, rc] + [rr] * 4
        cols = [rel_c0, rel_c1] + [c_t1[free_o], c_u1[free_o], c_t2[free_o], c_u2[free_o]]
        vals = [wr, -wr] + [w_c * c1, -w_c * c1, -w_c * c2, w_c * c2]
        rhs = [np.zeros(r0), np.zeros(nf)]
        rp = r0 + nf + np.arange(npn)
        rows += [rp, rp, rp + npn, rp + npn]
        cols += [c_t1[pinned], c_u1[pinned], c_t2[pinned], c_u2[pinned]]
        wp = w_c * wo[pinned]
        vals += [wp, -wp, wp, -wp]
        rhs += [-wp * lam_min * e1[pinned], -wp * lam_min * e2[pinned]]
        rm = r0 + nf + 2 * npn + np.arange(n_mot_rows)
        rows += [np.repeat(rm, mot_c.shape[1])]
        cols += [mot_c.ravel()]
        vals += [mot_v.ravel()]
        rhs += [np.zeros(n_mot_rows)]
        rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        rhs = np.concatenate(rhs)
        n_rows = r0 + nf + 2 * npn + n_mot_rows
        A = sp.csr_matrix((vals, (rows, cols)), shape=(n_rows, n_cols))
        fv = np.where(fixed, fixed_val, 0.0)
        rhs = rhs - A @ fv
        return A[:, free_idx], rhs

    def full_x(x_free):
        x = np.where(fixed, fixed_val, 0.0)
        x[free_idx] = x_free
        return x

    def depths(x, pinned):
        a1 = x[c_t1] - x[c_u1]
        a2 = x[c_t2] - x[c_u2]
        lam = -(a1 * e1 + a2 * e2) / en ** 2
        lam = np.where(pinned, lam_min, lam)
        if ref_obs >= 0:
            lam[~not_ref] = 1.0
        grad = w_c ** 2 * (e1 * (a1 + lam * e1) + e2 * (a2 + lam * e2))
        return lam, grad

    pinned = np.zeros(len(ob), bool)
    x = np.where(fixed, fixed_val, 0.0)
    lam = np.zeros(len(ob))
    robust_w = np.ones(n_const_rows + len(ob))
    iterations = 0
    n_down = 0
    rel_down = np.zeros(0, np.int64)  # relations the IRLS left below reject_weight (indices into relations)
    if len(ob) and len(free_idx):
        for irls in range(max(config.robust_iterations, 0) + 1):
            x, lam, pinned, it = _active_set(assemble, full_x, depths, pinned, robust_w, not_ref, lam_min, h0)
            iterations += it
            if irls == config.robust_iterations or (n_const_rows == 0 and not config.robust_observations):
                break
            noise = 0.5 / camera.K[0, 0] * float(np.median(np.abs(lam)))  # half a pixel at the median depth

            def weights(res):  # Cauchy, scale: the robust spread, at least half a pixel of noise
                scale = max(1.4826 * float(np.median(np.abs(res))), noise,
                            1e-6 * max(1.0, float(np.median(np.abs(lam)))))
                return 1.0 / (1.0 + (res / (config.robust_k * scale)) ** 2)

            r = x[rel_c0] - x[rel_c1]
            new_w = np.ones(n_const_rows + len(ob))
            if config.robust_observations:  # an observation off its track's line: a member of another line
                a1, a2 = x[c_t1] - x[c_u1], x[c_t2] - x[c_u2]
                new_w[n_const_rows:] = weights((a1 * e2 - a2 * e1) / en)  # ray-to-line distance
            if n_pair_rows:
                new_w[:n_pair_rows] = weights(r[:n_pair_rows])
            if config.floor_tolerance > 0 and n_const_rows > n_pair_rows:
                # one-sided: a 'floor' line above the floor is a furniture top (upward normals too);
                # no line lies below the floor. Scale: a share of the camera-to-floor distance.
                above = np.maximum(r[n_pair_rows:], 0.0) / (config.floor_tolerance * abs(h0 if h0 else 1.0))
                new_w[n_pair_rows:] = 1.0 / (1.0 + above ** 2)
            if np.allclose(new_w, robust_w, atol=1e-3):
                break
            robust_w = new_w
        n_down = int(np.sum(robust_w[:n_const_rows] < 0.5))
        # what the robust solve found far off, the bundle adjustment does not get
        rel_down = np.concatenate([np.flatnonzero(pair)[rs], np.flatnonzero(floor)[fs]])[
            robust_w[:n_const_rows] < config.reject_weight]
    elif len(ob):
        lam, _ = depths(x, pinned)

    # --- scale normalisation -----------------------------------------------------------------
    tau = x[:3 * Fk].reshape(Fk, 3)
    if scale_mode == "metric":
        s = H / (tau[:, _VERTICAL].mean() - h0)
    elif scale_mode == "camera_to_floor":
        s = 1.0 / (tau[:, _VERTICAL].mean() - h0)
    else:
        s = 1.0 / lam.mean() if len(lam) else 1.0
        if use_spin and config.spin_arm_m > 0:
            arm = float(np.hypot(*x[col_arm:col_arm + 2])) * s  # in mean-depth units
            if np.isfinite(arm) and arm > 0.01:  # a spin at all (1 % of the mean depth): units ~ metres
                s *= config.spin_arm_m / arm
                scale_mode = "spin_arm"
    if not np.isfinite(s) or s <= 0:
        log.warning("linear: degenerate scale (%s); left unnormalised", s)
        s = 1.0
    x = x * s
    lam = lam * s
    tau = x[:3 * Fk].reshape(Fk, 3)
    h = x[col_h]

    centers = np.full((F, 3), np.nan)
    centers[frames] = tau @ M

    # --- lines: from the observations of registered frames -----------------------------------
    P = centers[o_f] + lam[:, None] * D[ob]  # (n, 3) observation points (world)
    Pm = P @ M.T
    coord = np.full((T, 3), 0.0)
    for k in range(3):
        has_k = o_axis[ob] != k
        coord[:, k] = _group_median(Pm[has_k, k], o_t[has_k], T)
    coord[np.arange(T), axis] = 0.0
    n_obs_sys = np.bincount(o_t, minlength=T)  # observations in the system
    valid = in_sys & (n_obs_sys > 0) & (n_obs_sys + n_rel >= 2)
    valid &= np.isfinite(coord).all(axis=1)
    taylor = np.where(valid[:, None], coord @ M, np.nan)
    direction = M[axis]
    extent = _extents(pre, camera, obs[ob], o_t, centers[o_f], taylor, direction, T)
    valid &= np.isfinite(extent).all(axis=1)
    lines = LineModel(taylor=taylor, direction=direction.copy(), axis=tracks.axis.astype(np.int8),
                      extent=extent, valid=valid)

    # --- residual report ---------------------------------------------------------------------
    xr = x
    res = {
        "scale": scale_mode,
        "metric": scale_mode == "metric",
        "frames": int(F),
        "registered": int(registered.sum()),
        "solved": int(Fk),
        "tracks_solved": int(len(tq)),
        "observations": int(len(ob)),
        "depths_at_bound": int(pinned.sum()),
        "active_set_iterations": int(iterations),
        "relations_downweighted": int(n_down),
        "floor_height": float(h) if use_floor else None,
        "scale_factor": float(s),  # final units per solve units (the depth bound applies in solve units)
        "depth_min": float(lam.min()) if len(lam) else None,
        "depth_median": float(np.median(lam)) if len(lam) else None,
        "unregistered_reasons": reason_counts(reasons, registered),
        "unregistered_reason_codes": reasons.tolist(),  # per frame, into UNREGISTERED_REASONS
    }
    a1 = xr[c_t1] - xr[c_u1] + lam * e1
    a2 = xr[c_t2] - xr[c_u2] + lam * e2
    res["colinearity_rms"] = _rms(np.concatenate([a1, a2]))
    res["colinearity_count"] = int(len(ob))
    for kind in (ORTHOGONAL, PARALLEL, JUNCTION):
        m = rs & (r_kind == kind)
        r = xr[u_col(r_a[m], r_k[m])] - xr[u_col(r_b[m], r_k[m])] if np.any(m) else np.zeros(0)
        res[f"{RELATION_NAMES[kind]}_rms"] = _rms(r)
        res[f"{RELATION_NAMES[kind]}_count"] = int(np.sum(m))
    r = xr[u_col(f_t[fs], np.full(int(fs.sum()), _VERTICAL))] - h if np.any(fs) else np.zeros(0)
    res["floor_rms"] = _rms(r)
    res["floor_count"] = int(np.sum(fs))
    res["seconds"] = time.perf_counter() - t_start
    log.info("linear: registered %d / %d frames, %d lines, colinearity rms %.3g (%s scale) in %.2f s",
             int(registered.sum()), F, int(valid.sum()), res["colinearity_rms"] or 0.0, scale_mode, res["seconds"])
    kept = np.ones(relations.n, bool)
    kept[rel_down] = False
    return Solution(R_wc=np.asarray(pre.R_wc, dtype=np.float64).copy(), centers=centers, registered=registered,
                    lines=lines, camera=camera, metric=scale_mode == "metric", residuals=res, relations_kept=kept)


def _motion_rows(frames: np.ndarray, yaw: np.ndarray, config: LinearConfig) -> tuple[np.ndarray, np.ndarray]:
    """Returns (cols (R, m), vals (R, m)) of the body-motion prior rows on the centre coordinates.

    The camera is held out from the body and turns with it, so its velocity is constant in a frame
    that turns with the camera's heading ``yaw`` (about the vertical Manhattan axis): with
    ``Q_i = Rz(-yaw_i)``, ``motion_order`` 2 asks ``w (Q_b (T_c - T_b) - Q_a (T_b - T_a)) / g^2 = 0`` for
    consecutive registered frames a < b < c (g = the larger index gap) -- exact for a uniform
    turn on a circle -- and ``motion_order`` 1 asks ``w (T_b - T_a) / g = 0``. Steps across a gap
    above ``motion_max_gap`` frames get no row. Three rows (Manhattan coordinates) per triple/pair.
    """
    w = config.motion_weight
    order = config.motion_order
    Fk = len(frames)
    if w <= 0 or Fk < order + 1:
        return np.zeros((0, 3 * (order + 1)), int), np.zeros((0, 3 * (order + 1)))
    gaps = np.diff(frames)
    if order == 2:
        g = np.maximum(gaps[:-1], gaps[1:])
        keep = np.flatnonzero(g <= config.motion_max_gap)
        c, s_ = np.cos(yaw[frames]), np.sin(yaw[frames])
        Q = np.zeros((Fk, 3, 3))
        Q[:, 0, 0], Q[:, 0, 1], Q[:, 1, 0], Q[:, 1, 1], Q[:, 2, 2] = c, s_, -s_, c, 1.0  # Rz(-yaw)
        a, b = keep, keep + 1
        blocks = np.stack([Q[a], -(Q[a] + Q[b]), Q[b]], axis=1)  # (n, 3 frames, 3 rows, 3 coords)
        blocks = blocks * (w / g[keep].astype(float) ** 2)[:, None, None, None]
        idx = keep[:, None] + np.arange(3)[None]  # registered-frame indices (a, b, c)
    else:
        keep = np.flatnonzero(gaps <= config.motion_max_gap)
        eye = np.broadcast_to(np.eye(3), (len(keep), 3, 3))
        blocks = np.stack([-eye, eye], axis=1) * (w / gaps[keep].astype(float))[:, None, None, None]
        idx = keep[:, None] + np.arange(2)[None]
    m = idx.shape[1]
    # row (n, r): sum over frames j and coordinates k of blocks[n, j, r, k] * tau[idx[n, j], k]
    cols = np.broadcast_to(3 * idx[:, :, None, None] + np.arange(3)[None, None, None, :], blocks.shape)
    cols = cols.transpose(0, 2, 1, 3).reshape(-1, 3 * m)
    vals = blocks.transpose(0, 2, 1, 3).reshape(-1, 3 * m)
    return cols, vals


def _spin_rows(frames: np.ndarray, fwd: np.ndarray, turned: np.ndarray, col0: int,
               config: LinearConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """Returns (cols (R, 5), vals (R, 5), number of unknowns) of the spin-model rows (``factors.spin_prior``).

    The person turns about a stand point ``S`` and holds the phone out in front, so each centre
    lies on a circle in the direction the camera looks: ``T_i = S + a h_i + b h_i^perp`` with
    ``h_i`` the horizontal unit direction of frame i's optical axis (Manhattan coordinates) and
    ``(a, b)`` the arm's length times the cosine / sine of its fixed angle to the optical axis --
    linear in (T, S, a, b). ``S`` is interpolated by the turned angle between knots
    ``spin_knot_deg`` apart (:func:`factors.spin_prior.spin_knots`). Rows
    (:func:`factors.spin_prior.spin_model_rows`): ``w (T_i[k] - S_i[k] - a h_i[k] - b h_i^perp[k])``
    for the two horizontal axes, ``w_z (T_i[z] - S_i[z])`` (the phone's height is constant), and
    ``w_walk (S_{j+1} - S_j)`` between neighbouring knots. Columns from ``col0``: the knots
    (3 each), then a, b. One shared arm binds the scale of every part of the sweep.
    """
    from factors.spin_prior import horizontal_direction, spin_knots, spin_model_rows

    h = horizontal_direction(np.eye(3), np.asarray(fwd, dtype=np.float64)[frames])
    j, alpha, n_knots = spin_knots(np.asarray(turned, dtype=np.float64)[frames], config.spin_knot_deg)
    kind, centre, cols, vals = spin_model_rows(h, j, alpha, n_knots)
    w = config.spin_weight * np.array([1.0, config.spin_vertical_ratio, config.spin_walk_ratio])[kind]
    has_c = centre >= 0
    # the centre's column (tau: 3 x registered-frame index + axis, as ``centre``) or a zero entry
    c0 = np.where(has_c, centre, col0)
    cols = np.column_stack([c0, col0 + cols])
    vals = np.column_stack([np.where(has_c, 1.0, 0.0), -vals]) * w[:, None]
    return cols, vals, 3 * n_knots + 2


def _active_set(assemble, full_x, depths, pinned, robust_w, not_ref, lam_min, h0, max_iterations=30):
    """Returns (x, depths, pinned, iterations): least squares with depths >= lam_min by a primal active set.

    Violating depths are pinned at the bound; pinned depths whose gradient says the objective
    decreases inside the feasible region are released; repeat until neither happens.
    """
    for it in range(1, max_iterations + 1):
        A, rhs = assemble(pinned, robust_w)
        x = full_x(_solve_normal(A, rhs))
        lam, grad = depths(x, pinned)
        tol = 1e-9 * max(1.0, abs(h0))
        violate = ~pinned & not_ref & (lam < lam_min - tol)
        release = pinned & (grad < -tol)
        if not violate.any() and not release.any():
            return x, lam, pinned, it
        pinned = (pinned | violate) & ~release
    log.warning("linear: depth active set did not converge in %d iterations", max_iterations)
    return x, lam, pinned, max_iterations


def _rms(r: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(r ** 2))) if len(r) else None


def _extents(pre: Preprocessed, camera: Camera, seg_ids: np.ndarray, seg_track: np.ndarray, seg_centers: np.ndarray,
             taylor: np.ndarray, direction: np.ndarray, T: int) -> np.ndarray:
    """Returns (T, 2) the line parameters (s0, s1) spanned by the closest points to the end-point rays."""
    ext = np.full((T, 2), np.nan)
    if len(seg_ids) == 0:
        return ext
    lo = np.full(T, np.inf)
    hi = np.full(T, -np.inf)
    p = taylor[seg_track]
    u = direction[seg_track]
    for which in ("start", "end"):
        s = closest_on_lines(p, u, seg_centers, observation_rays(pre, camera, seg_ids, which))
        good = np.isfinite(s)
        np.minimum.at(lo, seg_track[good], s[good])
        np.maximum.at(hi, seg_track[good], s[good])
    has = np.isfinite(lo) & np.isfinite(hi)
    ext[has, 0] = lo[has]
    ext[has, 1] = hi[has]
    return ext
