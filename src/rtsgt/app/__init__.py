"""The application layer: rtsgt's use cases as plain functions, called by the command line
(:mod:`rtsgt.cli`, declarations and printing only), :mod:`rtsgt.batch` and Python users
alike. Layers: docs/architecture.md#layers.
"""

from rtsgt.app.run import DeploymentRun, run_deployment

__all__ = ["DeploymentRun", "run_deployment"]
