"""Option ``junction_sides``: a line's L-junctions tell on which side its faces lie (beyond paper §3.2).

Also beyond the paper (``junction_sides``): an L-junction tells on which
side of each of its lines the face lies (the inside of the L), and that side
is a direction of the Manhattan frame (:func:`face_sides`), the same in every
frame. A bookshelf's front edge bounds the front towards its top edge; a
quad from that edge to a wall line on its other side, where the wall behind
shows the same normal, is dropped: its line has faces of that orientation
only on the side the junctions show (:func:`junction_sided`). A line no
junction touches keeps all its pairs. Measured: ``RelationsConfig``.
"""
from __future__ import annotations

import logging

import numpy as np

from ..data import Camera, Preprocessed
from ..geometry import world_rays

log = logging.getLogger("panosfm.relations")


def face_sides(pre: Preprocessed, camera: Camera, seg_i: np.ndarray, seg_j: np.ndarray, axis: np.ndarray,
               labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (s_i, s_j) (P,) in {-1, 0, +1}: which way the face on plane ``axis`` runs from each segment to the other.

    Our addition to paper §3.2. Segment i (Manhattan label ``a``) on the plane
    ``x_axis = k`` bounds a face that extends from it along the plane's other
    direction ``3 - a - axis``; its sign, in the Manhattan frame (so the same
    in every frame), is the sign of that coordinate of the way from i's
    mid-point to j's on the plane, found from the viewing rays alone (the
    unknown ``k`` has the sign of the rays' ``axis`` coordinate). 0 where a
    ray runs nearly inside the plane (the plane seen edge-on).
    """
    if len(seg_i) == 0:
        z = np.zeros(0, np.int64)
        return z, z.copy()
    R = pre.R_wc.astype(np.float64)
    dirs = pre.manhattan.directions
    mid = pre.segments.midpoints
    frame = pre.segments.frame

    def rays(s):  # (P, 3) unit viewing rays of the mid-points in Manhattan coordinates
        r = world_rays(camera.K, R[frame[s]], mid[s]) @ dirs.T
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    n = np.arange(len(seg_i))
    rx, ry = rays(seg_i), rays(seg_j)
    c = np.asarray(axis, np.int64)
    xc, yc = rx[n, c], ry[n, c]
    edge_on = (np.abs(xc) < 0.05) | (np.abs(yc) < 0.05) | (np.sign(xc) != np.sign(yc))
    xc, yc = np.where(edge_on, 1.0, xc), np.where(edge_on, 1.0, yc)
    out = []
    for u, v, uc, vc, lab in ((rx, ry, xc, yc, labels[seg_i]), (ry, rx, yc, xc, labels[seg_j])):
        along = 3 - lab - c
        out.append(np.where(edge_on, 0, np.sign(uc) * np.sign(v[n, along] / vc - u[n, along] / uc)).astype(np.int64))
    return out[0], out[1]


def junction_sided(track_of: np.ndarray, n_tracks: int, seg_i: np.ndarray, seg_j: np.ndarray, axis: np.ndarray,
                   s_i: np.ndarray, s_j: np.ndarray) -> np.ndarray:
    """Returns (T, 3, 2) bool: ``[t, k, 0/1]`` whether a junction puts a face of plane normal ``k`` on the -/+ side of track t.

    The inside of an L-junction (paper §3.2's junction coplanarity, with our
    corner and normal checks) is a face the two lines bound: each line's face
    on that plane lies towards the other line (:func:`face_sides`).
    """
    known = np.zeros((n_tracks, 3, 2), bool)
    for s, side in ((seg_i, s_i), (seg_j, s_j)):
        m = side != 0
        known[track_of[s[m]], axis[m], (side[m] > 0).astype(np.int64)] = True
    return known


def drop_contradicted_sides(pre: Preprocessed, camera: Camera, labels: np.ndarray, track_of: np.ndarray,
                            n_tracks: int, quad: tuple, junctions: tuple, min_support: int) -> tuple:
    """Returns the quad coplanarities ``quad`` (kind, seg_i, seg_j, axis) less those the junctions' sides contradict.

    A face runs from a line only to the sides its L-junctions show (junction
    track pairs seen in at least ``min_support`` frames): a bookshelf's front
    edge bounds the front towards its top edge, and the wall beyond it (same
    normal, further back) is another plane.
    """
    kind, i, j, axis = quad
    ji, jj, jk = junctions
    a, b = np.minimum(track_of[ji], track_of[jj]), np.maximum(track_of[ji], track_of[jj])
    _, inv, cnt = np.unique(np.column_stack([a, b, jk]), axis=0, return_inverse=True, return_counts=True)
    strong = cnt[inv.ravel()] >= min_support
    ji, jj, jk = ji[strong], jj[strong], jk[strong]
    known = junction_sided(track_of, n_tracks, ji, jj, jk, *face_sides(pre, camera, ji, jj, jk, labels))
    contradicted = np.zeros(len(i), bool)
    for s, side in zip((i, j), face_sides(pre, camera, i, j, axis, labels)):
        t = track_of[s]
        here = known[t, axis, (side > 0).astype(np.int64)]
        there = known[t, axis, (side < 0).astype(np.int64)]
        contradicted |= (side != 0) & there & ~here
    log.debug("junction sides: %d of %d quad pairs contradicted", int(contradicted.sum()), len(i))
    return kind[~contradicted], i[~contradicted], j[~contradicted], axis[~contradicted]
