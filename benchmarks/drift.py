"""Drift by segment length on simulated deployments: an odometry with a known drift, and the
ground truth's own floor against the exact truth.

Run: ``python benchmarks/drift.py [--deployments 6] [--duration 120] [--first-seed 24000]``

For each deployment ``first_seed + k`` (:mod:`rtsgt.simulation`): simulate, run the pipeline
(linear engine) and take the run's continuous ground truth. Two estimates at 10 Hz:

- the exact truth: its drift is the ground truth's own error, so that the rms of its
  segments' drift should equal the floor the ground truth's relative covariance gives
  (printed: rms / floor, pooled over each deployment's segments of path and of time);
- an odometry that drifts by a known law: a heading error growing by ``b`` rad per metre of
  path (``b`` uniform in 0.01-0.1 deg/m, either sign) and a scale error ``k`` uniform in
  0.1-1 %, composed along the path. Its rotational drift over a segment is ``|b|`` times the
  segment's path, so the KITTI rotational drift should be ``|b|`` (printed: measured /
  injected, pooled over the lengths), above a floor; the translational drift is printed with
  its floor.

Also printed: the time the drift step takes (its floor queries the continuous ground truth's
relative covariance of at most 50 segments per length). The numbers of
docs/evaluating.md#drift-by-segment-length are this script's output for the defaults.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rtsgt.app import read_ground_truth
from rtsgt.evaluation import evaluate
from rtsgt.evaluation import evaluator as ev
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import write_run
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import PoseTrajectory


def odometry(p: np.ndarray, R: np.ndarray, b: float, k: float) -> tuple[np.ndarray, np.ndarray]:
    """The truth's path with a heading error ``b s`` (rad, ``s`` its path length) and a scale
    error ``k``, composed along the path (world-frame left perturbation about z)."""
    steps = np.diff(p, axis=0, prepend=p[:1])
    s = np.cumsum(np.linalg.norm(steps, axis=1))
    Rz = Rotation.from_rotvec(np.outer(b * s, [0.0, 0.0, 1.0])).as_matrix()
    pe = p[0] + (1.0 + k) * np.cumsum(np.einsum("nij,nj->ni", Rz, steps), axis=0)
    return pe, Rz @ R


def one(seed: int, duration: float, tmp: Path) -> dict:
    rng = np.random.default_rng(seed)
    sim = simulate_deployment(SimulationConfig(duration_s=duration), rng)
    data, opts = load_deployment(write_deployment(sim, tmp / f"dep{seed}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_pipeline(data, opts.updated(engine="linear", seed=seed))
    gt = read_ground_truth(write_run(result, tmp / f"run{seed}"))
    t = np.arange(result.groundtruth.t[0], result.groundtruth.t[-1], 0.1)
    p, q = sim.truth_at(t)
    R = Rotation.from_quat(q).as_matrix()
    b = np.radians(rng.uniform(0.01, 0.1)) * rng.choice([-1.0, 1.0])
    k = rng.uniform(0.001, 0.01)
    pe, Re = odometry(p, R, b, k)
    out = {"seed": seed, "b_deg_per_m": np.degrees(abs(b)), "k_pct": 100 * k}
    spent = {}
    orig = ev.drift_step

    def timed(*args):
        t0 = time.perf_counter()
        r = orig(*args)
        spent["s"] = time.perf_counter() - t0
        return r

    ev.drift_step = timed
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            exact = evaluate(gt, PoseTrajectory(t, p, q), align="se3")
            out["exact_s"] = spent["s"]
            drifting = evaluate(gt, PoseTrajectory(t, pe, matrix_to_quat_xyzw(Re)), align="se3")
    finally:
        ev.drift_step = orig
    for kind in ("distance", "time"):
        seg = getattr(exact.drift, kind)
        for part in ("translation", "rotation"):
            rms = float(np.sqrt(np.mean(getattr(seg, f"{part}_error") ** 2)))
            out[f"exact_{kind}_{part}_rms_over_floor"] = rms / getattr(seg, f"{part}_floor_all")
    d = drifting.drift.distance
    out.update(lengths=d.lengths_from, path=float(d.lengths[-1]),
               t_pct=100 * d.translation_all, t_floor_pct=100 * d.translation_floor_all,
               r_deg_per_m=np.degrees(d.rotation_all),
               r_floor_deg_per_m=np.degrees(d.rotation_floor_all),
               r_over_b=d.rotation_all / abs(b))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=6)
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--first-seed", type=int, default=24000)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for j in range(args.deployments):
            r = one(args.first_seed + j, args.duration, Path(tmp))
            rows.append(r)
            print(f"seed {r['seed']}: injected {r['b_deg_per_m']:.4f} deg/m, {r['k_pct']:.2f} %;"
                  f" measured {r['r_deg_per_m']:.4f} deg/m (x {r['r_over_b']:.4f}, floor "
                  f"{r['r_floor_deg_per_m']:.4f}), {r['t_pct']:.3f} % (floor "
                  f"{r['t_floor_pct']:.3f} %); exact truth rms / floor: path "
                  f"{r['exact_distance_translation_rms_over_floor']:.3f} / "
                  f"{r['exact_distance_rotation_rms_over_floor']:.3f}, time "
                  f"{r['exact_time_translation_rms_over_floor']:.3f} / "
                  f"{r['exact_time_rotation_rms_over_floor']:.3f}; drift step "
                  f"{r['exact_s']:.2f} s; {r['lengths']}", flush=True)
    for key in ("r_over_b", "exact_distance_translation_rms_over_floor",
                "exact_distance_rotation_rms_over_floor", "exact_time_translation_rms_over_floor",
                "exact_time_rotation_rms_over_floor", "exact_s"):
        v = np.array([r[key] for r in rows])
        print(f"{key}: median {np.median(v):.3f}, range {v.min():.3f}-{v.max():.3f}")


if __name__ == "__main__":
    main()
