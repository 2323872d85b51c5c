"""Every figure the README and docs/ quote about the real excerpt, the demo and the worked
mounting example, from real runs, into ``docs/figures.json``.

Run: ``python benchmarks/readme_figures.py [--only excerpt demo mounting]`` (all three by
default; a group not asked for keeps its figures in the JSON). About 15 s for the excerpt,
1-2 min for the demo and 1 min for the mounting example on the 2-core development machine.

Groups (each a flat mapping of name -> number in the JSON):

- ``excerpt``: ``examples/rts_20221110/deployment.toml`` through the library
  (:func:`rtsgt.io.deployment.load_deployment`, :func:`rtsgt.pipeline.run_pipeline`) with the
  defaults (seed 0, Monte Carlo, M = 1000), its ``summary.json`` as the run writes it
  (:func:`rtsgt.io.run_dir.run_summary`) and the per-source analysis of ``rtsgt analyze``;
- ``demo``: ``rtsgt demo`` as a user runs it (the console script, default options, the HTML
  report included), timed, and its ground truth compared with the simulated truth;
- ``mounting``: the README's worked example of ``rtsgt evaluate --estimate all`` (a simulated
  deployment, seed 3, 180 s; the exact pose of a sensor turned 180 deg, 0.4 m ahead, 0.3 m
  up, 30 ms late), through the console script.

The README and the docs quote a figure as the number followed by a marker naming it, e.g.
``2.51<!-- fig:excerpt.median_sigma_t_mm --> mm``; ``tests/test_readme_figures.py`` checks that
every marked number is the JSON's at the precision printed, and recomputes the ``excerpt``
group from a run of the excerpt (:func:`excerpt_figures`). Timings (``*_s`` of the ``demo`` and
``mounting`` groups) are measurements of one run on the machine the script ran on.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: The committed figures.
FIGURES_JSON = REPO / "docs" / "figures.json"
#: The shipped excerpt of a real deployment.
EXAMPLE_TOML = REPO / "examples" / "rts_20221110" / "deployment.toml"
#: What ``rtsgt demo`` simulates by default (its ``--seed`` and ``--duration``).
DEMO_SEED, DEMO_DURATION_S = 0, 600.0
#: The worked mounting example: simulation seed and duration, the sensor's pose in the body
#: frame (rotation about z, rad; lever arm, m) and its clock's delay (s).
MOUNTING_SEED, MOUNTING_DURATION_S = 3, 180.0
MOUNTING_YAW_RAD, MOUNTING_LEVER_M, MOUNTING_DELAY_S = np.pi, (0.4, 0.0, 0.3), 0.03
GROUPS = ("excerpt", "demo", "mounting")
REGIMES = ("overall", "static", "manoeuvring", "cruising", "far")
SOURCES = ("instrument", "tilt", "atmosphere", "time_sync", "calibration")


def excerpt_figures() -> dict[str, float]:
    """The real excerpt's figures: one run with the defaults (seed 0), no file written."""
    from rtsgt.io.deployment import load_deployment
    from rtsgt.io.run_dir import run_summary
    from rtsgt.pipeline import run_pipeline
    from rtsgt.report.analysis import analyze

    data, opts = load_deployment(EXAMPLE_TOML)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the run's own warnings (self-checks) are not figures
        record = run_pipeline(data, opts)
        s = json.loads(json.dumps(run_summary(record), default=_plain))
        a = analyze(record, bins="0,75,150", engine="linear")
    f: dict[str, float] = {}
    f["poses_kept"] = s["poses"]["kept"]
    f["poses_queried"] = s["poses"]["queried"]
    f["common_intervals"] = len(s["intervals_s"])
    f["time_span_s"] = s["poses"]["last_t"] - s["poses"]["first_t"]
    m1 = [v for k, v in s["filters"].items() if k.startswith("module1_")]
    f["measurements"] = sum(v["n_in"] for v in m1)
    f["module1_removed"] = sum(v["n_in"] - v["n_kept"] for v in m1)
    f["module2_removed"] = s["filters"]["module2"]["n_in"] - s["filters"]["module2"]["n_kept"]
    f["median_sigma_t_mm"] = s["median_uncertainty"]["translation_mm"]
    f["median_sigma_r_mrad"] = s["median_uncertainty"]["rotation_mrad"]
    f["inter_prism_median_deviation_mm"] = 1e3 * s["gates"]["median_distance_error_m"]
    ip = s["self_checks"]["inter_prism_distances"]
    for r in REGIMES:
        c = ip["overall"] if r == "overall" else ip["regimes"][r]
        f[f"z2_{r}"] = c["mean_z2"]
        f[f"z2_{r}_poses"] = c["poses"]
        f[f"z2_{r}_lo"], f[f"z2_{r}_hi"] = c["interval_95"]
        f[f"z2_{r}_shared"] = c["shared_fraction"]
        f[f"z2_{r}_shared_pct"] = 100 * c["shared_fraction"]
        f[f"z2_{r}_neff"] = c["n_eff"]
    cv = s["self_checks"]["block_cv"]["overall"]
    f["block_cv_overall"] = cv["nees_per_dof"]
    prisms = s["prisms"]
    for axis, k in zip("xyz", range(3), strict=True):
        f[f"qc1_{axis}_e3"] = 1e3 * prisms["1"]["qc_m2_s3"][k][k]
    mp = [p["qc_fit"]["motion_prior"] for p in prisms.values()]
    for name, cls in (("standing", "standing"), ("fast", "0.3-1 m/s^2")):
        scales = [m["scales"][cls] for m in mp]
        f[f"scale_{name}_min"], f[f"scale_{name}_max"] = min(scales), max(scales)
    gain = [m["loo_log_predictive_classes"] - m["loo_log_predictive_constant"] for m in mp]
    f["loo_gain_min"], f["loo_gain_max"] = min(gain), max(gain)
    loo = [p["qc_fit"]["loo_nees_per_dof"] for p in prisms.values()]
    f["loo_nees_min"], f["loo_nees_max"] = min(loo), max(loo)
    st = s["self_checks"]["inter_prism_structure"]
    f["structure_f"] = st["prism_orientation"]["f"]
    f["structure_f_critical"] = st["prism_orientation"]["critical"]
    f["clock_chi2_dof"] = st["clock"]["chi2_per_dof"]
    for pair in ("2-1", "3-1", "3-2"):
        key = pair.replace("-", "")
        f[f"clock_offset_{key}_ms"] = st["clock"]["offsets_ms"][pair]["run"]
        f[f"clock_offset_{key}_sigma_ms"] = st["clock"]["offsets_ms"][pair]["sigma"]
    cal = s["calibration"]
    for k in ("2", "3"):
        f[f"gcp_yaw{k}_deg"] = cal["stations"][k]["yaw_deg"]
    f["gcp_residual_median_mm"] = cal["residuals_mm"]["median"]
    f["gcp_residual_max_mm"] = cal["residuals_mm"]["max"]
    gcp = s["self_checks"]["gcp_fit"]
    for k in ("2", "3"):
        f[f"gcp_factor{k}"] = gcp["stations"][k]["variance_factor"]
    f["gcp_added_vertical_mm"] = gcp["added_shot_sigma_mm"]["vertical"]
    f["levelling_p_min"] = min(v["p_value"] for v in gcp["levelling"].values())
    f["bin_0_75_count"], f["bin_75_150_count"] = a.bin_counts[:2]
    for src in SOURCES:
        f[f"source_{src}_mm"] = a.median_mm[src]
        f[f"source_{src}_0_75_mm"], f[f"source_{src}_75_150_mm"] = a.bin_median_mm[src][:2]
    return {k: _number(v) for k, v in f.items()}


