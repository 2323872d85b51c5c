"""Simulated deployments with known truth (``rtsgt simulate``, ``rtsgt demo``).

:func:`simulate_deployment` computes a deployment in memory (numeric core, no files);
:func:`write_deployment` writes it as the files of a real deployment plus its truth.
"""

from rtsgt.simulation.deployment import (
    ObservationTruth,
    SimulatedDeployment,
    SimulationConfig,
    SimulationTruth,
    SurveyShots,
    TruthModel,
    atmospheric_ppm,
    simulate_deployment,
)
from rtsgt.simulation.files import write_deployment

__all__ = [
    "ObservationTruth",
    "SimulatedDeployment",
    "SimulationConfig",
    "SimulationTruth",
    "SurveyShots",
    "TruthModel",
    "atmospheric_ppm",
    "simulate_deployment",
    "write_deployment",
]
