"""The constrained linear system (paper §3.3): its unknowns, and rows for colinearity, coplanarity and the floor.

Unknowns (paper §3.3 "Model"): the camera centres ``T_i`` and one depth ``lambda`` per line
observation -- the segment mid-point ``P = T_i + lambda D`` along its unit world viewing ray
``D = R_wc K^-1 x~`` (normalised). Rotations (``pre.R_wc``) and the Manhattan directions are known.

Formulation choices (documented deviations are marked *):

* Coordinates are taken in the Manhattan frame: ``tau_i[k] = T_i . N_k`` (``N_k`` = the
  Manhattan directions). A line of axis ``a`` is fixed by its two coordinates ``u[k] = P . N_k``,
  ``k != a`` (its position in the plane orthogonal to its direction).
* Colinearity (paper: ``(P_i - P_j) . N = 0`` for every pair of a track's observations) is
  written* with the per-track offsets ``u`` as extra unknowns: ``(T_i + lambda D) . N_k - u[k] = 0``
  for each observation and both ``k != a``. Minimising over ``u`` gives exactly the paper's
  all-pairs sum divided by the track length, with 2 rows per observation instead of O(n^2).
* A coplanarity with normal axis ``k`` (orthogonal, parallel, junction) is ``(P_l - P_m) . N_k = 0``;
  since ``N_k`` is orthogonal to both lines this equals ``u_l[k] - u_m[k] = 0`` for every choice
  of observations once colinearity holds, so it is written on the offsets. Relations whose normal
  axis is one of the tracks' own axes are impossible and skipped.
* Floor coplanarity: every floor track's vertical offset equals one floor height ``h``.
* The depths are eliminated per observation (each appears only in its two colinearity rows),
  leaving a small sparse least-squares problem in ``tau, u`` (:meth:`LinearSystem.assemble`); the
  depths follow by back-substitution (:meth:`LinearSystem.depths`). The depth bound and the
  robust weights: :mod:`.robust`.
* The priors on the centres (body motion, spin model; not in the paper) add rows, and the spin
  model unknowns: :mod:`.priors`.
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
import scipy.sparse as sp

from ..config import LinearConfig
from ..data import FLOOR, JUNCTION, ORTHOGONAL, PARALLEL, Camera, Preprocessed, Relations, Tracks
from ..geometry import world_rays
from .priors import PriorRows, prior_rows

log = logging.getLogger("panosfm.linear")

OTHER_AXES = np.array([[1, 2], [0, 2], [0, 1]])  # the two Manhattan axes orthogonal to axis a
VERTICAL = 2


def observation_rays(pre: Preprocessed, camera: Camera, segments: np.ndarray | None = None,
                     which: str = "mid") -> np.ndarray:
    """Returns (N, 3) unit WORLD viewing rays ``D = R_wc K^-1 x~`` of segment mid-points (or end points).

    ``which`` is ``"mid"``, ``"start"`` (x1, y1) or ``"end"`` (x2, y2). Paper §3.3, "Model".
    """
    seg = pre.segments
    idx = np.arange(seg.n) if segments is None else np.asarray(segments)
    ep = seg.endpoints[idx].astype(np.float64)
    pts = {"mid": 0.5 * (ep[:, :2] + ep[:, 2:]), "start": ep[:, :2], "end": ep[:, 2:]}[which]
    return world_rays(camera.K, pre.R_wc[seg.frame[idx]], pts)


@dataclasses.dataclass(frozen=True, eq=False)
class Observations:
    """The tracked observations (paper §3.3 "Model"): each a segment mid-point ``P = T_i + lambda D``.

    All (O,): ``seg`` the segment, ``frame``, ``track`` and its Manhattan ``axis``; ``ray`` (O, 3)
    the unit world viewing ray ``D``; ``k1``, ``k2`` the two Manhattan axes orthogonal to the
    line and ``d1``, ``d2`` the ray's coordinates along them (``dn`` = their norm, > 0: a ray
    along its own line fixes nothing and is left out).
    """

    seg: np.ndarray
    frame: np.ndarray
    track: np.ndarray
    axis: np.ndarray
    ray: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    dn: np.ndarray


def tracked_observations(pre: Preprocessed, tracks: Tracks, camera: Camera, M: np.ndarray) -> Observations:
    """Returns the tracked observations and their viewing rays in Manhattan coordinates (paper §3.3 "Model")."""
    seg = pre.segments
    T = tracks.n
    axis = tracks.axis.astype(int)
    obs = np.flatnonzero(tracks.track_of >= 0)
    obs = obs[(tracks.track_of[obs] < T)]
    o_frame = seg.frame[obs].astype(int)
    o_track = tracks.track_of[obs].astype(int)
    o_axis = axis[o_track]
    D = observation_rays(pre, camera, obs)  # (O, 3) world
    Dm = D @ M.T  # ray coordinates along the Manhattan axes
    k1 = OTHER_AXES[o_axis, 0]
    k2 = OTHER_AXES[o_axis, 1]
    O = np.arange(len(obs))
    d1, d2 = Dm[O, k1], Dm[O, k2]
    dn = np.hypot(d1, d2)
    ok = dn > 1e-6  # a ray along its own line fixes nothing
    obs, o_frame, o_track, o_axis, D, k1, k2, d1, d2, dn = (
        x[ok] for x in (obs, o_frame, o_track, o_axis, D, k1, k2, d1, d2, dn))
    return Observations(seg=obs, frame=o_frame, track=o_track, axis=o_axis, ray=D, k1=k1, k2=k2, d1=d1, d2=d2, dn=dn)


@dataclasses.dataclass(frozen=True, eq=False)
class UsableRelations:
    """The relations the linear solve can use (paper §3.2, §3.3 "Coplanarity constraints").

    ``pair`` (R,) and ``floor`` (R,) masks into the relations; of the pair coplanarities (P,):
    ``a``, ``b`` the tracks, ``k`` the normal axis, ``kind``; ``floor_track`` (Fl,) the floor lines.
    """

    pair: np.ndarray
    floor: np.ndarray
    a: np.ndarray
    b: np.ndarray
    k: np.ndarray
    kind: np.ndarray
    floor_track: np.ndarray


def _valid_relations(relations: Relations, axis: np.ndarray, config: LinearConfig) -> tuple[np.ndarray, np.ndarray]:
    """Returns (pair relation mask, floor relation mask) of relations the linear solve can use."""
    T = len(axis)
    kind = relations.kind
    a, b, k = relations.track_a, relations.track_b, relations.normal_axis.astype(int)
    in_a = (a >= 0) & (a < T)
    in_b = (b >= 0) & (b < T)
    ax_a = np.where(in_a, axis[np.clip(a, 0, max(T - 1, 0))], -1) if T else np.full(len(a), -1)
    ax_b = np.where(in_b, axis[np.clip(b, 0, max(T - 1, 0))], -1) if T else np.full(len(a), -1)
    pair = (np.isin(kind, (ORTHOGONAL, PARALLEL, JUNCTION)) & in_a & in_b & (a != b)
            & (k != ax_a) & (k != ax_b) & (k >= 0) & (k < 3) & (config.coplanarity_weight > 0))
    floor = (kind == FLOOR) & in_a & (ax_a != VERTICAL) & (ax_a >= 0) & (config.floor_weight > 0)
    n_bad = int(np.sum(np.isin(kind, (ORTHOGONAL, PARALLEL, JUNCTION)) & ~pair)) if config.coplanarity_weight > 0 else 0
    if n_bad:
        log.warning("linear: skipped %d coplanarities whose normal axis is a line's own axis", n_bad)
    return pair, floor


def usable_relations(relations: Relations, axis: np.ndarray, config: LinearConfig) -> UsableRelations:
    """Returns the coplanarity and floor relations the solve can use (a normal axis not a line's own axis)."""
    pair, floor = _valid_relations(relations, axis, config)
    return UsableRelations(pair=pair, floor=floor,
                           a=relations.track_a[pair].astype(int), b=relations.track_b[pair].astype(int),
                           k=relations.normal_axis[pair].astype(int), kind=relations.kind[pair].astype(int),
                           floor_track=relations.track_a[floor].astype(int))


@dataclasses.dataclass(frozen=True, eq=False)
class SystemMembers:
    """What enters the system: the registered frames' observations of tracks with enough constraints.

    ``obs`` (n,) indices into :class:`Observations`; ``pairs`` (P,) and ``floor`` (Fl,) masks into
    :class:`UsableRelations`; per track (T,): ``n_obs`` its observations in registered frames,
    ``n_rel`` its relations among live tracks, ``in_sys`` whether it is in the system.
    """

    obs: np.ndarray
    pairs: np.ndarray
    floor: np.ndarray
    n_obs: np.ndarray
    n_rel: np.ndarray
    in_sys: np.ndarray


def system_members(registered: np.ndarray, obs: Observations, rels: UsableRelations, T: int) -> SystemMembers:
    """Returns the observations, relations and tracks of the system over the registered frames (the only unknowns).

    A track enters with at least two constraints (observations + relations), a relation when both its tracks do.
    """
    r_a, r_b, f_t = rels.a, rels.b, rels.floor_track
    o_sel = registered[obs.frame]
    n_obs = np.bincount(obs.track[o_sel], minlength=T)
    live = n_obs > 0
    rs = live[r_a] & live[r_b]
    fs = live[f_t]
    n_rel = np.bincount(r_a[rs], minlength=T) + np.bincount(r_b[rs], minlength=T) + np.bincount(f_t[fs], minlength=T)
    in_sys = live & (n_obs + n_rel >= 2)
    rs &= in_sys[r_a] & in_sys[r_b]
    fs &= in_sys[f_t]
    o_sel &= in_sys[obs.track]
    return SystemMembers(obs=np.flatnonzero(o_sel), pairs=rs, floor=fs, n_obs=n_obs, n_rel=n_rel, in_sys=in_sys)


@dataclasses.dataclass(frozen=True, eq=False)
class Unknowns:
    """The unknowns' columns (paper §3.3 "Model", in Manhattan coordinates).

    ``tau`` (3 per registered frame: ``3 frame_col[f] + k``), the two offsets ``u`` of each track in
    the system (``3 Fk + 2 track_col[t] + slot``), the floor height ``h`` (``col_h``), then with the
    spin model (``use_spin``) its stand-point knots (3 each) and arm (a, b: ``col_arm``, the last two).
    ``frames`` (Fk,) the registered frames, ``tracks`` the tracks in the system, ``track_axis`` (T,).
    """

    frames: np.ndarray
    frame_col: np.ndarray
    tracks: np.ndarray
    track_col: np.ndarray
    track_axis: np.ndarray
    col_h: int
    n_cols: int
    use_spin: bool

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def col_arm(self) -> int:
        """The spin model's arm (a, b): its last two unknowns (:func:`.priors._spin_rows`)."""
        return self.n_cols - 2

    def tau_col(self, frame: np.ndarray, k: np.ndarray) -> np.ndarray:
        return 3 * self.frame_col[frame] + k

    def u_col(self, track: np.ndarray, k: np.ndarray) -> np.ndarray:
        slot = (k == OTHER_AXES[self.track_axis[track], 1]).astype(int)
        return 3 * self.n_frames + 2 * self.track_col[track] + slot


def lay_out_unknowns(pre: Preprocessed, M: np.ndarray, registered: np.ndarray, in_sys: np.ndarray,
                     axis: np.ndarray, config: LinearConfig) -> tuple[Unknowns, PriorRows]:
    """Returns the unknowns' columns and the priors' rows on them (the spin model adds unknowns after ``h``)."""
    F, T = len(registered), len(in_sys)
    frames = np.flatnonzero(registered)
    Fk = len(frames)
    frame_col = np.full(F, -1)
    frame_col[frames] = np.arange(Fk)
    tq = np.flatnonzero(in_sys)
    track_col = np.full(T, -1)
    track_col[tq] = np.arange(len(tq))
    n_u = 2 * len(tq)
    col_h = 3 * Fk + n_u
    col_spin = col_h + 1  # spin model: stand-point knots (3 Manhattan coordinates each), a, b (_spin_rows)
    priors = prior_rows(pre, M, frames, col_spin, config)
    n_cols = col_h + 1 + priors.n_unknowns
    return Unknowns(frames=frames, frame_col=frame_col, tracks=tq, track_col=track_col, track_axis=axis,
                    col_h=col_h, n_cols=n_cols, use_spin=priors.use_spin), priors


@dataclasses.dataclass(frozen=True, eq=False)
class LinearSystem:
    """The constrained linear system (paper §3.3) with the depths eliminated, in the gauge's fixed unknowns.

    Rows, in order: the relations (coplanarities, then floor: ``w (x[rel_c0] - x[rel_c1]) = 0``,
    ``rel_index`` the relation of each), the colinearity rows of the observations whose depth is free
    (depth eliminated), two rows per observation pinned at the depth bound, the priors' rows. Per
    observation (n,): the columns ``c_t1, c_u1, c_t2, c_u2`` of its frame's ``tau`` and its track's
    ``u`` along ``k1, k2``, its ray's coordinates ``e1, e2`` (norm ``en``); ``not_ref``: all but the
    one whose depth the gauge fixes (``ref_obs``).
    """

    n_cols: int
    fixed: np.ndarray
    fixed_val: np.ndarray
    free_idx: np.ndarray
    rel_c0: np.ndarray
    rel_c1: np.ndarray
    rel_w: np.ndarray
    rel_index: np.ndarray
    n_pair_rows: int
    prior_cols: np.ndarray
    prior_vals: np.ndarray
    c_t1: np.ndarray
    c_u1: np.ndarray
    c_t2: np.ndarray
    c_u2: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    en: np.ndarray
    not_ref: np.ndarray
    ref_obs: int
    w_c: float
    lam_min: float

    @property
    def n_const_rows(self) -> int:
        """The relation rows (coplanarity, floor), reweighted by the IRLS."""
        return len(self.rel_c0)

    @property
    def n_obs(self) -> int:
        return len(self.not_ref)

    def assemble(self, pinned: np.ndarray, robust_w: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
        """Returns (A_free, b) for the depths pinned at the bound and the relations' IRLS weights."""
        c_t1, c_u1, c_t2, c_u2 = self.c_t1, self.c_u1, self.c_t2, self.c_u2
        e1, e2, en, w_c, lam_min = self.e1, self.e2, self.en, self.w_c, self.lam_min
        n_mot_rows = len(self.prior_cols)
        free_o = ~pinned & self.not_ref
        nf, npn = int(free_o.sum()), int(pinned.sum())
        r0 = self.n_const_rows
        rr = r0 + np.arange(nf)
        wo = np.sqrt(robust_w[r0:])  # observations' IRLS weights (ones unless robust_observations)
        c1, c2 = wo[free_o] * e2[free_o] / en[free_o], wo[free_o] * e1[free_o] / en[free_o]
        rc = np.arange(r0)
        wr = self.rel_w * np.sqrt(robust_w[:r0])
        rows = [rc, rc] + [rr] * 4
        cols = [self.rel_c0, self.rel_c1] + [c_t1[free_o], c_u1[free_o], c_t2[free_o], c_u2[free_o]]
        vals = [wr, -wr] + [w_c * c1, -w_c * c1, -w_c * c2, w_c * c2]
        rhs = [np.zeros(r0), np.zeros(nf)]
        rp = r0 + nf + np.arange(npn)
        rows += [rp, rp, rp + npn, rp + npn]
        cols += [c_t1[pinned], c_u1[pinned], c_t2[pinned], c_u2[pinned]]
        wp = w_c * wo[pinned]
        vals += [wp, -wp, wp, -wp]
        rhs += [-wp * lam_min * e1[pinned], -wp * lam_min * e2[pinned]]
        rm = r0 + nf + 2 * npn + np.arange(n_mot_rows)
        rows += [np.repeat(rm, self.prior_cols.shape[1])]
        cols += [self.prior_cols.ravel()]
        vals += [self.prior_vals.ravel()]
        rhs += [np.zeros(n_mot_rows)]
        rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        rhs = np.concatenate(rhs)
        n_rows = r0 + nf + 2 * npn + n_mot_rows
        A = sp.csr_matrix((vals, (rows, cols)), shape=(n_rows, self.n_cols))
        fv = np.where(self.fixed, self.fixed_val, 0.0)
        rhs = rhs - A @ fv
        return A[:, self.free_idx], rhs

    def full_x(self, x_free: np.ndarray) -> np.ndarray:
        """Returns (n_cols,) all unknowns: the free ones ``x_free`` and the gauge's fixed values."""
        x = np.where(self.fixed, self.fixed_val, 0.0)
        x[self.free_idx] = x_free
        return x

    def depths(self, x: np.ndarray, pinned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((n,) depths by back-substitution, (n,) the objective's gradient in each depth)."""
        e1, e2, en, w_c = self.e1, self.e2, self.en, self.w_c
        a1 = x[self.c_t1] - x[self.c_u1]
        a2 = x[self.c_t2] - x[self.c_u2]
        lam = -(a1 * e1 + a2 * e2) / en ** 2
        lam = np.where(pinned, self.lam_min, lam)
        if self.ref_obs >= 0:
            lam[~self.not_ref] = 1.0
        grad = w_c ** 2 * (e1 * (a1 + lam * e1) + e2 * (a2 + lam * e2))
        return lam, grad


def build_system(obs: Observations, rels: UsableRelations, members: SystemMembers, unknowns: Unknowns,
                 priors: PriorRows, fixed_val: np.ndarray, ref_obs: int, config: LinearConfig) -> LinearSystem:
    """Returns the system's rows: colinearity per observation, coplanarity and floor per relation, the priors.

    ``fixed_val`` (n_cols,): the gauge's fixed unknowns (NaN: free); ``ref_obs`` the observation whose
    depth it fixes (-1: none). Paper §3.3 "Colinearity constraints", "Coplanarity constraints".
    """
    w_c, w_p, w_f = config.colinearity_weight, config.coplanarity_weight, config.floor_weight
    u_col, tau_col = unknowns.u_col, unknowns.tau_col
    r_a, r_b, r_k, f_t = rels.a, rels.b, rels.k, rels.floor_track
    rs, fs = members.pairs, members.floor
    fixed = ~np.isnan(fixed_val)
    free_idx = np.flatnonzero(~fixed)

    # relation rows (coplanarity, floor): w * (x[rel_c0] - x[rel_c1]) = 0, reweighted by IRLS
    rel_c0 = np.concatenate([u_col(r_a[rs], r_k[rs]), u_col(f_t[fs], np.full(int(fs.sum()), VERTICAL))])
    rel_c1 = np.concatenate([u_col(r_b[rs], r_k[rs]), np.full(int(fs.sum()), unknowns.col_h)])
    rel_w = np.concatenate([np.full(int(rs.sum()), w_p), np.full(int(fs.sum()), w_f)])
    rel_index = np.concatenate([np.flatnonzero(rels.pair)[rs], np.flatnonzero(rels.floor)[fs]])

    # colinearity rows: (T_i + lambda D) . N_k - u[k] = 0 along both k != axis, the depth eliminated
    ob = members.obs
    o_f, o_t = obs.frame[ob], obs.track[ob]
    c_t1, c_t2 = tau_col(o_f, obs.k1[ob]), tau_col(o_f, obs.k2[ob])
    c_u1, c_u2 = u_col(o_t, obs.k1[ob]), u_col(o_t, obs.k2[ob])
    return LinearSystem(n_cols=unknowns.n_cols, fixed=fixed, fixed_val=fixed_val, free_idx=free_idx,
                        rel_c0=rel_c0, rel_c1=rel_c1, rel_w=rel_w, rel_index=rel_index, n_pair_rows=int(rs.sum()),
                        prior_cols=priors.cols, prior_vals=priors.vals,
                        c_t1=c_t1, c_u1=c_u1, c_t2=c_t2, c_u2=c_u2, e1=obs.d1[ob], e2=obs.d2[ob], en=obs.dn[ob],
                        not_ref=ob != ref_obs, ref_obs=ref_obs, w_c=w_c, lam_min=config.min_depth_m)
