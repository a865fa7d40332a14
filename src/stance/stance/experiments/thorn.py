"""Humanoid removing a thorn from its right foot behind its back (paper Figs. 11-12).

Stack, highest priority first (world frame, m and rad):
  0. left toe and left heel positions held where they start;
  1. CoM x, y over the middle of the left sole;
  2. right hand and right toe positions, one shared target THORN_OFFSET from the pelvis
     (the floating base joint: behind it, to the right, below);
  3. head orientation: the start orientation turned HEAD_YAW about the world z axis and
     pitched HEAD_PITCH down (looking back toward hand and foot);
  4. posture: the start configuration.
Progressive clamping and clamping run from the same start; the total error is the sum of
the error norms of levels 0-3 (m and rad added as numbers, as the paper's "total error").

Humanoids: Talos (toe and heel frames added +-SOLE_HALF_LENGTH along each sole's x axis; its
knee leg_right_4_joint is a single flexion DoF) and the mannequin of stance.models (knee
flexion + twist as in the paper, spherical joints limited by stance.swing models).

The mannequin starts from "standing" with the right knee flexed START_KNEE_FLEXION (right
foot lifted behind it, standing on the left foot). From the straight-knee "standing" neither
strategy gets below ERROR_THRESHOLD in MAX_STEPS: the first steps extend the right knee onto
its 0 rad limit (flexing a straight knee first lowers the toe, which must rise 0.75 m), the
leg then lifts straight and the hip limits stall it with the hand 0.49 m and the toe 0.37 m
from the target (total error 1.5). The target is not the cause: an offline optimization
(scipy, same limits) meets levels 0-3 exactly with the right knee flexed about 1.8 rad. Any
start flexion from 0.4 to 1 rad reaches the threshold (0.3 rad does not).

Iterations to a total error of 0.1 (paper, mannequin: progressive 393, clamping 455):
mannequin 107 and 107, Talos 111 and 111. Both strategies pace the reach by REACH_GAIN (the
error falls by 3 % per step) and the right knee's flexion and twist never enter their damping
zones (flexion ends at 2.16 rad, zone from 2.2), so the paper's earlier hand-over from knee
twist to flexion does not happen and progressive clamping only ties clamping. With the knee
twist limited to +-0.2 rad instead of +-0.6, progressive clamping does damp the twist (h up
to 0.44) and the knee flexes further (2.17 rad against 2.15), yet both still take 107
iterations: the reach gain paces the error, and the reach never waits on the knee.

The paper gives neither its damping factor lambda nor its step size, so `reproduce` also
sweeps both (lambda 0.05, 0.2, 0.5; reach gain 0.03, 0.2, 1.0, each task's step capped at
0.05 m or rad, as the paper limits a constraint's variation): the strategies tie at lambda
0.05; at 0.2 and 0.5 progressive clamping needs 2-9 % more iterations than clamping on the
mannequin (371 against 342 at lambda 0.5, gain 0.03), and on Talos 1-2 % more, except 4 %
fewer at lambda 0.5, gain 0.03 (342 against 356). Its damping slows the joints in their
zones, which the others make up for less well under a larger lambda; the paper's hand-over
from knee twist to flexion does not show here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pinocchio as pin

from ..pik import PIKSolver
from ..robot import Robot
from ..stack import TaskSpec
from . import pyplot, run_strategy, save_figure, write_table

SOLE_HALF_LENGTH = 0.1                         # m, Talos toe and heel frames from the sole
THORN_OFFSET = np.array([-0.35, -0.2, -0.25])  # m, shared hand/toe target from the pelvis
HEAD_YAW = -1.2                                # rad about world z (turn right, look back)
HEAD_PITCH = 0.5                               # rad, looking down
ACTIVATION = 0.2                               # rad, damping zone thickness (1-DoF joints)
DAMPING = 0.05                                 # damped least squares lambda
REACH_GAIN = 0.03                              # error fraction per step, hand, toe, head
ERROR_THRESHOLD = 0.1                          # total error the paper counts iterations to
SWEEP_DAMPINGS = (0.05, 0.2, 0.5)              # lambda values of the sensitivity sweep
SWEEP_GAINS = (0.03, 0.2, 1.0)                 # reach gains of the sensitivity sweep
START_KNEE_FLEXION = 0.6                       # rad, mannequin's right knee at the start
MAX_STEPS = 1500
STRATEGY_NAMES = ("progressive", "clamping")
COUNTED_TASKS = ("left_toe", "left_heel", "com", "right_hand", "right_toe", "head")


@dataclass(frozen=True)
class Humanoid:
    """What the experiment needs to know about one robot (frame and DoF names)."""

    load: Callable[[], Robot]
    start: str                  # reference configuration
    frames: dict                # role -> frame: left_toe, left_heel, right_toe, hand, head
    knee_dofs: tuple            # drawn bold in the damping figure
    right_leg_dofs: tuple       # damped DoFs of the right leg, hip to ankle
    limit_models: Callable[[Robot], list] = lambda robot: []


def add_sole_frames(model: pin.Model) -> None:
    """Add Talos' {left,right}_{toe,heel} operational frames (in place)."""
    for side in ("left", "right"):
        sole_id = model.getFrameId(f"{side}_sole_link")
        sole = model.frames[sole_id]
        for name, sign in (("toe", 1.0), ("heel", -1.0)):
            offset = pin.SE3(np.eye(3), np.array([sign * SOLE_HALF_LENGTH, 0.0, 0.0]))
            model.addFrame(pin.Frame(f"{side}_{name}", sole.parentJoint, sole_id,
                                     sole.placement * offset, pin.FrameType.OP_FRAME))


