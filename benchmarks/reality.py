"""Honesty of the ground truth when the simulation is wrong in the ways reality is.

Run: ``python benchmarks/reality.py [--deployments 20] [--duration 150] [--engine mc]
[--samples 300] [--first-seed 7000] [--effects none tracking_lag ...] [--prior select]
[--correlated-noise inflate|ignore]``

For every deployment ``first_seed + k`` and every reality effect alone
(:mod:`rtsgt.simulation.reality`, default sizes), plus none, the deployment is simulated,
written as files, read back and run through the whole pipeline (as ``benchmarks/honesty.py``
does). Per effect, pooled over the deployments:

- position (3 dof) and pose (6 dof) NEES / dof and the share of poses whose 95 % region holds
  the truth (:func:`rtsgt.simulation.compare.compare_to_truth`): 1 and 0.95 if honest;
- the effect's size on the ground truth: RMS and largest difference of the position error
  (ground truth minus truth) between the run with the effect and the run of the same seed
  without it, mm; where the truth is the same (every effect but ``jerky_ramps``) this is the
  difference of the ground-truth positions themselves;
- how often the run's self-checks flag it (``RunRecord.self_checks``): the inter-prism
  distance check overall and in any of its regimes, and every other check (each key of
  ``self_checks``) wherever in it a ``verdict`` is ``optimistic`` or ``pessimistic``, as the
  share of deployments flagged; ``any`` is the share flagged by at least one check. The
  ``none`` row is the rate of false alarms;
- ``inflated``: the share of deployments whose white covariance was inflated for the
  time-correlated noise the static-stretch check found (:mod:`rtsgt.noise.correlated`;
  ``--correlated-noise ignore`` runs the paper's independent measurements).

Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from rtsgt.io.deployment import load_deployment
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth
from rtsgt.simulation.reality import REALITY_EFFECTS, RealityEffects

FLAGGED = ("optimistic", "pessimistic")


def run_one(effect: str, seed: int, duration: float, engine: str, samples: int,
            tmp: Path, prior: str | None = None,
            correlated_noise: str | None = None) -> dict:
    """One deployment with ``effect`` alone (``"none"``: no effect): errors and checks."""
    fx = RealityEffects() if effect == "none" else RealityEffects.only(effect)
    sim = simulate_deployment(SimulationConfig(duration_s=duration, reality=fx),
                              np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"{effect}-{seed}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        extra = {k: v for k, v in (("prior", prior), ("correlated_noise", correlated_noise))
                 if v is not None}  # the GP's motion prior and correlated noise, else defaults
        record = run_pipeline(data, opts.updated(seed=seed, engine=engine, samples=samples,
                                                 **extra))
    gt = record.groundtruth
    p, q = sim.truth_at(gt.t)
    c = compare_to_truth(gt, p, q)
    checks = record.self_checks
    ip = checks["inter_prism_distances"]
    flags = {name: flagged(v) for name, v in checks.items()}
    flags["inter_prism_distances"] = ip["overall"]["verdict"] in FLAGGED
    flags["inter_prism_regime"] = any(v["verdict"] in FLAGGED for v in ip["regimes"].values())
    return {"t": gt.t, "error": c.error[:, :3], "n3": c.nees_position.values,
            "n6": c.nees_pose.values, "flags": flags,
            "inflated": bool(record.correlated_noise.get("applied"))}


def flagged(check) -> bool:
    """Whether a ``verdict`` anywhere in a self-check's (nested) result is a failure."""
    if isinstance(check, dict):
        return check.get("verdict") in FLAGGED or any(flagged(v) for v in check.values())
    if isinstance(check, (list, tuple)):
        return any(flagged(v) for v in check)
    return False


def error_change_mm(run: dict, base: dict) -> np.ndarray:
    """Change of the position error (mm) at the effect run's times inside the base run's."""
    inside = (run["t"] >= base["t"][0]) & (run["t"] <= base["t"][-1])
    base_err = np.stack([np.interp(run["t"][inside], base["t"], base["error"][:, i])
                         for i in range(3)], axis=-1)
    return 1e3 * np.linalg.norm(run["error"][inside] - base_err, axis=1)


def summary(runs: list[dict], bases: list[dict]) -> dict:
    a3 = np.concatenate([r["n3"] for r in runs])
    a6 = np.concatenate([r["n6"] for r in runs])
    diff = np.concatenate([error_change_mm(r, b) for r, b in zip(runs, bases, strict=True)])
    return {
        "poses": a3.size, "nees3": a3.mean() / 3, "in3": np.mean(a3 <= chi2.ppf(0.95, 3)),
        "nees6": a6.mean() / 6, "in6": np.mean(a6 <= chi2.ppf(0.95, 6)),
        "rms_mm": float(np.sqrt(np.mean(diff**2))) if diff.size else 0.0,
        "max_mm": float(np.max(diff)) if diff.size else 0.0,
        "flags": {name: np.mean([r["flags"].get(name, False) for r in runs])
                  for name in runs[0]["flags"]},
        "any": np.mean([any(r["flags"].values()) for r in runs]),
        "inflated": np.mean([r["inflated"] for r in runs]),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=20)
    ap.add_argument("--duration", type=float, default=150.0)
    ap.add_argument("--engine", default="mc")
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--first-seed", type=int, default=7000)
    ap.add_argument("--effects", nargs="+", default=["none", *REALITY_EFFECTS],
                    choices=["none", *REALITY_EFFECTS])
    ap.add_argument("--prior", default=None, choices=["wnoa", "wnoj", "select"],
                    help="the GP's motion prior (default: the option's default)")
    ap.add_argument("--correlated-noise", default=None, choices=["inflate", "ignore"],
                    help="[interpolation] correlated_noise of the runs (ignore: the paper; default: the option's default)")
    args = ap.parse_args(argv)
    seeds = range(args.first_seed, args.first_seed + args.deployments)
    effects = ["none", *(e for e in args.effects if e != "none")]
    print(f"{args.deployments} deployments x {args.duration:g} s (seeds {seeds.start}-"
          f"{seeds.stop - 1}), engine {args.engine}, {args.samples} samples, correlated_noise "
          f"{args.correlated_noise}; defaults of RealityEffects\n")
    with tempfile.TemporaryDirectory() as tmp:
        bases = None
        for effect in effects:
            t0 = time.perf_counter()
            runs = [run_one(effect, s, args.duration, args.engine, args.samples, Path(tmp),
                            args.prior, args.correlated_noise) for s in seeds]
            if bases is None:
                bases = runs
                names = list(runs[0]["flags"])
                print("| effect | poses | NEES pos /3 | in 95 % | NEES pose /6 | in 95 % | "
                      "change RMS mm | change max mm | "
                      + " | ".join(f"flags: {n}" for n in names)
                      + " | flags: any | inflated | time |")
                print("|---|" + "---:|" * (10 + len(names)))
            r = summary(runs, bases)
            print(f"| {effect} | {r['poses']} | {r['nees3']:.2f} | {r['in3']:.3f} | "
                  f"{r['nees6']:.2f} | {r['in6']:.3f} | {r['rms_mm']:.2f} | {r['max_mm']:.2f} | "
                  + " | ".join(f"{r['flags'].get(n, 0.0):.0%}" for n in names)
                  + f" | {r['any']:.0%} | {r['inflated']:.0%} | {time.perf_counter() - t0:.0f} s |",
                  flush=True)


if __name__ == "__main__":
    main()
