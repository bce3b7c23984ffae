"""detect_relations: the coplanarity tests of paper §3.2 on each frame's tracked segments, merged across frames.

The steps, in order (a function each):

1. :func:`tracked_segments`: the segments that belong to a track, labelled
   with their track's Manhattan axis (only these are tested);
2. :func:`_orthogonal_parallel_coplanarity`: nearby pairs through the quad
   normal test (:mod:`.quads`) and, with the floor-contact option, the
   cannot-links among the same pairs (:mod:`.floor_contacts`);
3. :func:`_junction_coplanarity`: pairs whose endpoints meet as an L
   (:mod:`.junctions`);
4. with ``junction_sides``, quad pairs on the wrong side of a line's
   L-junctions are dropped (:mod:`.junction_sides`);
5. :func:`_floor_coplanarity`: horizontal segments inside the floor region
   (:mod:`.floor`), less those a vertical hangs from;
6. :func:`_merged_across_frames`: one relation per (kind, track pair, normal
   axis), its support the number of frames that found it; weak junctions
   and cannot-linked pairs are dropped.
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..config import RelationsConfig
from ..data import FLOOR, JUNCTION, Camera, NormalMaps, Preprocessed, Relations, Tracks
from .floor import floor_masks, inside_floor
from .floor_contacts import FloorContacts, cannot_linked, contradicted_pairs, floor_contacts, hanging_verticals
from .junction_sides import drop_contradicted_sides
from .junctions import junction_test
from .pairs import segment_pairs
from .quads import quad_normal_test

log = logging.getLogger("panosfm.relations")


def empty_relations() -> Relations:
    """Returns a :class:`Relations` with no rows."""
    z = np.zeros(0, np.int32)
    return Relations(z.astype(np.int8), z, z.copy(), z.astype(np.int8), z.copy())


@dataclasses.dataclass(frozen=True)
class TrackedSegments:
    """The segments the coplanarity tests see (arrays indexed by segment id, N = all segments of the capture).

    ``labels`` (N,) int64: the Manhattan axis of the segment's track (-1:
    untracked); ``tracked`` (n,): ids of the tracked segments with an axis;
    ``track_of`` (N,): track id (-1: none); ``frame`` (N,) int64; ``ep`` (N, 4)
    float64 endpoints (image pixels); ``min_side``: min(w, h) of the image,
    pixels; ``span``: how far apart along x the frames lie in the one
    ``cKDTree`` of candidate pairs (:func:`~.pairs.segment_pairs`).
    """

    labels: np.ndarray
    tracked: np.ndarray
    track_of: np.ndarray
    frame: np.ndarray
    ep: np.ndarray
    min_side: float
    span: float


def tracked_segments(pre: Preprocessed, tracks: Tracks, camera: Camera) -> TrackedSegments:
    """Returns the :class:`TrackedSegments` of ``pre``'s segments: those of a track, labelled with its axis."""
    seg = pre.segments
    track_of = np.asarray(tracks.track_of)
    labels = np.full(seg.n, -1, np.int64)
    tracked = np.flatnonzero(track_of >= 0)
    labels[tracked] = tracks.axis[track_of[tracked]]
    tracked = tracked[labels[tracked] >= 0]
    return TrackedSegments(labels, tracked, track_of, seg.frame.astype(np.int64), seg.endpoints.astype(np.float64),
                           float(min(camera.width, camera.height)), 4.0 * (camera.width + camera.height))


def track_rows(track_of: np.ndarray, kind, i: np.ndarray, j: np.ndarray | None, axis) -> tuple[np.ndarray, ...]:
    """Returns the (kind, track_a, track_b, normal_axis) columns of segment pairs (i, j), track_a <= track_b.

    ``j`` None: a FLOOR relation of segment i alone (track_b -1).
    """
    a, b = track_of[i], (track_of[j] if j is not None else np.full(len(i), -1))
    if j is not None:
        a, b = np.minimum(a, b), np.maximum(a, b)
    return np.broadcast_to(kind, len(i)), a, b, np.broadcast_to(axis, len(i))


def _orthogonal_parallel_coplanarity(pre: Preprocessed, normals: NormalMaps, s: TrackedSegments,
                                     config: RelationsConfig, contacts: FloorContacts | None):
    """Returns ((kind, seg_i, seg_j, normal_axis) of the pairs passing the quad test, cannot-links or None).

    Candidates: pairs of one frame whose mid-points or endpoints are within
    ``max_pair_dist_frac * min(w, h)``. With floor ``contacts`` the same pairs
    give the cannot-links (:func:`~.floor_contacts.contradicted_pairs`).
    """
    seg = pre.segments
    pts = np.concatenate([seg.midpoints[s.tracked], s.ep[s.tracked, :2], s.ep[s.tracked, 2:]])
    owner = np.tile(s.tracked, 3)
    pairs = segment_pairs(pts, np.tile(s.frame[s.tracked], 3), owner, config.max_pair_dist_frac * s.min_side, s.span)
    quad = quad_normal_test(pre, normals, pairs[:, 0], pairs[:, 1], s.labels, config, pre.manhattan.directions)
    cannot = None
    if contacts is not None:
        cannot = contradicted_pairs(contacts, s.ep, pairs[:, 0], pairs[:, 1], s.labels, s.frame, s.track_of,
                                    config.floor_contact_frac * s.min_side, config.t_junction_frac * s.min_side,
                                    config.floor_contact_min_frames)
    log.debug("quad tests: %d candidate pairs, %d accepted", len(pairs), len(quad[1]))
    return quad, cannot


