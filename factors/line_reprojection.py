"""Line reprojection factor (paper §3.4): segment-averaged pixel distance to the projected 3D line.

The 3D line ``l`` is ``{Lambda_l + s A_l}`` (``taylor_line``); in frame ``i``
with ``R_wc_i`` and centre ``c_i`` it projects to the image line ``K^-T n``
with ``n = R_wc_i^T ((Lambda_l - c_i) x A_l)``. For an observed segment with
endpoints x1, x2 let d1, d2 be their signed pixel distances to that line.
The paper averages the (squared) distance over all points of the segment
(Taylor & Kriegman): along the segment the distance is linear, so the mean
squared distance is ``(d1² + d1 d2 + d2²) / 3``. Each observation gives the
2-vector

    r = [ (d1 + d2) / 2,  (d1 - d2) / (2 sqrt 3) ],   ||r||² = (d1² + d1 d2 + d2²) / 3.

One factor holds several observations of ONE line (a track or a chunk of it),
residuals stacked, which keeps the number of Python callbacks low (see
``notes/gtsam-python-performance.md``). Keys, in order:
``[line, centre_1..centre_n, (rotation_1..rotation_n), (focal)]``.

* line: ``gtsam.Point3`` Lambda_l;
* centres: ``gtsam.Point3`` camera centres (world, m);
* rotations: ``gtsam.Rot3`` R_wc (right perturbation ``R Exp(w)``). When the
  rotations are not variables (phase 1) they are constants bound in the factor;
* focal: a 1-vector ``f`` = fx in pixels; fy = f * fy0 / fx0 keeps the aspect
  of the base ``K``; the principal point is fixed. Absent: ``K`` is constant.

The residuals and their analytic Jacobians are computed in one place,
:func:`reprojection_terms`, vectorised over observations. The factor's callback
uses it for its few observations; :class:`LineReprojectionSet` uses it for all of
a graph's observations at once, so that an optimiser driven from Python
linearises them in one call (measured, 300 frames, ~2,800 tracks: the bundle
adjustment 23 -> 10 s).
"""
from __future__ import annotations

import functools

import gtsam
import numpy as np

from factors.robust import noise_model, robust_loss, robust_weight

_S3 = 1.0 / (2.0 * np.sqrt(3.0))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Returns row-wise cross products of (N, 3) arrays (np.cross is slow on small arrays)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def _endpoint_distances(endpoints: np.ndarray, direction: np.ndarray, lam: np.ndarray, C: np.ndarray, R: np.ndarray,
                        fx: float, fy: float, cx: float, cy: float):
    """Returns (n, m1, m2, s, d1, d2): the camera-frame interpretation-plane normals, the endpoints' normalised
    rays, the image-line scale and the endpoints' signed pixel distances to the projected lines; vectorised."""
    w = _cross(lam - C, direction)                         # (N, 3) world normal of the interpretation plane
    n = np.einsum("nji,nj->ni", R, w)                      # camera frame
    N = len(n)
    m1 = np.empty((N, 3))
    m2 = np.empty((N, 3))
    m1[:, 0] = (endpoints[:, 0] - cx) / fx
    m1[:, 1] = (endpoints[:, 1] - cy) / fy
    m2[:, 0] = (endpoints[:, 2] - cx) / fx
    m2[:, 1] = (endpoints[:, 3] - cy) / fy
    m1[:, 2] = m2[:, 2] = 1.0
    s = np.sqrt((n[:, 0] / fx) ** 2 + (n[:, 1] / fy) ** 2)
    return n, m1, m2, s, (n * m1).sum(1) / s, (n * m2).sum(1) / s