def load_talos() -> Robot:
    """Talos with the toe and heel frames."""
    talos = Robot.from_example_robot_data("talos")
    add_sole_frames(talos.model)
    return Robot(model=talos.model, urdf=talos.urdf, floating_base=talos.floating_base,
                 reference_configurations=talos.reference_configurations)


def load_mannequin() -> Robot:
    """The mannequin with a "right_knee_flexed" reference configuration: "standing" with the
    right knee flexed START_KNEE_FLEXION (the right foot lifted off the floor)."""
    from ..models import build_mannequin

    mannequin = build_mannequin()
    start = mannequin.initial_configuration("standing")
    start[mannequin.model.joints[mannequin.joint_id("right_knee")].idx_q] = START_KNEE_FLEXION
    mannequin.reference_configurations["right_knee_flexed"] = start
    return mannequin


def mannequin_limits(robot: Robot) -> list:
    from ..models import MANNEQUIN_LIMIT_FILE
    from ..swing import load_limit_file

    return load_limit_file(MANNEQUIN_LIMIT_FILE, robot)


def _ball(joint: str) -> tuple:
    return (f"{joint}_swing_x", f"{joint}_swing_y", f"{joint}_twist")


HUMANOIDS = {
    "talos": Humanoid(
        load=load_talos, start="half_sitting",
        frames={"left_toe": "left_toe", "left_heel": "left_heel", "right_toe": "right_toe",
                "hand": "gripper_right_base_link", "head": "head_2_link"},
        knee_dofs=("leg_right_4_joint",),
        right_leg_dofs=tuple(f"leg_right_{index}_joint" for index in range(1, 7))),
    "mannequin": Humanoid(
        load=load_mannequin, start="right_knee_flexed",
        frames={"left_toe": "left_toe", "left_heel": "left_heel", "right_toe": "right_toe",
                "hand": "right_hand", "head": "head"},
        knee_dofs=("right_knee", "right_knee_twist"),
        right_leg_dofs=(*_ball("right_hip"), "right_knee", "right_knee_twist",
                        *_ball("right_ankle")[:2]),  # the ankle twist is locked: h = 1
        limit_models=mannequin_limits),
}


def thorn_stack(frames: dict, reach_gain: float = REACH_GAIN) -> list:
    return [
        TaskSpec("left_toe", "position", frames["left_toe"], priority=0, gain=0.5),
        TaskSpec("left_heel", "position", frames["left_heel"], priority=0, gain=0.5),
        TaskSpec("com", "com", priority=1, axes=("x", "y"), gain=0.2),
        TaskSpec("right_hand", "position", frames["hand"], priority=2, gain=reach_gain),
        TaskSpec("right_toe", "position", frames["right_toe"], priority=2, gain=reach_gain),
        TaskSpec("head", "orientation", frames["head"], priority=3, gain=reach_gain),
        TaskSpec("posture", "posture", priority=4, gain=0.02),
    ]


def thorn_solver(humanoid: Humanoid, robot: Robot, strategy: str, q_start,
                 compiled_loop: bool = True, damping: float = DAMPING,
                 reach_gain: float = REACH_GAIN) -> PIKSolver:
    """Solver with the thorn stack (damping: lambda; reach_gain: the hand, toe and head
    tasks' gain); targets from the kinematics of q_start."""
    solver = PIKSolver(robot, strategy=strategy, damping=damping, lm_damping=0.0,  # paper's
                       activation=ACTIVATION,                         # constant damping
                       limit_models=humanoid.limit_models(robot), compiled_loop=compiled_loop)
    solver.set_stack(thorn_stack(humanoid.frames, reach_gain), q_start)  # held at q_start
    data, model = robot.data, robot.model
    place = {role: data.oMf[model.getFrameId(frame)] for role, frame in humanoid.frames.items()}
    solver.task("com").set_target(
        0.5 * (place["left_toe"].translation + place["left_heel"].translation))
    thorn = pin.SE3(np.eye(3), data.oMi[1].translation + THORN_OFFSET)
    solver.task("right_hand").set_target(thorn)
    solver.task("right_toe").set_target(thorn)
    turn = pin.rpy.rpyToMatrix(0.0, 0.0, HEAD_YAW) @ pin.rpy.rpyToMatrix(0.0, HEAD_PITCH, 0.0)
    solver.task("head").set_target(pin.SE3(turn @ place["head"].rotation,
                                           place["head"].translation))
    return solver


