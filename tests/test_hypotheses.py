"""Hypotheses and their verification, with known answers: several distinct RANSAC poses,
the fusion weight of a modality that is pure noise, the verification score of the true
pose against its 180-degree flip, and the choice of a candidate's hypothesis."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from pipeline.common.config import RefineParams, RegisterParams
from pipeline.method.geometry.transforms import rotation_angle_deg
from pose_helpers import random_rotation
from pipeline.method.registration.fusion import match_signal, modality_weight
from pipeline.method.registration.ransac import RansacParams, distinct_poses, ransac_align, ransac_hypotheses
from pipeline.method.scene_side import coarse_hypotheses, matchable_model, refine_candidates


def _problem(seed: int, signal: dict[str, float]):
    """A 2000-point model and a 600-point noisy partial scene under a known pose, with
    geometric (32-d) and visual (16-d) features; ``signal[m]`` of the scene points have
    their model point's feature (plus noise) in modality m, the others random ones."""
    rng = np.random.default_rng(seed)
    model = rng.normal(size=(2000, 3)) * [60, 40, 25]
    R, t = random_rotation(rng), np.array([20.0, -10.0, 650.0])
    idx = rng.choice(2000, 600, replace=False)
    scene = model[idx] @ R.T + t + rng.normal(scale=0.5, size=(600, 3))
    feats, scene_feats = {}, {}
    for m, dim in (("geometric", 32), ("visual", 16)):
        f = rng.normal(size=(2000, dim)).astype(np.float32)
        s = f[idx] + 0.05 * rng.normal(size=(600, dim)).astype(np.float32)
        wrong = rng.random(600) > signal[m]
        s[wrong] = rng.normal(size=(wrong.sum(), dim))
        feats[m], scene_feats[m] = f, s
    return {"points": model.astype(np.float32), **feats}, scene, scene_feats, R, t


def test_match_signal_is_chance_for_random_matches_and_large_for_true_ones():
    features, scene, sf, R, t = _problem(0, {"geometric": 1.0, "visual": 0.0})
    rng = np.random.default_rng(1)
    true = np.argmin(np.linalg.norm(features["points"][None] - ((scene - t) @ R)[:, None], axis=2), axis=1)
    thr = 0.05 * 250.0
    assert match_signal(features["points"], true, scene, R, t, thr) > 100
    chance = [match_signal(features["points"], rng.integers(0, 2000, size=600), scene, R, t, thr) for _ in range(50)]
    assert abs(np.mean(chance)) < 0.5 and 0.5 < np.std(chance) < 1.5 and max(chance) < 3
    assert modality_weight(3.0) == 0.0 and modality_weight(4.5) == 0.5 and modality_weight(9.0) == 1.0


def test_ransac_hypotheses_are_distinct_and_the_first_is_the_winner():
    features, scene, sf, R, t = _problem(2, {"geometric": 0.15, "visual": 0.0})
    params = RansacParams(inlier_frac=0.02)
    hyps = ransac_hypotheses(features["points"], features["geometric"], scene, sf["geometric"], 250.0, params=params,
                             seed=1, k=3)
    best = ransac_align(features["points"], features["geometric"], scene, sf["geometric"], 250.0, params=params, seed=1)
    assert 2 <= len(hyps) <= 3
    np.testing.assert_array_equal(hyps[0].R, best.R)  # keeping runners-up does not change the winner
    assert rotation_angle_deg(hyps[0].R, R) < 0.5 and np.linalg.norm(hyps[0].t - t) < 1.0
    for i in range(len(hyps)):
        for j in range(i):
            assert (rotation_angle_deg(hyps[i].R, hyps[j].R) > 30 or np.linalg.norm(hyps[i].t - hyps[j].t) > 50)
    assert hyps[0].n_inliers >= max(h.n_inliers for h in hyps[1:])
    poses = [(np.eye(3), np.zeros(3)), (np.eye(3), np.array([1.0, 0, 0])), (np.eye(3), np.array([100.0, 0, 0]))]
    assert distinct_poses(poses, 3, 30.0, 50.0) == [0, 2]


