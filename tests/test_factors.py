"""Factors: analytic Jacobians vs central differences on each variable's retract; residual semantics."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import factors
from factors import taylor_line

UNIT = gtsam.noiseModel.Isotropic.Sigma


def _dim(values, key):
    return values.atVector(key).size if _is_vector(values, key) else 3


def _is_vector(values, key):
    try:
        values.atVector(key)
        return True
    except Exception:
        return False


def _retract_one(values, key, delta):
    """Returns a copy of ``values`` with only ``key`` retracted by ``delta``."""
    vv = gtsam.VectorValues()
    for k in values.keys():
        vv.insert(k, delta if k == key else np.zeros(_dim(values, k)))
    return values.retract(vv)


def check_jacobians(factor, values, eps=1e-6, rtol=1e-5, atol=1e-7):
    """Asserts the factor's analytic Jacobians equal central differences of its unwhitened error."""
    jf = factor.linearize(values)
    A, b = jf.jacobian()
    # tests use unit isotropic noise: whitened == unwhitened
    np.testing.assert_allclose(-b, factor.unwhitenedError(values), rtol=1e-10, atol=1e-12)
    col = 0
    for key in jf.keys():
        d = _dim(values, key)
        num = np.zeros((len(b), d))
        for a in range(d):
            e = np.zeros(d)
            e[a] = eps
            num[:, a] = (factor.unwhitenedError(_retract_one(values, key, e))
                         - factor.unwhitenedError(_retract_one(values, key, -e))) / (2 * eps)
        ana = A[:, col:col + d]
        scale = max(1.0, np.abs(num).max())
        np.testing.assert_allclose(ana, num, rtol=rtol, atol=atol * scale * 1e2,
                                   err_msg=f"Jacobian of key {gtsam.DefaultKeyFormatter(key)}")
        col += d


def random_rot(rng):
    return Rotation.random(random_state=rng).as_matrix()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_colinearity_and_coplanarity_jacobians(seed):
    rng = np.random.default_rng(seed)
    L, M, H, C = gtsam.symbol("l", 0), gtsam.symbol("l", 1), gtsam.symbol("h", 0), gtsam.symbol("c", 0)
    v = gtsam.Values()
    v.insert(L, rng.normal(size=3))
    v.insert(M, rng.normal(size=3))
    v.insert(C, rng.normal(size=3))
    v.insert(H, np.array([rng.normal()]))
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    check_jacobians(factors.colinearity_factor(L, n, UNIT(1, 1.0)), v)
    check_jacobians(factors.coplanarity_factor(L, M, n, UNIT(1, 1.0)), v)
    check_jacobians(factors.floor_factor(L, H, n, UNIT(1, 1.0)), v)
    check_jacobians(factors.plane_offset_factor(L, C, n, 0.7, UNIT(1, 1.0)), v)
    # semantics
    lam_l, lam_m = v.atPoint3(L), v.atPoint3(M)
    assert factors.coplanarity_factor(L, M, n, UNIT(1, 1.0)).unwhitenedError(v)[0] == pytest.approx(n @ (lam_l - lam_m))
    assert factors.floor_factor(L, H, n, UNIT(1, 1.0)).unwhitenedError(v)[0] == pytest.approx(n @ lam_l - v.atVector(H)[0])


def _reprojection_state(rng, nobs):
    """A line seen by nobs cameras around the origin, all looking at it."""
    A = np.eye(3)[rng.integers(3)]
    p = rng.normal(size=3) * 0.3 + 2.5 * np.cross(A, rng.normal(size=3) + 0.1).clip(-1, 1)
    lam = taylor_line.taylor_from_point_direction(p, A) + 0.05 * A  # off the constraint on purpose
    K = np.array([[500.0, 0, 320], [0, 480.0, 240], [0, 0, 1]])
    C = rng.normal(size=(nobs, 3)) * 0.1
    R = []
    for c in C:
        z = (lam - c) / np.linalg.norm(lam - c)  # optical axis towards the line
        x = np.cross(z, rng.normal(size=3))
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R0 = np.stack([x, y, z], axis=1)
        R.append(R0 @ Rotation.from_rotvec(rng.normal(size=3) * 0.05).as_matrix())
    R = np.array(R)
    # observed endpoints: project two points on the line, add noise
    from panosfm_graph.geometry import project
    ep = []
    for c, Rw in zip(C, R):
        X = np.stack([lam - 0.4 * A, lam + 0.5 * A])
        uv, _ = project(K, Rw, c, X)
        ep.append(uv.ravel() + rng.normal(size=4) * 2.0)
    return A, lam, K, C, R, np.array(ep)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("variant", ["fixed_rot", "rot", "rot_focal", "fixed_rot_focal"])
