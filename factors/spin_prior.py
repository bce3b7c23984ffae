"""Spin prior (our addition to paper §3.4): each camera centre lies on the circle the phone describes.

The person turns about a stand point and holds the phone out in front, so a
frame's centre ``c`` is the stand point ``S`` plus the arm, which keeps a
fixed angle to the horizontal viewing direction ``h`` of the frame:

    c - S = a h + b h_perp    (horizontal),    (c - S) . up = 0    (vertical)

with ``h_perp`` = ``h`` turned 90 degrees about ``up``; ``(a, b)`` is the
arm's length times the cosine / sine of that angle. A person's feet shuffle,
so the stand point may wander: it is interpolated linearly, by the angle the
camera has turned, between knots ``S_j`` a fixed turn apart
(:func:`spin_knots`), neighbouring knots tied by a random-walk prior (a
``BetweenFactorPoint3``). The residual is written in the Manhattan frame
(rows of ``manhattan``: the two horizontal directions, then up). Variables:
``c``, ``S_j`` Point3 (world, m), ``(a, b)`` a 2-vector (m). The one shared
arm ties the scale of every part of the sweep, which line parallax alone
leaves free wherever the sweep is weakly connected.
"""
from __future__ import annotations

import functools

import gtsam
import numpy as np

from factors.line_reprojection import push_split_column


def spin_knots(turned_deg: np.ndarray, knot_deg: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Returns (j (N,) int, alpha (N,), number of knots): ``S = (1 - alpha) S_j + alpha S_{j+1}`` per frame.

    ``turned_deg`` (N,) is how far each frame has turned since the first;
    knots lie every ``knot_deg`` degrees (``knot_deg`` <= 0: one fixed stand
    point, ``alpha`` = 0).
    """
    t = np.asarray(turned_deg, dtype=np.float64)
    t = t - (t.min() if len(t) else 0.0)
    if knot_deg <= 0 or len(t) == 0 or t.max() <= 0:
        return np.zeros(len(t), np.int64), np.zeros(len(t)), 1
    n_int = max(int(np.ceil(t.max() / knot_deg)), 1)
    step = t.max() / n_int  # knots spread evenly over the turn
    u = t / step
    j = np.minimum(np.floor(u).astype(np.int64), n_int - 1)
    return j, u - j, n_int + 1


def spin_model_rows(h: np.ndarray, j: np.ndarray, alpha: np.ndarray,
                    n_knots: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns the linear spin model as rows ``centre[c] - sum(vals * x[cols]) = 0`` (kind 0, 1) or ``sum(vals * x[cols]) = 0`` (kind 2).

    The unknowns ``x`` are the knots (3 Manhattan coordinates each, ``3 j + k``)
    then the arm (a, b) at ``3 n_knots``; for each of the ``n`` frames
    (``h`` (n, 2) its horizontal viewing direction, ``j``/``alpha`` from
    :func:`spin_knots`) two horizontal rows (kind 0) and one vertical row
    (kind 1), then three random-walk rows per pair of neighbouring knots
    (kind 2, ``S_{j+1} - S_j``). Returns (kind (R,), centre (R,): the index
    ``3 i + k`` of the centre coordinate or -1, cols (R, 4), vals (R, 4)).
    The linear solve and the bundle adjustment's initial fit use the same rows.
    """
    n, K = len(h), int(n_knots)
    j1 = np.minimum(j + 1, K - 1)
    kind, centre, cols, vals = [], [], [], []
    for k in range(3):
        centre.append(3 * np.arange(n) + k)
        if k < 2:
            kind.append(np.zeros(n, np.int8))
            hp = (-h[:, 1], h[:, 0])[k]
            cols.append(np.column_stack([3 * j + k, 3 * j1 + k, np.full(n, 3 * K), np.full(n, 3 * K + 1)]))
            vals.append(np.column_stack([1.0 - alpha, alpha, h[:, k], hp]))
        else:
            kind.append(np.ones(n, np.int8))
            cols.append(np.column_stack([3 * j + 2, 3 * j1 + 2, 3 * j + 2, 3 * j + 2]))
            vals.append(np.column_stack([1.0 - alpha, alpha, np.zeros(n), np.zeros(n)]))
    if K > 1:
        kn = np.repeat(np.arange(K - 1), 3)
        kk = np.tile(np.arange(3), K - 1)
        zero = np.zeros(len(kn))
        kind.append(np.full(len(kn), 2, np.int8))
        centre.append(np.full(len(kn), -1))
        cols.append(np.column_stack([3 * (kn + 1) + kk, 3 * kn + kk, 3 * kn + kk, 3 * kn + kk]))
        vals.append(np.column_stack([np.ones(len(kn)), -np.ones(len(kn)), zero, zero]))
    return np.concatenate(kind), np.concatenate(centre), np.concatenate(cols), np.concatenate(vals)


def spin_prior_error(manhattan: np.ndarray, h: np.ndarray, alpha: float, this: gtsam.CustomFactor,
                     values: gtsam.Values, jacobians) -> np.ndarray:
    """Returns the 3-vector ``M (c - S) - [a h + b h_perp, 0]`` (m): the centre's offset from the spin circle.

    Keys: c, S_j, S_{j+1}, (a, b); ``S = (1 - alpha) S_j + alpha S_{j+1}``.
    ``manhattan`` (3, 3) rows: horizontal axes 0, 1 and up; ``h`` (2,) the
    unit horizontal viewing direction in Manhattan coordinates (axes 0, 1).
    """
    keys = this.keys()
    c = values.atPoint3(keys[0])
    s = (1.0 - alpha) * values.atPoint3(keys[1]) + alpha * values.atPoint3(keys[2])
    ab = values.atVector(keys[3])
    arm = np.array([[h[0], -h[1]], [h[1], h[0]], [0.0, 0.0]])  # columns: h, h_perp (Manhattan coordinates)
    if jacobians is not None:
        jacobians[0] = manhattan.copy()
        jacobians[1] = -(1.0 - alpha) * manhattan
        jacobians[2] = -alpha * manhattan
        jacobians[3] = -arm
    return manhattan @ (c - s) - arm @ ab


def spin_prior_factor(center_key: int, knot_keys: tuple[int, int], alpha: float, arm_key: int,
                      manhattan: np.ndarray, view_dir: np.ndarray, noise) -> gtsam.CustomFactor:
    """Returns a CustomFactor on (Point3 c, Point3 S_j, Point3 S_{j+1}, 2-vector (a, b)) putting c on the spin circle.

    ``view_dir`` (3,) is the frame's optical axis (world); its horizontal
    part, in Manhattan coordinates, is the ``h`` of :func:`spin_prior_error`.
    ``noise`` is 3-dimensional (horizontal, horizontal, vertical). With one
    stand point pass the same key twice and ``alpha`` = 0.
    """
    M = np.asarray(manhattan, dtype=np.float64).reshape(3, 3)
    h = horizontal_direction(M, view_dir)
    keys = [center_key, knot_keys[0], knot_keys[1], arm_key]
    return gtsam.CustomFactor(noise, keys, functools.partial(spin_prior_error, M, h, float(alpha)))


def horizontal_direction(manhattan: np.ndarray, view_dir: np.ndarray) -> np.ndarray:
    """Returns (..., 2) the unit horizontal part of world directions ``view_dir`` (..., 3) in Manhattan axes 0, 1."""
    v = np.asarray(view_dir, dtype=np.float64) @ np.asarray(manhattan, dtype=np.float64).T
    h = v[..., :2]
    return h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)