@pytest.mark.parametrize("noise", ["visual", "geometric"])
def test_a_modality_of_pure_noise_gets_no_weight(noise):
    signal = {"geometric": 0.5, "visual": 0.5, noise: 0.0}
    features, scene, sf, R, t = _problem(3, signal)
    model = matchable_model(features, pca_dim=64)
    assert model.modalities == ("geometric", "visual")
    res = coarse_hypotheses(model, scene, sf["geometric"], sf["visual"], 250.0, RegisterParams(), seed=0)
    weights = {"geometric": res.w_geometric, "visual": res.w_visual}
    good = "geometric" if noise == "visual" else "visual"
    assert weights[noise] == 0.0 and weights[good] == 1.0
    signals = {"geometric": res.signal_geometric, "visual": res.signal_visual}
    assert signals[noise] < 3 < 6 < signals[good]
    by_source = {h.source: h.registration for h in res.hypotheses}
    # the weighted fusion is the good modality alone: a duplicate of its own pose, dropped
    assert {"geometric", "visual"} <= set(by_source) <= {"geometric", "visual", "fused"}
    assert rotation_angle_deg(by_source[good].R, R) < 1.0 and np.linalg.norm(by_source[good].t - t) < 2.0
    assert rotation_angle_deg(by_source[noise].R, R) > 10.0


def test_both_modalities_with_signal_keep_the_papers_fusion():
    features, scene, sf, R, t = _problem(4, {"geometric": 0.3, "visual": 0.3})
    res = coarse_hypotheses(matchable_model(features, 64), scene, sf["geometric"], sf["visual"], 250.0,
                            RegisterParams(), seed=0)
    assert (res.w_geometric, res.w_visual) == (1.0, 1.0)
    assert "weighted" not in {h.source for h in res.hypotheses}
    # every source finds the pose: the later ones repeat the first and are dropped
    assert res.hypotheses[0].source == "geometric" and rotation_angle_deg(res.hypotheses[0].registration.R, R) < 1.0
    assert all(rotation_angle_deg(h.registration.R, R) > 5.0 for h in res.hypotheses[1:])


def test_refine_picks_each_candidates_best_verified_hypothesis():
    rows = []
    for cand_id in (0, 1):
        for hyp in range(3):
            rows.append({"cand_id": cand_id, "scene_id": 1, "im_id": 0, "obj_id": 1, "prior_score": 0.9, "hyp": hyp,
                         "source": ["geometric", "visual", "fused"][hyp], "n_inliers": 10, "inlier_ratio": 0.1,
                         "R": np.eye(3).ravel().tolist(), "t": [0.0, 0.0, 500.0 + 10 * hyp], "ransac_fitness": 0.9})
    registered = pd.DataFrame(rows)
    scores = {(0, 510.0): 0.8, (1, 500.0): 0.7}  # candidate 0: hypothesis 1; candidate 1: hypothesis 0

    class Verify:
        def __call__(self, im_id, cand_id, obj_id, R, t, diameter, evidence):
            from pipeline.method.refinement.verification import Verification

            s = scores.get((cand_id, float(t[2])), 0.1)
            return Verification(s, s, s, 0.0, evidence, s)

    hyps, cands, _ = refine_candidates(registered, lambda c: None, lambda o: None, {1: 100.0},
                                       RefineParams(icp=False), Verify())
    assert len(hyps) == 6 and hyps.chosen.sum() == 2
    assert cands.set_index("cand_id").hyp.to_dict() == {0: 1, 1: 0}
    assert cands.set_index("cand_id").source.to_dict() == {0: "visual", 1: "geometric"}
    assert cands.verification.tolist() == [0.8, 0.7]
    with pytest.raises(ValueError, match="verifier"):
        refine_candidates(registered, lambda c: None, lambda o: None, {1: 100.0}, RefineParams(icp=False), None)


@pytest.fixture(scope="module")
def rendered_frame():
    """A synthetic object rendered at a known pose: depth with sensor-like noise, the mask."""
    from pipeline.method.render import Renderer
    from pipeline.evaluation.synth.objects import build_object

    mesh = build_object(8).model
    K = np.array([[572.4, 0.0, 320.0], [0.0, 573.6, 240.0], [0.0, 0.0, 1.0]])
    R = random_rotation(np.random.default_rng(5))
    t = np.array([10.0, -20.0, 700.0])
    # No renderer outlives the fixture: pyrender's EGL teardown terminates the display
    # that every other open renderer uses, so renderers are opened and closed in turn.
    with Renderer(640, 480, znear=1.0, zfar=100000.0) as renderer:
        renderer.add_mesh(1, mesh)
        depth = renderer.render_depth(1, R, t, K)
    mask = depth > 0
    rng = np.random.default_rng(6)
    noisy = np.where(mask, depth + rng.normal(scale=1.5, size=depth.shape), 0).astype(np.float32)
    noisy[rng.random(depth.shape) < 0.1] = 0  # holes
    return {"mesh": mesh, "K": K, "R": R, "t": t, "depth": noisy, "mask": mask,
            "diameter": float(np.linalg.norm(mesh.extents))}


