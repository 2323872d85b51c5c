"""``rtsgt plan``: the uncertainty of the ground truth, predicted from a layout before going out.

:mod:`rtsgt.planning.layout` builds the layout (stations, markers and their calibration, the
rig); :mod:`rtsgt.planning.predict` predicts the pose covariance a run would report at any
pose; :mod:`rtsgt.planning.gp_factor` is the GP's part of it; :mod:`rtsgt.planning.plan` maps
it over an area or along a path and checks the layout against the paper's advice
(docs/planning.md).
"""

from rtsgt.planning.gp_factor import gp_factor, gp_posterior_covariance
from rtsgt.planning.layout import (
    Layout,
    PlannedStation,
    layout_from_deployment,
    layout_from_positions,
    synthetic_gcp_shots,
)
from rtsgt.planning.plan import (
    DEFAULT_HEADINGS,
    PlanResult,
    check_advice,
    plan_area,
    plan_path,
    waypoint_path,
)
from rtsgt.planning.predict import (
    DEFAULT_QC_M2_S3,
    PosePrediction,
    RobotMotion,
    heading_poses,
    predict_poses,
    qc_from_run,
)

__all__ = ["DEFAULT_HEADINGS", "DEFAULT_QC_M2_S3", "Layout", "PlanResult", "PlannedStation", "PosePrediction", "RobotMotion",
           "check_advice", "gp_factor", "gp_posterior_covariance", "heading_poses",
           "layout_from_deployment", "layout_from_positions", "plan_area", "plan_path",
           "predict_poses", "qc_from_run", "synthetic_gcp_shots", "waypoint_path"]
