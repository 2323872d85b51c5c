"""The choices and defaults the command line's options show, in a module that imports nothing.

``rtsgt --help`` and ``rtsgt <command> --help`` build every option's declaration (its
default, the choices its help lists) without importing numpy, scipy or matplotlib
(:mod:`rtsgt.cli.main`). The constants those declarations need live here, each written once;
the module that uses each (named in its comment) imports it from here and keeps it under its
own name, so that ``rtsgt.calibration.gcp.DEFAULT_WEIGHTING`` and the like still read as
before.
"""

from __future__ import annotations

#: What the stations are calibrated from (:mod:`rtsgt.calibration.gcp`,
#: :mod:`rtsgt.calibration.dynamic`).
CALIBRATION_METHODS = ("gcp", "dynamic", "joint")
#: The models of a station's transform (docs/noise-model.md#levelled-stations-4-dof).
CALIBRATION_MODELS = ("6dof", "4dof")
#: How the markers of a station's GCP fit are weighted (docs/noise-model.md#weights-of-the-gcps).
CALIBRATION_WEIGHTINGS = ("gls", "trace", "none")
#: The weighting of :func:`rtsgt.calibration.calibrate` and of a run's ``[calibration]``: the
#: paper's. The generalised least squares is honest and sharper on simulated shots, but on the
#: real excerpt it makes the standing poses' inter-prism distances optimistic
#: (docs/noise-model.md).
DEFAULT_WEIGHTING = "none"
#: GCP file formats understood by :func:`rtsgt.io.gcp_csv.read_gcp_shots`.
GCP_FORMATS = ("auto", "rts-project", "csv")

#: The pose engine that estimates the trajectory from every raw measurement at once, after the
#: per-prism poses (docs/joint.md); the per-prism engines are :data:`rtsgt.pose.POSE_ENGINES`
#: (:class:`rtsgt.options.PoseOptions`).
JOINT_ENGINE = "joint"

#: How Qc is chosen by default (:class:`rtsgt.options.InterpolationOptions`).
DEFAULT_QC = "loo"
#: The GP's motion prior by default, white noise on the acceleration (the paper's;
#: :class:`rtsgt.options.InterpolationOptions`).
DEFAULT_PRIOR = "wnoa"
#: Default longest gap between two measurements across which a query is answered, s
#: (the gap-splitting threshold tau_s of Vaidis et al. 2022; :mod:`rtsgt.interpolation.gp`).
DEFAULT_MAX_GAP_S = 3.0

#: Trajectory formats understood by :func:`rtsgt.io.trajectory.read_trajectory` (there:
#: ``FORMATS``).
TRAJECTORY_FORMATS = ("tum", "kitti", "euroc", "rtsgt", "bag")
#: Alignment methods understood by :func:`rtsgt.evaluation.align.align_trajectories`.
ALIGN_METHODS = ("none", "se3", "sim3", "4dof", "scale", "origin")
#: Alignments the mounting can be estimated with (:mod:`rtsgt.evaluation.mounting`).
JOINT_ALIGNMENTS = ("none", "se3", "sim3", "4dof")
#: Default max distance (s) from an estimate time to the ground truth's nearest measurement,
#: for a ground truth without a gap limit of its own (a trajectory file); a run directory's
#: own limit is used for a run (``rtsgt evaluate``; :mod:`rtsgt.evaluation.options`).
DEFAULT_MAX_DT_S = 0.5
#: Pose relations (evo's ``--pose_relation`` names) -> (evo's title words, unit)
#: (:mod:`rtsgt.io.evo_results`).
POSE_RELATIONS = {
    "trans_part": ("translation part", "m"),
    "angle_deg": ("rotation angle in degrees", "deg"),
    "full": ("full transformation", "unit-less"),
}

#: Lower edges of the default range bins, m (the paper's: 0-75, 75-150, > 150 m;
#: :mod:`rtsgt.report.analysis`).
DEFAULT_BINS_M = (0.0, 75.0, 150.0)

#: The simulator's reality effects, in the order of their random streams
#: (:mod:`rtsgt.simulation.reality`).
REALITY_EFFECTS = ("correlated_noise", "prism_cyclic", "tracking_lag", "clock_drift",
                   "jerky_ramps", "remote_weather", "tripod_settling")
#: The simulator's presets and the duration each simulates unless told (s)
#: (:mod:`rtsgt.simulation.presets`).
SIMULATION_PRESETS = {"field-hour": 3600.0}
#: Environment variable with the number of processes that write a run directory
#: (:data:`rtsgt.io.run_dir.WRITE_PROCESSES`; the command line sets 2 unless it is set).
WRITE_PROCESSES_ENV = "RTSGT_WRITE_PROCESSES"

#: Exit status of an interrupted command (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130
#: The line an interrupted command prints on stderr.
INTERRUPTED_LINE = "error: interrupted"
