"""The data that flows between stages: small frozen dataclasses of numpy arrays.

Struct-of-arrays everywhere: one array per attribute, indexed by segment,
track, frame or relation. Conventions (see ``capture-format.md``):

* world frame right-handed, metres, +z up; camera frame OpenCV (x right,
  y down, z forward);
* ``R_wc`` rotates camera-frame vectors into the world (world_from_camera);
  the paper's ``R_i`` is ``R_wc[i].T``;
* ``centers`` are camera centres in the world (the paper's ``T_i``);
* pixel (0, 0) is the centre of the top-left pixel;
* Manhattan axes are indexed 0, 1, 2 (x, y, z; z is the vertical one);
  label -1 means "not a Manhattan segment".
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

AXIS_NAMES = ("x", "y", "z")
UNLABELLED = -1


@dataclass(frozen=True)
class Camera:
    """Intrinsics in COLMAP's models: PINHOLE, SIMPLE_PINHOLE or OPENCV.

    ``params`` follow COLMAP's order. For OPENCV the pipeline works on
    undistorted pixel coordinates (see ``capture.Camera.undistort_points``);
    ``K`` is the pinhole part.
    """

    model: str
    width: int
    height: int
    params: np.ndarray  # (P,) float64

    @property
    def K(self) -> np.ndarray:
        """Returns the 3x3 pinhole intrinsic matrix."""
        p = self.params
        if self.model == "SIMPLE_PINHOLE":
            fx = fy = p[0]
            cx, cy = p[1], p[2]
        else:
            fx, fy, cx, cy = p[:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> np.ndarray:
        """Returns OpenCV distortion coefficients (k1, k2, p1, p2); zeros for pinhole models."""
        if self.model == "OPENCV":
            return np.asarray(self.params[4:8], dtype=np.float64)
        return np.zeros(4)

    @property
    def min_side(self) -> int:
        return min(self.width, self.height)


@dataclass(frozen=True)
class GroundTruth:
    """``ground_truth/`` of a capture, for the frames that were taken.

    ``normals(i)`` / ``depth(i)`` load one frame's maps lazily (camera frame,
    H x W x 3 float32 unit normals towards the camera; H x W float32 depth
    along the optical axis, 0 where no surface), resized to the capture's
    working resolution; ``None`` when the capture has none.
    """

    R_wc: np.ndarray  # (F, 3, 3) float64
    centers: np.ndarray  # (F, 3) float64
    lines: np.ndarray  # (M, 6) float64, x1 y1 z1 x2 y2 z2 (m)
    line_labels: np.ndarray  # (M,) int8, Manhattan axis 0/1/2 (or -1)
    scene: dict  # scene.json
    normals: Callable[[int], np.ndarray | None] = field(repr=False, default=lambda i: None)
    depth: Callable[[int], np.ndarray | None] = field(repr=False, default=lambda i: None)
    has_normals: bool = False
    has_depth: bool = False

    @property
    def camera_height_m(self) -> float:
        """Returns the true mean camera height above the floor (the room's lowest z in ``scene.json``), in m."""
        return float(np.mean(self.centers[:, 2]) - self.scene.get("room", {}).get("min", [0, 0, 0])[2])


@dataclass(frozen=True)
class Capture:
    """A validated capture. Frames are read lazily with :meth:`frame`.

    ``camera`` is at the working resolution (after ``CaptureConfig.scale``).
    ``frame_names`` are file names (``frames/``) or ``video.mp4#000123``.
    """

    root: Path
    camera: Camera
    frame_names: tuple[str, ...]
    timestamps: np.ndarray  # (F,) float64 seconds
    R_wc_imu: np.ndarray  # (F, 3, 3) float64, IMU attitude slerped to each frame
    ground_truth: GroundTruth | None
    reader: Callable[[int], np.ndarray] = field(repr=False, compare=False)  # index -> BGR uint8 HxWx3
    # False: camera.json gave no focal length; ``camera`` holds a provisional one (lines/focal.py estimates it)
    focal_given: bool = True

    @property
    def n_frames(self) -> int:
        return len(self.frame_names)

    def frame(self, i: int) -> np.ndarray:
        """Returns frame ``i`` as a BGR uint8 image at the working resolution."""
        return self.reader(i)

    def frames(self) -> Iterator[np.ndarray]:
        for i in range(self.n_frames):
            yield self.reader(i)


@dataclass(frozen=True)
class Segments:
    """Line segments of all frames, sorted by frame (paper §3.1).

    ``endpoints[s] = (x1, y1, x2, y2)`` in undistorted pixels at working
    resolution. Segments of frame ``f`` are ``frame_offsets[f]:frame_offsets[f+1]``.
    ``colors`` is the mean BGR colour along each segment (for the quarter view).
    ``contrast`` (optional) is each segment's polarity: the mean grey level on the left of the
    direction ``(x1, y1) -> (x2, y2)`` (image axes: x right, y down) minus that on its right; the
    tracker does not match an edge with the opposite-polarity edge beside it (a trim's two sides).
    """

    endpoints: np.ndarray  # (S, 4) float32
    frame: np.ndarray  # (S,) int32
    frame_offsets: np.ndarray  # (F + 1,) int64
    colors: np.ndarray  # (S, 3) uint8
    contrast: np.ndarray | None = None  # (S,) float32 grey levels, or None (unknown)

    @property
    def n(self) -> int:
        return len(self.frame)

    @property
    def lengths(self) -> np.ndarray:
        d = self.endpoints[:, 2:] - self.endpoints[:, :2]
        return np.hypot(d[:, 0], d[:, 1])

    @property
    def midpoints(self) -> np.ndarray:
        return 0.5 * (self.endpoints[:, :2] + self.endpoints[:, 2:])

    def of_frame(self, f: int) -> slice:
        return slice(int(self.frame_offsets[f]), int(self.frame_offsets[f + 1]))


@dataclass(frozen=True)
class Thumbnails:
    """Small JPEG copies of every frame, made while detection reads them (for the rerun timeline).

    Frame ``f`` is ``jpeg[offsets[f]:offsets[f+1]]`` (JPEG bytes, ``width`` pixels wide).
    """

    jpeg: np.ndarray  # (B,) uint8, all frames' JPEG bytes concatenated
    offsets: np.ndarray  # (F + 1,) int64
    width: int

    @property
    def n(self) -> int:
        return len(self.offsets) - 1

    def get(self, f: int) -> bytes:
        return self.jpeg[int(self.offsets[f]):int(self.offsets[f + 1])].tobytes()

    @staticmethod
    def from_list(items: list[bytes], width: int) -> "Thumbnails":
        sizes = np.array([len(b) for b in items], dtype=np.int64)
        jpeg = np.frombuffer(b"".join(items), dtype=np.uint8).copy()
        return Thumbnails(jpeg=jpeg, offsets=np.concatenate([[0], np.cumsum(sizes)]), width=int(width))


@dataclass(frozen=True)
class ManhattanFrame:
    """The three Manhattan directions (paper §3.1): rows are unit world vectors x, y, z.

    Right-handed (``det = +1``); row 2 is the vertical direction, near world +z.
    """

    directions: np.ndarray  # (3, 3) float64


@dataclass(frozen=True)
class Preprocessed:
    """Output of preprocessing (paper §3.1): segments, Manhattan frame, labels, refined rotations."""

    segments: Segments
    manhattan: ManhattanFrame
    labels: np.ndarray  # (S,) int8 Manhattan axis per segment, -1 if none
    R_wc: np.ndarray  # (F, 3, 3) float64 refined world_from_camera rotations
    R_wc_imu: np.ndarray  # (F, 3, 3) float64 the IMU rotations they started from


@dataclass(frozen=True)
class Tracks:
    """Line tracks (supplement §3): each Manhattan segment belongs to at most one track.

    ``track_of[s]`` is the track id of segment ``s`` or -1. ``axis[t]`` is the
    track's Manhattan axis. A track holds at most one segment per frame.
    """

    track_of: np.ndarray  # (S,) int32
    axis: np.ndarray  # (T,) int8

    @property
    def n(self) -> int:
        return len(self.axis)

    def members(self) -> tuple[np.ndarray, np.ndarray]:
        """Returns (segment ids sorted by track, offsets (T+1,)) for iterating track members."""
        seg = np.flatnonzero(self.track_of >= 0)
        order = np.argsort(self.track_of[seg], kind="stable")
        seg = seg[order]
        counts = np.bincount(self.track_of[seg], minlength=self.n)
        offsets = np.concatenate([[0], np.cumsum(counts)])
        return seg, offsets


@dataclass(frozen=True)
class PointTracks:
    """Point tracks (our addition; points/tracking.py): observation ``k`` is track ``track[k]`` seen in frame
    ``frame[k]`` at ``xy[k]`` (undistorted pixels, working resolution), sorted by frame."""

    frame: np.ndarray  # (N,) int32
    track: np.ndarray  # (N,) int32
    xy: np.ndarray  # (N, 2) float32

    @property
    def n(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0


@dataclass(frozen=True)
class NormalMaps:
    """Per-frame surface normals in the WORLD frame (paper §3.2), at low resolution.

    ``maps[f]`` is h x w x 3 float16 unit normals; pixel (u, v) of the working
    image maps to ``(u * scale, v * scale)`` here. ``valid`` marks pixels with
    a usable normal (e.g. the oracle's depth > 0).
    """

    maps: np.ndarray  # (F, h, w, 3) float16
    valid: np.ndarray  # (F, h, w) bool
    scale: float  # normal-map pixels per working-image pixel
    source: str


# Relation kinds (paper §3.2). Colinearity comes from tracks and is not listed here.
ORTHOGONAL, PARALLEL, JUNCTION, FLOOR = 0, 1, 2, 3
RELATION_NAMES = ("orthogonal", "parallel", "junction", "floor")


@dataclass(frozen=True)
class Relations:
    """Detected coplanarities between tracks (paper §3.2), deduplicated across frames.

    ``track_b = -1`` for floor relations: the track lies on the single floor
    plane. ``normal_axis`` is the Manhattan axis of the common plane's normal.
    ``support`` counts the frames in which the relation was detected.
    """

    kind: np.ndarray  # (R,) int8: ORTHOGONAL, PARALLEL, JUNCTION, FLOOR
    track_a: np.ndarray  # (R,) int32
    track_b: np.ndarray  # (R,) int32 (-1 for FLOOR)
    normal_axis: np.ndarray  # (R,) int8
    support: np.ndarray  # (R,) int32

    @property
    def n(self) -> int:
        return len(self.kind)

    def counts(self) -> dict[str, int]:
        return {name: int(np.sum(self.kind == k)) for k, name in enumerate(RELATION_NAMES)}

    def subset(self, index: np.ndarray) -> "Relations":
        """Returns the relations selected by ``index`` (a boolean mask or integer indices)."""
        return Relations(*(np.asarray(getattr(self, f.name))[index] for f in fields(Relations)))

    def between(self, line_ok: np.ndarray) -> np.ndarray:
        """Returns (R,) bool: the relations whose lines (``track_a``, and ``track_b`` of a pair) all have ``line_ok`` (T,)."""
        ok = np.asarray(line_ok, bool)

        def has(t: np.ndarray) -> np.ndarray:
            inside = (t >= 0) & (t < len(ok))
            return inside & ok[np.where(inside, t, 0)] if len(ok) else np.zeros(len(t), bool)

        return has(self.track_a) & ((self.kind == FLOOR) | has(self.track_b))


@dataclass(frozen=True)
class LineModel:
    """3D Manhattan lines, one per track: Taylor parameterisation (paper §3.4).

    ``taylor[t]`` is Lambda_t, the point of the line closest to the origin
    (perpendicular to its direction). ``extent[t] = (s0, s1)``: the segment
    is ``taylor + s * direction`` for s in [s0, s1]. ``direction[t]`` is the
    unit world direction (the Manhattan direction of ``axis[t]``).
    """

    taylor: np.ndarray  # (T, 3) float64
    direction: np.ndarray  # (T, 3) float64
    axis: np.ndarray  # (T,) int8
    extent: np.ndarray  # (T, 2) float64
    valid: np.ndarray  # (T,) bool: False where the track could not be placed

    @property
    def endpoints(self) -> np.ndarray:
        """Returns (T, 6) segment endpoints x1 y1 z1 x2 y2 z2."""
        a = self.taylor + self.extent[:, :1] * self.direction
        b = self.taylor + self.extent[:, 1:] * self.direction
        return np.concatenate([a, b], axis=1)


@dataclass(frozen=True)
class Solution:
    """Camera poses and 3D lines from the linear solve or bundle adjustment.

    Only frames with ``registered[f]`` have a pose; the others are NaN and
    must never be written out.
    """

    R_wc: np.ndarray  # (F, 3, 3)
    centers: np.ndarray  # (F, 3), NaN where not registered
    registered: np.ndarray  # (F,) bool
    lines: LineModel
    camera: Camera  # possibly refined intrinsics (BA phase 3)
    metric: bool  # scale is metric (a camera height was given)
    residuals: dict  # per constraint type / phase, for summary.json
    # (R,) bool over the relations the solver was given: those this solution rests on (the linear solve:
    # all but the floor relations linear.floor_verified finds above the floor; the bundle adjustment: those
    # it used after verification and rejection). A later solve from this one leaves the others out.
    # Empty: not recorded (a hand-made solution), every relation counts
    relations_kept: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
