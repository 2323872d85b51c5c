"""The joint engine: the robot's SE(3) trajectory, the stations and the atmosphere estimated
together from every raw polar measurement (issue 23, steps 2 and 2b). docs/joint.md."""

from rtsgt.joint.estimate import JointResult, estimate_joint

__all__ = ["JointResult", "estimate_joint"]