def run_thorn(robot_name: str = "talos", max_steps: int = MAX_STEPS,
              damping: float = DAMPING, reach_gain: float = REACH_GAIN) -> dict:
    """{strategy: Trajectory} from the humanoid's start, each stopped once its total error
    is below ERROR_THRESHOLD (or after max_steps)."""
    humanoid = HUMANOIDS[robot_name]
    robot = humanoid.load()
    q_start = robot.initial_configuration(humanoid.start)
    return {name: run_strategy(thorn_solver(humanoid, robot, name, q_start, damping=damping,
                                            reach_gain=reach_gain),
                               q_start, max_steps, COUNTED_TASKS, stop_below=ERROR_THRESHOLD)
            for name in STRATEGY_NAMES}


def sweep(robot_name: str = "talos", dampings=SWEEP_DAMPINGS, gains=SWEEP_GAINS,
          max_steps: int = MAX_STEPS) -> list:
    """Iterations to ERROR_THRESHOLD of each strategy (None: not within max_steps) for
    every lambda in dampings and reach gain in gains: how much the comparison depends on
    two settings the paper does not give."""
    rows = []
    for damping in dampings:
        for gain in gains:
            runs = run_thorn(robot_name, max_steps, damping=damping, reach_gain=gain)
            iterations = {name: run.first_step_below(ERROR_THRESHOLD)
                          for name, run in runs.items()}
            rows.append({"damping": damping, "reach_gain": gain,
                         **{f"{name}_iterations": count for name, count in iterations.items()},
                         "progressive_over_clamping": (
                             iterations["progressive"] / iterations["clamping"]
                             if None not in iterations.values() else None)})
    return rows


def summary(runs: dict) -> list:
    return [{
        "strategy": name,
        "iterations_to_total_error_0.1": run.first_step_below(ERROR_THRESHOLD),
        "final_total_error": float(run.total_error[-1]),
        "steps_run": len(run.total_error),
    } for name, run in runs.items()]


def plot_thorn(humanoid: Humanoid, robot_name: str, runs: dict, outdir: Path) -> list:
    """thorn_errors.png (Fig. 12 top) and thorn_damping.png (h of the right leg's DoFs per
    strategy, knee bold; Fig. 12 bottom). Returns the paths."""
    plt = pyplot()
    outdir.mkdir(parents=True, exist_ok=True)
    figure, axis = plt.subplots(figsize=(7, 4.5))
    for name, run in runs.items():
        reached = run.first_step_below(ERROR_THRESHOLD)
        axis.plot(run.total_error, label=f"{name}: below {ERROR_THRESHOLD} at iteration "
                  f"{reached if reached is not None else 'never'}")
    axis.axhline(ERROR_THRESHOLD, color="black", linestyle="--", linewidth=1)
    axis.set_yscale("log")
    axis.set_xlabel("iteration")
    axis.set_ylabel("total error (m + rad, levels 0-3)")
    axis.set_title(f"Thorn experiment on {robot_name}: total error")
    axis.grid(alpha=0.3, which="both")
    axis.legend()
    figure.tight_layout()
    paths = [save_figure(figure, outdir / "thorn_errors.png")]

    figure, axes = plt.subplots(len(runs), 1, figsize=(8, 3.4 * len(runs)), sharex=True)
    for axis, (name, run) in zip(axes, runs.items()):
        for dof in humanoid.right_leg_dofs:
            bold = dof in humanoid.knee_dofs
            axis.plot(run.damping[:, run.damped_dofs.index(dof)], label=dof,
                      linewidth=2.5 if bold else 1.0, linestyle="-" if bold else "--")
        axis.set_ylim(-0.05, 1.05)
        axis.set_ylabel(f"{name}: h")
        axis.grid(alpha=0.3)
    axes[0].set_title("Right leg damping h (knee solid and bold; clamping: 0 or 1)")
    axes[-1].legend(fontsize=7, ncol=3, loc="center right")
    axes[-1].set_xlabel("iteration")
    figure.tight_layout()
    paths.append(save_figure(figure, outdir / "thorn_damping.png"))
    return paths


def reproduce(outdir: Path, robot_name: str = "talos", max_steps: int = MAX_STEPS) -> list:
    """Run, plot and tabulate, then the sweep's table; returns the written paths."""
    runs = run_thorn(robot_name, max_steps)
    paths = plot_thorn(HUMANOIDS[robot_name], robot_name, runs, outdir)
    paths.extend(write_table(outdir, "thorn", f"Thorn experiment on {robot_name} "
                             "(Figs. 11-12)", summary(runs)))
    paths.extend(write_table(outdir, "thorn_sweep", f"Thorn experiment on {robot_name}: "
                             f"iterations to a total error of {ERROR_THRESHOLD} per lambda "
                             "and reach gain", sweep(robot_name, max_steps=max_steps)))
    return paths
