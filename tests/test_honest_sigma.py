"""The reliability check (panosfm_graph.graph.reliability; issue #63): every frame's std from independent evidence,
doubtful frames, the run's verdict, --strict, and a run whose inputs contradict each other called doubtful."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from panosfm_graph.config import VerifyConfig
from panosfm_graph.data import Camera, LineModel, ManhattanFrame, Preprocessed, Segments, Solution
from panosfm_graph.graph.reliability import Evidence, aligned_gap, honest_sigma, imu_gap_deg, verify_solution

F = 120
CFG = VerifyConfig()


def _spin(n: int = F, arm: float = 0.35, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A spin's true rotations (looking out along the arm, level) and centres on a 0.35 m circle."""
    a = np.linspace(0.0, 2.2 * np.pi, n)
    c = np.stack([arm * np.cos(a), arm * np.sin(a), np.full(n, 1.5)], axis=1)
    R = np.stack([Rotation.from_euler("ZX", [ai - np.pi / 2, -np.pi / 2]).as_matrix() for ai in a])
    return R, c


def test_an_alternative_a_similarity_away_has_no_gap():
    R, c = _spin()
    A = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    c_alt = 2.5 * c @ A.T + [4.0, -1.0, 0.3]  # another gauge: turned, scaled, shifted
    R_alt = np.einsum("ij,njk->nik", A, R)
    dist, ang = aligned_gap(c_alt, R_alt, c, R, np.ones(F, bool), 0.7)
    assert np.max(dist) < 1e-9 and np.max(ang) < 1e-6


def test_a_frame_the_independent_solution_contradicts_gets_a_large_std_and_a_reason():
    R, c = _spin()
    rng = np.random.default_rng(1)
    diam = 0.7
    lines_c = c + rng.normal(0, 0.001, c.shape)  # the lines' own solution, the truth but where it is bent
    bump = np.arange(40, 60)
    lines_c[bump] += [0.06 * diam, 0.0, 0.0]  # 6 % of the diameter there
    points_c = c + rng.normal(0, 0.001, c.shape)
    src = ["points"] * F  # the final solution came from the points: the lines are the independent check
    out = honest_sigma(c, R, np.ones(F, bool), np.full(F, 0.002), src,
                       [Evidence("lines", lines_c, R, np.ones(F, bool)), Evidence("points", points_c, R, np.ones(F, bool))],
                       CFG)
    sig, doubt = out["sigma_rel"], out["doubtful"]
    quiet = np.setdiff1d(np.arange(F), np.arange(30, 70))
    assert np.all(sig[quiet] < CFG.flag_sigma_rel) and not doubt[quiet].any()
    assert np.all(sig[45:55] > 2 * np.median(sig[quiet])) and doubt[45:55].all()
    assert all("lines' own solution puts it" in out["why"][i] for i in range(45, 55))
    assert 0.035 < np.median(out["other_rel"][45:55]) < 0.07  # 6 %, less what the similarity takes up
    # the same bump in the points' solution (the frames' own source): the nearest evidence, far less weight
    out2 = honest_sigma(c, R, np.ones(F, bool), np.full(F, 0.002), src,
                        [Evidence("lines", points_c, R, np.ones(F, bool)), Evidence("points", lines_c, R, np.ones(F, bool))],
                        CFG)
    assert np.all(out2["sigma_rel"][45:55] < sig[45:55])


def test_a_frame_far_from_every_solution_is_doubtful_whatever_its_std():
    """verify.max_gap_rel: the final solution bent 6 % of the diameter away from the only independent solution (its
    own source's, the points'; the lines' missing), with a small model std: the geometric mean of the evidence
    discounts the one large gap, the gap alone makes the frames doubtful."""
    R, c = _spin()
    rng = np.random.default_rng(4)
    diam = 0.7
    final = c.copy()
    final[40:60] += [0.06 * diam, 0.0, 0.0]
    points_c = c + rng.normal(0, 0.001, c.shape)
    args = (final, R, np.ones(F, bool), np.full(F, 0.002), ["points"] * F,
            [Evidence("points", points_c, R, np.ones(F, bool))])
    off = honest_sigma(*args, dataclasses.replace(CFG, max_gap_rel=0.0))
    on = honest_sigma(*args, CFG)
    assert np.all(off["gap_rel"][45:55] > CFG.max_gap_rel)  # 6 %, less what the similarity takes up
    assert not off["doubtful"][45:55].any()  # the std alone leaves them confident
    assert on["doubtful"][45:55].all() and all("from every independent solution" in on["why"][i] for i in range(45, 55))
    assert not on["doubtful"][:30].any() and not on["doubtful"][70:].any()


def test_imu_relative_rotations_catch_a_turned_frame():
    R, c = _spin()
    R_imu = Rotation.from_euler("z", np.linspace(0, 3, F)[:, None], degrees=True).as_matrix() @ R  # a 3 deg drift: harmless
    R_bad = R.copy()
    R_bad[70] = Rotation.from_euler("y", 2.0, degrees=True).as_matrix() @ R[70]
    gap = imu_gap_deg(R_bad, R_imu, np.ones(F, bool), 5)
    assert gap[70] == pytest.approx(2.0, abs=0.15) and np.all(gap[:60] < 0.2)
    out = honest_sigma(c, R_bad, np.ones(F, bool), np.full(F, 0.002), ["lines"] * F, [], CFG, R_imu=R_imu)
    assert out["doubtful"][70] and "IMU" in out["why"][70] and not out["doubtful"][:60].any()