def test_line_reprojection_jacobians(seed, variant):
    rng = np.random.default_rng(seed)
    nobs = 1 + seed
    A, lam, K, C, R, ep = _reprojection_state(rng, nobs)
    v = gtsam.Values()
    L = gtsam.symbol("l", 7)
    ck = [gtsam.symbol("c", i) for i in range(nobs)]
    rk = [gtsam.symbol("r", i) for i in range(nobs)]
    F = gtsam.symbol("f", 0)
    v.insert(L, lam)
    for k, c in zip(ck, C):
        v.insert(k, c)
    with_rot = variant.startswith("rot")
    with_focal = variant.endswith("focal")
    if with_rot:
        for k, Rw in zip(rk, R):
            v.insert(k, gtsam.Rot3(Rw))
    if with_focal:
        v.insert(F, np.array([K[0, 0] * 1.02]))
    f = factors.line_reprojection_factor(L, ck, ep, A, K, UNIT(2 * nobs, 1.0),
                                         rotation_keys=rk if with_rot else None,
                                         R_wc_fixed=None if with_rot else R,
                                         focal_key=F if with_focal else None)
    check_jacobians(f, v, eps=1e-6, rtol=2e-4, atol=1e-6)


@pytest.mark.parametrize("with_rot,robust", [(False, "none"), (True, "none"), (True, "huber"), (False, "cauchy")])
def test_line_reprojection_set_equals_its_factors(with_rot, robust):
    """The vectorised set (one call per linearisation) gives the factors' cost and Gauss-Newton system exactly."""
    rng = np.random.default_rng(11)
    v = gtsam.Values()
    lk, ck, rk, eps, dirs, Rs = [], [], [], [], [], []
    for line, nobs in enumerate([3, 11, 1]):  # 11 > chunk 8: one line in two factors
        A, lam, K, C, R, ep = _reprojection_state(rng, nobs)
        v.insert(gtsam.symbol("l", line), lam)
        for j, (c, Rw) in enumerate(zip(C, R)):
            cam = 100 * line + j
            v.insert(gtsam.symbol("c", cam), c)
            v.insert(gtsam.symbol("r", cam), gtsam.Rot3(Rw))
            lk.append(gtsam.symbol("l", line))
            ck.append(gtsam.symbol("c", cam))
            rk.append(gtsam.symbol("r", cam))
        eps.append(ep)
        dirs.append(np.broadcast_to(A, (nobs, 3)))
        Rs.append(R)
    rep = factors.LineReprojectionSet(lk, ck, np.concatenate(eps), np.concatenate(dirs), K, 0.7,
                                      rotation_keys=rk if with_rot else None,
                                      R_wc_fixed=None if with_rot else np.concatenate(Rs), robust=robust, k=2.0)
    assert len(rep) == 15
    assert rep.runs(8) == ([(0, 3), (3, 11), (11, 14), (14, 15)] if robust == "none" else [(i, i + 1) for i in range(15)])
    g = gtsam.NonlinearFactorGraph()
    for f in rep.factors(8):
        g.add(f)
    assert g.size() == (4 if robust == "none" else 15)  # a kernel weighs each observation: one factor each
    assert rep.error(v) == pytest.approx(g.error(v), rel=1e-12)
    assert rep.error(v) > 1.0  # the state is off the observations on purpose
    if robust != "none":  # some observations are beyond the kernel's threshold: the kernel matters
        plain = factors.LineReprojectionSet(lk, ck, np.concatenate(eps), np.concatenate(dirs), K, 0.7,
                                            rotation_keys=rk if with_rot else None,
                                            R_wc_fixed=None if with_rot else np.concatenate(Rs))
        assert rep.error(v) < 0.9 * plain.error(v)
    ref, mine = g.linearize(v), rep.linearize(v)
    assert mine.size() == 15
    keys = sorted(set(ref.keys()))
    order = gtsam.Ordering()
    for k in keys:
        order.push_back(k)
    for a, b in zip(mine.hessian(order), ref.hessian(order)):  # (A^T A, A^T b)
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())


