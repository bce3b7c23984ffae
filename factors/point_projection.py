"""Point reprojection (our addition; issue #40): a texture corner seen by a frame.

The frame's centre ``c``, the point ``P`` and, when it is a variable, the
frame's rotation ``R_wc`` (right perturbation ``R Exp(w)``, as GTSAM's Rot3)
give the pixel offset of ``P``'s projection from the tracked corner:

    X = R_wc^T (P - c),   r = (fx X_x / X_z + cx - u,  fy X_y / X_z + cy - v)

with Jacobians ``D R_wc^T`` for ``P``, its negative for ``c`` and ``D [X]_x``
for ``w`` (``D`` the projection's 2x3 derivative at ``X``). A point behind
the camera (``X_z`` below ``MIN_DEPTH``) gives the residual at that depth, so
the optimiser sees a large but finite error.

:func:`point_projection_factor` is one observation as a ``gtsam.CustomFactor``
(the reference, checked against numerical derivatives); :class:`PointProjectionSet`
is many at once, evaluated and linearised in one vectorised call for
:func:`panosfm_graph.graph.lm.levenberg_marquardt` (as
:class:`factors.LineReprojectionSet`).
"""
from __future__ import annotations

import functools

import gtsam
import numpy as np

from factors.line_reprojection import push_split_column
from factors.robust import robust_loss, robust_weight

MIN_DEPTH = 1e-3  # solution units


def _skew(v: np.ndarray) -> np.ndarray:
    """Returns (N, 3, 3) the cross-product matrices of (N, 3) vectors."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def point_terms(uv: np.ndarray, P: np.ndarray, C: np.ndarray, R: np.ndarray, K: np.ndarray,
                jacobians: bool = False, fx: float | None = None):
    """Returns the (N, 2) pixel residuals of N observations ``uv`` of points ``P`` (N, 3) from centres ``C`` (N, 3)
    at rotations ``R`` (N, 3, 3); ``fx`` a focal length replacing K's (fy keeps the aspect). With ``jacobians``
    also the (N, 2, 3) Jacobians on the centre, the point and the rotation (right perturbation) and the (N, 2) one
    on fx."""
    X = np.einsum("nji,nj->ni", R, P - C)
    z = np.maximum(X[:, 2], MIN_DEPTH)
    aspect = K[1, 1] / K[0, 0]
    fx = K[0, 0] if fx is None else float(fx)
    fy = fx * aspect
    r = np.stack([fx * X[:, 0] / z + K[0, 2] - uv[:, 0], fy * X[:, 1] / z + K[1, 2] - uv[:, 1]], axis=1)
    if not jacobians:
        return r
    D = np.zeros((len(X), 2, 3))
    D[:, 0, 0], D[:, 1, 1] = fx / z, fy / z
    D[:, 0, 2], D[:, 1, 2] = -fx * X[:, 0] / z**2, -fy * X[:, 1] / z**2
    D[X[:, 2] < MIN_DEPTH, :, 2] = 0.0
    J_p = np.einsum("nij,nkj->nik", D, R)  # D R^T
    J_r = np.einsum("nij,njk->nik", D, _skew(X))
    J_f = np.stack([X[:, 0] / z, aspect * X[:, 1] / z], axis=1)
    return r, -J_p, J_p, J_r, J_f


def project_points(R_wc: np.ndarray, centers: np.ndarray, points: np.ndarray, K: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((N, 2) pixels, (N,) depth along the optical axis) of ``points`` (N, 3) seen from frames (N, 3, 3),
    (N, 3); vectorised over observations."""
    X = np.einsum("nji,nj->ni", R_wc, points - centers)
    z = np.maximum(X[:, 2], MIN_DEPTH)
    uv = np.stack([K[0, 0] * X[:, 0] / z + K[0, 2], K[1, 1] * X[:, 1] / z + K[1, 2]], axis=1)
    return uv, X[:, 2]