def _solution(R, c, source, model_sigma):
    cam = Camera("PINHOLE", 480, 270, np.array([400.0, 400.0, 239.5, 134.5]))
    lines = LineModel(taylor=np.zeros((0, 3)), direction=np.zeros((0, 3)), axis=np.zeros(0, np.int8),
                      extent=np.zeros((0, 2)), valid=np.zeros(0, bool))
    return Solution(R_wc=R.copy(), centers=c.copy(), registered=np.ones(len(c), bool), lines=lines, camera=cam,
                    metric=False, residuals={"frame_source": list(source), "frame_sigma_rel": list(model_sigma)})


def _pre(R):
    seg = Segments(endpoints=np.zeros((0, 4), np.float32), frame=np.zeros(0, np.int32),
                   frame_offsets=np.zeros(len(R) + 1, np.int64), colors=np.zeros((0, 3), np.uint8))
    return Preprocessed(segments=seg, manhattan=ManhattanFrame(np.eye(3)), labels=np.zeros(0, np.int8), R_wc=R,
                        R_wc_imu=R)


def test_verdict_strict_and_left_out_frames():
    R, c = _spin()
    rng = np.random.default_rng(2)
    lines_c = c + rng.normal(0, 0.001, c.shape)
    lines_c[80:100] += [0.25, 0.0, 0.0]  # the lines' solution 35 % of the diameter off there: nothing to keep
    lines_c[20:30] += [0.03, 0.0, 0.0]  # ... 4 % here: doubtful
    ev = [Evidence("lines", lines_c, R, np.ones(F, bool)), Evidence("points", c, R, np.ones(F, bool))]
    sol = _solution(R, c, ["points"] * F, [0.002] * F)
    out = verify_solution(_pre(R), sol, CFG, evidence=ev)
    v = out.residuals["verify"]
    assert v["verdict"] == "doubtful" and any("doubtful" in r for r in v["reasons"])
    assert not out.registered[85:95].all() and v["left_out"] > 0
    assert all(w.startswith("left out") for w, r in zip(out.residuals["frame_doubtful_why"], out.registered)
               if not r)
    assert out.residuals["frame_doubtful"][25] and out.registered[25]
    sig = out.residuals["frame_sigma_rel"]
    assert all((s is None) == (not r) for s, r in zip(sig, out.registered))
    strict = verify_solution(_pre(R), sol, dataclasses.replace(CFG, strict=True), evidence=ev)
    assert strict.registered.sum() < out.registered.sum()
    assert not np.any(np.asarray(strict.residuals["frame_doubtful"]) & strict.registered)
    assert not strict.registered[22:28].any() and strict.registered[:15].all()
    # every solution agrees: trusted, nothing flagged
    calm = verify_solution(_pre(R), sol, CFG, evidence=[Evidence("lines", c, R, np.ones(F, bool))])
    assert calm.residuals["verify"]["verdict"] == "trusted" and not any(calm.residuals["frame_doubtful"])


def test_a_doubtful_run_vouches_only_for_frames_an_independent_solution_places():
    """verify.doubt_unchecked: the lines' own solution places frames 0-59 only (the points placed the rest) and is
    4 % off over frames 20-39: the run is doubtful, and frames 60-119, which nothing independent of the points places,
    are flagged with the reason; off, they are vouched for by their std alone. A run that checks out stays trusted
    with its unchecked frames unflagged."""
    R, c = _spin()
    rng = np.random.default_rng(3)
    lines_c = c + rng.normal(0, 0.001, c.shape)
    lines_c[20:40] += [0.03, 0.0, 0.0]
    lines_reg = np.arange(F) < 60
    ev = [Evidence("lines", lines_c, R, lines_reg), Evidence("points", c, R, np.ones(F, bool))]
    sol = _solution(R, c, ["points"] * F, [0.002] * F)
    on = verify_solution(_pre(R), sol, CFG, evidence=ev)
    off = verify_solution(_pre(R), sol, dataclasses.replace(CFG, doubt_unchecked=False), evidence=ev)
    assert on.residuals["verify"]["verdict"] == off.residuals["verify"]["verdict"] == "doubtful"
    flagged_on, flagged_off = (np.asarray(x.residuals["frame_doubtful"]) for x in (on, off))
    assert not flagged_off[60:].any() and flagged_on[60:].all()
    assert all("no solution independent" in on.residuals["frame_doubtful_why"][i] for i in range(60, F))
    assert not flagged_on[:15].any()  # checked by the lines' solution and within it
    calm = verify_solution(_pre(R), sol, CFG, evidence=[Evidence("lines", c, R, lines_reg)])
    assert calm.residuals["verify"]["verdict"] == "trusted" and not any(calm.residuals["frame_doubtful"])


def test_a_wrong_focal_length_is_called_doubtful_and_no_frame_is_confidently_wrong(tmp_path):
    """The issue's test: a capture whose inputs contradict each other (camera.json's focal length 20 % long) gives a
    doubtful verdict, and every frame that is not accurate is flagged doubtful (none is vouched for)."""
    from panosfm_graph.cli import main
    from panosfm_graph.evaluate import evaluate_reconstruction
    from panosfm_graph.synth import synthesize

    cap = synthesize(tmp_path / "cap", "living", 80, (480, 270), seed=4, sway_m=0.03, gt_maps=False)
    cam = json.loads((cap / "camera.json").read_text())
    cam["params"][0] *= 1.2
    cam["params"][1] *= 1.2
    (cap / "camera.json").write_text(json.dumps(cam))
    assert main(["run", str(cap), str(tmp_path / "out"), "--no-rerun"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["focal"]["focal_px"] == pytest.approx(cam["params"][0])  # a given focal length is kept
    assert summary["verdict"]["status"] == "doubtful"
    assert any("focal length" in r for r in summary["verdict"]["reasons"])
    m = evaluate_reconstruction(cap, tmp_path / "out")
    un = m["uncertainty"]
    assert un["verdict"] == "doubtful" and un["confident_wrong"] == 0
