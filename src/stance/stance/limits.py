"""Joint limit models and strategies for the clamping loop of the PIK (Raunhardt and Boulic).

A limit model owns some velocity degrees of freedom (v indices) of the robot and knows
their limits; given a candidate variation dq it decides which of its free DoFs must be
fixed, and to what variation, before the prioritized solution is evaluated again with the
fixed variations as highest-priority equality constraints. It reports h per DoF.
A strategy says how the models decide (clamping only, or progressive clamping) and may add
levels of its own.

- none: nothing is ever fixed.
- gpm (Liegeois gradient projection): nothing is fixed either; one lowest-priority level
  steps down the gradient of the joint-limit criterion, inside what the tasks leave free.
- clamping (Baerlocher-Boulic): a joint whose q + dq leaves [lower, upper] is fixed on the
  limit it crosses.
- progressive: equations 1-5 of the paper. Inside a damping zone of thickness `activation`
  next to a limit, a variation heading toward that limit is damped by the cubic
  h = 3 d^2 - 2 d^3 of the normalized activation distance d; the damped variation
  (1 - h) dq is fixed. A variation leaving the limits is clamped on them (h = 1).

Only revolute (1-coordinate) joints are handled here; the floating base is never limited.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .hierarchy import Level


@dataclass
class LimitDecision:
    """Velocity DoFs (indices into dq) to fix and their fixed variations."""

    index: np.ndarray
    dq: np.ndarray
    h: np.ndarray     # damping value per fixed DoF, 1 = clamped on the limit


@numba.njit(cache=True)
def cubic_step(d):
    """h(d) = -2 d^3 + 3 d^2 for d clipped to [0, 1] (0 at the threshold, 1 at the limit)."""
    d = min(max(d, 0.0), 1.0)
    return d * d * (3.0 - 2.0 * d)


NEGLIGIBLE_VARIATION = 1e-12  # rad: below this a joint variation is not worth a re-solve


@numba.njit(cache=True)
def fix_joints(configuration, variation, indices, table, progressive, fixed, fixed_dq, h):
    """Equations 2-5, then the clamping check (with progressive False only the check, h in
    {0, 1}), for the joints at indices = [q indices; v indices] of the configuration (nq)
    and variation (nv) not fixed yet; table = [lower; upper; lower_threshold;
    upper_threshold; thickness] (few arguments: each costs numba's dispatch). A joint to
    damp or clamp is fixed in place in fixed, fixed_dq and h (nv each), nothing is
    returned boxed. Returns how many were fixed."""
    q_index, v_index = indices
    lower, upper, lower_threshold, upper_threshold, thickness = table
    count = 0
    for j in range(len(q_index)):
        v = v_index[j]
        q, dq = configuration[q_index[j]], variation[v]
        if fixed[v] or (abs(dq) <= NEGLIGIBLE_VARIATION and lower[j] <= q <= upper[j]):
            continue                # (a joint outside its limits goes back even unmoved)
        q_next = q + dq
        damping, damped_dq = 0.0, 0.0
        if q_next > upper[j]:
            damping, damped_dq = 1.0, upper[j] - q
        elif q_next < lower[j]:
            damping, damped_dq = 1.0, lower[j] - q
        elif progressive:
            if q_next > q and q > upper_threshold[j]:
                damping = cubic_step((q - upper_threshold[j]) / thickness[j])
            elif q_next < q and q < lower_threshold[j]:
                damping = cubic_step((lower_threshold[j] - q) / thickness[j])
            damped_dq = (1.0 - damping) * dq
        if damping > 0.0:
            fixed[v], fixed_dq[v], h[v] = True, damped_dq, damping
            count += 1
    return count


def decision_by_fixing(model, q, dq, free, progressive: bool) -> LimitDecision:
    """The decision of a model that fixes in place (model.fix; v_index: its velocity
    DoFs), taken on scratch arrays: the free DoFs it fixes, their variations and h."""
    fixed, fixed_dq, h = ~free, np.zeros(len(free)), np.zeros(len(free))
    model.fix(q, dq, fixed, fixed_dq, h, progressive)
    index = model.v_index[fixed[model.v_index] & free[model.v_index]]
    return LimitDecision(index, fixed_dq[index], h[index])


@numba.njit(cache=True)
def keep_inside_bounds(q, q_next, q_index, lower, upper):
    """RevoluteLimits.keep_inside compiled: q_next[i] clipped (in place) to
    [min(lower, q[i]), max(upper, q[i])] for i in q_index."""
    for j in range(len(q_index)):
        i = q_index[j]
        q_next[i] = min(max(q_next[i], min(lower[j], q[i])), max(upper[j], q[i]))


class RevoluteLimits:
    """Limit model of 1-coordinate joints (revolute or prismatic): bounds and damping
    thresholds (rad or m).

    activation: damping zone thickness next to each limit (rad), at most
    `max_activation_fraction` of the joint's range so narrow joints keep a free middle.
    """

    def __init__(self, names, q_index, v_index, lower, upper, activation: float = 0.2,
                 max_activation_fraction: float = 0.4):
        self.dof_names = list(names)
        self.indices = np.array([q_index, v_index], dtype=np.int64).reshape(2, -1)
        self.q_index, self.v_index = self.indices  # views
        lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        thickness = np.minimum(activation, max_activation_fraction * (upper - lower))
        self.table = np.array([lower, upper, lower + thickness, upper - thickness,
                               thickness]).reshape(5, -1)
        (self.lower, self.upper, self.lower_threshold, self.upper_threshold,
         self.thickness) = self.table  # views

    @classmethod
    def from_robot(cls, robot, activation: float = 0.2, owned_v=()) -> RevoluteLimits:
        """Every limited 1-DoF joint of the robot (the floating base never) but those whose
        velocity DoF is in `owned_v` (limited by another model, e.g. a joint group)."""
        keep = ~np.isin(robot.limited_v_index, np.asarray(list(owned_v), dtype=int))
        return cls(np.asarray(robot.limited_joint_names)[keep].tolist(),
                   robot.limited_q_index[keep], robot.limited_v_index[keep],
                   robot.lower[keep], robot.upper[keep], activation)

    def keep_inside(self, q, q_next) -> None:
        """Project q_next (in place) into the limits without ever moving a joint further
        out than q: removes the negligible overshoot of variations the decision ignored."""
        keep_inside_bounds(q, q_next, self.q_index, self.lower, self.upper)

    def fix(self, q, dq, fixed, fixed_dq, h, progressive: bool) -> bool:
        """Fix in place (fixed, fixed_dq, h: nv) the DoFs not fixed yet that dq must not
        move freely; True if any. q: configuration (nq), dq: candidate variation (nv)."""
        return fix_joints(q, dq, self.indices, self.table, progressive, fixed, fixed_dq,
                          h) > 0

    def decide(self, q, dq, free, progressive: bool) -> LimitDecision:
        """q: configuration (nq), dq: candidate variation (nv), free: bool (nv)."""
        return decision_by_fixing(self, q, dq, free, progressive)


class Strategy:
    """Base of the joint limit strategies: how limit models decide, and extra levels."""

    name = ""
    enforces_limits = True
    progressive = False

    def decide(self, model, q, dq, free) -> LimitDecision:
        return model.decide(q, dq, free, self.progressive)

    def fix(self, model, q, dq, fixed, fixed_dq, h) -> bool:
        """The model's decision written in place into the clamping loop's arrays (nv
        each); True if it fixes any DoF."""
        return model.fix(q, dq, fixed, fixed_dq, h, self.progressive)

    def extra_levels(self, solver, q) -> list:
        """Levels appended below the task levels (lowest priority); none by default."""
        return []


class NoLimits(Strategy):
    name = "none"
    enforces_limits = False

    def decide(self, model, q, dq, free) -> LimitDecision:
        empty = np.zeros(0)
        return LimitDecision(np.zeros(0, dtype=int), empty, empty)

    def fix(self, model, q, dq, fixed, fixed_dq, h) -> bool:
        return False


class GradientProjection(NoLimits):
    """Liegeois gradient projection method: limits are not enforced, the joints are only
    attracted toward mid-range in the nullspace of every task (lowest priority level).

    Criterion over the n limited 1-DoF joints (dimensionless):
      H(q) = 1/(2n) sum_i ((q_i - mid_i) / (upper_i - lower_i))^2,
      dH/dq_i = (q_i - mid_i) / (n (upper_i - lower_i)^2)   (1/rad).
    The level asks dq_i = -gain dH/dq_i on those joints (gain in rad^2 per IK step). With the
    default gain 1, a joint of range 2 rad among 7 moves 1/28 of its offset from mid-range
    per step when the tasks leave it free.
    """

    name = "gpm"

    def __init__(self, gain: float = 1.0):
        self.gain = gain

    def extra_levels(self, solver, q) -> list:
        robot = solver.robot  # every limited 1-DoF joint, also those in joint groups
        count = len(robot.limited_v_index)
        if count == 0:
            return []
        span = robot.upper - robot.lower
        gradient = (q[robot.limited_q_index] - 0.5 * (robot.upper + robot.lower)) / (
            count * span**2)
        selection = np.zeros((count, robot.model.nv))
        selection[np.arange(count), robot.limited_v_index] = 1.0
        return [Level(jacobian=selection, target=-self.gain * gradient)]


class Clamping(Strategy):
    """Baerlocher-Boulic clamping: fix on the limit any joint that q + dq takes outside."""

    name = "clamping"


class ProgressiveClamping(Strategy):
    """Raunhardt-Boulic progressive clamping (eq. 1-5), then the clamping check."""

    name = "progressive"
    progressive = True


STRATEGIES = {strategy.name: strategy for strategy in (
    NoLimits, GradientProjection, Clamping, ProgressiveClamping)}


def make_strategy(name: str):
    if name not in STRATEGIES:
        raise ValueError(f"unknown joint limit strategy {name!r} "
                         f"(expected one of {', '.join(STRATEGIES)})")
    return STRATEGIES[name]()
