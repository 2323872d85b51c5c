"""Simulated deployments with known truth (``rtsgt simulate``, ``rtsgt demo``).

:func:`simulate_deployment` computes a deployment in memory (numeric core, no files);
:func:`write_deployment` writes it as the files of a real deployment plus its truth;
:class:`RealityEffects` (in :class:`SimulationConfig`) adds errors the estimator's noise model
does not have (:mod:`rtsgt.simulation.reality`).
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
from rtsgt.simulation.reality import REALITY_EFFECTS, RealityEffects

__all__ = [
    "REALITY_EFFECTS",
    "ObservationTruth",
    "RealityEffects",
    "SimulatedDeployment",
    "SimulationConfig",
    "SimulationTruth",
    "SurveyShots",
    "TruthModel",
    "atmospheric_ppm",
    "simulate_deployment",
    "write_deployment",
]
