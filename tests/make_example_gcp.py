"""Generate ``src/rtsgt/data/example_gcp.txt``, the small synthetic GCP file shipped with rtsgt.

Three levelled stations (pure yaw + translation, as after the compensator) shoot eight markers
at 4-60 m; the shots get Trimble S7 instrument and tilt noise (seeded), the RTS_project
additive constant of 0.01 m is removed from the distances, and values are written with six
significant digits like the RTS_project ``GCP.txt`` exporter. Not shipped; run from the
repository root::

    python tests/make_example_gcp.py [OUTPUT]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from rtsgt.geometry.so3 import exp_so3
from rtsgt.io.rts_project import write_gcp_rts_project
from rtsgt.measurement.instruments import TRIMBLE_S7
from rtsgt.measurement.polar import cartesian_to_polar
from rtsgt.noise.perturb import sample_polar_errors
from rtsgt.types import GcpShots

SEED = 20221110
ADDITIVE_CONSTANT = 0.01
DEFAULT_OUTPUT = Path(__file__).resolve().parents[1] / "src" / "rtsgt" / "data" / "example_gcp.txt"

#: True ``T_world_station`` (yaw in degrees, translation in m); world = station 1.
TRUTH = {
    "1": (0.0, (0.0, 0.0, 0.0)),
    "2": (125.0, (12.5, -4.2, 0.35)),
    "3": (-40.0, (-6.8, 9.1, -0.42)),
}

#: Marker positions in the world frame, m.
MARKERS = np.array([
    [3.1, 2.4, -0.8],
    [-14.0, 6.5, 0.6],
    [22.0, 18.0, 1.4],
    [35.0, -12.0, 0.2],
    [-8.0, -25.0, -1.1],
    [5.0, 44.0, 2.3],
    [-38.0, -30.0, -0.4],
    [52.0, 20.0, 1.9],
])


def truth_transform(station: str) -> tuple[np.ndarray, np.ndarray]:
    """``(R_world_station, t_world_station)`` of the example."""
    yaw_deg, t = TRUTH[station]
    return exp_so3(np.array([0.0, 0.0, np.radians(yaw_deg)])), np.array(t, dtype=float)


def make_shots(seed: int = SEED) -> GcpShots:
    """The example shots (raw distances, six significant digits)."""
    rng = np.random.default_rng(seed)
    station, marker, hz, v, d, t = [], [], [], [], [], []
    for k, s in enumerate(TRUTH):
        R, tr = truth_transform(s)
        p_station = (MARKERS - tr) @ R  # R^T (p_world - t)
        h, z, dist = cartesian_to_polar(p_station)
        hs, zs, ds = (a[0] for a in sample_polar_errors(h, z, dist, TRIMBLE_S7, 1, rng))
        station += [s] * len(MARKERS)
        marker += [str(m + 1) for m in range(len(MARKERS))]
        hz.append(np.mod(hs, 2 * np.pi))
        v.append(zs)
        d.append(ds - ADDITIVE_CONSTANT)
        t.append(1668094000.0 + 600.0 * k + 45.0 * np.arange(len(MARKERS)) + rng.uniform(0, 1, 8))

    def six(a):
        return np.array([float(f"{x:.6g}") for x in np.concatenate(a)])

    return GcpShots(
        station=station, marker=marker, hz=six(hz), v=six(v), d=six(d),
        t=np.round(np.concatenate(t), 6), additive_constant=ADDITIVE_CONSTANT,
    )


def main(argv: list[str]) -> None:
    out = Path(argv[1]) if len(argv) > 1 else DEFAULT_OUTPUT
    write_gcp_rts_project(out, make_shots())
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv)
