"""Point tracks (our addition; issue #40): texture corners that give parallax where the lines do not."""
from .tracking import loop_pairs, rotation_homography, track_points

__all__ = ["loop_pairs", "rotation_homography", "track_points"]
