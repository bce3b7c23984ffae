"""Registration (paper §3.3, our determinacy criteria): which frames' translations the linear solve can determine.

The paper solves every frame; a frame whose lines do not fix its centre leaves the system singular
(or, with the depth bound, arbitrary), so the solve takes only the frames it can determine:

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

(* marks a deviation from the paper.) Why a frame is left out is reported per frame
(:data:`UNREGISTERED_REASONS`).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..config import LinearConfig
from ..data import Preprocessed
from ..geometry import turned_degrees
from .system import VERTICAL, Observations, UsableRelations


def determinable_frames(pre: Preprocessed, obs: Observations, rels: UsableRelations, M: np.ndarray,
                        axis: np.ndarray, config: LinearConfig) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((F,) bool registered frames, (F,) int8 reasons): the frames whose translation the lines determine.

    Each observation of a known line constrains its frame's centre to the line's interpretation
    plane (normal ``N_axis x D``, paper §3.3 "Model"); :func:`register_frames` keeps the frames
    those planes and the tracks' links fix. With ``zero_translation`` (the paper's baseline) every
    frame with an observation is kept.
    """
    F = len(pre.R_wc)
    n_int = np.cross(M[obs.axis], obs.ray)
    n_int /= np.maximum(np.linalg.norm(n_int, axis=1, keepdims=True), 1e-12)
    if config.zero_translation:
        registered = np.zeros(F, bool)
        registered[obs.frame] = True
        reasons = np.where(registered, 0, 1).astype(np.int8)
    else:
        bridge = config.motion_bridge_deg if config.motion_weight > 0 else 0.0
        registered, reasons = register_frames(F, obs.frame, obs.track, n_int, axis, rels.a, rels.b, rels.k,
                                              rels.floor_track, config.min_view_eig,
                                              turned_deg=turned_degrees(pre.R_wc), bridge_deg=bridge, manhattan=M,
                                              spin_links=config.spin_links and config.spin_weight > 0,
                                              spin_height=config.spin_height and config.spin_weight > 0)
    return registered, reasons


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
            weak[:, VERTICAL] = False
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
                if k == VERTICAL:
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
            horizontal = [k for k in range(3) if k != VERTICAL]
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
