"""Point tracks (our addition; issue #40): texture corners that give parallax where the lines do not."""
from .stitch import StitchedFocal, arm_focal, spin_focal, stitched_focal
from .tracking import PointTracker, loop_pairs, rotation_homography, track_points

__all__ = ["PointTracker", "StitchedFocal", "arm_focal", "loop_pairs", "rotation_homography", "spin_focal", "stitched_focal",
           "track_points"]