def test_line_reprojection_is_segment_averaged_distance():
    rng = np.random.default_rng(5)
    A, lam, K, C, R, ep = _reprojection_state(rng, 3)
    d1, d2 = factors.segment_distances(ep, np.broadcast_to(lam, (3, 3)), A, R, C, K)
    # brute force: distance of 2001 points along each segment to the projected line
    lines = taylor_line.project_line(np.broadcast_to(lam, (3, 3)), A, R, C, K)
    t = np.linspace(0, 1, 2001)
    for s in range(3):
        pts = ep[s, :2] + t[:, None] * (ep[s, 2:] - ep[s, :2])
        dist = pts @ lines[s, :2] + lines[s, 2]
        assert dist[0] == pytest.approx(d1[s], rel=1e-9, abs=1e-9)
        assert dist[-1] == pytest.approx(d2[s], rel=1e-9, abs=1e-9)
        r = factors.segment_residuals(d1[s:s + 1], d2[s:s + 1])
        assert np.sum(r**2) == pytest.approx(np.trapezoid(dist**2, t), rel=1e-6)
    # exact line, exact endpoints -> zero residual
    from panosfm_graph.geometry import project
    lam0 = taylor_line.taylor_from_point_direction(lam, A)
    uv, _ = project(K, R[0], C[0], np.stack([lam0, lam0 + A]))
    d1, d2 = factors.segment_distances(uv.reshape(1, 4), lam0[None], A, R[:1], C[:1], K)
    assert abs(d1[0]) < 1e-8 and abs(d2[0]) < 1e-8


def test_imu_rotation_factor_zero_at_measurement_and_jacobian():
    rng = np.random.default_rng(3)
    Ri, Rj = random_rot(rng), random_rot(rng)
    ki, kj = gtsam.symbol("r", 0), gtsam.symbol("r", 1)
    noise = factors.imu_noise(0.2)
    f = factors.imu_rotation_factor(ki, kj, Ri, Rj, noise)
    v = gtsam.Values()
    v.insert(ki, gtsam.Rot3(Ri))
    v.insert(kj, gtsam.Rot3(Rj))
    assert np.linalg.norm(f.unwhitenedError(v)) < 1e-9
    # perturb j by 0.5 deg about its own z axis: error = that rotation vector
    dv = np.radians([0.0, 0.0, 0.5])
    v2 = gtsam.Values()
    v2.insert(ki, gtsam.Rot3(Ri))
    v2.insert(kj, gtsam.Rot3(Rj @ Rotation.from_rotvec(dv).as_matrix()))
    np.testing.assert_allclose(f.unwhitenedError(v2), dv, atol=1e-9)
    # whitened error = 0.5 deg / 0.2 deg sigma
    assert np.sqrt(2 * f.error(v2)) == pytest.approx(2.5, rel=1e-6)


def test_noise_models_and_weights():
    assert factors.sigma_from_weight(1e4) == pytest.approx(0.01)
    nm = factors.noise_model(1, 0.01, "huber", 1.345)
    # whitened residual 10 sigmas: Huber loss k(|r| - k/2) instead of r²/2
    assert nm.loss(nm.squaredMahalanobisDistance(np.array([0.1]))) == pytest.approx(1.345 * (10 - 1.345 / 2), rel=1e-6)
    nc = factors.noise_model(1, 1.0, "cauchy", 2.0)
    assert nc.loss(nc.squaredMahalanobisDistance(np.array([2.0]))) == pytest.approx(2.0 * np.log(2.0), rel=1e-6)
    np.testing.assert_allclose(factors.robust_weight([0.5, 10.0], "huber", 1.0), [1.0, 0.1])
    # the vectorised weights are GTSAM's kernels' weights, for every kernel
    r = np.array([0.0, 0.5, 1.345, 3.0, 30.0])
    for name in ("huber", "cauchy", "geman_mcclure"):
        kernel = factors.robust_kernel(name, 1.345)
        np.testing.assert_allclose(factors.robust_weight(r, name, 1.345), [kernel.weight(x) for x in r], rtol=1e-9)
    # Geman-McClure redescends: a residual 100 sigmas off costs no more than k^2 / 2 (Cauchy: log-growing)
    ng = factors.noise_model(1, 1.0, "geman_mcclure", 1.345)
    nc = factors.noise_model(1, 1.0, "cauchy", 1.345)
    big = lambda nm: nm.loss(nm.squaredMahalanobisDistance(np.array([100.0])))  # noqa: E731
    assert big(ng) <= 1.345**2 / 2 + 1e-9 and big(nc) > 5 * big(ng)
    with pytest.raises(ValueError):
        factors.noise_model(1, 1.0, "tukeyx")


