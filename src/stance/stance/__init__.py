"""Stance algorithm library: prioritized inverse kinematics with progressive clamping.

Plain Python on Pinocchio and numpy; nothing here imports rclpy. Nodes are thin adapters
over this library.
"""

from .hierarchy import DampedHierarchy, Level
from .pik import PIKSolver, StepResult
from .robot import Robot, RobotModelError
from .stack import StackError, TaskSpec, parse_stack_yaml, validate_stack
from .tasks import TargetError

__all__ = [
    "DampedHierarchy", "Level", "PIKSolver", "Robot", "RobotModelError", "StackError",
    "StepResult", "TargetError", "TaskSpec", "parse_stack_yaml", "validate_stack",
]
