"""Planar kinematic chain with three conflicting positional tasks (paper Figs. 9-10).

Chain: fixed base, LINK_COUNT revolute joints about the world z axis, links of LINK_LENGTH
along each joint's x axis, every joint limited to [-1, 1] rad with damping zones 0.5 rad
thick (activation thresholds +-0.5 rad as in Fig. 10). Effectors sit at the ends of links
EFFECTOR_LINKS; their x, y targets (world frame, m) have strictly decreasing priorities.

Why GPM crosses the limits of joints 2 and 3: the targets are those of a posture with joints
2 and 3 bent past 1 rad (effectors 1 and 2) plus a tip target 0.2 m beyond reach (so the
final errors are not zero and equal for every method: the tip can at best point at it).
The three tasks take six of the seven DoFs; the Liegeois level only has the remaining
one-dimensional nullspace (and none once the tip task saturates), so it cannot hold joints
2 and 3 back while the tasks bend them (joint 5 also overshoots transiently). Clamping and
progressive clamping reach the same task errors with joints 2 and 3 on or inside their
limits, the other joints taking over.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin

from ..limits import GradientProjection
from ..pik import PIKSolver
from ..robot import Robot
from ..stack import TaskSpec
from . import Trajectory, pyplot, run_strategy, save_figure, write_table

LINK_COUNT = 7
LINK_LENGTH = 0.3          # m
JOINT_LIMIT = 1.0          # rad, symmetric
ACTIVATION = 0.5           # rad: damping zones [0.5, 1] and [-1, -0.5]
EFFECTOR_LINKS = (4, 5, 7)  # effector k sits at the end of link EFFECTOR_LINKS[k]
TARGETS = ((0.107, -0.757), (0.047, -1.051), (-0.014, -1.872))  # m, world x, y
TASK_GAIN = 0.05           # fraction of the task error asked per IK step
DAMPING = 0.05             # damped least squares lambda
GPM_GAIN = 1.0             # rad^2 per step (GradientProjection default)
STEPS = 400
STRATEGY_NAMES = ("gpm", "clamping", "progressive")
LIMIT_TOLERANCE = 1e-6     # rad: beyond the limit by more than this is a violation


def effector_name(index: int) -> str:
    return f"effector{index + 1}"


def build_chain() -> Robot:
    """The planar chain as a fixed-base Robot (joints joint1..jointN, frames effector1..3)."""
    model = pin.Model()
    parent = 0
    bound = np.array([JOINT_LIMIT])
    for link in range(LINK_COUNT):
        offset = pin.SE3(np.eye(3), np.array([0.0 if link == 0 else LINK_LENGTH, 0.0, 0.0]))
        parent = model.addJoint(parent, pin.JointModelRZ(), offset, f"joint{link + 1}",
                                np.array([10.0]), np.array([10.0]), -bound, bound)
        model.appendBodyToJoint(parent, pin.Inertia(1.0, np.array([LINK_LENGTH / 2, 0, 0]),
                                                    1e-3 * np.eye(3)), pin.SE3.Identity())
    tip = pin.SE3(np.eye(3), np.array([LINK_LENGTH, 0.0, 0.0]))
    for index, link in enumerate(EFFECTOR_LINKS):
        model.addFrame(pin.Frame(effector_name(index), link, 0, tip, pin.FrameType.OP_FRAME))
    return Robot(model=model, urdf="", floating_base=False)


def chain_solver(robot: Robot, strategy: str, q_start, hierarchy: str = "svd") -> PIKSolver:
    """Solver with the three effector tasks (priorities 0, 1, 2) aimed at TARGETS, on the
    SVD or the QP hierarchy (PIKSolver's `hierarchy`)."""
    solver = PIKSolver(robot, strategy=strategy, damping=DAMPING, lm_damping=0.0,  # paper's
                       activation=ACTIVATION, hierarchy=hierarchy)  # constant damping
    if strategy == "gpm":
        solver.strategy = GradientProjection(gain=GPM_GAIN)
    specs = [TaskSpec(effector_name(index), "position", effector_name(index), priority=index,
                      axes=("x", "y"), gain=TASK_GAIN) for index in range(len(TARGETS))]
    solver.set_stack(specs, q_start)
    for index, (x, y) in enumerate(TARGETS):
        solver.task(effector_name(index)).set_target(pin.SE3(np.eye(3), np.array([x, y, 0.0])))
    return solver


def run_chain(steps: int = STEPS, hierarchy: str = "svd") -> dict:
    """{strategy: Trajectory} from the straight chain, same targets for all."""
    robot = build_chain()
    q_start = np.zeros(robot.model.nq)
    counted = [effector_name(index) for index in range(len(TARGETS))]
    runs = {name: run_strategy(chain_solver(robot, name, q_start, hierarchy), q_start, steps,
                               counted)
            for name in STRATEGY_NAMES}
    return runs


def violations(trajectory: Trajectory) -> np.ndarray:
    """Largest excursion beyond +-JOINT_LIMIT per joint over the run (rad, 0 if none)."""
    return np.maximum(np.abs(trajectory.q).max(axis=0) - JOINT_LIMIT, 0.0)


def violating_joints(trajectory: Trajectory) -> list:
    """1-based numbers of the joints that ever leave their limits."""
    return [int(joint) + 1 for joint in np.flatnonzero(violations(trajectory) > LIMIT_TOLERANCE)]


def peak_acceleration_near_limits(trajectory: Trajectory) -> float:
    """Largest |q[k+1] - 2 q[k] + q[k-1]| (rad per step^2) over joints and steps where
    |q[k]| is inside a damping zone or beyond (|q| > JOINT_LIMIT - ACTIVATION)."""
    acceleration = np.abs(np.diff(trajectory.q, n=2, axis=0))
    near = np.abs(trajectory.q[1:-1]) > JOINT_LIMIT - ACTIVATION
    return float(np.max(acceleration * near, initial=0.0))


def summary(runs: dict) -> list:
    """One row of numbers per strategy (the table of the report)."""
    return [{
        "strategy": name,
        "final_total_error_m": float(run.total_error[-1]),
        "violating_joints": violating_joints(run),
        "max_violation_rad": float(violations(run).max()),
        "peak_acceleration_near_limits_rad_per_step2": peak_acceleration_near_limits(run),
        "steps": len(run.total_error),
    } for name, run in runs.items()]


def plot_chain(runs: dict, outdir: Path) -> list:
    """chain_joints.png (Fig. 10 left), chain_errors.png (Fig. 10 right), chain_damping.png
    (h of progressive clamping per joint, the colors of Fig. 9). Returns the paths."""
    plt = pyplot()
    outdir.mkdir(parents=True, exist_ok=True)
    names = runs["progressive"].damped_dofs
    colors = plt.cm.tab10(np.arange(len(names)))
    paths = []

    figure, axes = plt.subplots(1, len(runs), figsize=(5 * len(runs), 4.5), sharey=True)
    for axis, (strategy, run) in zip(axes, runs.items()):
        for joint, color in enumerate(colors):
            axis.plot(run.q[:, joint], color=color, label=names[joint])
        for level in (-JOINT_LIMIT, JOINT_LIMIT):
            axis.axhline(level, color="black", linestyle="--", linewidth=1)
        for level in (-JOINT_LIMIT + ACTIVATION, JOINT_LIMIT - ACTIVATION):
            axis.axhline(level, color="gray", linestyle=":", linewidth=1)
        axis.set_title(f"{strategy}: violates {violating_joints(run) or 'none'}")
        axis.set_xlabel("iteration")
        axis.grid(alpha=0.3)
    axes[0].set_ylabel("joint angle (rad); limits dashed, thresholds dotted")
    axes[-1].legend(loc="lower right", fontsize=8)
    figure.tight_layout()
    paths.append(save_figure(figure, outdir / "chain_joints.png"))

    figure, axis = plt.subplots(figsize=(7, 4.5))
    for strategy, run in runs.items():
        axis.plot(run.total_error, label=f"{strategy} (final {run.total_error[-1]:.3f} m)")
    axis.set_xlabel("iteration")
    axis.set_ylabel("sum of the three effector errors (m)")
    axis.set_title("Error convergence (tasks conflict: final error > 0)")
    axis.grid(alpha=0.3)
    axis.legend()
    figure.tight_layout()
    paths.append(save_figure(figure, outdir / "chain_errors.png"))

    progressive = runs["progressive"]
    figure, axis = plt.subplots(figsize=(7, 4.5))
    for joint, color in enumerate(colors):
        axis.plot(progressive.damping[:, joint], color=color, label=names[joint])
    axis.set_xlabel("iteration")
    axis.set_ylabel("progressive clamping h (0 free, 1 clamped)")
    axis.set_ylim(-0.05, 1.05)
    axis.set_title("Progressive clamping: damping h per joint")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    paths.append(save_figure(figure, outdir / "chain_damping.png"))
    return paths


def reproduce(outdir: Path, steps: int = STEPS) -> list:
    """Run, plot and tabulate; returns the written paths."""
    runs = run_chain(steps)
    paths = plot_chain(runs, outdir)
    paths.extend(write_table(outdir, "chain", "Kinematic chain (Figs. 9-10)", summary(runs)))
    return paths
