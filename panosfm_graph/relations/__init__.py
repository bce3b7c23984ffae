"""Geometric relationship detection between line tracks (paper §3.2, 'Geometric relationship detection').

Four coplanarity tests on the segments of each frame, then deduplicated
across frames into relations between *tracks* (colinearity is the tracks
themselves). One module per test, one per option beyond the paper:

* :mod:`.detect`: :func:`detect_relations`, the tests in order and the merge
  across frames (start reading here);
* :mod:`.quads`: **orthogonal** and **parallel** coplanarity, the quad normal
  test (the mean normal inside the quad of two segments), and our veto of a
  quad another segment crosses (:func:`quad_crossed`);
* :mod:`.junctions`: **junction** coplanarity, endpoints that meet as an L;
* :mod:`.floor`: **floor** coplanarity, horizontal segments inside the floor
  region (:func:`floor_masks`);
* :mod:`.floor_contacts`: option (``floor_contact_frac``), where segments meet
  the floor vetoes coplanarities (:func:`floor_contacts`,
  :func:`consistent_planes`, :func:`hanging_verticals`);
* :mod:`.junction_sides`: option (``junction_sides``), a line's L-junctions
  show on which side its faces lie (:func:`face_sides`);
* :mod:`.pairs`: candidate segment pairs of one frame (one ``cKDTree``);
* :mod:`.judge`: ground-truth judging for benchmarks and tests.

Known limits (measured on real pipeline output, ``tools/bench_relations.py``):
normals cannot tell two parallel planes apart (a bookshelf's front and the
wall behind it, a desk top and the floor seen past it), so orthogonal /
parallel pairs across such an occluding edge pass (oracle precision
0.73-0.95), and the tops of tables and sofa seats are taken for floor when
the floor itself is out of view (oracle floor precision 0.2-0.56).
"""
from __future__ import annotations

from .detect import TrackedSegments, detect_relations, empty_relations, track_rows, tracked_segments
from .floor import FLOOR_SAMPLES, floor_masks, inside_floor, on_mask
from .floor_contacts import (FloorContacts, cannot_linked, consistent_planes, contradicted_pairs, floor_consistent,
                             floor_contacts, hanging_verticals, occluding_t)
from .judge import judge_relations, relations_true, track_gt_edges
from .junction_sides import drop_contradicted_sides, face_sides, junction_sided
from .junctions import junction_test
from .pairs import segment_pairs
from .quads import MIN_SEPARATION_PX, QUAD_GRID, quad_crossed, quad_normal_stats, quad_normal_test

__all__ = [
    "detect_relations", "empty_relations", "tracked_segments", "TrackedSegments", "track_rows",
    "quad_normal_test", "quad_normal_stats", "quad_crossed", "QUAD_GRID", "MIN_SEPARATION_PX",
    "junction_test", "floor_masks", "on_mask", "inside_floor", "FLOOR_SAMPLES",
    "FloorContacts", "floor_contacts", "floor_consistent", "occluding_t", "contradicted_pairs",
    "consistent_planes", "cannot_linked", "hanging_verticals",
    "face_sides", "junction_sided", "drop_contradicted_sides", "segment_pairs",
    "relations_true", "track_gt_edges", "judge_relations",
]
