"""The constrained, robust solve (paper §3.3): least squares with ``lambda >= min_depth`` and reweighted relations.

* Depth bound: the paper solves the constrained problem with the dual active-set method of QPC;
  here* a primal active set (:func:`_active_set`): violating depths are pinned at the bound
  (their two rows kept explicitly) and released when their multiplier changes sign. Each
  least-squares solve is direct (:func:`_solve_normal`: sparse normal equations, Jacobi-scaled).
* Robust coplanarities* (``robust_iterations`` rounds, 3 by default; the paper: plain least squares): the
  coplanarity rows are reweighted by a Cauchy kernel on their residuals (scale: the residuals' robust
  spread, at least half a pixel at the median depth) and the system solved again. A false coplanarity
  (a cabinet front 7-9 cm before the wall, normals alike) otherwise bends the whole solve: measured
  (``tools/bench_ba.py --real``, office, oracle normals) lines 11.4 -> 1.3 cm from the surfaces.
  The relations left below ``reject_weight`` (0.1: a residual over 7 robust sigmas) are not handed
  on: the bundle adjustment would take them in again (measured, default normals, living: its lines
  2.3 -> 0.7 cm from the surfaces).
* Floor outliers* (``floor_tolerance`` > 0, with ``robust_iterations``): a floor relation whose line
  ends up above the floor (a furniture top: upward normals too) is downweighted, one-sided.

(* marks a deviation from the paper.)
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from ..config import LinearConfig
from ..data import Camera
from .system import LinearSystem

log = logging.getLogger("panosfm.linear")


@dataclasses.dataclass(frozen=True, eq=False)
class Estimate:
    """The solve's result in solve units: ``x`` (n_cols,) all unknowns, ``depths`` (n,) per observation.

    ``pinned`` (n,): depths at the bound; ``iterations``: active-set solves in all; ``n_down``:
    relations the IRLS left below weight 0.5; ``rejected``: indices into the relations of those it
    left below ``reject_weight``.
    """

    x: np.ndarray
    depths: np.ndarray
    pinned: np.ndarray
    iterations: int
    n_down: int
    rejected: np.ndarray


def solve_constrained(system: LinearSystem, camera: Camera, h0: float, config: LinearConfig) -> Estimate:
    """Returns the least-squares solution with every depth >= ``min_depth_m``, the relations reweighted by IRLS.

    Paper §3.3 (constrained linear least squares); ``h0``: the floor height the gauge fixes.
    """
    n_const_rows = system.n_const_rows
    pinned = np.zeros(system.n_obs, bool)
    x = np.where(system.fixed, system.fixed_val, 0.0)
    lam = np.zeros(system.n_obs)
    robust_w = np.ones(n_const_rows + system.n_obs)
    iterations = 0
    n_down = 0
    rel_down = np.zeros(0, np.int64)  # relations the IRLS left below reject_weight (indices into relations)
    if system.n_obs and len(system.free_idx):
        for irls in range(max(config.robust_iterations, 0) + 1):
            x, lam, pinned, it = _active_set(system, pinned, robust_w, h0)
            iterations += it
            if irls == config.robust_iterations or (n_const_rows == 0 and not config.robust_observations):
                break
            new_w = _robust_weights(system, x, lam, camera, h0, config)
            if np.allclose(new_w, robust_w, atol=1e-3):
                break
            robust_w = new_w
        n_down = int(np.sum(robust_w[:n_const_rows] < 0.5))
        # what the robust solve found far off, the bundle adjustment does not get
        rel_down = system.rel_index[robust_w[:n_const_rows] < config.reject_weight]
    elif system.n_obs:
        lam, _ = system.depths(x, pinned)
    return Estimate(x=x, depths=lam, pinned=pinned, iterations=iterations, n_down=n_down, rejected=rel_down)


def _robust_weights(system: LinearSystem, x: np.ndarray, lam: np.ndarray, camera: Camera, h0: float,
                    config: LinearConfig) -> np.ndarray:
    """Returns (n_const_rows + n,) the IRLS weights of the relation rows (and, optionally, the observations)."""
    n_const_rows, n_pair_rows = system.n_const_rows, system.n_pair_rows
    noise = 0.5 / camera.K[0, 0] * float(np.median(np.abs(lam)))  # half a pixel at the median depth
    r = x[system.rel_c0] - x[system.rel_c1]
    new_w = np.ones(n_const_rows + system.n_obs)
    if config.robust_observations:  # an observation off its track's line: a member of another line
        a1, a2 = x[system.c_t1] - x[system.c_u1], x[system.c_t2] - x[system.c_u2]
        res = (a1 * system.e2 - a2 * system.e1) / system.en  # ray-to-line distance
        new_w[n_const_rows:] = _cauchy_weights(res, lam, noise, config.robust_k)
    if n_pair_rows:
        new_w[:n_pair_rows] = _cauchy_weights(r[:n_pair_rows], lam, noise, config.robust_k)
    if config.floor_tolerance > 0 and n_const_rows > n_pair_rows:
        # one-sided: a 'floor' line above the floor is a furniture top (upward normals too);
        # no line lies below the floor. Scale: a share of the camera-to-floor distance.
        above = np.maximum(r[n_pair_rows:], 0.0) / (config.floor_tolerance * abs(h0 if h0 else 1.0))
        new_w[n_pair_rows:] = 1.0 / (1.0 + above ** 2)
    return new_w


def _cauchy_weights(res: np.ndarray, lam: np.ndarray, noise: float, robust_k: float) -> np.ndarray:
    """Returns Cauchy weights of ``res``; scale: the robust spread, at least half a pixel of ``noise``."""
    scale = max(1.4826 * float(np.median(np.abs(res))), noise,
                1e-6 * max(1.0, float(np.median(np.abs(lam)))))
    return 1.0 / (1.0 + (res / (robust_k * scale)) ** 2)


def _active_set(system: LinearSystem, pinned: np.ndarray, robust_w: np.ndarray, h0: float,
                max_iterations: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Returns (x, depths, pinned, iterations): least squares with depths >= lam_min by a primal active set.

    Violating depths are pinned at the bound; pinned depths whose gradient says the objective
    decreases inside the feasible region are released; repeat until neither happens.
    """
    for it in range(1, max_iterations + 1):
        A, rhs = system.assemble(pinned, robust_w)
        x = system.full_x(_solve_normal(A, rhs))
        lam, grad = system.depths(x, pinned)
        tol = 1e-9 * max(1.0, abs(h0))
        violate = ~pinned & system.not_ref & (lam < system.lam_min - tol)
        release = pinned & (grad < -tol)
        if not violate.any() and not release.any():
            return x, lam, pinned, it
        pinned = (pinned | violate) & ~release
    log.warning("linear: depth active set did not converge in %d iterations", max_iterations)
    return x, lam, pinned, max_iterations


def _solve_normal(A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
    """Returns argmin |A x - b| by Jacobi-scaled sparse normal equations (a tiny ridge guards empty columns).

    The normal matrix is symmetric: SuperLU orders it by minimum degree on its own pattern, not on its
    columns (COLAMD, the default), which fills in far less (600-frame spin: 73 -> 18 ms a solve, the same
    solution to 1e-9).
    """
    N = (A.T @ A).tocsc()
    diag = N.diagonal()
    s = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    S = sp.diags(s)
    Ns = (S @ N @ S + 1e-12 * sp.identity(N.shape[0])).tocsc()
    y = spsolve(Ns, s * (A.T @ b), permc_spec="MMD_AT_PLUS_A")
    return s * np.atleast_1d(y)