def point_projection_error(R_wc: np.ndarray | None, K: np.ndarray, uv: np.ndarray, has_focal: bool,
                           this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns the 2-vector pixel residual of the point (key 1) seen from the centre (key 0) at rotation ``R_wc``
    (held) or, when ``R_wc`` is None, at the rotation of key 2; with ``has_focal`` the last key is the focal
    length fx (a 1-vector; fy keeps K's aspect)."""
    keys = this.keys()
    R = values.atRot3(keys[2]).matrix() if R_wc is None else R_wc
    fx = values.atVector(keys[-1])[0] if has_focal else None
    out = point_terms(uv[None], values.atPoint3(keys[1])[None], values.atPoint3(keys[0])[None], R[None], K,
                      jacobians=jacobians is not None, fx=fx)
    if jacobians is None:
        return out[0]
    r, J_c, J_p, J_r, J_f = out
    jacobians[0], jacobians[1] = J_c[0], J_p[0]
    if R_wc is None:
        jacobians[2] = J_r[0]
    if has_focal:
        jacobians[len(keys) - 1] = J_f[0][:, None]
    return r[0]


def point_projection_factor(center_key: int, point_key: int, uv: np.ndarray, K: np.ndarray, noise, *,
                            R_wc: np.ndarray | None = None, rotation_key: int | None = None,
                            focal_key: int | None = None) -> gtsam.CustomFactor:
    """Returns a CustomFactor on (Point3 centre, Point3 point[, Rot3 rotation][, focal]):
    :func:`point_projection_error` (2-dim ``noise``); give the held ``R_wc`` or the variable's ``rotation_key``."""
    if (R_wc is None) == (rotation_key is None):
        raise ValueError("give R_wc or rotation_key")
    R = None if R_wc is None else np.asarray(R_wc, np.float64).reshape(3, 3)
    fn = functools.partial(point_projection_error, R, np.asarray(K, np.float64).reshape(3, 3),
                           np.asarray(uv, np.float64).reshape(2), focal_key is not None)
    keys = [center_key, point_key] + ([] if rotation_key is None else [rotation_key])
    keys += [] if focal_key is None else [int(focal_key)]
    return gtsam.CustomFactor(noise, keys, fn)


class PointProjectionSet:
    """Many point observations (:func:`point_terms`), evaluated and linearised in one vectorised call.

    Isotropic noise of ``sigma`` pixels, and when ``robust`` is not "none" that
    kernel with threshold ``k`` on each observation's whitened residual norm (as
    ``factors.noise_model(2, sigma, robust, k)`` on :func:`point_projection_factor`).
    Each observation's rotation is held (``R_wc_fixed`` (N, 3, 3)) or a
    variable (``rotation_keys``, None where held). With ``focal_key`` (every
    rotation a variable) the focal length fx is a variable too, its column
    split from the 3-key factors as :class:`factors.LineReprojectionSet`'s.
    """

    def __init__(self, center_keys, point_keys, uv: np.ndarray, K: np.ndarray, sigma: float,
                 R_wc_fixed: np.ndarray, rotation_keys=None, robust: str = "huber", k: float = 1.345,
                 focal_key: int | None = None):
        robust_weight(np.zeros(1), robust, k)  # an unknown kernel is an error here
        self.robust, self.k, self.sigma = robust, float(k), float(sigma)
        self.uv = np.ascontiguousarray(uv, np.float64).reshape(-1, 2)
        n = len(self.uv)
        self.K = np.asarray(K, np.float64)
        self.center_keys = [int(c) for c in center_keys]
        self.point_keys = [int(p) for p in point_keys]
        self.R_fixed = np.ascontiguousarray(R_wc_fixed, np.float64).reshape(n, 3, 3)
        self.rotation_keys = [None] * n if rotation_keys is None else [None if r is None else int(r)
                                                                        for r in rotation_keys]
        if len(self.center_keys) != n or len(self.point_keys) != n or len(self.rotation_keys) != n:
            raise ValueError("one centre, point (and rotation) key per observation expected")
        self._free = np.array([r is not None for r in self.rotation_keys], bool)
        self._centers, self._center_of = np.unique(np.asarray(self.center_keys, np.uint64), return_inverse=True)
        self._points, self._point_of = np.unique(np.asarray(self.point_keys, np.uint64), return_inverse=True)
        free_keys = np.asarray([r for r in self.rotation_keys if r is not None], np.uint64)
        self._rots, self._rot_of = np.unique(free_keys, return_inverse=True)
        self._unit = gtsam.noiseModel.Unit.Create(2)
        self.focal_key = None if focal_key is None else int(focal_key)
        if self.focal_key is not None and not self._free.all():
            raise ValueError("a focal variable needs every observation's rotation a variable")

    def __len__(self) -> int:
        return len(self.uv)

    def _fx(self, values: gtsam.Values) -> float | None:
        return None if self.focal_key is None else float(values.atVector(self.focal_key)[0])

    def subset(self, keep: np.ndarray) -> "PointProjectionSet":
        """Returns the set of the observations where ``keep`` (N,) bool is True."""
        idx = np.flatnonzero(keep)
        return PointProjectionSet([self.center_keys[k] for k in idx], [self.point_keys[k] for k in idx], self.uv[idx],
                                  self.K, self.sigma, self.R_fixed[idx], [self.rotation_keys[k] for k in idx],
                                  self.robust, self.k, self.focal_key)

    def point_rms(self, values: gtsam.Values) -> np.ndarray:
        """Returns (N,) the RMS residual norm (pixels) over all observations of each observation's point."""
        sq = np.sum(self.residuals(values) ** 2, axis=1)
        n = np.bincount(self._point_of, minlength=len(self._points))
        return np.sqrt(np.bincount(self._point_of, weights=sq, minlength=len(self._points)) / np.maximum(n, 1))[
            self._point_of]

    def _state(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        C = np.array([values.atPoint3(int(k)) for k in self._centers]).reshape(-1, 3)[self._center_of]
        P = np.array([values.atPoint3(int(k)) for k in self._points]).reshape(-1, 3)[self._point_of]
        R = self.R_fixed
        if len(self._rots):
            R = R.copy()
            R[self._free] = np.array([values.atRot3(int(k)).matrix() for k in self._rots]).reshape(-1, 3, 3)[
                self._rot_of]
        return C, P, R

    def residuals(self, values: gtsam.Values) -> np.ndarray:
        """Returns the (N, 2) residuals in pixels at ``values``."""
        C, P, R = self._state(values)
        return point_terms(self.uv, P, C, R, self.K, fx=self._fx(values))

    def error(self, values: gtsam.Values) -> float:
        """Returns the kernel's cost summed over the observations' whitened residual norms (``graph.error`` of
        the factors)."""
        r = self.residuals(values)
        return float(np.sum(robust_loss(np.linalg.norm(r, axis=1) / self.sigma, self.robust, self.k)))

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """Returns the whitened linearisation at ``values`` (one ``JacobianFactor`` per observation), reweighted by
        the kernel as gtsam's ``Robust::WhitenSystem``."""
        C, P, R = self._state(values)
        r, J_c, J_p, J_r, J_f = point_terms(self.uv, P, C, R, self.K, jacobians=True, fx=self._fx(values))
        w = np.full(len(r), 1.0 / self.sigma)
        if self.robust != "none":
            w *= np.sqrt(robust_weight(np.linalg.norm(r, axis=1) * w, self.robust, self.k))
        b = -w[:, None] * r
        A_c, A_p, A_r = w[:, None, None] * J_c, w[:, None, None] * J_p, w[:, None, None] * J_r
        gfg = gtsam.GaussianFactorGraph()
        unit = self._unit
        for kc, ac, kp, ap, kr, ar, bb in zip(self.center_keys, A_c, self.point_keys, A_p, self.rotation_keys, A_r,
                                              b):
            if kr is None:
                gfg.push_back(gtsam.JacobianFactor(kc, ac, kp, ap, bb, unit))
            else:
                gfg.push_back(gtsam.JacobianFactor(kc, ac, kp, ap, kr, ar, bb, unit))
        if self.focal_key is not None:  # a 4th key: split into cross terms (line_reprojection.push_split_column)
            parts = [(self._centers, self._center_of, A_c), (self._points, self._point_of, A_p),
                     (self._rots, self._rot_of, A_r)]
            push_split_column(gfg, self.focal_key, parts, w[:, None, None] * J_f[:, :, None], b)
        return gfg
