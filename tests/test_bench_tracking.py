"""tools/bench_tracking.py: the oracle join of fragments of one ground-truth line (no pipeline run)."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench_tracking import fragmentation, join_by_ground_truth  # noqa: E402

from panosfm_graph.data import Tracks  # noqa: E402


def _tracks():
    """Five tracks over frames 0-9: 0, 1, 2 on GT line 7 (0: frames 0-3, 1: 5-7, 2: 2-4 beside 0), 3 on line 8,
    4 unknown; one segment per (track, frame), segment lengths 10 + frame, track 2's 5 px shorter."""
    spans = {0: range(0, 4), 1: range(5, 8), 2: range(2, 5), 3: range(0, 10), 4: range(3, 6)}
    track_of, frame, length = [], [], []
    for t, fs in spans.items():
        for f in fs:
            track_of.append(t)
            frame.append(f)
            length.append(10.0 + f - (5.0 if t == 2 else 0.0))
    tracks = Tracks(track_of=np.array(track_of, np.int32), axis=np.array([0, 0, 0, 1, 2], np.int8))
    return tracks, np.array(frame), np.array(length), np.array([7, 7, 7, 8, -1])


def test_disjoint_join_takes_fragments_not_pieces_seen_side_by_side():
    tracks, frame, length, line = _tracks()
    before = fragmentation(tracks, frame, line)
    assert before["tracks"] == 5 and before["tracks_mapped"] == 4 and before["gt_lines"] == 2
    assert before["tracks_per_line"] == 2.0 and before["lines_in_pieces"] == 1
    assert before["fragment_pairs"] == 2  # 0-1 and 2-1 share no frame; 0-2 share frames 2 and 3
    joined, _ = join_by_ground_truth(tracks, frame, length, line, disjoint=True)
    to = joined.track_of
    # the longest of line 7's tracks (0, 4 frames) takes 1 (no common frame); 2 overlaps it and stays apart
    assert to[0] == to[4] != to[7]  # segment 4 is track 1's first (frame 5), 7 is track 2's first (frame 2)
    assert joined.n == 4 and (to >= 0).all()
    assert sorted(joined.axis.tolist()) == [0, 0, 1, 2]
    _, new = join_by_ground_truth(tracks, frame, length, line, disjoint=True)
    assert new.tolist() == [0, 0, 1, 2, 3]  # each old track's id among the joined ones
    after = fragmentation(joined, frame, np.array([7, 7, 8, -1]))  # joined ids: 0 (+1), 2, 3, 4
    assert after["fragment_pairs"] == 0


def test_join_all_keeps_the_longest_segment_of_a_frame():
    tracks, frame, length, line = _tracks()
    joined, _ = join_by_ground_truth(tracks, frame, length, line, disjoint=False)
    assert joined.n == 3
    to = joined.track_of
    line7 = to[0]
    # frames 2 and 3 held a segment of track 0 and one of track 2 (5 px shorter): track 0's stay
    assert (to[:7] == line7).all()  # tracks 0 and 1: segments 0-6
    assert (to[7:9] == -1).all() and to[9] == line7  # track 2: frames 2, 3 dropped, frame 4 joined
    on = np.flatnonzero(to == line7)
    assert len(np.unique(frame[on])) == len(on)  # one segment per frame


def test_near_join_chains_fragments_in_time_only():
    tracks, frame, length, line = _tracks()
    # track 1 (frames 5-7) starts 2 frames after track 2 (2-4) ends, 2 after track 0 (0-3) ... but 0 and 2 overlap:
    # in time order 0 (0-3), 2 (2-4: overlaps, starts a chain of its own), 1 (5-7: 1 frame after 2) -> 2 + 1
    joined, _ = join_by_ground_truth(tracks, frame, length, line, disjoint=True, near_frames=1)
    to = joined.track_of
    assert joined.n == 4 and to[4] == to[7] != to[0]  # track 1's first segment joins track 2's
    # a gap of 2 frames is beyond near_frames=0... and 1..3 joins nothing further here
    apart, _ = join_by_ground_truth(tracks, frame, length, line, disjoint=True, near_frames=0)
    assert apart.n == 5