def segment_distances(endpoints: np.ndarray, taylor: np.ndarray, direction: np.ndarray, R_wc: np.ndarray,
                      centers: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Returns (d1, d2): signed pixel distances of the segments' endpoints to the projected lines; vectorised over (N,)."""
    *_, d1, d2 = _endpoint_distances(np.asarray(endpoints, dtype=np.float64), direction, taylor, centers, R_wc,
                                     K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    return d1, d2


def segment_residuals(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Returns (N, 2) residuals whose squared norms are the segment-averaged squared distances (d1² + d1 d2 + d2²) / 3."""
    return np.stack([0.5 * (d1 + d2), _S3 * (d1 - d2)], axis=-1)


def reprojection_terms(endpoints: np.ndarray, direction: np.ndarray, lam: np.ndarray, C: np.ndarray, R: np.ndarray,
                       K: np.ndarray, fx: float | None = None, jacobians: bool = False):
    """Returns the (N, 2) segment-averaged residuals (pixels) of N observations, with their Jacobians if asked.

    Vectorised over observations: ``endpoints`` (N, 4) pixels, ``direction``
    A (3,) or (N, 3), ``lam`` Lambda (3,) or (N, 3), centres ``C`` (N, 3),
    ``R`` R_wc (N, 3, 3), base intrinsics ``K``; ``fx`` a focal length
    replacing K's (fy keeps the aspect). With ``jacobians``: also the (N, 2, 3)
    Jacobians with respect to Lambda, the centre and the rotation (right
    perturbation), and the (N, 2) one with respect to fx.
    """
    fx0, fy0, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if fx is None:
        fx, fy = fx0, fy0
    else:
        fy = fx * fy0 / fx0
    n, m1, m2, s, d1, d2 = _endpoint_distances(endpoints, direction, lam, C, R, fx, fy, cx, cy)
    N = len(n)
    r = segment_residuals(d1, d2)
    if not jacobians:
        return r
    # d d_k / d n = (m_k - d_k q) / s with q = (n1 / fx², n2 / fy², 0) / s
    q = np.zeros((N, 3))
    q[:, 0] = n[:, 0] / (fx * fx * s)
    q[:, 1] = n[:, 1] / (fy * fy * s)
    g1 = (m1 - d1[:, None] * q) / s[:, None]
    g2 = (m2 - d2[:, None] * q) / s[:, None]
    G = np.empty((N, 2, 3))                                # rows of the two residuals, w.r.t. n
    G[:, 0] = 0.5 * (g1 + g2)
    G[:, 1] = _S3 * (g1 - g2)
    v = np.einsum("nij,nkj->nki", R, G)                    # R g: gradient w.r.t. the world normal w
    J_c = _cross(v, np.reshape(direction, (-1, 1, 3)))     # d/dc = (R g) x A ; d/dLambda = -(R g) x A
    J_rot = _cross(G, n[:, None, :])                       # d/dw_rot = g x n (right perturbation)
    J_f = np.zeros((N, 2))
    J_f[:, 0] = n[:, 2] / (fx * s)                         # d d_k / d fx, equal for both endpoints
    return r, -J_c, J_c, J_rot, J_f


def line_reprojection_error(endpoints: np.ndarray, direction: np.ndarray, K: np.ndarray, R_fixed: np.ndarray | None,
                            has_focal: bool, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns the stacked (2n,) segment-averaged reprojection residuals (pixels) of one line in n frames.

    ``endpoints`` (n, 4) pixels; ``direction`` A (3,); ``K`` base intrinsics;
    ``R_fixed`` (n, 3, 3) constant R_wc when rotations are not variables.
    Jacobians are analytic (:func:`reprojection_terms`; module docstring for the keys' order).
    """
    keys = this.keys()
    nobs = len(endpoints)
    lam = values.atPoint3(keys[0])
    C = np.array([values.atPoint3(k) for k in keys[1:1 + nobs]])
    if R_fixed is None:
        R = np.array([values.atRot3(k).matrix() for k in keys[1 + nobs:1 + 2 * nobs]])
    else:
        R = R_fixed
    fx = values.atVector(keys[-1])[0] if has_focal else None
    if jacobians is None:
        return reprojection_terms(endpoints, direction, lam, C, R, K, fx).ravel()
    r, J_l, J_c, J_r, J_f = reprojection_terms(endpoints, direction, lam, C, R, K, fx, jacobians=True)
    jacobians[0] = J_l.reshape(2 * nobs, 3)
    rows = np.arange(2 * nobs)
    blocks = np.zeros((nobs, 2 * nobs, 3))
    blocks[rows // 2, rows] = J_c.reshape(2 * nobs, 3)
    for j in range(nobs):
        jacobians[1 + j] = blocks[j]
    if R_fixed is None:
        blocks = np.zeros((nobs, 2 * nobs, 3))
        blocks[rows // 2, rows] = J_r.reshape(2 * nobs, 3)
        for j in range(nobs):
            jacobians[1 + nobs + j] = blocks[j]
    if has_focal:
        jacobians[len(keys) - 1] = J_f.reshape(2 * nobs, 1)
    return r.ravel()


def line_reprojection_factor(line_key: int, center_keys, endpoints: np.ndarray, direction: np.ndarray, K: np.ndarray,
                             noise, rotation_keys=None, R_wc_fixed: np.ndarray | None = None,
                             focal_key: int | None = None) -> gtsam.CustomFactor:
    """Returns one CustomFactor for the observations of one line in n frames (2n residuals, pixels).

    Give ``rotation_keys`` (Rot3 variables) or ``R_wc_fixed`` (n, 3, 3)
    constants; ``focal_key`` adds the focal length as a variable. ``noise``
    must have dimension 2n (e.g. ``robust.noise_model(2 * n, sigma_px)``).
    """
    ep = np.ascontiguousarray(endpoints, dtype=np.float64).reshape(-1, 4)
    nobs = len(ep)
    center_keys = [int(k) for k in center_keys]
    if len(center_keys) != nobs:
        raise ValueError("one centre key per observation expected")
    keys = [int(line_key)] + center_keys
    if rotation_keys is not None:
        rotation_keys = [int(k) for k in rotation_keys]
        if len(rotation_keys) != nobs:
            raise ValueError("one rotation key per observation expected")
        keys += rotation_keys
        R_fixed = None
    else:
        if R_wc_fixed is None:
            raise ValueError("give rotation_keys or R_wc_fixed")
        R_fixed = np.ascontiguousarray(R_wc_fixed, dtype=np.float64).reshape(nobs, 3, 3)
    if focal_key is not None:
        keys.append(int(focal_key))
    a = np.asarray(direction, dtype=np.float64).reshape(3)
    fn = functools.partial(line_reprojection_error, ep, a, np.asarray(K, dtype=np.float64), R_fixed, focal_key is not None)
    return gtsam.CustomFactor(noise, keys, fn)


class LineReprojectionSet:
    """The line reprojection terms of many observations, evaluated and linearised in one vectorised call.

    The same residuals and analytic Jacobians as :func:`line_reprojection_factor`
    (both come from :func:`reprojection_terms`), for all of a graph's
    observations at once, with isotropic Gaussian noise of ``sigma`` pixels
    (and, when ``robust`` is not "none", that kernel with threshold ``k`` on
    each observation's whitened residual norm, as gtsam's ``Robust`` noise model on
    a factor of one observation):
    :meth:`error` is what the factors add to ``graph.error`` and
    :meth:`linearize` the ``gtsam.GaussianFactorGraph`` they linearise to (one
    ``JacobianFactor`` per observation on its line, centre and, when they are
    variables, rotation). An optimiser driven from Python
    (notes/gtsam-python-performance.md) then makes one Python call per
    linearisation instead of one callback per factor.

    With ``focal_key`` the focal length fx (a 1-vector variable, as
    :func:`line_reprojection_factor`'s) is a variable too. Its column would be a
    fourth key per observation, more than Python can give a ``JacobianFactor``,
    so :meth:`linearize` splits each observation's quadratic
    ``0.5 ||A_l dl + A_c dc + A_r dr + a_f df - b||^2`` exactly into the
    3-key ``JacobianFactor`` without ``a_f``, for each line, centre and
    rotation ``x`` one 2-key ``HessianFactor`` on (x, focal) holding only the
    cross term ``dx^T (sum A_x^T a_f) df`` summed over x's observations, and
    one 1-key ``HessianFactor`` on the focal with ``sum a_f^T a_f`` and
    ``sum a_f^T b``. The cross-term factors are not positive semi-definite on
    their own, but elimination sums all factors on a frontal variable, so the
    system solved is the factors' (measured, 600-frame living capture, focal
    free: phase 3 and its re-solve 1.6 + 0.9 s -> 0.17 + 0.09 s, the whole
    bundle adjustment 11.7 -> 4.8 s, same results).
    """

    def __init__(self, line_keys, center_keys, endpoints: np.ndarray, directions: np.ndarray, K: np.ndarray,
                 sigma: float, rotation_keys=None, R_wc_fixed: np.ndarray | None = None, robust: str = "none",
                 k: float = 1.345, focal_key: int | None = None):
        robust_weight(np.zeros(1), robust, k)  # an unknown kernel is an error here
        self.robust, self.k = robust, float(k)
        self.endpoints = np.ascontiguousarray(endpoints, dtype=np.float64).reshape(-1, 4)
        n = len(self.endpoints)
        self.directions = np.ascontiguousarray(directions, dtype=np.float64).reshape(n, 3)
        self.K = np.asarray(K, dtype=np.float64)
        self.sigma = float(sigma)
        self.line_keys = [int(k) for k in line_keys]
        self.center_keys = [int(k) for k in center_keys]
        self.rotation_keys = None if rotation_keys is None else [int(k) for k in rotation_keys]
        if len(self.line_keys) != n or len(self.center_keys) != n or (
                self.rotation_keys is not None and len(self.rotation_keys) != n):
            raise ValueError("one line, centre (and rotation) key per observation expected")
        if self.rotation_keys is None:
            if R_wc_fixed is None:
                raise ValueError("give rotation_keys or R_wc_fixed")
            self.R_fixed = np.ascontiguousarray(R_wc_fixed, dtype=np.float64).reshape(n, 3, 3)
        else:
            self.R_fixed = None
        # each variable is read once per evaluation
        self._lines, self._line_of = np.unique(np.asarray(self.line_keys, np.uint64), return_inverse=True)
        self._centers, self._center_of = np.unique(np.asarray(self.center_keys, np.uint64), return_inverse=True)
        if self.rotation_keys is not None:
            self._rots, self._rot_of = np.unique(np.asarray(self.rotation_keys, np.uint64), return_inverse=True)
        self.focal_key = None if focal_key is None else int(focal_key)
        self._unit = gtsam.noiseModel.Unit.Create(2)

    def __len__(self) -> int:
        return len(self.endpoints)

    def _state(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lam = np.array([values.atPoint3(int(k)) for k in self._lines]).reshape(-1, 3)[self._line_of]
        C = np.array([values.atPoint3(int(k)) for k in self._centers]).reshape(-1, 3)[self._center_of]
        if self.R_fixed is not None:
            return lam, C, self.R_fixed
        R = np.array([values.atRot3(int(k)).matrix() for k in self._rots]).reshape(-1, 3, 3)[self._rot_of]
        return lam, C, R

    def _fx(self, values: gtsam.Values) -> float | None:
        return None if self.focal_key is None else float(values.atVector(self.focal_key)[0])

    def residuals(self, values: gtsam.Values) -> np.ndarray:
        """Returns the (N, 2) residuals in pixels at ``values``."""
        lam, C, R = self._state(values)
        return reprojection_terms(self.endpoints, self.directions, lam, C, R, self.K, self._fx(values))

    def error(self, values: gtsam.Values) -> float:
        """Returns the kernel's cost summed over the observations' whitened residual norms (``graph.error`` of
        the factors)."""
        r = self.residuals(values)
        return float(np.sum(robust_loss(np.linalg.norm(r, axis=1) / self.sigma, self.robust, self.k)))

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """Returns the whitened linearisation at ``values``: ``w ||J delta + r||^2 / sigma^2`` per observation (``w``
        the kernel's weight at the residual, 1 without one); with a focal variable split as the class docstring
        tells."""
        lam, C, R = self._state(values)
        r, J_l, J_c, J_r, J_f = reprojection_terms(self.endpoints, self.directions, lam, C, R, self.K,
                                                   self._fx(values), jacobians=True)
        w = np.full(len(r), 1.0 / self.sigma)
        if self.robust != "none":  # iteratively reweighted, as gtsam's Robust::WhitenSystem
            w *= np.sqrt(robust_weight(np.linalg.norm(r, axis=1) * w, self.robust, self.k))
        w = w[:, None]
        b = -w * r
        w = w[:, :, None]
        A_l, A_c = w * J_l, w * J_c
        A_r = None if self.rotation_keys is None else w * J_r
        gfg = gtsam.GaussianFactorGraph()
        unit = self._unit
        if A_r is None:
            for kl, al, kc, ac, bb in zip(self.line_keys, A_l, self.center_keys, A_c, b):
                gfg.push_back(gtsam.JacobianFactor(kl, al, kc, ac, bb, unit))
        else:
            for kl, al, kc, ac, kr, ar, bb in zip(self.line_keys, A_l, self.center_keys, A_c, self.rotation_keys, A_r,
                                                  b):
                gfg.push_back(gtsam.JacobianFactor(kl, al, kc, ac, kr, ar, bb, unit))
        if self.focal_key is not None:
            self._push_focal_terms(gfg, A_l, A_c, A_r, w[:, :, 0] * J_f, b)
        return gfg

    def _push_focal_terms(self, gfg: gtsam.GaussianFactorGraph, A_l: np.ndarray, A_c: np.ndarray,
                          A_r: np.ndarray | None, a_f: np.ndarray, b: np.ndarray) -> None:
        """Adds the focal's part of the observations' whitened quadratics (A (N, 2, 3) per variable, a_f and b
        (N, 2)): :func:`push_split_column`."""
        parts = [(self._lines, self._line_of, A_l), (self._centers, self._center_of, A_c)]
        if A_r is not None:
            parts.append((self._rots, self._rot_of, A_r))
        push_split_column(gfg, self.focal_key, parts, a_f[:, :, None], b)

    def factors(self, chunk: int = 8, focal_key: int | None = None) -> list[gtsam.CustomFactor]:
        """Returns the same terms as :func:`line_reprojection_factor` s, one on each of :meth:`runs` ``(chunk)``,
        with the focal length ``focal_key`` (default: the set's) as a variable when given."""
        if focal_key is None:
            focal_key = self.focal_key
        return [line_reprojection_factor(
            self.line_keys[c0], self.center_keys[c0:c1], self.endpoints[c0:c1], self.directions[c0], self.K,
            noise_model(2 * (c1 - c0), self.sigma, self.robust, self.k),
            rotation_keys=None if self.rotation_keys is None else self.rotation_keys[c0:c1],
            R_wc_fixed=None if self.R_fixed is None else self.R_fixed[c0:c1], focal_key=focal_key)
            for c0, c1 in self.runs(chunk)]

    def runs(self, chunk: int) -> list[tuple[int, int]]:
        """Returns the (start, stop) observation ranges of :meth:`factors`: one line's consecutive observations,
        ``chunk`` at most -- one with a robust kernel, which weighs each observation on its own."""
        if self.robust != "none":
            chunk = 1
        lk = np.asarray(self.line_keys, np.uint64)
        starts = np.flatnonzero(np.r_[True, lk[1:] != lk[:-1]])
        ends = np.r_[starts[1:], len(lk)]
        return [(int(c0), int(min(c0 + chunk, b))) for a, b in zip(starts, ends) for c0 in range(a, b, chunk)]


def push_split_column(gfg: gtsam.GaussianFactorGraph, column_key: int, parts, A_col: np.ndarray, b: np.ndarray) -> None:
    """Adds to ``gfg`` the part of many whitened rows ``A x + A_col dz - b`` that a shared variable ``column_key``
    (``z``) adds to the rows' ``JacobianFactor`` s without it (a column Python cannot give them as a 4th key).

    ``parts``: (keys (V,), of (N,), A (N, m, d)) per kind of variable, row ``n``'s block on ``keys[of[n]]``;
    ``A_col`` (N, m, e) the rows' blocks on ``z``, ``b`` (N, m) their right-hand sides. GTSAM's HessianFactor
    error is ``0.5 (f - 2 x^T g + x^T G x)``: a Jacobian factor ``A x - b`` gives ``G = A^T A``, ``g = A^T b``;
    the off-diagonal block G12 of a 2-key factor enters twice, so the cross term ``dx^T A_x^T A_col dz`` is a
    (variable, z) factor with ``G12 = sum A_x^T A_col`` over the variable's rows and G11, G22, g zero; then one
    factor on ``z`` with ``sum A_col^T A_col`` and ``sum A_col^T b``. The cross-term factors are not positive
    semi-definite on their own, but elimination sums all factors on a frontal variable, so the system solved is
    the rows' (:class:`LineReprojectionSet`'s focal length, :class:`factors.SpinPriorSet`'s arm).
    """
    e = A_col.shape[2]
    z_ee, z_e = np.zeros((e, e)), np.zeros(e)
    for keys, of, A in parts:
        d = A.shape[2]
        cross = np.zeros((len(keys), d, e))
        np.add.at(cross, of, np.einsum("nij,nik->njk", A, A_col))  # sum over each variable's rows of A_x^T A_col
        z_dd, z_d = np.zeros((d, d)), np.zeros(d)
        for key, g12 in zip(np.asarray(keys).tolist(), cross):
            gfg.push_back(gtsam.HessianFactor(int(key), column_key, z_dd, g12, z_d, z_ee, z_e, 0.0))
    gfg.push_back(gtsam.HessianFactor(column_key, np.einsum("nij,nik->jk", A_col, A_col),
                                      np.einsum("nij,ni->j", A_col, b), 0.0))
