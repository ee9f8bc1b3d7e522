"""The point-pair-feature peer's worker: OpenCV's ``cv2.ppf_match_3d`` (Drost et al. 2010)
in its own virtual environment (opencv-contrib, which cannot share the project's env).

Run by ``benchmarks/peers.py`` as ``<peers venv>/bin/python peer_ppf_worker.py IN.npz OUT.npz``
with nothing of the project importable: numpy and cv2 only.

IN.npz:
    params        0-d str array, JSON: rel_sampling, rel_distance, scene_sample_step,
                  rel_scene_distance, n_icp (poses refined), icp_iterations,
                  icp_tolerance, icp_rejection, icp_levels, num_angles
    model_<obj>   (N, 6) float32: model points (mm) and unit outward normals (training)
    icpmodel_<obj> (N', 6) float32: a subset of them, the ICP's model (ICP on all is slow)
    cand_ids      (C,) int64; cand_obj (C,) int64: each candidate's object
    scene_<cand>  (P, 6) float32: the candidate's points (mm, camera frame) and normals
OUT.npz:
    train_obj (K,) int64, train_s (K,) float64: each object's training time
    cand_ids (C,) int64, poses (C, n, 4, 4) float64 model-to-camera (mm), votes (C, n)
    float64, residual (C, n) float64 (NaN where fewer than n poses came), n_poses (C,)
    int64, match_s (C,) float64: each candidate's match + ICP time, s

Prints ``done <cand_id>`` on stdout after each candidate (the caller's progress bar).
"""

from __future__ import annotations

import json
import sys
import time

import cv2
import numpy as np


def main(inp: str, out: str) -> None:
    data = np.load(inp)
    p = json.loads(str(data["params"]))
    cv2.setNumThreads(1)
    cv2.setRNGSeed(0)
    cand_ids = data["cand_ids"].astype(np.int64)
    cand_obj = data["cand_obj"].astype(np.int64)
    n = int(p["n_icp"])
    detectors, train_obj, train_s = {}, [], []
    for obj in sorted(set(cand_obj.tolist())):
        model = np.ascontiguousarray(data[f"model_{obj}"], np.float32)
        t0 = time.perf_counter()
        det = cv2.ppf_match_3d_PPF3DDetector(float(p["rel_sampling"]), float(p["rel_distance"]),
                                             float(p.get("num_angles", 30)))
        det.trainModel(model)
        train_obj.append(obj)
        train_s.append(time.perf_counter() - t0)
        detectors[obj] = (det, np.ascontiguousarray(data[f"icpmodel_{obj}"], np.float32))
    C = len(cand_ids)
    poses = np.full((C, n, 4, 4), np.nan)
    votes = np.full((C, n), np.nan)
    residual = np.full((C, n), np.nan)
    n_poses = np.zeros(C, np.int64)
    match_s = np.zeros(C)
    icp = cv2.ppf_match_3d_ICP(int(p["icp_iterations"]), float(p["icp_tolerance"]), float(p["icp_rejection"]),
                               int(p["icp_levels"]))
    for i, (cand, obj) in enumerate(zip(cand_ids, cand_obj)):
        det, model = detectors[int(obj)]
        scene = np.ascontiguousarray(data[f"scene_{cand}"], np.float32)
        t0 = time.perf_counter()
        results = det.match(scene, 1.0 / float(p["scene_sample_step"]), float(p["rel_scene_distance"]))
        results = list(results)[:n]
        if results and int(p["icp_iterations"]) > 0:
            _, results = icp.registerModelToScene(model, scene, results)
            results = list(results)
        match_s[i] = time.perf_counter() - t0
        n_poses[i] = len(results)
        for j, r in enumerate(results[:n]):
            poses[i, j] = np.asarray(r.pose, np.float64)
            votes[i, j] = float(r.numVotes)
            residual[i, j] = float(r.residual)
        print(f"done {int(cand)}", flush=True)
    np.savez(out, train_obj=np.asarray(train_obj, np.int64), train_s=np.asarray(train_s, np.float64),
             cand_ids=cand_ids, poses=poses, votes=votes, residual=residual, n_poses=n_poses, match_s=match_s)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: peer_ppf_worker.py IN.npz OUT.npz")
    main(sys.argv[1], sys.argv[2])
