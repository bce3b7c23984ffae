"""The shared ray helpers (geometry.py) against points projected with known cameras."""
import numpy as np

from panosfm_graph.geometry import closest_on_lines, pixel_rays, project, quat_wxyz_to_matrix, world_rays

K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 180.0], [0.0, 0.0, 1.0]])


def _cameras(n, rng):
    q = rng.normal(size=(n, 4))
    R = quat_wxyz_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))
    return R, rng.normal(scale=0.3, size=(n, 3))


def test_world_rays_point_at_the_points_they_see():
    rng = np.random.default_rng(0)
    R, C = _cameras(20, rng)
    X = C + np.einsum("nij,nj->ni", R, np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(2, 5, 20)])  # in front
    uv = np.array([project(K, R[n], C[n], X[n:n + 1])[0][0] for n in range(20)])
    D = world_rays(K, R, uv)
    want = (X - C) / np.linalg.norm(X - C, axis=1, keepdims=True)
    assert np.allclose(D, want, atol=1e-12)
    # pixel_rays keeps any leading shape (floor_contacts passes (n, k, 2) samples)
    grid = uv.reshape(4, 5, 2)
    assert pixel_rays(K, grid).shape == (4, 5, 3)
    assert np.allclose(pixel_rays(K, grid).reshape(-1, 3), pixel_rays(K, uv))


def test_closest_on_lines_finds_the_seen_point_and_refuses_parallel_rays():
    rng = np.random.default_rng(1)
    n = 50
    P = rng.normal(size=(n, 3))
    U = rng.normal(size=(n, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    s_true = rng.uniform(-2, 2, n)
    O = rng.normal(scale=3.0, size=(n, 3))
    D = P + s_true[:, None] * U - O
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    assert np.allclose(closest_on_lines(P, U, O, D), s_true, atol=1e-9)
    # a ray along its line has no nearest point: NaN, not a huge number
    s = closest_on_lines(P[:3], U[:3], O[:3], U[:3])
    assert np.all(np.isnan(s))
    # the threshold is the squared sine of the angle: 1e-3 rad (sin^2 1e-6) passes at 1e-9, not at 1e-5
    tilt = np.cross(U[0], [0.0, 0.0, 1.0])
    tilt /= np.linalg.norm(tilt)
    d = np.cos(1e-3) * U[0] + np.sin(1e-3) * tilt
    assert np.isfinite(closest_on_lines(P[:1], U[:1], O[:1], d[None]))[0]
    assert np.isnan(closest_on_lines(P[:1], U[:1], O[:1], d[None], min_sin2=1e-5))[0]
