"""The bundle adjustment's problem (paper §3.4): its variables' keys and what it optimises.

The gtsam keys of the variables (:func:`center_key`, :func:`rotation_key`, :func:`line_key`,
:func:`stand_key`, ``FLOOR_KEY`` ...; the list is in the package docstring), the selection of the
frames, tracks, observations and relations that enter one problem (:func:`_select` into
:class:`_Problem`), whether the floor relations are used (:func:`floor_held_scale`), and the
relations' sigmas and residuals shared by the graph, the rejection rounds and the determinacy.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

import factors

from ..config import GraphConfig
from ..data import FLOOR, JUNCTION, ORTHOGONAL, PARALLEL, Preprocessed, Relations, Solution, Tracks


def center_key(i: int) -> int:
    """Returns the gtsam key of frame i's centre (Point3)."""
    return gtsam.symbol("c", int(i))


def rotation_key(i: int) -> int:
    """Returns the gtsam key of frame i's R_wc (Rot3)."""
    return gtsam.symbol("r", int(i))


def line_key(t: int) -> int:
    """Returns the gtsam key of track t's Taylor vector Lambda_t (Point3)."""
    return gtsam.symbol("l", int(t))


def point_key(p: int) -> int:
    """Returns the key of point track ``p`` (Point3; the motion model's point observations)."""
    return gtsam.symbol("p", int(p))


FLOOR_KEY = gtsam.symbol("h", 0)
FOCAL_KEY = gtsam.symbol("f", 0)
ARM_KEY = gtsam.symbol("a", 0)  # spin prior: the arm (a, b) (2-vector)
DRIFT_KEY = gtsam.symbol("d", 0)  # rotation prior: the heading-drift slope left in the prior (1-vector, rad)


def stand_key(j: int) -> int:
    """Returns the gtsam key of the spin prior's stand-point knot j (Point3)."""
    return gtsam.symbol("s", int(j))


_KIND_SWITCH = {ORTHOGONAL: "coplanarity_orthogonal", PARALLEL: "coplanarity_parallel",
                JUNCTION: "coplanarity_junction", FLOOR: "coplanarity_floor"}


@dataclass(frozen=True)
class _Problem:
    """The selected variables and observations of one BA problem (internal)."""

    frames: np.ndarray  # registered frames with a centre variable (sorted)
    rot_frames: np.ndarray  # registered frames (rotation variables in phases >= 2)
    lines: np.ndarray  # optimised tracks (sorted)
    obs_seg: np.ndarray  # observations (segment ids), sorted by track then frame
    obs_track: np.ndarray
    obs_frame: np.ndarray
    directions: np.ndarray  # (T, 3) unit world direction per track
    rel_idx: np.ndarray  # relations usable (both tracks optimised, type switched on)


def _select(pre: Preprocessed, tracks: Tracks, relations: Relations, initial: Solution, config: GraphConfig) -> _Problem:
    """Returns the problem's variables and observations: valid tracks seen in >= 2 registered frames."""
    seg = pre.segments
    tr = tracks.track_of
    valid_track = initial.lines.valid.copy() if len(initial.lines.valid) == tracks.n else np.ones(tracks.n, bool)
    s = np.flatnonzero(tr >= 0)
    s = s[initial.registered[seg.frame[s]] & valid_track[tr[s]]]
    n_obs = np.bincount(tr[s], minlength=tracks.n)
    line_ok = valid_track & (n_obs >= 2) & np.all(np.isfinite(initial.lines.taylor), axis=1)
    s = s[line_ok[tr[s]]]
    order = np.lexsort((seg.frame[s], tr[s]))
    s = s[order]
    directions = pre.manhattan.directions[np.clip(tracks.axis, 0, 2)]
    keep = np.zeros(relations.n, bool)
    for kind, switch in _KIND_SWITCH.items():
        if getattr(config, switch):
            keep |= relations.kind == kind
    if not floor_held_scale(initial):  # the linear solve found them no floor (or had none): neither is the BA's
        keep &= relations.kind != FLOOR
    if len(initial.relations_kept) == relations.n:  # nor those it rejected (floor lines above the floor, IRLS outliers)
        keep &= initial.relations_kept
    rel_idx = np.flatnonzero(keep & relations.between(line_ok)) if relations.n else np.zeros(0, int)
    frames = np.unique(seg.frame[s])
    if config.spin_position and config.spin_sigma_m > 0 and len(frames):
        # a steady spin: the frames the linear solve placed on the circle without a line in view (a blank wall)
        # stay variables, held by the spin prior alone
        frames = np.union1d(frames, np.flatnonzero(initial.registered))
    return _Problem(frames=frames, rot_frames=np.flatnonzero(initial.registered),
                    lines=np.flatnonzero(line_ok), obs_seg=s, obs_track=tr[s], obs_frame=seg.frame[s].astype(np.int64),
                    directions=directions, rel_idx=rel_idx)


def initial_values(prob: _Problem, sol: Solution) -> gtsam.Values:
    """Returns the problem's centres and Taylor vectors at ``sol``'s values."""
    values = gtsam.Values()
    for i in prob.frames:
        values.insert(center_key(i), np.asarray(sol.centers[i], dtype=np.float64))
    for t in prob.lines:
        values.insert(line_key(t), np.asarray(sol.lines.taylor[t], dtype=np.float64))
    return values


def floor_held_scale(initial: Solution) -> bool:
    """Returns whether ``initial``'s scale rests on floor relations (metric or camera-to-floor = 1).

    Where the linear solve dropped every floor relation (none verified, or fewer floor lines than
    ``min_floor_lines``: ``linear.floor_verified``) its scale is arbitrary, and the bundle adjustment
    leaves the floor out too rather than bring back what was found to be no floor. A solution without
    a recorded scale mode (a hand-made initial solution) keeps its floor relations.
    """
    mode = initial.residuals.get("scale") if isinstance(initial.residuals, dict) else None
    return mode not in ("mean_depth", "spin_arm")


def _relation_sigma(config: GraphConfig) -> float:
    """Returns the colinearity / coplanarity sigma: weight ``relation_weight`` relative to reprojection (paper §3.4)."""
    return factors.sigma_from_weight(config.relation_weight, config.reprojection_sigma_px)


def relation_sigmas(relations: Relations, config: GraphConfig) -> np.ndarray:
    """Returns (R,) per-relation sigmas: the relation sigma divided by sqrt(support) when ``support_weighting``.

    A relation detected in k frames counts as k detections (the paper's
    per-frame constraints, deduplicated here), so a sporadic false detection
    cannot outweigh a relation seen in many frames.
    """
    sigma = np.full(relations.n, _relation_sigma(config))
    if config.support_weighting:
        sigma /= np.sqrt(np.maximum(relations.support, 1))
    return sigma


def relation_residuals(relations: Relations, directions: np.ndarray, taylor: np.ndarray, floor_h: float) -> np.ndarray:
    """Returns (R,) coplanarity residuals (m): ``(Lambda_a - Lambda_b) . n`` or, for floor, ``Lambda_a . n - h``."""
    n = directions[relations.normal_axis.astype(int)]
    a = taylor[relations.track_a]
    b = taylor[np.clip(relations.track_b, 0, None)]
    pair = np.sum((a - b) * n, axis=1)
    floor = np.sum(a * n, axis=1) - floor_h
    return np.where(relations.kind == FLOOR, floor, pair)
