"""Priors on the camera centres (our addition to paper §3.3): rows of the body-motion prior and the spin model.

Documented deviations from the paper (it has neither):

* Body-motion prior* (``motion_weight`` > 0, off in the paper): the phone is held out from the
  body and turns with it, so the centres' velocity is nearly constant in a frame turning with the
  camera's heading: rows ``w (Q_b (T_c - T_b) - Q_a (T_b - T_a)) = 0`` on consecutive registered
  frames (``Q = Rz(-yaw)``, exact for a uniform turn on a circle). It regularises the weak
  depth/translation modes of short tracks (measured: fragmented 4-frame tracks, office, 120
  frames: 48 % -> 0.7 % of the trajectory diameter) but never registers a frame (:mod:`.registration`).
* Spin model* (``spin_weight`` > 0, on by default; off in the paper): the person turns about a stand
  point and holds the phone out in front, so every centre lies on a circle in the direction the camera
  looks: ``T_i = S_i + a h_i + b h_i^perp`` (``h_i`` the horizontal viewing direction, ``(a, b)`` the arm,
  one for the whole sweep; the stand point ``S_i`` interpolated between knots ``spin_knot_deg`` of turn
  apart, neighbouring knots tied), linear in ``T, S, a, b`` (:func:`_spin_rows`). Parts of the sweep joined
  by few tracks otherwise take their own scale (measured, office capture 12: the ends of the sweep at 25-70
  times the middle's scale, 36 % centre error; with the model 3.4 %, 0.6 % after bundle adjustment,
  which carries the same model as a factor). It does not register a frame.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..config import LinearConfig
from ..data import Preprocessed
from ..geometry import turned_degrees


@dataclasses.dataclass(frozen=True, eq=False)
class PriorRows:
    """The priors' rows: ``cols`` (R, m) and ``vals`` (R, m), row r = sum_j vals[r, j] x[cols[r, j]] = 0.

    The body-motion rows first, then the spin model's (``use_spin``), which brings ``n_unknowns``
    unknowns of its own (stand-point knots, arm) after the floor height.
    """

    cols: np.ndarray
    vals: np.ndarray
    use_spin: bool
    n_unknowns: int


def prior_rows(pre: Preprocessed, M: np.ndarray, frames: np.ndarray, col_spin: int,
               config: LinearConfig) -> PriorRows:
    """Returns the body-motion prior's and the spin model's rows on the registered ``frames``' centres.

    ``col_spin``: the column of the spin model's first unknown.
    """
    Fk = len(frames)
    use_spin = config.spin_weight > 0 and Fk >= 3 and not config.zero_translation
    fwd = np.asarray(pre.R_wc, dtype=np.float64)[:, :, 2] @ M.T  # optical axes in Manhattan coordinates
    if use_spin:
        spin_c, spin_v, n_spin = _spin_rows(frames, fwd, turned_degrees(pre.R_wc), col_spin, config)
    # body-motion prior rows: w_m * (second or first difference of consecutive registered centres) = 0
    mot_c, mot_v = _motion_rows(frames, np.arctan2(fwd[:, 1], fwd[:, 0]), config)
    if use_spin:
        width = max(mot_c.shape[1], spin_c.shape[1])
        pad = lambda a, v: np.pad(a, ((0, 0), (0, width - a.shape[1])), constant_values=v)  # noqa: E731
        mot_c = np.concatenate([pad(mot_c, 0), pad(spin_c, 0)])
        mot_v = np.concatenate([pad(mot_v, 0.0), pad(spin_v, 0.0)])
    return PriorRows(cols=mot_c, vals=mot_v, use_spin=use_spin, n_unknowns=n_spin if use_spin else 0)


def _motion_rows(frames: np.ndarray, yaw: np.ndarray, config: LinearConfig) -> tuple[np.ndarray, np.ndarray]:
    """Returns (cols (R, m), vals (R, m)) of the body-motion prior rows on the centre coordinates.

    The camera is held out from the body and turns with it, so its velocity is constant in a frame
    that turns with the camera's heading ``yaw`` (about the vertical Manhattan axis): with
    ``Q_i = Rz(-yaw_i)``, ``motion_order`` 2 asks ``w (Q_b (T_c - T_b) - Q_a (T_b - T_a)) / g^2 = 0`` for
    consecutive registered frames a < b < c (g = the larger index gap) -- exact for a uniform
    turn on a circle -- and ``motion_order`` 1 asks ``w (T_b - T_a) / g = 0``. Steps across a gap
    above ``motion_max_gap`` frames get no row. Three rows (Manhattan coordinates) per triple/pair.
    """
    w = config.motion_weight
    order = config.motion_order
    Fk = len(frames)
    if w <= 0 or Fk < order + 1:
        return np.zeros((0, 3 * (order + 1)), int), np.zeros((0, 3 * (order + 1)))
    gaps = np.diff(frames)
    if order == 2:
        g = np.maximum(gaps[:-1], gaps[1:])
        keep = np.flatnonzero(g <= config.motion_max_gap)
        c, s_ = np.cos(yaw[frames]), np.sin(yaw[frames])
        Q = np.zeros((Fk, 3, 3))
        Q[:, 0, 0], Q[:, 0, 1], Q[:, 1, 0], Q[:, 1, 1], Q[:, 2, 2] = c, s_, -s_, c, 1.0  # Rz(-yaw)
        a, b = keep, keep + 1
        blocks = np.stack([Q[a], -(Q[a] + Q[b]), Q[b]], axis=1)  # (n, 3 frames, 3 rows, 3 coords)
        blocks = blocks * (w / g[keep].astype(float) ** 2)[:, None, None, None]
        idx = keep[:, None] + np.arange(3)[None]  # registered-frame indices (a, b, c)
    else:
        keep = np.flatnonzero(gaps <= config.motion_max_gap)
        eye = np.broadcast_to(np.eye(3), (len(keep), 3, 3))
        blocks = np.stack([-eye, eye], axis=1) * (w / gaps[keep].astype(float))[:, None, None, None]
        idx = keep[:, None] + np.arange(2)[None]
    m = idx.shape[1]
    # row (n, r): sum over frames j and coordinates k of blocks[n, j, r, k] * tau[idx[n, j], k]
    cols = np.broadcast_to(3 * idx[:, :, None, None] + np.arange(3)[None, None, None, :], blocks.shape)
    cols = cols.transpose(0, 2, 1, 3).reshape(-1, 3 * m)
    vals = blocks.transpose(0, 2, 1, 3).reshape(-1, 3 * m)
    return cols, vals


def _spin_rows(frames: np.ndarray, fwd: np.ndarray, turned: np.ndarray, col0: int,
               config: LinearConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """Returns (cols (R, 5), vals (R, 5), number of unknowns) of the spin-model rows (``factors.spin_prior``).

    The person turns about a stand point ``S`` and holds the phone out in front, so each centre
    lies on a circle in the direction the camera looks: ``T_i = S + a h_i + b h_i^perp`` with
    ``h_i`` the horizontal unit direction of frame i's optical axis (Manhattan coordinates) and
    ``(a, b)`` the arm's length times the cosine / sine of its fixed angle to the optical axis --
    linear in (T, S, a, b). ``S`` is interpolated by the turned angle between knots
    ``spin_knot_deg`` apart (:func:`factors.spin_prior.spin_knots`). Rows
    (:func:`factors.spin_prior.spin_model_rows`): ``w (T_i[k] - S_i[k] - a h_i[k] - b h_i^perp[k])``
    for the two horizontal axes, ``w_z (T_i[z] - S_i[z])`` (the phone's height is constant), and
    ``w_walk (S_{j+1} - S_j)`` between neighbouring knots. Columns from ``col0``: the knots
    (3 each), then a, b. One shared arm binds the scale of every part of the sweep.
    """
    from factors.spin_prior import horizontal_direction, spin_knots, spin_model_rows

    h = horizontal_direction(np.eye(3), np.asarray(fwd, dtype=np.float64)[frames])
    j, alpha, n_knots = spin_knots(np.asarray(turned, dtype=np.float64)[frames], config.spin_knot_deg)
    kind, centre, cols, vals = spin_model_rows(h, j, alpha, n_knots)
    w = config.spin_weight * np.array([1.0, config.spin_vertical_ratio, config.spin_walk_ratio])[kind]
    has_c = centre >= 0
    # the centre's column (tau: 3 x registered-frame index + axis, as ``centre``) or a zero entry
    c0 = np.where(has_c, centre, col0)
    cols = np.column_stack([c0, col0 + cols])
    vals = np.column_stack([np.where(has_c, 1.0, 0.0), -vals]) * w[:, None]
    return cols, vals, 3 * n_knots + 2

