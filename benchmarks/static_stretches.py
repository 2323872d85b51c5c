"""The static stretches a run finds against the simulator's true stops, at the default rate and
sparse (0.8 Hz), and the stretches and static relative-pose check of real deployments.

    python benchmarks/static_stretches.py --seeds 20 --duration 300
    python benchmarks/static_stretches.py --real examples/rts_20221110/deployment.toml

Per rate: the share of the true standing time found (recall), the share of the found time that
was truly standing (precision, the truth's prisms not moving), and the largest true motion of a
prism inside a found stretch (mm). Seeds 8300 on, 300 s, stop probability 0.5, the ``linear`` engine. Numbers (and those of the
first rule: 0.05 m/s, 2 s margins, 5 s minimum): docs/self-checks.md#stretches.
"""

from __future__ import annotations

import argparse
import tempfile
import warnings
from pathlib import Path

import numpy as np

from rtsgt.checks.static import static_stretches
from rtsgt.interpolation.prisms import gp_velocity_z2
from rtsgt.io.deployment import load_deployment
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment


def true_standing(t: np.ndarray, prisms: np.ndarray) -> np.ndarray:
    """Per truth sample (N,), whether no prism moves (step to the next sample under 1 um)."""
    step = np.max(np.linalg.norm(np.diff(prisms, axis=0), axis=2), axis=1)
    still = step < 1e-6
    return np.r_[still, still[-1]] & np.r_[still[0], still]


def score(iv: np.ndarray, t: np.ndarray, still: np.ndarray, prisms: np.ndarray):
    """(true standing s, found s, found and truly standing s, largest motion in a stretch, m)."""
    dt = float(np.median(np.diff(t)))
    inside = np.zeros(t.size, bool)
    motion = 0.0
    for a, b in iv:
        m = (t >= a) & (t <= b)
        inside |= m
        if m.any():
            motion = max(motion, float(np.max(np.linalg.norm(prisms[m] - prisms[m][0], axis=2))))
    return still.sum() * dt, inside.sum() * dt, (inside & still).sum() * dt, motion


def simulated(seed: int, rate_hz: float, duration_s: float, tmp: Path):
    cfg = SimulationConfig(duration_s=duration_s, rate_hz=rate_hz, stop_probability=0.5)
    sim = simulate_deployment(cfg, np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"d{seed}_{rate_hz:g}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        record = run_pipeline(data, opts.updated(seed=seed, engine="linear"))
    c = record.computation
    t = c.prisms.t[c.keep]
    iv = static_stretches(t, c.prisms.xyz[c.keep], gp_velocity_z2(c.gps, t))
    truth = sim.truth
    return score(iv, truth.t, true_standing(truth.t, truth.prisms_world), truth.prisms_world)


def real(config: str) -> None:
    data, opts = load_deployment(config)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        record = run_pipeline(data, opts.updated(seed=0))
    sr = record.self_checks["static_relative"]
    t0 = float(record.groundtruth.t[0])
    print(config, "stretches (s after the first pose):",
          [[round(a - t0, 1), round(b - t0, 1)] for a, b in
           record.self_checks["static_noise"]["stretches_s"]])
    for lag, v in sr["lags"].items():
        print(f"  lag {lag} s: pairs {v['pairs']}, NEES/dof {v['nees_per_dof']}, {v['verdict']}")
    print("  overall", sr["overall"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--rates", type=float, nargs="+", default=[2.5, 0.8])
    ap.add_argument("--real", nargs="*", default=[])
    args = ap.parse_args()
    for config in args.real:
        real(config)
    if args.real:
        return
    with tempfile.TemporaryDirectory() as tmp:
        for rate in args.rates:
            rows = np.array([simulated(8300 + s, rate, args.duration, Path(tmp))
                             for s in range(args.seeds)])
            standing, found, right, motion = rows.T
            print(f"rate {rate:g} Hz, {args.seeds} deployments of {args.duration:g} s: "
                  f"true standing {standing.sum():.0f} s, found {found.sum():.0f} s; "
                  f"recall {right.sum() / standing.sum():.3f}, precision "
                  f"{right.sum() / max(found.sum(), 1e-9):.3f}; largest true motion in a "
                  f"stretch {1e3 * motion.max():.4f} mm; runs with a stretch {(found > 0).sum()}")


if __name__ == "__main__":
    main()