def spin_noise(horizontal_sigma_m: float, vertical_sigma_m: float, robust: str = "none", k: float = 1.345):
    """Returns the 3-dim diagonal noise model (sigmas in m) of :func:`spin_prior_factor`, robustified by ``robust``."""
    from factors.robust import robust_kernel

    base = gtsam.noiseModel.Diagonal.Sigmas(np.array([horizontal_sigma_m, horizontal_sigma_m, vertical_sigma_m]))
    kernel = robust_kernel(robust, k)
    return base if kernel is None else gtsam.noiseModel.Robust.Create(kernel, base)


class SpinPriorSet:
    """The spin prior terms of many frames, evaluated and linearised in one vectorised call.

    The same residuals and Jacobians as :func:`spin_prior_factor` (the residual is linear in its
    variables), for every frame at once, with the noise of :func:`spin_noise` (diagonal sigmas, the
    ``robust`` kernel with threshold ``k`` on each frame's whitened residual norm), for
    :func:`panosfm_graph.graph.levenberg_marquardt`'s ``batches``: :meth:`error` is what the factors add
    to ``graph.error`` and :meth:`linearize` what they linearise to. A term has four keys (centre, two
    knots, arm), one more than Python can give a ``JacobianFactor``, so the arm's column is split off
    exactly as :class:`factors.LineReprojectionSet` splits the focal length's: a 3-key (2-key with one
    knot) ``JacobianFactor`` per frame, per centre and knot one (variable, arm) ``HessianFactor`` with
    the cross term, one ``HessianFactor`` on the arm.
    """

    def __init__(self, center_keys, knot_keys, alpha, arm_key: int, manhattan: np.ndarray, view_dirs: np.ndarray,
                 horizontal_sigma_m: float, vertical_sigma_m: float, robust: str = "none", k: float = 1.345):
        from factors.robust import robust_weight

        robust_weight(np.zeros(1), robust, k)  # an unknown kernel is an error here
        self.robust, self.k = robust, float(k)
        self.center_keys = [int(c) for c in center_keys]
        self.knot_keys = np.asarray(knot_keys, dtype=np.uint64).reshape(len(self.center_keys), 2)
        self.alpha = np.asarray(alpha, dtype=np.float64).reshape(-1)
        self.arm_key = int(arm_key)
        self.M = np.asarray(manhattan, dtype=np.float64).reshape(3, 3)
        h = horizontal_direction(self.M, view_dirs)
        self.arm = np.zeros((len(h), 3, 2))  # per frame: columns h, h_perp (Manhattan coordinates)
        self.arm[:, 0, 0], self.arm[:, 1, 0], self.arm[:, 0, 1], self.arm[:, 1, 1] = h[:, 0], h[:, 1], -h[:, 1], h[:, 0]
        self.inv_sigma = 1.0 / np.array([horizontal_sigma_m, horizontal_sigma_m, vertical_sigma_m], dtype=np.float64)
        self._knots, self._knot_of = np.unique(self.knot_keys.ravel(), return_inverse=True)
        self._knot_of = self._knot_of.reshape(-1, 2)
        self._unit = gtsam.noiseModel.Unit.Create(3)

    def __len__(self) -> int:
        return len(self.center_keys)

    def residuals(self, values: gtsam.Values) -> np.ndarray:
        """Returns the (N, 3) residuals (m, Manhattan coordinates) of :func:`spin_prior_error` at ``values``."""
        c = np.array([values.atPoint3(k) for k in self.center_keys]).reshape(-1, 3)
        S = np.array([values.atPoint3(int(k)) for k in self._knots]).reshape(-1, 3)
        s = (1.0 - self.alpha)[:, None] * S[self._knot_of[:, 0]] + self.alpha[:, None] * S[self._knot_of[:, 1]]
        ab = np.asarray(values.atVector(self.arm_key), dtype=np.float64)
        return (c - s) @ self.M.T - self.arm @ ab

    def _whitened(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        from factors.robust import robust_weight

        e = self.residuals(values) * self.inv_sigma
        return e, np.sqrt(robust_weight(np.linalg.norm(e, axis=1), self.robust, self.k))

    def error(self, values: gtsam.Values) -> float:
        """Returns the kernel's cost summed over the frames' whitened residual norms (``graph.error`` of the
        factors)."""
        from factors.robust import robust_loss

        e = self.residuals(values) * self.inv_sigma
        return float(np.sum(robust_loss(np.linalg.norm(e, axis=1), self.robust, self.k)))

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """Returns the whitened linearisation at ``values`` (``w`` the kernel's IRLS weight, as gtsam's
        ``Robust::WhitenSystem``), the arm's column split as the class docstring tells."""
        e, w = self._whitened(values)
        W = w[:, None] * self.inv_sigma[None, :]  # (N, 3) row scales
        b = -w[:, None] * e
        A_c = W[:, :, None] * self.M[None]  # d r / d c = M
        A_j = -(1.0 - self.alpha)[:, None, None] * A_c
        A_j1 = -self.alpha[:, None, None] * A_c
        A_ab = -W[:, :, None] * self.arm
        gfg = gtsam.GaussianFactorGraph()
        unit = self._unit
        kj, kj1 = self.knot_keys[:, 0].tolist(), self.knot_keys[:, 1].tolist()
        for i, kc in enumerate(self.center_keys):
            if kj[i] == kj1[i]:
                gfg.push_back(gtsam.JacobianFactor(kc, A_c[i], kj[i], A_j[i] + A_j1[i], b[i], unit))
            else:
                gfg.push_back(gtsam.JacobianFactor(kc, A_c[i], kj[i], A_j[i], kj1[i], A_j1[i], b[i], unit))
        # the arm's column (a 4th key): cross-term HessianFactors per centre and knot, one on the arm
        push_split_column(gfg, self.arm_key, [(self.center_keys, np.arange(len(self)), A_c),
                                              (self._knots, self._knot_of[:, 0], A_j),
                                              (self._knots, self._knot_of[:, 1], A_j1)], A_ab, b)
        return gfg
