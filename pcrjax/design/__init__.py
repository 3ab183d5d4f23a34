"""Trajectory design by gradient through the differentiable rollout: point-to-point moves without
residual vibration (`moves`), the fastest such move within the actuators' limits (`fastest`), and
tracking a platform path within those limits (`tracking`)."""

from .fastest import fastest_move
from .moves import (
    Move,
    MovePrograms,
    default_lever,
    design_move,
    plan_move,
    settling,
    shortest_duration,
    step_times,
    verify,
    vibration,
)
from .splines import bspline_basis, correction_basis, smooth_step
from .tracking import Tracking, design_tracking, plan_tracking, verify_tracking

__all__ = [
    "Move",
    "MovePrograms",
    "Tracking",
    "bspline_basis",
    "correction_basis",
    "default_lever",
    "design_move",
    "design_tracking",
    "fastest_move",
    "plan_move",
    "plan_tracking",
    "settling",
    "shortest_duration",
    "smooth_step",
    "step_times",
    "verify",
    "verify_tracking",
    "vibration",
]