def demo_figures(tmp: Path) -> dict[str, float]:
    """``rtsgt demo`` with its defaults, timed; its ground truth against the simulated truth
    (the simulation drawn again from the demo's seed: the same deployment)."""
    from rtsgt.io.run_dir import read_run
    from rtsgt.simulation import SimulationConfig, simulate_deployment
    from rtsgt.simulation.compare import compare_to_truth

    out = tmp / "demo"
    wall = _rtsgt("demo", "--out", out, "--quiet")
    record = read_run(out / "run")
    sim = simulate_deployment(SimulationConfig(duration_s=DEMO_DURATION_S),
                              np.random.default_rng(DEMO_SEED))
    gt = record.groundtruth
    cmp = compare_to_truth(gt, *sim.truth_at(gt.t))
    d = cmp.to_dict()
    sig = 1e3 * np.sqrt(np.trace(gt.cov[:, :3, :3], axis1=1, axis2=2))
    f = {"wall_s": wall, "poses_kept": len(gt),
         "position_rmse_mm": d["position_error_mm"]["rmse"],
         "median_sigma_t_mm": float(np.median(sig)),
         "rotation_rmse_mrad": d["rotation_error_mrad"]["rmse"]}
    for name, n in (("position", cmp.nees_position), ("pose", cmp.nees_pose)):
        f[f"nees_{name}_per_dof"] = n.mean / n.dof
        f[f"nees_{name}_inside_95_pct"] = 100 * n.fraction_inside_95
    return {k: _number(v) for k, v in f.items()}


