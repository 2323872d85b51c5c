"""rtsgt: robotic total station ground truth.

Turns robotic total station (RTS) measurements into 6-DOF ground-truth trajectories with a
covariance at every pose, and evaluates SLAM / odometry trajectories against that uncertain
ground truth. The package is laid out by pipeline stage::

    measurement  -> noise -> calibration -> filtering -> interpolation -> pose -> evaluation
    (io, simulation, report and cli sit at the edges and call into the numeric core)
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
