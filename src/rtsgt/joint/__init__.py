"""The joint engine: the robot's SE(3) trajectory, the stations and the atmosphere estimated
together from every raw polar measurement (issue 23, step 2). docs/joint.md."""

from rtsgt.joint.estimate import JointResult, estimate_joint

__all__ = ["JointResult", "estimate_joint"]
