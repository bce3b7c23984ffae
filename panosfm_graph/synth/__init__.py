"""Synthetic spin captures of Manhattan box rooms (ray-cast), with ground truth.

``synthesize(out_dir, scene="living", n_frames=300)`` writes a capture in the
format of ``capture-format.md`` (frames, camera.json, frames.csv, imu.csv and
ground_truth/). The pieces are usable alone: :func:`make_scene` /
:data:`SCENES` (box rooms), :func:`spin_trajectory` (ground-truth poses),
:func:`imu_stream` (drifting IMU attitude), :func:`render_frame` (colour,
depth, normals of one view). ``cut_spin(panorama, out_dir)`` writes a
rotation-only spin capture cut from an equirectangular panorama (:mod:`.panorama`).
``room_spin(panorama, layout, out)`` writes a hand-held spin with parallax inside the panorama's room, its surfaces
painted with the panorama (:mod:`.pano_room`); ``scene="random"`` is a procedural room and spin (:mod:`.procedural`).
``phone_recording(capture, out)`` re-expresses a capture as a phone video with raw
gyroscope and accelerometer logs (:mod:`.phone`).
"""
from .scenes import SCENES, Faces, Scene, make_scene, scene_from_json, yaw_matrix
from .trajectory import SpinParams, imu_stream, spin_params, spin_pose, spin_trajectory
from .render import intrinsics, raycast, render_frame
from .writer import frame_name, synthesize
from .panorama import cut_spin, read_layout, read_panorama, render_view
from .phone import phone_recording
from .pano_room import read_room_layout, room_spin
from .procedural import random_spin

__all__ = [
    "SCENES", "Faces", "Scene", "make_scene", "scene_from_json", "yaw_matrix",
    "SpinParams", "imu_stream", "spin_params", "spin_pose", "spin_trajectory",
    "intrinsics", "raycast", "render_frame", "frame_name", "synthesize",
    "cut_spin", "read_layout", "read_panorama", "render_view", "phone_recording", "read_room_layout", "room_spin",
    "random_spin",
]
