"""The application layer: rtsgt's use cases as plain functions, called by the command line
(:mod:`rtsgt.cli`, declarations and printing only), :mod:`rtsgt.batch` and Python users
alike. Layers: docs/architecture.md#layers.
"""

from rtsgt.app.evaluate import (
    load_ground_truth,
    load_position_ground_truth,
    read_ground_truth,
    read_position_ground_truth,
    run_evaluation,
    save_evo_results,
)
from rtsgt.app.run import DeploymentRun, run_deployment

__all__ = ["DeploymentRun", "load_ground_truth", "load_position_ground_truth",
           "read_ground_truth", "read_position_ground_truth", "run_deployment",
           "run_evaluation", "save_evo_results"]
