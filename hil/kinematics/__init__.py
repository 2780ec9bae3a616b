"""Robot kinematics (millimetres and radians at the API)."""

from hil.kinematics.ur import (
    UR3_JOINT_LIMITS_RAD,
    UR3_REACH_MM,
    UR_DH,
    DHParams,
    ur_forward,
    ur_inverse,
)

__all__ = ["UR3_JOINT_LIMITS_RAD", "UR3_REACH_MM", "UR_DH", "DHParams", "ur_forward", "ur_inverse"]