def test_verification_prefers_the_true_pose_over_its_flip(rendered_frame):
    from pipeline.method.geometry.crops import mask_to_bbox
    from pipeline.method.refinement.verification import verification_window, verify_pose
    from pipeline.method.render import Renderer

    f = rendered_frame
    window = verification_window(mask_to_bbox(f["mask"]), f["depth"].shape)
    tol = max(5.0, 0.05 * f["diameter"])
    with Renderer(640, 480, znear=1.0, zfar=100000.0) as renderer:
        renderer.add_mesh(1, f["mesh"])
        true = verify_pose(renderer, 1, f["R"], f["t"], f["K"], f["depth"], f["mask"], window, tol)
        # the flip: 180 degrees about the model's x axis, its centre kept in place
        flip = np.diag([1.0, -1.0, -1.0])
        centre = np.asarray(f["mesh"].vertices).mean(axis=0)
        R_f = f["R"] @ flip
        t_f = f["t"] + f["R"] @ centre - R_f @ centre
        flipped = verify_pose(renderer, 1, R_f, t_f, f["K"], f["depth"], f["mask"], window, tol)
    assert true.silhouette > 0.98 and true.depth_fit > 0.98 and true.coverage > 0.98 and true.free_space < 0.01
    assert flipped.value < true.value - 0.2
    assert flipped.depth_fit < 0.8 and flipped.silhouette < true.silhouette


def test_occluders_are_neither_evidence_for_nor_against_a_pose():
    from pipeline.method.refinement.verification import compare_depth

    rendered = np.zeros((40, 40), np.float32)
    rendered[10:30, 10:30] = 500.0
    observed = np.full((40, 40), 900.0, np.float32)  # a wall behind
    observed[10:30, 10:30] = 500.0
    observed[10:30, 10:20] = 300.0  # an occluder covers the left half of the object
    observed[25:30, 25:30] = 0.0  # a sensor hole
    mask = np.zeros((40, 40), bool)
    mask[10:30, 20:30] = True  # the visible half is the candidate
    v = compare_depth(rendered, observed, mask, tol=10.0)
    assert v.silhouette == 1.0 and v.depth_fit == 1.0 and v.free_space == 0.0
    assert v.coverage == 1.0  # every mask pixel with depth is explained
    # the same pose one object-length too close: it stands in front of the wall
    v2 = compare_depth(np.where(rendered > 0, 200.0, 0).astype(np.float32), observed, mask, tol=10.0)
    assert v2.free_space == 1.0 and v2.depth_fit == 0.0 and v2.value < v.value - 1.0


def test_coherent_but_wrong_matches_lose_to_the_stronger_modality():
    """Matches that are wrong but spatially coherent (a smooth colour descriptor on a real
    image: they all agree with one wrong pose) pass a held-out test of their own; only
    their disagreement with the other modality's pose shows them. The stronger modality
    keeps its weight, and every hypothesis counts its inliers among the weighted
    matches, so that the true pose has the evidence."""
    features, scene, sf, R, t = _problem(5, {"geometric": 0.5, "visual": 0.0})
    rng = np.random.default_rng(7)
    model = features["points"]
    # visual: 30 % of the scene points carry the feature of where a pose flipped by 180
    # degrees about the model's z axis puts them (coherent), the rest random ones
    in_model = (scene - t) @ R
    flipped = in_model * [-1.0, -1.0, 1.0]
    wrong = np.argmin(np.linalg.norm(model[None] - flipped[:, None], axis=2), axis=1)
    coherent = rng.random(600) < 0.3
    sf["visual"][coherent] = features["visual"][wrong[coherent]]
    res = coarse_hypotheses(matchable_model(features, 64), scene, sf["geometric"], sf["visual"], 250.0,
                            RegisterParams(), seed=0)
    assert not res.agree and res.signal_visual > 6  # the visual matches pass their own test
    assert (res.w_geometric, res.w_visual) == (1.0, 0.0)
    by_source = {h.source: h.registration for h in res.hypotheses if h.source_rank == 0}
    assert rotation_angle_deg(by_source["geometric"].R, R) < 1.0
    assert rotation_angle_deg(by_source["visual"].R, R) > 170.0  # the flip
    assert by_source["geometric"].n_inliers > 3 * by_source["visual"].n_inliers