def test_taylor_helpers_roundtrip():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(5, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = rng.normal(size=(5, 3))
    lam = taylor_line.taylor_from_point_direction(p, d)
    np.testing.assert_allclose(np.sum(lam * d, axis=1), 0, atol=1e-12)
    # Lambda is the closest point: the norm is the line's distance from the origin
    s = taylor_line.line_extent(lam, d, p)
    np.testing.assert_allclose(lam + s[:, None] * d, p, atol=1e-12)
    pl = taylor_line.plucker(lam, d)
    np.testing.assert_allclose(np.linalg.norm(pl[:, 3:], axis=1), np.linalg.norm(lam, axis=1), atol=1e-12)


def _normal_equations(factor, values, order):
    g = gtsam.GaussianFactorGraph()
    g.push_back(factor.linearize(values))
    return g.augmentedHessian(order)


@pytest.mark.parametrize("robust", ["none", "huber", "cauchy"])
def test_builtin_relation_factors_equal_custom(robust):
    rng = np.random.default_rng(11)
    L, M = gtsam.symbol("l", 0), gtsam.symbol("l", 1)
    v = gtsam.Values()
    v.insert(L, rng.normal(size=3))
    v.insert(M, rng.normal(size=3))
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    sigma = 0.01
    pairs = [
        (factors.coplanarity_factor(L, M, n, factors.noise_model(1, sigma, robust)),
         factors.coplanarity_factor_builtin(L, M, n, sigma, robust)),
    ]
    if robust == "none":
        pairs.append((factors.colinearity_factor(L, n, factors.noise_model(1, sigma)),
                      factors.colinearity_factor_builtin(L, n, sigma)))
    for custom, builtin in pairs:
        assert builtin.error(v) == pytest.approx(custom.error(v), rel=1e-10)
        # same whitened normal equations (the builtin has two extra zero rows)
        order = gtsam.Ordering()
        for k in custom.keys():
            order.push_back(k)
        Hc, Hb = (_normal_equations(f, v, order) for f in (custom, builtin))
        np.testing.assert_allclose(Hb, Hc, rtol=1e-9, atol=1e-9 * np.abs(Hc).max())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_spin_prior_jacobians_and_semantics(seed):
    """The spin prior's analytic Jacobians equal central differences; it is zero on the spin circle."""
    rng = np.random.default_rng(seed)
    M = random_rot(rng).T  # rows: two horizontal Manhattan axes and up
    C, S0, S1, AB = gtsam.symbol("c", 3), gtsam.symbol("s", 0), gtsam.symbol("s", 1), gtsam.symbol("a", 0)
    view = rng.normal(size=3)
    alpha = float(rng.uniform())
    v = gtsam.Values()
    v.insert(C, rng.normal(size=3))
    v.insert(S0, rng.normal(size=3))
    v.insert(S1, rng.normal(size=3))
    v.insert(AB, rng.normal(size=2))
    f = factors.spin_prior_factor(C, (S0, S1), alpha, AB, M, view, UNIT(3, 1.0))
    check_jacobians(f, v)
    # a centre on the circle about the interpolated stand point, at its height
    h = factors.horizontal_direction(M, view)
    a, b = 0.35, -0.04
    arm_m = np.array([a * h[0] - b * h[1], a * h[1] + b * h[0], 0.0])  # Manhattan coordinates
    s0, s1 = np.array([0.3, -1.2, 1.5]), np.array([0.36, -1.1, 1.52])
    s = (1 - alpha) * s0 + alpha * s1
    for lift, expect in ((0.0, [0.0, 0.0, 0.0]), (0.05, [0.0, 0.0, 0.05])):  # 5 cm above: the vertical residual only
        on = gtsam.Values()
        on.insert(C, s + M.T @ arm_m + lift * M[2])
        on.insert(S0, s0)
        on.insert(S1, s1)
        on.insert(AB, np.array([a, b]))
        np.testing.assert_allclose(f.unwhitenedError(on), expect, atol=1e-12)


@pytest.mark.parametrize("robust,n_knots", [("none", 3), ("huber", 3), ("huber", 1)])
def test_spin_prior_set_equals_the_factors(robust, n_knots):
    """factors.SpinPriorSet: the same cost and the same linearisation (augmented Hessian, the arm's column split
    into cross-term HessianFactors) as a graph of spin_prior_factor CustomFactors, with a robust kernel (some
    frames far off the circle) and with one knot (both knot keys the same)."""
    rng = np.random.default_rng(5)
    M = random_rot(rng).T
    n = 12
    turned = np.linspace(0.0, 330.0, n)
    j, alpha, K = factors.spin_knots(turned, 0.0 if n_knots == 1 else 165.0)
    assert K == n_knots
    centres = [gtsam.symbol("c", i) for i in range(n)]
    knots = [(gtsam.symbol("s", jj), gtsam.symbol("s", min(jj + 1, K - 1))) for jj in j]
    AB = gtsam.symbol("a", 0)
    views = rng.normal(size=(n, 3))
    v = gtsam.Values()
    for i, c in enumerate(centres):
        v.insert(c, rng.normal(size=3) * (0.02 if i % 4 else 0.5))  # every 4th far off: the kernel acts
    for jj in range(K):
        v.insert(gtsam.symbol("s", jj), rng.normal(size=3) * 0.01)
    v.insert(AB, np.array([0.3, 0.02]))
    noise = factors.spin_noise(0.02, 0.03, robust, 1.345)
    graph = gtsam.NonlinearFactorGraph()
    for c, kk, al, view in zip(centres, knots, alpha, views):
        graph.add(factors.spin_prior_factor(c, kk, al, AB, M, view, noise))
    batch = factors.SpinPriorSet(centres, knots, alpha, AB, M, views, 0.02, 0.03, robust, 1.345)
    assert abs(batch.error(v) - graph.error(v)) < 1e-9 * max(1.0, graph.error(v))
    order = gtsam.Ordering()
    for k in v.keys():
        order.push_back(k)
    H_graph = graph.linearize(v).augmentedHessian(order)
    H_set = batch.linearize(v).augmentedHessian(order)
    np.testing.assert_allclose(H_set, H_graph, rtol=1e-9, atol=1e-9 * np.abs(H_graph).max())


def test_spin_knots_interpolate_by_turn():
    """Knots spread evenly over the turn; each frame lies between knots j and j + 1 at fraction alpha."""
    turned = np.linspace(0.0, 380.0, 39)
    j, alpha, n = factors.spin_knots(turned, 90.0)
    assert n == 6  # ceil(380 / 90) = 5 intervals of 76 degrees
    np.testing.assert_allclose((j + alpha) * 76.0, turned, atol=1e-9)
    assert j.max() == 4 and alpha[-1] == pytest.approx(1.0)
    j0, a0, n0 = factors.spin_knots(turned, 0.0)
    assert n0 == 1 and not j0.any() and not a0.any()


@pytest.mark.parametrize("name", ["none", "huber", "cauchy", "geman_mcclure"])
def test_robust_loss_and_weight_equal_gtsam(name):
    e = np.array([0.0, 0.3, 1.0, 2.5, 7.0])
    est = factors.robust_kernel(name, 1.7)
    loss, weight = factors.robust_loss(e, name, 1.7), factors.robust_weight(e, name, 1.7)
    if est is None:
        np.testing.assert_allclose(loss, 0.5 * e**2)
        np.testing.assert_allclose(weight, 1.0)
    else:
        np.testing.assert_allclose(loss, [est.loss(x) for x in e], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(weight[1:], [est.weight(x) for x in e[1:]], rtol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_drift_prior_jacobians_and_semantics(seed):
    """The drift-slope rotation prior's analytic Jacobians equal central differences; at s = 0 it is GTSAM's
    PriorFactorRot3, and a frame turned by s tau about up has zero error."""
    rng = np.random.default_rng(seed)
    Rk, Sk = gtsam.symbol("r", 4), gtsam.symbol("d", 0)
    Rp = random_rot(rng)
    up = rng.normal(size=3)
    up /= np.linalg.norm(up)
    tau = float(rng.uniform(-0.5, 0.5))
    f = factors.drift_prior_factor(Rk, Sk, Rp, up, tau, UNIT(3, 1.0))
    v = gtsam.Values()
    v.insert(Rk, gtsam.Rot3(Rp @ Rotation.from_rotvec(rng.normal(scale=0.3, size=3)).as_matrix()))
    v.insert(Sk, np.array([rng.normal(scale=0.5)]))
    check_jacobians(f, v)
    plain = gtsam.PriorFactorRot3(Rk, gtsam.Rot3(Rp), UNIT(3, 1.0))
    zero = gtsam.Values()
    zero.insert(Rk, v.atRot3(Rk))
    zero.insert(Sk, np.array([0.0]))
    np.testing.assert_allclose(f.unwhitenedError(zero), plain.unwhitenedError(zero), atol=1e-12)
    s = 0.01
    on = gtsam.Values()
    on.insert(Rk, gtsam.Rot3(Rotation.from_rotvec(s * tau * up).as_matrix() @ Rp))
    on.insert(Sk, np.array([s]))
    np.testing.assert_allclose(f.unwhitenedError(on), 0.0, atol=1e-12)
    np.testing.assert_allclose(factors.drift_times(np.array([0, 5, 10]), 11), [-0.5, 0.0, 0.5])


def _shared_frames_problem(rng, n_frames=4, n_lines=5, per_line=3):
    """Lines seen from frames that share them (so each centre and rotation has several observations), the state
    off the observations, the focal 2 % off the base K's."""
    from panosfm_graph.geometry import project
    K = np.array([[500.0, 0, 320], [0, 480.0, 240], [0, 0, 1]])
    C = rng.normal(size=(n_frames, 3)) * 0.1
    R = np.array([Rotation.from_rotvec(rng.normal(size=3) * 0.15).as_matrix() for _ in range(n_frames)])
    v = gtsam.Values()
    F = gtsam.symbol("f", 0)
    v.insert(F, np.array([K[0, 0] * 1.02]))
    for i in range(n_frames):
        v.insert(gtsam.symbol("c", i), C[i] + rng.normal(size=3) * 0.02)
        v.insert(gtsam.symbol("r", i), gtsam.Rot3(R[i] @ Rotation.from_rotvec(rng.normal(size=3) * 0.01).as_matrix()))
    lk, ck, rk, eps, dirs, Rs = [], [], [], [], [], []
    for line in range(n_lines):
        A = np.eye(3)[line % 2]  # x or y: across the cameras' view along +z
        p = np.array([0.0, 0.0, 3.0]) + rng.normal(size=3) * 0.5
        lam = taylor_line.taylor_from_point_direction(p, A)
        v.insert(gtsam.symbol("l", line), lam + rng.normal(size=3) * 0.03)
        for i in rng.choice(n_frames, per_line, replace=False):
            uv, _ = project(K, R[i], C[i], np.stack([p - 0.4 * A, p + 0.5 * A]))
            eps.append(uv.ravel() + rng.normal(size=4) * 2.0)
            lk.append(gtsam.symbol("l", line))
            ck.append(gtsam.symbol("c", i))
            rk.append(gtsam.symbol("r", i))
            dirs.append(A)
            Rs.append(R[i])
    return v, F, K, lk, ck, rk, np.array(eps), np.array(dirs), np.array(Rs)


def _damped(gfg, values, lam=0.1):
    """``gfg`` with lm.levenberg_marquardt's damping: a JacobianFactor sqrt(lam) I on every variable (the gauge
    freedoms make this problem indeterminate at lam = 1e-3, linearised by the factors or by the set alike)."""
    out = gtsam.GaussianFactorGraph()
    out.push_back(gfg)
    for k in values.keys():
        d = values.atVector(k).size if chr(gtsam.Symbol(k).chr()) == "f" else 3
        out.push_back(gtsam.JacobianFactor(k, np.sqrt(lam) * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
    return out


@pytest.mark.parametrize("with_rot,robust", [(True, "none"), (True, "huber"), (False, "none"), (True, "cauchy")])
def test_line_reprojection_set_with_focal_equals_its_factors(with_rot, robust):
    """With the focal as a variable, the set's split linearisation (3-key JacobianFactors, (variable, focal) cross
    HessianFactors, one focal HessianFactor) is the factors' (4 keys each): same cost, same information matrix and
    vector, same linear error at a random step and the same damped Gauss-Newton step on every key."""
    rng = np.random.default_rng(3)
    v, F, K, lk, ck, rk, ep, dirs, Rs = _shared_frames_problem(rng)
    if not with_rot:
        for k in rk:
            if v.exists(k):
                v.erase(k)
    rep = factors.LineReprojectionSet(lk, ck, ep, dirs, K, 0.7, rotation_keys=rk if with_rot else None,
                                      R_wc_fixed=None if with_rot else Rs, robust=robust, k=2.0, focal_key=F)
    fs = rep.factors(8)
    assert all(F in f.keys() for f in fs)  # the set's focal is its factors' by default
    g = gtsam.NonlinearFactorGraph()
    for f in fs:
        g.add(f)
    assert rep.error(v) == pytest.approx(g.error(v), rel=1e-12)
    assert rep.error(v) > 1.0
    ref, mine = g.linearize(v), rep.linearize(v)
    n_vars = 5 + 4 + (4 if with_rot else 0)
    assert mine.size() == len(rep) + n_vars + 1  # per observation, per variable, the focal
    keys = sorted(set(ref.keys()))
    assert sorted(set(mine.keys())) == keys
    order = gtsam.Ordering()
    for k in keys:
        order.push_back(k)
    for a, b in zip(mine.hessian(order), ref.hessian(order)):  # (A^T A, A^T b)
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-10 * np.abs(b).max())
    step, zero = gtsam.VectorValues(), gtsam.VectorValues()
    for k in keys:
        step.insert(k, rng.normal(size=1 if k == F else 3) * (1.0 if k == F else 0.01))
        zero.insert(k, np.zeros(1 if k == F else 3))
    assert mine.error(step) == pytest.approx(ref.error(step), rel=1e-10)
    assert mine.error(zero) == pytest.approx(ref.error(zero), rel=1e-10)
    assert abs(ref.error(step) - ref.error(zero)) > 1e-2 * ref.error(step)  # the step matters
    d_ref, d_mine = _damped(ref, v).optimize(), _damped(mine, v).optimize()
    assert abs(d_ref.at(F)[0]) > 1e-3  # the focal moves
    for k in keys:
        np.testing.assert_allclose(d_mine.at(k), d_ref.at(k), rtol=1e-7, atol=1e-9 * np.abs(d_ref.at(k)).max(),
                                   err_msg=gtsam.DefaultKeyFormatter(k))


@pytest.mark.parametrize("robust", ["none", "huber", "geman_mcclure"])
def test_line_reprojection_set_with_focal_error_equals_its_factors(robust):
    """With the focal as a variable, the set's cost and residuals read fx from the values: the factors' at every
    focal (and not the base K's)."""
    v, F, K, lk, ck, rk, ep, dirs, Rs = _shared_frames_problem(np.random.default_rng(4))
    rep = factors.LineReprojectionSet(lk, ck, ep, dirs, K, 0.7, rotation_keys=rk, robust=robust, k=2.0, focal_key=F)
    fixed_k = factors.LineReprojectionSet(lk, ck, ep, dirs, K, 0.7, rotation_keys=rk, robust=robust, k=2.0)
    fs = rep.factors(8)
    g = gtsam.NonlinearFactorGraph()
    for f in fs:
        g.add(f)
    for fx in (0.97, 1.0, 1.02, 1.1):
        v.update(F, np.array([K[0, 0] * fx]))
        assert rep.error(v) == pytest.approx(g.error(v), rel=1e-12)
        np.testing.assert_allclose(rep.residuals(v), np.concatenate([f.unwhitenedError(v).reshape(-1, 2) for f in fs]),
                                   rtol=1e-12, atol=1e-12)
        if fx != 1.0:
            assert abs(rep.error(v) - fixed_k.error(v)) > 1e-3 * rep.error(v)


def _point_state(rng, n):
    """n frames near the origin looking at points 2-4 m ahead, observations off by ~2 px."""
    K = np.array([[700.0, 0, 320], [0, 690.0, 240], [0, 0, 1]])
    R = np.stack([Rotation.from_rotvec(rng.normal(0, 0.1, 3)).as_matrix() for _ in range(n)])
    C = rng.normal(0, 0.1, (n, 3))
    P = C + np.einsum("nij,nj->ni", R, np.c_[rng.normal(0, 0.5, (n, 2)), rng.uniform(2, 4, n)])
    uv, depth = factors.project_points(R, C, P, K)
    assert np.all(depth > 1.0)
    return K, R, C, P, uv + rng.normal(0, 2.0, uv.shape)


@pytest.mark.parametrize("seed,with_rot,with_focal", [(0, False, False), (1, True, False), (2, True, False),
                                                      (3, False, True), (4, True, True)])
def test_point_projection_jacobians(seed, with_rot, with_focal):
    rng = np.random.default_rng(seed)
    K, R, C, P, uv = _point_state(rng, 1)
    v = gtsam.Values()
    ck, pk, rk, fk = gtsam.symbol("c", 0), gtsam.symbol("p", 0), gtsam.symbol("r", 0), gtsam.symbol("f", 0)
    v.insert(ck, C[0])
    v.insert(pk, P[0])
    if with_rot:
        v.insert(rk, gtsam.Rot3(R[0]))
    if with_focal:
        v.insert(fk, np.array([1.03 * K[0, 0]]))
    f = factors.point_projection_factor(ck, pk, uv[0], K, UNIT(2, 1.0), R_wc=None if with_rot else R[0],
                                        rotation_key=rk if with_rot else None, focal_key=fk if with_focal else None)
    check_jacobians(f, v, eps=1e-6, rtol=1e-5, atol=1e-6)
    # semantics: the exact projection gives a zero residual
    exact, _ = factors.project_points(R, C, P, K)
    f0 = factors.point_projection_factor(ck, pk, exact[0], K, UNIT(2, 1.0), R_wc=None if with_rot else R[0],
                                         rotation_key=rk if with_rot else None)
    np.testing.assert_allclose(f0.unwhitenedError(v), 0.0, atol=1e-9)
    assert np.linalg.norm(f.unwhitenedError(v)) > 0.5


@pytest.mark.parametrize("robust", ["none", "huber"])
def test_point_projection_set_equals_its_factors(robust):
    """The vectorised set gives the CustomFactors' cost and Gauss-Newton system, held and free rotations mixed."""
    rng = np.random.default_rng(4)
    n = 12
    K, R, C, P, uv = _point_state(rng, n)
    v = gtsam.Values()
    ck = [gtsam.symbol("c", i % 4) for i in range(n)]  # 4 frames, 6 points: shared variables
    pk = [gtsam.symbol("p", i % 6) for i in range(n)]
    rk = [gtsam.symbol("r", i % 4) if i % 4 >= 2 else None for i in range(n)]  # frames 2, 3 free
    for i in range(4):
        v.insert(ck[i], C[i])
        if i >= 2:
            v.insert(gtsam.symbol("r", i), gtsam.Rot3(R[i]))
    for i in range(6):
        v.insert(pk[i], P[i])
    R_obs = R[np.arange(n) % 4]
    rep = factors.PointProjectionSet(ck, pk, uv, K, 0.8, R_obs, rotation_keys=rk, robust=robust, k=1.345)
    g = gtsam.NonlinearFactorGraph()
    noise = factors.noise_model(2, 0.8, robust, 1.345)
    for i in range(n):
        g.add(factors.point_projection_factor(ck[i], pk[i], uv[i], K, noise,
                                              R_wc=None if rk[i] is not None else R_obs[i], rotation_key=rk[i]))
    assert rep.error(v) == pytest.approx(g.error(v), rel=1e-12)
    assert rep.error(v) > 10.0  # the observations are off the state: the test can fail
    order = gtsam.Ordering()
    for k in sorted(set(g.linearize(v).keys())):
        order.push_back(k)
    for a, b in zip(rep.linearize(v).hessian(order), g.linearize(v).hessian(order)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())


@pytest.mark.parametrize("robust", ["none", "huber"])
def test_point_projection_set_with_focal_equals_its_factors(robust):
    """With the focal as a variable (every rotation free) the set's split linearisation (3-key JacobianFactors and
    the focal's cross terms) is the 4-key factors': same cost at a focal off K's, same information matrix."""
    rng = np.random.default_rng(5)
    n = 12
    K, R, C, P, uv = _point_state(rng, n)
    fk = gtsam.symbol("f", 0)
    v = gtsam.Values()
    ck = [gtsam.symbol("c", i % 4) for i in range(n)]
    pk = [gtsam.symbol("p", i % 6) for i in range(n)]
    rk = [gtsam.symbol("r", i % 4) for i in range(n)]
    for i in range(4):
        v.insert(ck[i], C[i])
        v.insert(rk[i], gtsam.Rot3(R[i]))
    for i in range(6):
        v.insert(pk[i], P[i])
    v.insert(fk, np.array([0.97 * K[0, 0]]))
    R_obs = R[np.arange(n) % 4]
    rep = factors.PointProjectionSet(ck, pk, uv, K, 0.8, R_obs, rotation_keys=rk, robust=robust, k=1.345,
                                     focal_key=fk)
    g = gtsam.NonlinearFactorGraph()
    noise = factors.noise_model(2, 0.8, robust, 1.345)
    for i in range(n):
        g.add(factors.point_projection_factor(ck[i], pk[i], uv[i], K, noise, rotation_key=rk[i], focal_key=fk))
    assert rep.error(v) == pytest.approx(g.error(v), rel=1e-12)
    held = factors.PointProjectionSet(ck, pk, uv, K, 0.8, R_obs, rotation_keys=rk, robust=robust, k=1.345)
    assert abs(held.error(v) - rep.error(v)) > 1e-3 * rep.error(v)  # the focal in the values counts
    order = gtsam.Ordering()
    for k in sorted(set(g.linearize(v).keys())):
        order.push_back(k)
    for a, b in zip(rep.linearize(v).hessian(order), g.linearize(v).hessian(order)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.abs(b).max())
    with pytest.raises(ValueError):
        factors.PointProjectionSet(ck, pk, uv, K, 0.8, R_obs, rotation_keys=[None] + rk[1:], focal_key=fk)