def _junction_coplanarity(pre: Preprocessed, normals: NormalMaps, camera: Camera, s: TrackedSegments,
                          config: RelationsConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (seg_i, seg_j, normal_axis) of the junctions: segments of two labels whose ends meet as an L.

    Candidates: endpoints of one frame within ``junction_dist_frac * min(w, h)``
    (the paper's test); :func:`~.junctions.junction_test` adds the L checks.
    """
    ep = s.ep
    pts = np.concatenate([ep[s.tracked, :2], ep[s.tracked, 2:]])
    owner = np.tile(s.tracked, 2)
    pairs = segment_pairs(pts, np.tile(s.frame[s.tracked], 2), owner, config.junction_dist_frac * s.min_side, s.span)
    i, j = pairs[:, 0], pairs[:, 1]
    diff = s.labels[i] != s.labels[j]
    i, j = junction_test(pre, normals, i[diff], j[diff], s.labels, ep, s.min_side, config, pre.manhattan.directions,
                         (camera.width, camera.height))
    return i, j, 3 - s.labels[i] - s.labels[j]


def _floor_coplanarity(mask: np.ndarray, normals: NormalMaps, s: TrackedSegments, config: RelationsConfig,
                       contacts: FloorContacts | None) -> np.ndarray | None:
    """Returns the horizontal segments on the floor (None: no horizontal segment), less those a vertical hangs from."""
    hz = s.tracked[s.labels[s.tracked] != 2]
    if not len(hz):
        return None
    i = inside_floor(mask, s.frame, s.ep, hz, normals.scale)
    if contacts is not None and config.floor_hanging_frac > 0:  # tracks with a vertical hanging from them
        hang = hanging_verticals(contacts, s.ep, s.frame, s.labels, s.tracked, config.junction_corner_frac * s.min_side,
                                 config.floor_hanging_frac * s.min_side, s.span)
        i = i[~np.isin(s.track_of[i], s.track_of[hang])]
    return i


def _merged_across_frames(found: list[tuple[np.ndarray, ...]], cannot: list[np.ndarray], n_tracks: int,
                          config: RelationsConfig) -> Relations:
    """Returns the unique relations of the per-frame ``found`` rows, each with its support (frames).

    Junctions seen in fewer than ``junction_min_support`` frames are dropped,
    and with ``cannot`` links those :func:`~.floor_contacts.cannot_linked` drops.
    """
    rows = np.column_stack([np.concatenate(x).astype(np.int64) for x in zip(*found)])
    if len(rows) == 0:
        return empty_relations()
    uniq, support = np.unique(rows, axis=0, return_counts=True)
    weak = (uniq[:, 0] == JUNCTION) & (support < config.junction_min_support)
    if cannot:
        weak |= cannot_linked(uniq, support, weak, cannot, n_tracks, config.floor_contact_propagate)
    uniq, support = uniq[~weak], support[~weak]
    rel = Relations(
        kind=uniq[:, 0].astype(np.int8),
        track_a=uniq[:, 1].astype(np.int32),
        track_b=uniq[:, 2].astype(np.int32),
        normal_axis=uniq[:, 3].astype(np.int8),
        support=support.astype(np.int32),
    )
    log.info("relations: %s", rel.counts())
    return rel


def detect_relations(
    pre: Preprocessed, tracks: Tracks, normals: NormalMaps, camera: Camera, config: RelationsConfig
) -> Relations:
    """Returns the coplanarity relations between tracks, deduplicated across frames (paper §3.2).

    Only segments that belong to a track are tested. A relation is the
    unique (kind, min track, max track, normal axis); ``support`` counts the
    frames in which it was detected. FLOOR relations have ``track_b = -1``
    and ``normal_axis = 2``.
    """
    s = tracked_segments(pre, tracks, camera)
    if len(s.tracked) == 0:
        return empty_relations()
    mask = floor_masks(pre, normals, camera, config) if (config.floor or config.floor_contact_frac > 0) else None
    contacts = None
    if config.floor_contact_frac > 0:
        contacts = floor_contacts(pre, normals, camera, mask, s.labels, s.tracked)
    found, cannot = [], []  # (kind, track_a, track_b, normal_axis) columns of each test; cannot-links
    if config.orthogonal or config.parallel:
        quad, contradicted = _orthogonal_parallel_coplanarity(pre, normals, s, config, contacts)
        if contradicted is not None:
            cannot.append(contradicted)
    if config.junction:
        junctions = _junction_coplanarity(pre, normals, camera, s, config)
        found.append(track_rows(s.track_of, JUNCTION, *junctions))
    if config.orthogonal or config.parallel:
        if config.junction_sides and config.junction and len(quad[1]) and len(junctions[0]):
            quad = drop_contradicted_sides(pre, camera, s.labels, s.track_of, tracks.n, quad, junctions,
                                           config.junction_min_support)
        found.append(track_rows(s.track_of, *quad))
    if config.floor:
        on_floor = _floor_coplanarity(mask, normals, s, config, contacts)
        if on_floor is not None:
            found.append(track_rows(s.track_of, FLOOR, on_floor, None, 2))
    if not found:
        return empty_relations()
    return _merged_across_frames(found, cannot, tracks.n, config)
