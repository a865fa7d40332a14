"""Stance algorithm library: prioritized inverse kinematics with progressive clamping.

Plain Python on Pinocchio and numpy; nothing here imports rclpy. Nodes are thin adapters
over this library.
"""

from .numba_cache import use_source_keyed_cache

use_source_keyed_cache()  # before any compiled function is defined

from .hierarchy import DampedHierarchy, Level  # noqa: E402
from .pik import PIKSolver, StepResult  # noqa: E402
from .robot import Robot, RobotModelError  # noqa: E402
from .stack import StackError, TaskSpec, parse_stack_yaml, validate_stack  # noqa: E402
from .tasks import TargetError  # noqa: E402

__all__ = [
    "DampedHierarchy", "Level", "PIKSolver", "Robot", "RobotModelError", "StackError",
    "StepResult", "TargetError", "TaskSpec", "parse_stack_yaml", "validate_stack",
]