def test_turns_of_a_box_are_its_cube_turns_modulo_its_half_turns():
    """A box with three different sides: its symmetry group is the three half turns
    about its axes, so the 23 turns of the cube's group fall into 5 classes besides the
    group itself; a cube has none left; a near-symmetry comes first."""
    import trimesh

    from pipeline.method.geometry.symmetry import SymmetrySet
    from pipeline.method.refinement.turns import axis_turns, model_turns

    box = trimesh.creation.box(extents=(40.0, 60.0, 100.0))
    box.apply_translation([5.0, -3.0, 20.0])  # the turns are about the box's centre, not the origin
    points = np.asarray(box.vertices)
    centre = np.array([5.0, -3.0, 20.0])
    turns = axis_turns(points)
    assert turns.shape == (23, 4, 4)
    assert np.allclose(turns[:, :3, :3] @ centre + turns[:, :3, 3], centre)
    assert len({tuple(np.round(T[:3, :3]).ravel()) for T in turns}) == 23
    halves = []
    for axis in np.eye(3):
        T = np.eye(4)
        T[:3, :3] = 2 * np.outer(axis, axis) - np.eye(3)
        T[:3, 3] = centre - T[:3, :3] @ centre
        halves.append(T)
    kept = model_turns([], points, SymmetrySet(discrete=halves), 120.0)
    assert len(kept) == 5
    near = np.eye(4)
    near[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # a quarter turn about z
    near[:3, 3] = centre - near[:3, :3] @ centre
    with_near = model_turns([near], points, SymmetrySet(discrete=halves), 120.0)
    assert len(with_near) == 5 and np.allclose(with_near[0], near)
    cube = trimesh.creation.box(extents=(50.0, 50.0, 50.0))
    from pipeline.method.geometry.sampling import sample_surface
    from pipeline.method.geometry.symmetry import estimate_symmetries

    cube_points, cube_normals = sample_surface(cube, 10000, seed=0)
    assert len(model_turns([], cube_points, estimate_symmetries(cube_points, 86.6, cube_normals), 86.6)) == 0


def test_near_symmetries_of_an_almost_square_box_start_with_its_quarter_turn():
    import trimesh

    from pipeline.method.geometry.sampling import sample_surface
    from pipeline.method.geometry.symmetry import estimate_symmetries

    box = trimesh.creation.box(extents=(100.0, 115.0, 200.0))
    points, normals = sample_surface(box, 10000, seed=0)
    details: dict = {}
    sym = estimate_symmetries(points, float(np.linalg.norm(box.extents)), normals, details=details)
    assert len(sym.discrete) == 3  # the half turns
    T, score = details["near"][0]
    axis_angle = np.degrees(np.linalg.norm(Rotation.from_matrix(T[:3, :3]).as_rotvec()))
    assert 70.0 < axis_angle < 110.0 and abs(Rotation.from_matrix(T[:3, :3]).as_rotvec()[2]) > 0.95 * np.radians(axis_angle)
    assert 0.005 * 241.0 < score < 0.05 * 241.0


def _frame_refine_inputs(f: dict, points: np.ndarray, normals: np.ndarray) -> tuple:
    """What refine_candidates needs for the rendered frame ``f`` and its model samples:
    the scene's loaders, 1000 of its depth points (mm), the model's turns, the model."""
    from pipeline.method.geometry.symmetry import SymmetrySet
    from pipeline.method.refinement.turns import model_turns
    from pipeline.method.scene_side import SceneImages

    ys, xs = np.nonzero(f["mask"])
    bbox = (xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
    images = SceneImages(rgb=lambda i: None, depth=lambda i: f["depth"], K=lambda i: f["K"],
                         mesh=lambda o: f["mesh"], candidate=lambda c: (bbox, f["mask"]))
    ys, xs = np.nonzero(f["depth"] > 0)
    z = f["depth"][ys, xs]
    scene = np.stack([(xs - f["K"][0, 2]) * z / f["K"][0, 0], (ys - f["K"][1, 2]) * z / f["K"][1, 1], z], 1)
    scene = scene[np.random.default_rng(0).choice(len(scene), 1000, replace=False)]
    return images, scene, {1: model_turns([], points, SymmetrySet(), f["diameter"])}, \
        {"points": points, "normals": normals}


def test_a_turn_of_the_best_hypothesis_recovers_a_pose_ransac_got_half_a_turn_wrong(rendered_frame):
    """The only coarse hypothesis is the true pose turned half about the model's z axis
    (the toy truck's near-symmetry: chassis and wheels match, cab and cargo do not);
    refinement tries the turns of it, and the verification picks the true pose back,
    recording the turn and its parent. With ``turns`` 0 the wrong pose stays."""
    from pipeline.method.geometry.sampling import sample_surface
    from pipeline.method.refinement.turns import turned
    from pipeline.method.scene_side import PoseVerifier

    f = rendered_frame
    mesh = f["mesh"]
    points, normals = sample_surface(mesh, 3000, seed=0)
    half = np.eye(4)
    half[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    centre = (points.min(0) + points.max(0)) / 2
    half[:3, 3] = centre - half[:3, :3] @ centre
    R0, t0 = turned(f["R"], f["t"], half)
    registered = pd.DataFrame([{"cand_id": 0, "scene_id": 1, "im_id": 0, "obj_id": 1, "prior_score": 0.9, "hyp": 0,
                                "source": "fused", "n_inliers": 50, "inlier_ratio": 0.05, "R": R0.ravel().tolist(),
                                "t": t0.tolist(), "ransac_fitness": 0.5}])
    images, scene, turns, model = _frame_refine_inputs(f, points, normals)
    for n_turns, right in ((3, True), (0, False)):
        params = RefineParams(turns=n_turns)
        with PoseVerifier(images, params) as verify:
            hyps, cands, _ = refine_candidates(registered, lambda c: scene, lambda o: model, {1: f["diameter"]},
                                               params, verify, None, turns=turns)
        chosen = cands.iloc[0]
        error = rotation_angle_deg(np.reshape(chosen.R, (3, 3)), f["R"])
        assert (error < 3.0) == right, (n_turns, error)
        assert len(hyps) == 1 + n_turns
        if right:
            assert chosen.source == "turn" and chosen.parent == 0 and chosen.hyp >= 1
            assert chosen.n_inliers == 0 and chosen.evidence == 0.0
            assert (hyps.source == "turn").sum() == 3 and (hyps[hyps.source == "turn"].parent == 0).all()


def test_the_torch_paths_of_refine_make_the_numpy_paths_choices(rendered_frame):
    """refine_candidates on the scene device (the GPU path, here on the CPU): a
    candidate's hypotheses and its turns aligned together by the torch ICP and verified
    together by the torch comparison give the numpy paths' hypotheses (the same rows,
    poses to 1e-6, verification terms to 1e-6) and the same choice."""
    from pipeline.method.geometry.sampling import sample_surface
    from pipeline.method.geometry.transforms import perturb_pose
    from pipeline.method.refinement.verification import TERMS
    from pipeline.method.scene_side import PoseVerifier

    f = rendered_frame
    mesh = f["mesh"]
    points, normals = sample_surface(mesh, 3000, seed=0)
    rows = []
    for hyp, (angle, shift) in enumerate([(4.0, 8.0), (12.0, 20.0), (30.0, 30.0), (90.0, 10.0)]):
        R0, t0 = perturb_pose(f["R"], f["t"], angle, shift, rng=hyp)
        rows.append({"cand_id": 0, "scene_id": 1, "im_id": 0, "obj_id": 1, "prior_score": 0.9, "hyp": hyp,
                     "source": "fused", "n_inliers": 50 - hyp, "inlier_ratio": 0.05, "R": R0.ravel().tolist(),
                     "t": t0.tolist(), "ransac_fitness": 0.5})
    registered = pd.DataFrame(rows)
    images, scene, turns, model = _frame_refine_inputs(f, points, normals)
    params = RefineParams(turns=3)
    out, compared = {}, []
    for device in (None, "cpu"):
        with PoseVerifier(images, params, device) as verify:
            many = verify.many

            def counting_many(*args, many=many):
                compared.append((device, len(args[3])))
                return many(*args)

            out[device] = refine_candidates(registered, lambda c: scene, lambda o: model, {1: f["diameter"]},
                                            params, verify, None, turns=turns, scene_device=device,
                                            verify_many=counting_many)
    (h_np, c_np, _), (h_t, c_t, _) = out[None], out["cpu"]
    assert len(h_np) > len(registered)  # the turns ran
    # numpy verifies the hypotheses one at a time, the device path all four at once
    assert ("cpu", len(registered)) in compared and all(n < len(registered) for d, n in compared if d is None)
    for col in ("hyp", "source", "parent", "chosen", "n_inliers"):
        assert h_t[col].tolist() == h_np[col].tolist(), col
    for a, b in zip(h_t.itertuples(), h_np.itertuples()):
        assert rotation_angle_deg(np.reshape(a.R, (3, 3)), np.reshape(b.R, (3, 3))) < 1e-6, a.hyp
        assert np.abs(np.subtract(a.t, b.t)).max() < 1e-5, a.hyp
        assert a.fitness == pytest.approx(b.fitness, abs=1e-9)
        for term in TERMS:
            assert getattr(a, term) == pytest.approx(getattr(b, term), abs=1e-6), (a.hyp, term)
    assert c_t.hyp.tolist() == c_np.hyp.tolist()
    assert rotation_angle_deg(np.reshape(c_np.iloc[0].R, (3, 3)), f["R"]) < 3.0


def test_a_skipped_candidates_register_row_keeps_the_declared_dtypes():
    """semilmo has candidates skipped for too few points: their one row must not turn the
    integer columns into floats (the declaration refused it, and register failed)."""
    from pipeline.method.scene_side import register_candidates
    from pipeline.workflow.artifact_schema import COARSE_HYPOTHESES, check_table

    features, scene, sf, R, t = _problem(4, {"geometric": 0.3, "visual": 0.3})
    n = len(scene)
    candidates = pd.DataFrame({"cand_id": [0, 1], "scene_id": 1, "im_id": 0, "obj_id": 5, "prior_score": 0.9,
                               "status": ["ok", "skipped"], "reason": ["", "12 points < min_points 100"],
                               "n_points": [n, 0]})
    arrays = {"cand_id": np.array([0, 1]), "points": np.stack([scene, np.zeros_like(scene)]),
              "geometric": np.stack([sf["geometric"], np.zeros_like(sf["geometric"])]),
              "visual": np.stack([sf["visual"], np.zeros_like(sf["visual"])])}
    table, _ = register_candidates(candidates, arrays, lambda o: matchable_model(features, 64), {5: 250.0},
                                   RegisterParams(), lambda c: 0)
    check_table(COARSE_HYPOTHESES, table, "test")  # raises on a column of another dtype
    skipped = table[table.cand_id == 1].iloc[0]
    assert (skipped.status, skipped.source_rank, skipped.n_inliers, skipped.hyp) == ("skipped", -1, 0, 0)
    ok = table[table.cand_id == 0]
    assert rotation_angle_deg(np.asarray(ok.iloc[0].R).reshape(3, 3), R) < 1.0


def test_register_on_the_torch_path_makes_the_numpy_paths_hypotheses():
    """register_candidates with ``device`` (the GPU path, here on the CPU): RANSAC's loop
    and the feature matching in torch give the numpy path's table, every hypothesis,
    source, weight, signal and count the same and the poses to 1e-9, over candidates
    whose modalities agree, carry no signal or only some (a fractional weight)."""
    from pipeline.method.scene_side import register_candidates

    signals = [{"geometric": 0.3, "visual": 0.3}, {"geometric": 0.5, "visual": 0.0}, {"geometric": 0.0, "visual": 0.4},
               {"geometric": 0.08, "visual": 0.05}, {"geometric": 0.3, "visual": 0.03}]
    tables = {}
    for device in (None, "cpu"):
        rows = []
        for cand_id, signal in enumerate(signals):
            features, scene, sf, R, t = _problem(20 + cand_id, signal)
            candidates = pd.DataFrame({"cand_id": [cand_id], "scene_id": 1, "im_id": 0, "obj_id": 5,
                                       "prior_score": 0.9, "status": ["ok"], "reason": [""], "n_points": [len(scene)]})
            arrays = {"cand_id": np.array([cand_id]), "points": scene[None], "geometric": sf["geometric"][None],
                      "visual": sf["visual"][None]}
            table, _ = register_candidates(candidates, arrays, lambda o: matchable_model(features, 64), {5: 250.0},
                                           RegisterParams(), lambda c: c, device=device)
            rows.append(table)
        tables[device] = pd.concat(rows, ignore_index=True)
    a, b = tables[None], tables["cpu"]
    assert len(a) > len(signals) and set(a.source) >= {"geometric", "visual", "fused"}
    assert set(a.w_visual) > {0.0, 1.0}  # a fractional weight: the weighted fusion ran too
    for col in a.columns.drop(["R", "t", "time_s"]):
        assert b[col].tolist() == a[col].tolist(), col
    np.testing.assert_allclose(np.stack(b.R), np.stack(a.R), atol=1e-9)
    np.testing.assert_allclose(np.stack(b.t), np.stack(a.t), atol=1e-9)
