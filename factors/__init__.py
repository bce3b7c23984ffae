"""Custom GTSAM factors for panoramic line SfM (paper §3.4): numpy inputs + gtsam keys -> gtsam factors.

One small module per factor; each error function has analytic Jacobians,
checked against central differences in ``tests/test_factors.py``.
"""
from factors.colinearity import colinearity_error, colinearity_factor, colinearity_factor_builtin
from factors.coplanarity import (
    coplanarity_error,
    coplanarity_factor,
    coplanarity_factor_builtin,
    floor_error,
    floor_factor,
    plane_offset_error,
    plane_offset_factor,
)
from factors.heading_drift import drift_prior_error, drift_prior_factor, drift_times
from factors.imu_rotation import imu_noise, imu_rotation_factor
from factors.line_reprojection import (
    LineReprojectionSet,
    line_reprojection_error,
    line_reprojection_factor,
    reprojection_terms,
    segment_distances,
    segment_residuals,
)
from factors.point_projection import (
    PointProjectionSet,
    point_projection_error,
    point_projection_factor,
    point_terms,
    project_points,
)
from factors.robust import noise_model, projection_noise, robust_kernel, robust_loss, robust_weight, sigma_from_weight
from factors.spin_prior import (
    SpinPriorSet,
    horizontal_direction,
    spin_knots,
    spin_model_rows,
    spin_noise,
    spin_prior_error,
    spin_prior_factor,
)
from factors.taylor_line import (
    interpretation_normal,
    line_extent,
    plucker,
    project_line,
    taylor_from_point_direction,
    taylor_to_point_direction,
)

__all__ = [
    "colinearity_error", "colinearity_factor", "colinearity_factor_builtin",
    "coplanarity_error", "coplanarity_factor", "coplanarity_factor_builtin", "floor_error", "floor_factor",
    "plane_offset_error", "plane_offset_factor",
    "drift_prior_error", "drift_prior_factor", "drift_times",
    "imu_noise", "imu_rotation_factor",
    "LineReprojectionSet", "line_reprojection_error", "line_reprojection_factor", "reprojection_terms", "segment_distances", "segment_residuals",
    "PointProjectionSet", "point_projection_error", "point_projection_factor", "point_terms", "project_points",
    "noise_model", "projection_noise", "robust_kernel", "robust_loss", "robust_weight", "sigma_from_weight",
    "SpinPriorSet", "horizontal_direction", "spin_knots", "spin_model_rows", "spin_noise", "spin_prior_error", "spin_prior_factor",
    "interpretation_normal", "line_extent", "plucker", "project_line",
    "taylor_from_point_direction", "taylor_to_point_direction",
]