def mounting_figures(tmp: Path) -> dict[str, float]:
    """The README's worked example of a sensor's mounting and clock, as a user runs it."""
    from rtsgt.geometry.so3 import exp_so3, matrix_to_quat_xyzw
    from rtsgt.io.trajectory import read_tum, write_tum
    from rtsgt.types import PoseTrajectory

    sim, run, sensor = tmp / "sim", tmp / "run", tmp / "sensor.tum"
    _rtsgt("simulate", sim, "--seed", MOUNTING_SEED, "--duration", MOUNTING_DURATION_S)
    _rtsgt("run", sim / "deployment.toml", "--out", run, "--quiet")
    truth = read_tum(sim / "truth.tum")  # T_world_body, 100 Hz
    k = slice(100, -100, 10)  # 10 Hz
    R_bs, lever = exp_so3([0.0, 0.0, MOUNTING_YAW_RAD]), np.array(MOUNTING_LEVER_M)
    R = truth.rotation[k] @ R_bs
    p = truth.position[k] + truth.rotation[k] @ lever
    write_tum(sensor, PoseTrajectory(truth.t[k] - MOUNTING_DELAY_S, p, matrix_to_quat_xyzw(R)))
    f: dict[str, float] = {}
    for tag, extra in (("given", ()), ("estimated", ("--estimate", "all"))):
        t0 = time.perf_counter()
        e = json.loads(_rtsgt_out("evaluate", run, sensor, "--gt-engine", "linear", "--json",
                                  *extra))
        f[f"{tag}_evaluate_s"] = time.perf_counter() - t0
        f[f"{tag}_poses"] = e["ape"]["n"]
        f[f"{tag}_ape_t_rmse_mm"] = 1e3 * e["ape"]["translation_m"]["rmse"]
        f[f"{tag}_ape_r_rmse_deg"] = e["ape"]["rotation_deg"]["rmse"]
        f[f"{tag}_rpe_t_rmse_mm"] = 1e3 * e["rpe"]["translation_m"]["rmse"]
        f[f"{tag}_rpe_r_rmse_deg"] = e["rpe"]["rotation_deg"]["rmse"]
        f[f"{tag}_nees_position"] = e["nees"]["position"]["mean"]
        f[f"{tag}_nees_pose"] = e["nees"]["pose"]["mean"]
        f[f"{tag}_inside_95_position_pct"] = 100 * e["nees"]["position"]["fraction_inside_95"]
    m = e["mounting"]
    f["rotation_deg"] = m["rotation_angle_deg"]
    for axis, k in zip("xyz", range(3), strict=True):
        f[f"rotation_sigma_{axis}_deg"] = m["rotation_sigma_deg"][k]
        f[f"lever_{axis}_m"] = m["lever_m"][k]
        f[f"lever_sigma_{axis}_mm"] = 1e3 * m["lever_sigma_m"][k]
    f["clock_offset_ms"] = 1e3 * m["clock_offset_s"]
    f["clock_sigma_ms"] = 1e3 * m["clock_sigma_s"]
    f["fit_chi2_per_dof"] = m["fit"]["chi2"] / m["fit"]["dof"]
    f["effect_ape_t_mm"] = 1e3 * m["effect"]["ape_translation_m"]
    f["effect_ape_r_deg"] = m["effect"]["ape_rotation_deg"]
    f["noise_floor_ape_t_mm"] = 1e3 * e["noise_floor"]["ape_translation_m"]
    return {k: _number(v) for k, v in f.items()}


def _plain(o):
    """JSON of numpy values (what :func:`rtsgt.io.run_dir.write_json` writes)."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o))


def _number(v) -> float | int:
    return int(v) if isinstance(v, (int, np.integer)) else float(v)


def _command() -> list[str]:
    exe = shutil.which("rtsgt")
    return [exe] if exe else [sys.executable, "-c", "from rtsgt.cli.main import main; main()"]


def _rtsgt(*args) -> float:
    """Run the console script; the wall time, s."""
    t0 = time.perf_counter()
    subprocess.run(_command() + [str(a) for a in args], check=True, capture_output=True,
                   text=True)
    return time.perf_counter() - t0


def _rtsgt_out(*args) -> str:
    return subprocess.run(_command() + [str(a) for a in args], check=True, capture_output=True,
                          text=True).stdout


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=GROUPS, default=list(GROUPS))
    ap.add_argument("--out", type=Path, default=FIGURES_JSON)
    args = ap.parse_args(argv)
    figures = json.loads(args.out.read_text()) if args.out.is_file() else {}
    with tempfile.TemporaryDirectory() as tmp:
        for group in args.only:
            t0 = time.perf_counter()
            if group == "excerpt":
                figures[group] = excerpt_figures()
            else:
                figures[group] = globals()[f"{group}_figures"](Path(tmp) / group)
            print(f"{group}: {len(figures[group])} figures in {time.perf_counter() - t0:.1f} s")
    figures["about"] = ("written by benchmarks/readme_figures.py; quoted in README.md and docs/ "
                        "as NUMBER<!-- fig:GROUP.NAME -->, checked by "
                        "tests/test_readme_figures.py")
    args.out.write_text(json.dumps(figures, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
