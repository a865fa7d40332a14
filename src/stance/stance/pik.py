"""Prioritized inverse kinematics with the clamping / progressive clamping loop (Fig. 8).

One IK step from configuration q:
  1. kinematics of q (Pinocchio: joint Jacobians, frame placements, CoM Jacobian);
  2. the enabled tasks, grouped by priority, give one Level each (rows scaled by
     sqrt(weight), targets = the tasks' capped steps); each level's damped least squares
     lambda is lambda_k^2 = damping^2 + lm_damping |e_k|^2, e_k the level's target rows of
     the tasks that curve (all but posture; a CoM task's uncapped, gain x error) and the
     uncapped returns its inequality rows ask (gain x the CoM's distance outside a
     support polygon's edges):
     Levenberg-Marquardt damping as Pink's lm_damping (Sugihara, "Solvability-unconcerned
     inverse kinematics by the Levenberg-Marquardt method", 2011), large while a target is
     far or out of reach, so an unreachable target does not make the joints chatter, and
     `damping` alone once the targets are reached. The level's rows and targets, and the
     violation of its inequality rows in its objective (Inequalities.weight), are scaled
     by damping / lambda_k, so the hierarchy's one lambda acts as lambda_k on that level
     alone, and no level's damping depends on the levels below it;
  3. clamping loop: solve the hierarchy; ask every limit model, through the strategy, which
     of its free DoFs must be damped or clamped; fix them as highest-priority equalities;
     repeat until none is new (the strategy may add lowest-priority levels, e.g. GPM);
  4. optionally keep every joint under its velocity limit over dt, saturating the lowest
     levels first: levels are kept whole from the highest down while the sum stays within
     the limits, the first that would exceed them is scaled to fit and the ones below it
     are dropped, so a lower level never slows a higher one (each level's share lies in the
     nullspace of the ones above it); without per-level shares (QP hierarchy: velocity
     bounds are its inequalities), or when the fixed variations alone exceed the limits, dq
     is scaled uniformly. Dropping lower levels can turn a joint toward a limit the full
     solution moved it away from, so the limit pass of step 3 runs on the saturated dq
     too, and a DoF it fixes resumes the loop (then saturation again);
  5. q_next = integrate(q, dq) on the configuration manifold.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numba
import numpy as np
import pinocchio as pin

from .hierarchy import (DampedHierarchy, HierarchySolution, _damped_least_squares,
                        excludes_zero, level_start_state, restartable_solution,
                        solve_compiled, solve_levels)
from .limits import RevoluteLimits, fix_joints, make_strategy
from .qp_hierarchy import (BINDING_TOLERANCE, Inequalities, QPHierarchy, cascade_compiled,
                           empty_cascade_state)
from .robot import RobotModelError
from .stack import StackError, TaskSpec, parse_stack_yaml, short_repr, validate_stack
from .swing import NO_BALL, NO_GROUP, BallLimit, JointGroupLimit, ball_fix, group_fix
from .tasks import (LM_ERROR, LM_STEP, ComTask, FrameTask, FrameTaskBatch, SupportTask,
                    capped_steps, make_task, step_cap_groups)


MET_RELATIVE = 1e-3   # a level whose step residual is below this x its step is met,
MET_ABSOLUTE = 1e-12  # or below this (m, rad): rounding, on a level already on target
LM_DAMPING = 100.0    # lm_damping: Talos' hands out of reach hold still, reached ones
#                       converge as fast as without it (tests/test_lm_damping.py)


@dataclass
class LevelReport:
    priority: int
    tasks: list
    residual_norm: float        # |sqrt(w) e| stacked over the level's tasks, at q
    step_residual_norm: float   # |J dq - step| the hierarchy left, task units
    damping: float              # its damped least squares lambda this step (LM damping)
    decide_condition: object = field(default="met", repr=False)  # its condition, or the
    #                             arguments of _level_condition, run at the first read

    @property
    def condition(self) -> str:
        """met: step residual <= MET_RELATIVE x |step| (or MET_ABSOLUTE); singular: the
        level's own rows, damped by `damping`, cannot give its step either (rank-deficient
        or contradictory rows, a stretched limb); conflict: they could, but higher levels,
        clamped joints or bounds (velocity limits included) take what it needs; damped:
        its Levenberg-Marquardt damping holds part of the step back (a target far away or
        out of reach): at lambda = damping the levels above and the clamped joints would
        leave it its step, within the joint and velocity limits."""
        if not isinstance(self.decide_condition, str):
            self.decide_condition = _level_condition(*self.decide_condition)
        return self.decide_condition


@dataclass
class StepResult:
    q: np.ndarray               # configuration after the step
    dq: np.ndarray              # applied variation (nv)
    levels: list                # LevelReport per level with enabled tasks, highest first
    task_errors: dict           # task name -> |e| over its selected axes at q (m, rad)
    damping: np.ndarray         # h per limited DoF (0 free, 1 clamped on a limit), then
    #                             per joint group its swing's and its twist's
    clamped: np.ndarray         # bool per limited DoF: variation fixed in the loop (QP: a
    #                             damped 1-DoF joint bounded by it, _damping_bounds); per
    #                             group swing and twist: whether the rule altered its joints
    clamping_iterations: int    # hierarchy solutions evaluated
    solve_time: float           # s
    velocity_scale: float = 1.0  # velocity limits: factor on the first level that had to
    #                              slow down, the levels below it dropped (uniform: on dq)
    decide_binding: object = field(default_factory=list, repr=False)  # binding_constraints,
    #                             or PIKSolver._binding_names' arguments, run at the first read

    @property
    def binding_constraints(self) -> list:
        """Bounds on dq that bind: '<dof> lower|upper|velocity|damped', support rows
        '<task> edge <k>' (named at the first read: a step nobody reports pays nothing)."""
        if isinstance(self.decide_binding, tuple):
            self.decide_binding = PIKSolver._binding_names(*self.decide_binding)
        return self.decide_binding


@dataclass
class _Layout:
    """Row layout of the enabled tasks, rebuilt when the stack or an enable flag changes."""

    task_names: list            # in priority order
    disabled_tasks: list        # reported, not solved
    frame_tasks: FrameTaskBatch  # frame tasks, written in one call
    other_tasks: list           # (task, its Jacobian rows, its error rows) for the others:
    #                             views of the solver's stacked arrays
    priorities: list
    level_tasks: list
    offsets: np.ndarray         # level row offsets (levels + 1)
    task_starts: np.ndarray     # first row of each task
    row_scale: np.ndarray       # sqrt(weight) per row
    row_gain: np.ndarray        # task gain per row
    row_group: np.ndarray       # step cap group per row (Task.step_caps)
    group_cap: np.ndarray       # norm cap per group (task units per step)
    error_norms: np.ndarray     # filled per step: |e| per task, then |sqrt(w) e| per level
    lm_rows: np.ndarray         # per row, what LM damping counts (its task's lm_counts)
    level_scale: np.ndarray     # filled per step: damping / lambda per level (LM damping)
    support_tasks: list         # (enabled SupportTask, its level index): inequality rows


class PIKSolver:
    """Prioritized IK for one robot.

    strategy: joint limit strategy name (none, gpm, clamping, progressive).
    damping: damped least squares lambda once the targets are reached.
    lm_damping: Levenberg-Marquardt scale (module docstring, step 2; 0: lambda is always
        `damping`, as in the paper's experiments). activation: damping zone thickness (rad).
    dt: if set, joint variations respect the URDF velocity limits over dt seconds.
    hierarchy: the prioritized solver: "svd" (DampedHierarchy, damped least squares),
        "qp" (QPHierarchy on ProxSuite, with joint and velocity bounds as inequalities), or
        an object with solve_stacked(); one whose `uses_bounds` is true also receives
        per-DoF bounds on dq, and one with an `unconstrained` DampedHierarchy (as
        QPHierarchy) must return that hierarchy's solution wherever its levels stay within
        the bounds (hierarchy.first_level_out_of_bounds): the compiled clamping loop
        relies on it.
    limit_models: limit models beyond the robot's 1-DoF joints (e.g. swing joints, joint
        groups, which take their joints from the revolute model); their DoFs must not
        overlap. Each has v_index, dof_names, fix(), keep_inside() and warm_up(q), as
        swing.SwingTwistRule.
    locked_joints: names of actuated joints the IK never moves (e.g. grippers, which
        their own controllers command): their variations are 0 as highest-priority
        equalities from the first solution of every step on, so no limit or task ever
        costs a re-solve for them. RobotModelError for an unknown name or the base.
    compiled_loop: run the clamping loop in one compiled call where the hierarchy and
        limit models allow it (the same bits); False: always the general loop, the
        reference it is tested and benchmarked against.
    """

    def __init__(self, robot, strategy: str = "progressive", damping: float = 1e-3,
                 activation: float = 0.2, dt: float | None = None, hierarchy="svd",
                 limit_models=(), locked_joints=(), compiled_loop: bool = True,
                 lm_damping: float = LM_DAMPING):
        if not (math.isfinite(lm_damping) and lm_damping >= 0.0):
            raise ValueError(f"lm_damping must be finite and >= 0, got {lm_damping}")
        self.robot = robot
        self.locked_joints = list(locked_joints)
        self._locked_v = _locked_dofs(robot, self.locked_joints)
        self.strategy = make_strategy(strategy)
        self.hierarchy = make_hierarchy(hierarchy, robot, damping, dt)
        # the lambda the hierarchy solves with (a hierarchy object brings its own): LM
        # damping scales rows by it, the reports and level conditions use it
        self.damping = getattr(getattr(self.hierarchy, "unconstrained", self.hierarchy),
                               "damping", damping)
        self.lm_damping = float(lm_damping)
        if self.lm_damping > 0.0 and not self.damping > 0.0:
            raise ValueError("lm_damping needs damping > 0 (the rows of a level are scaled "
                             "by damping / its lambda)")
        self.limits = RevoluteLimits.from_robot(
            robot, activation, {int(v) for model in limit_models for v in model.v_index})
        self.limit_models = [self.limits, *limit_models]
        self._group_models = [model for model in limit_models
                              if isinstance(model, JointGroupLimit)]
        # h and clamped per limited DoF (v index), then each joint group's swing and twist
        self.limited_dof_names = [name for model in self.limit_models
                                  for name in model.dof_names] + \
            [name for group in self._group_models for name in group.report_names]
        self._dof_v_index = np.concatenate([model.v_index for model in self.limit_models])
        self.dt = dt
        speed_step = robot.velocity_limit * dt if dt is not None else np.zeros(0)
        usable = speed_step > 0
        self._speed_index = robot.limited_v_index[usable] if np.any(usable) else None
        self._inverse_speed_step = 1.0 / speed_step[usable]
        # |dq| bound per 1-DoF joint from its velocity limit over dt (inf: none)
        self._speed_bound = np.where(usable, speed_step, np.inf) if dt is not None else \
            np.full(len(robot.limited_v_index), np.inf)
        self._no_level_steps = np.zeros((0, robot.model.nv))
        self._no_position_limit_high = np.full(len(robot.limited_v_index), np.inf)
        self._no_position_limit_low = -self._no_position_limit_high
        self.tasks = {}
        self._needs_com = False
        self._layout = self._make_layout()
        self._uses_bounds = getattr(self.hierarchy, "uses_bounds", False)
        # the clamping loop in one compiled call: damped least squares (QPHierarchy: while
        # its unconstrained solves stay within the bounds), 1-DoF limits, joint groups and
        # spherical joints
        self._unconstrained = getattr(self.hierarchy, "unconstrained", self.hierarchy)
        self._one_call_loop = (compiled_loop
                               and isinstance(self._unconstrained, DampedHierarchy)
                               and all(isinstance(model, (JointGroupLimit, BallLimit))
                                       for model in limit_models))
        self._groups = tuple(model.kernel_arguments for model in limit_models
                             if isinstance(model, JointGroupLimit)) or (NO_GROUP,)
        self._balls = tuple(model.kernel_arguments for model in limit_models
                            if isinstance(model, BallLimit)) or (NO_BALL,)

    @property
    def strategy_name(self) -> str:
        return self.strategy.name

    def set_strategy(self, name: str) -> None:
        self.strategy = make_strategy(name)

    def compute_kinematics(self, q: np.ndarray, com: bool | None = None) -> None:
        """Fill robot.data for q: joint Jacobians, frame placements, CoM and its Jacobian
        (com: default when the stack has a CoM task)."""
        model, data = self.robot.model, self.robot.data
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        if self._needs_com if com is None else com:
            pin.jacobianCenterOfMass(model, data, False)

    def set_stack(self, specs, q: np.ndarray) -> None:
        """Replace the task stack atomically. Tasks that keep their name, kind and frame keep
        their targets; new tasks hold their value at q. On error nothing changes."""
        specs = validate_stack(specs, self.robot.model.existFrame)
        tasks = {spec.name: make_task(spec, self.robot) for spec in specs}
        for task in tasks.values():
            if isinstance(task, SupportTask) and \
                    not getattr(self.hierarchy, "uses_inequalities", False):
                raise StackError(f"task {task.name!r}: kind support is an inequality, which "
                                 "only the qp hierarchy solves (hierarchy: qp)")
        needs_com = any(isinstance(task, (ComTask, SupportTask)) for task in tasks.values())
        self.compute_kinematics(q, com=needs_com)  # raises on a bad q before any change
        for name, task in tasks.items():
            old = self.tasks.get(name)
            if old is not None and (old.spec.kind, old.spec.frame) == (task.spec.kind,
                                                                         task.spec.frame):
                task.keep_target(old)
            else:
                task.hold(self.robot, q)
        self.tasks, self._needs_com = tasks, needs_com
        self._layout = self._make_layout()

    def stack(self) -> list:
        return [task.spec for task in self.tasks.values()]

    def task(self, name: str):
        if name not in self.tasks:
            raise StackError(f"no task named {short_repr(name)} in the stack")
        return self.tasks[name]

    def set_enabled(self, name: str, enabled: bool) -> None:
        self.task(name).enabled = bool(enabled)
        self._layout = self._make_layout()

    def step(self, q: np.ndarray) -> StepResult:
        """One IK step from q (see module docstring)."""
        start = time.perf_counter()
        robot = self.robot
        self.compute_kinematics(q)
        jacobian, target, error = self._fill_levels(q)
        offsets = self._layout.offsets
        inequalities, returns = self._support_inequalities()
        level_scale = self._lm_scale(jacobian, target, inequalities, returns)
        if inequalities is not None:
            inequalities = inequalities._replace(weight=level_scale[inequalities.level])

        extra = self.strategy.extra_levels(self, q)
        if extra:
            jacobian, target, offsets = _append_levels(jacobian, target, offsets, extra)
        bounds = self._dq_bounds(q) if self._uses_bounds else None
        nv = robot.model.nv
        fixed = np.zeros(nv, dtype=bool)
        fixed[self._locked_v] = True        # at 0, like a clamped joint, from the start
        fixed_dq = np.zeros(nv)
        h = np.zeros(nv)
        for group in self._group_models:
            group.report[:] = 0.0
        solution, iterations, finished = None, 0, False
        if self._one_call_loop and self.strategy.enforces_limits and inequalities is None:
            solution, iterations, finished = self._compiled_clamping(
                q, jacobian, target, offsets, fixed, fixed_dq, h, bounds)
        if not finished:    # the general loop, or on from a compiled solution out of bounds
            solution, more = self._clamping(q, jacobian, target, offsets, bounds, fixed,
                                            fixed_dq, h, solution, inequalities)
            iterations += more

        dq, scale = self._within_velocity_limits(solution, fixed_dq)
        while scale < 1.0 and self.strategy.enforces_limits and \
                self._limit_pass(q, dq, fixed, fixed_dq, h):    # step 4, saturated dq
            solution, more = self._clamping(q, jacobian, target, offsets, bounds, fixed,
                                            fixed_dq, h, inequalities=inequalities)
            iterations += more
            dq, scale = self._within_velocity_limits(solution, fixed_dq)
        step_residuals = solution.step_residuals if scale == 1.0 else \
            _level_residuals(jacobian, target, offsets, dq)
        unsaturated = None if scale == 1.0 else solution.step_residuals
        if inequalities is not None:
            step_residuals = _with_shortfalls(step_residuals, inequalities, dq)
            if unsaturated is not None:
                unsaturated = _with_shortfalls(unsaturated, inequalities, solution.dq)
        q_next = pin.integrate(robot.model, q, dq)
        if self.strategy.enforces_limits:
            for model in self.limit_models:
                model.keep_inside(q, q_next)
        held = (fixed.copy(), fixed_dq.copy(),
                bounds if bounds is not None else partial(self._dq_bounds, q.copy()),
                None if unsaturated is None else np.array(unsaturated, dtype=float))
        levels, task_errors = self._reports(q, error, step_residuals, jacobian, target,
                                            level_scale, held, inequalities)
        binding = solution.binding
        if binding and bounds is not None:
            binding = (self, binding, solution.dq, fixed, fixed_dq, h)
        fixed[self._locked_v] = False       # reported: fixed by the limits
        damping, clamped = h[self._dof_v_index], fixed[self._dof_v_index]
        if self._group_models:              # then each group's swing and twist
            reports = np.array([group.report for group in self._group_models])
            damping = np.concatenate([damping, reports[:, :2].ravel()])
            clamped = np.concatenate([clamped, np.repeat(reports[:, 2] > 0.0, 2)])
        return StepResult(q=q_next, dq=dq, levels=levels, task_errors=task_errors,
                          damping=damping, clamped=clamped, clamping_iterations=iterations,
                          solve_time=time.perf_counter() - start, velocity_scale=scale,
                          decide_binding=binding)

    def _lm_scale(self, jacobian, target, inequalities, returns) -> np.ndarray:
        """Each level's factor damping / lambda_k (module docstring, step 2; 1 without LM
        damping), its rows of the stacked Jacobian and target scaled by it in place;
        inequalities: the support tasks', or None; returns: per row of theirs, the
        uncapped return that counts in its level's lambda_k (m)."""
        layout = self._layout
        scale = layout.level_scale
        if self.lm_damping:
            returned = _NO_RETURNS
            if inequalities is not None:
                returned = np.zeros(len(scale))
                np.add.at(returned, inequalities.level, returns ** 2)
            _lm_scale_levels(jacobian, target, self._error, layout.row_gain,
                             layout.row_scale, layout.offsets, layout.lm_rows, self.damping,
                             self.lm_damping, returned, scale)
        return scale

    def _binding_names(self, names, dq, fixed, fixed_dq, h) -> list:
        """The QP hierarchy's binding names with '<joint> damped' for the damped 1-DoF
        joints (bounded by their damped variation, _damping_bounds) whose dq (rad) is on
        that variation (fixed, fixed_dq, h: the step's, nv each; the locked joints, unfixed
        for the report, have h = 0)."""
        v = self.limits.v_index
        damped = fixed[v] & (h[v] > 0.0) & (h[v] < 1.0) & (fixed_dq[v] != 0.0)
        on = v[damped & (np.abs(dq[v] - fixed_dq[v]) <= BINDING_TOLERANCE)]
        rename = getattr(self.hierarchy, "with_damping_bounds", None)  # a hierarchy object
        return names if rename is None else rename(names, on)         # may not name them

    def _clamping(self, q, jacobian, target, offsets, bounds, fixed, fixed_dq, h,
                  solution=None, inequalities=None):
        """Step 3 (module docstring) for any hierarchy, limit models and strategy: the
        final HierarchySolution and how many solutions it took; fixed, fixed_dq and h (nv
        each) filled in place. solution: a restartable one with these fixed joints (the
        compiled loop's), which the first solve restarts from. inequalities: the support
        tasks' (QPHierarchy's Inequalities), None without any."""
        iterations = 0
        options = {} if inequalities is None else {"inequalities": inequalities}
        if bounds is not None:          # hot starts kept per fixed and damped joints (the
            options["kept_key"] = fixed  # array the limit passes below fill in place)
        while True:
            equal, solve_bounds = fixed, bounds
            if bounds is not None:     # damped joints bounded, not fixed (_damping_bounds)
                equal, lower, upper = _damping_bounds(fixed, fixed_dq, h, self.limits.v_index,
                                                      *bounds)
                solve_bounds = (lower, upper)
            index = equal.nonzero()[0]
            restart = {} if getattr(solution, "restart", None) is None else \
                {"previous": solution}  # re-solve only the levels the new fixes touch
            solution = self.hierarchy.solve_stacked(jacobian, target, offsets, index,
                                                    fixed_dq[index], bounds=solve_bounds,
                                                    **restart, **options)
            iterations += 1
            if not self._limit_pass(q, solution.dq, fixed, fixed_dq, h):
                return solution, iterations

    def _limit_pass(self, q, dq, fixed, fixed_dq, h) -> bool:
        """Every limit model's decision on the variation dq (nv) from q, through the
        strategy, written in place into fixed, fixed_dq and h; True if it fixed a DoF."""
        changed = False
        for model in self.limit_models:
            changed |= self.strategy.fix(model, q, dq, fixed, fixed_dq, h)
        return changed

    def _compiled_clamping(self, q, jacobian, target, offsets, fixed, fixed_dq, h,
                           bounds=None):
        """_clamping in one compiled call, when the 1-DoF joints, joint groups and
        spherical joints are the only limit models and the hierarchy is DampedHierarchy,
        or QPHierarchy (bounds: its (lower, upper)), whose cascades it runs too as long as
        their hot starts hold: the same kernels (the limit models' on disjoint DoFs, so in
        any order), so the same bits, without the Python around each solution and limit
        pass. Returns (HierarchySolution, solutions, finished):
        finished, the final one; else the solution whose levels left the bounds
        (QPHierarchy with hot starts off), or whose cascade reached a level for ProxSuite,
        not counted and restartable, fixed, fixed_dq and h as it was solved with, for
        _clamping to go on from (its solve restarts at no level: the same bits, the same
        decision). NaN bounds go to _clamping (which refuses them) at once."""
        unconstrained, limits, hierarchy = self._unconstrained, self.limits, self.hierarchy
        lower, upper = (np.zeros(0), np.zeros(0)) if bounds is None else bounds
        if np.isnan(lower).any() or np.isnan(upper).any():
            return None, 0, False
        cascades = isinstance(hierarchy, QPHierarchy) and hierarchy.hot_start
        cascade_state = hierarchy.cascade_state(len(offsets) - 1, jacobian.shape[1]) \
            if cascades else _NO_CASCADE_STATE
        (dq, level_steps, residuals, iterations, finished, cascaded, solved_fixed,
         solved_values, level_bases, level_ranks, level_starts) = _clamping_loop(
            jacobian, target, offsets, q, limits.indices, limits.table, self._groups,
            self._balls, self.strategy.progressive, fixed, fixed_dq, h, unconstrained.damping,
            unconstrained.rank_tolerance, lower, upper, cascades, cascade_state,
            limits.v_index)
        if finished and cascaded:
            enforced = cascade_state[-2]    # scratch arrays: the next step reuses them
            _, lower, upper = _damping_bounds(fixed, fixed_dq, h, limits.v_index, lower, upper)
            return hierarchy.cascade_solution(dq, residuals.copy(), enforced, lower,
                                              upper), iterations, True
        if finished:
            return HierarchySolution(dq=dq, step_residuals=residuals,
                                     level_steps=level_steps), iterations, True
        return restartable_solution(jacobian, target, solved_fixed, solved_values, dq,
                                    residuals, level_steps, level_bases, level_ranks,
                                    level_starts), iterations, False

    def warm_up(self, q: np.ndarray) -> None:
        """Compile (or load from numba's disk cache) the step's kernels, including the
        velocity-saturation path, by one discarded step from q: the first compilation of a
        source version takes about 80-90 s on a 2-core machine (Talos, the mannequin; each
        set of limit models compiles its own clamping loop, 15 s more for Talos' groups),
        which a real-time loop must not pay on its first cycle; then 0.5 s from the cache."""
        robot, nv = self.robot, self.robot.model.nv
        self.step(q)   # leaves the stacked Jacobian and target filled at q
        offsets = self._layout.offsets
        _level_residuals(self._jacobian, self._target, offsets, np.zeros(nv))
        if len(offsets) > 1:   # what a level's condition calls from Python (_level_condition)
            #                    once a level falls short: pik_node's first plan paid it,
            #                    40-80 ms of cache load in its control loop
            rows = slice(offsets[0], offsets[1])
            _damped_least_squares(self._jacobian[rows], self._target[rows], self.damping ** 2)
            DampedHierarchy(damping=self.damping).solve_stacked(
                self._jacobian[:offsets[1]].copy(), self._target[:offsets[1]].copy(),
                offsets[:2], np.zeros(0, dtype=np.int64), np.zeros(0))
            self._dq_bounds(q)   # the bounds it checks (the svd hierarchy's steps need none)
        # kernels a later stack or strategy may need: the task kinds', the joint limits'
        for spec in (TaskSpec("com", "com"),
                     TaskSpec("frame", "pose", frame=robot.model.frames[-1].name)):
            make_task(spec, robot).jacobian_and_error(robot, q)
        self.limits.decide(q, np.zeros(nv), np.ones(nv, dtype=bool), True)
        self.limits.keep_inside(q, q.copy())
        if self._one_call_loop:   # the strategy can change at run time
            self._compiled_clamping(q, self._jacobian, self._target, self._layout.offsets,
                                    np.zeros(nv, dtype=bool), np.zeros(nv), np.zeros(nv),
                                    self._dq_bounds(q) if self._uses_bounds else None)
        for model in self.limit_models[1:]:
            model.warm_up(q)
        if hasattr(self.hierarchy, "warm_up"):   # QPHierarchy: kernels of binding bounds
            self.hierarchy.warm_up()
        self.forget_starts()                     # the first real step starts afresh

    def forget_starts(self) -> None:
        """Drop what steps taken so far left to start the next one from (QPHierarchy's
        kept active sets and QPs; its counters go on): the next step is a fresh solver's,
        bit for bit. For a step the caller discarded, after warm_up's, and at a jump to
        another configuration."""
        if hasattr(self.hierarchy, "forget_starts"):
            self.hierarchy.forget_starts()

    def levels(self) -> list:
        """(priority, task names) of each level with enabled tasks, highest first."""
        return list(zip(self._layout.priorities, self._layout.level_tasks))

    def task_poses(self, name: str):
        """(target, current) SE3 of a frame or CoM task at the last computed kinematics
        (CoM: translation only); (None, None) for a posture task."""
        task = self.task(name)
        return task.target_pose(), task.current_pose(self.robot)

    def _make_layout(self) -> _Layout:
        enabled = sorted((task for task in self.tasks.values() if task.enabled),
                         key=lambda task: task.priority)
        row_count = sum(task.dimension for task in enabled)
        jacobian = self._jacobian = np.zeros((row_count, self.robot.model.nv))
        error = self._error = np.zeros(row_count)
        self._target = np.zeros(row_count)
        others, priorities, level_tasks, offsets, starts, scales = [], [], [], [0], [], []
        gains, support, lm_counts = [], [], []
        row = 0
        for task in enabled:
            if not priorities or priorities[-1] != task.priority:
                if priorities:
                    offsets.append(row)
                priorities.append(task.priority)
                level_tasks.append([])
            level_tasks[-1].append(task.name)
            if isinstance(task, SupportTask):
                support.append((task, len(priorities) - 1))
            scale = float(np.sqrt(task.weight))
            if not isinstance(task, FrameTask):
                rows = slice(row, row + task.dimension)
                others.append((task, jacobian[rows], error[rows]))
            starts.append(row)
            scales.extend([scale] * task.dimension)
            gains.extend([task.gain] * task.dimension)
            lm_counts.extend([task.lm_counts] * task.dimension)
            row += task.dimension
        if priorities:
            offsets.append(row)
        frames = [index for index, task in enumerate(enabled) if isinstance(task, FrameTask)]
        return _Layout([task.name for task in enabled],
                       [task for task in self.tasks.values() if not task.enabled],
                       FrameTaskBatch(self.robot, [enabled[index] for index in frames],
                                      [starts[index] for index in frames]),
                       others, priorities, level_tasks, np.array(offsets, dtype=np.int64),
                       np.array(starts, dtype=np.int64), np.array(scales), np.array(gains),
                       *step_cap_groups(enabled), np.zeros(len(enabled) + len(priorities)),
                       np.array(lm_counts, dtype=np.int8), np.ones(len(priorities)), support)

    def _fill_levels(self, q):
        """Write every enabled task's rows into the stacked Jacobian, error and target
        (Jacobian and target rows scaled by sqrt(weight))."""
        jacobian, target, error = self._jacobian, self._target, self._error
        layout, robot = self._layout, self.robot
        layout.frame_tasks.write(robot, jacobian, error)
        for task, task_jacobian, task_error in layout.other_tasks:
            task.write(robot, q, task_jacobian, task_error)
        _weighted_rows(jacobian, error, layout.row_gain, layout.row_group, layout.group_cap,
                       layout.row_scale, target)
        return jacobian, target, error

    def _reports(self, q, error, step_residuals, jacobian, target, level_scale, held,
                 inequalities):
        """LevelReports and task errors; step_residuals (of the rows as solved, each level
        scaled by level_scale) reported in task units; held: _level_condition's;
        inequalities: the support tasks' (weighted as solved), or None. A support task's
        error is its CoM's distance outside (m), part of its level's residual."""
        layout = self._layout
        norms = layout.error_norms
        _error_norms(error, layout.task_starts, layout.offsets, layout.row_scale, norms)
        norms = norms.tolist()  # Python floats without one call per value
        task_count = len(layout.task_names)
        task_errors = dict(zip(layout.task_names, norms[:task_count]))
        level_norms = norms[task_count:]
        for task, level in layout.support_tasks:    # an inequality: its distance outside
            task_errors[task.name] = task.distance_outside(self.robot)
            level_norms[level] = math.hypot(level_norms[level], task_errors[task.name])
        solved = np.asarray(step_residuals, dtype=float)[:len(level_scale)]
        levels = list(map(LevelReport, layout.priorities, layout.level_tasks, level_norms,
                          (solved / level_scale).tolist(),
                          (self.damping / level_scale).tolist(),
                          self._conditions(jacobian, target, solved.tolist(), held,
                                           inequalities)))
        for task in layout.disabled_tasks:
            _, task_error = task.jacobian_and_error(self.robot, q)
            task_errors[task.name] = task.distance_outside(self.robot) \
                if isinstance(task, SupportTask) else float(np.linalg.norm(task_error))
        return levels, task_errors

    def _conditions(self, jacobian, target, step_residuals, held, inequalities) -> list:
        """LevelReport.decide_condition of each level with tasks (the strategy's extra
        levels, last, are not reported): _level_condition's arguments, on one copy of the
        step's rows shared by the levels (the solver's arrays are reused next step; a
        step whose report nobody reads pays the copies only), each level's violated
        inequality rows among them (_with_violated_rows)."""
        offsets = self._layout.offsets
        rows, wanted = jacobian[:offsets[-1]].copy(), target[:offsets[-1]].copy()
        if inequalities is not None:
            rows, wanted, offsets = _with_violated_rows(rows, wanted, offsets, inequalities)
        problem = (rows, wanted, offsets, self.damping ** 2,
                   self._layout.level_scale.copy(), held)
        return [(problem, level, residual)
                for level, residual in enumerate(step_residuals[:len(offsets) - 1])]

    def _support_inequalities(self):
        """(Inequalities, returns) of the enabled support tasks at robot.data's
        kinematics ((None, None) without a polygon): each polygon edge a row of its task's
        level, and the uncapped return LM damping counts of it (m,
        SupportTask.write_inequalities)."""
        tasks = [(task, level) for task, level in self._layout.support_tasks
                 if task.edge_count]
        if not tasks:
            return None, None
        count = sum(task.edge_count for task, _ in tasks)
        rows, room = np.empty((count, self.robot.model.nv)), np.empty(count)
        returns = np.empty(count)
        levels, labels, start = [], [], 0
        for task, level in tasks:
            end = start + task.edge_count
            task.write_inequalities(self.robot, rows[start:end], room[start:end],
                                    returns[start:end])
            levels += [level] * task.edge_count
            labels += [f"{task.name} edge {edge}" for edge in range(task.edge_count)]
            start = end
        return Inequalities(rows, room, np.array(levels, dtype=np.int64), labels), returns

    def _dq_bounds(self, q):
        """Per-DoF bounds on dq (nv each): the 1-DoF joint limits when the strategy enforces
        them (none and gpm leave them free, as on the SVD hierarchy), never requiring a
        start outside them to move further out, and velocity limits over dt; +-inf
        elsewhere."""
        robot = self.robot
        lower, upper = (robot.lower, robot.upper) if self.strategy.enforces_limits else \
            (self._no_position_limit_low, self._no_position_limit_high)
        return _joint_dq_bounds(q, robot.limited_q_index, robot.limited_v_index, lower,
                                upper, self._speed_bound, robot.model.nv)

    def _within_velocity_limits(self, solution, fixed_dq: np.ndarray) -> tuple:
        """(dq, factor): the solution under the 1-DoF joints' velocity limits over dt, lowest
        levels saturated first (module docstring, step 4); factor 1.0 when nothing is."""
        if self._speed_index is None:
            return solution.dq, 1.0
        level_steps = solution.level_steps  # None: no per-level shares, uniform scaling
        return _velocity_saturation(
            solution.dq, fixed_dq, self._no_level_steps if level_steps is None else level_steps,
            level_steps is not None, self._speed_index, self._inverse_speed_step)


@numba.njit(cache=True)
def _clamping_loop(jacobian, target, offsets, q, limit_indices, limit_table, groups, balls,
                   progressive, fixed, fixed_dq, h, damping, rank_tolerance, bound_lower,
                   bound_upper, cascades, cascade_state, revolute_v):
    """PIKSolver._clamping for DampedHierarchy, RevoluteLimits (the indices and table
    of limits.fix_joints), joint groups (swing.group_fix's arguments, or NO_GROUP) and
    spherical joints (swing.ball_fix's, or NO_BALL) in one call: each solution restarts
    from the previous one's levels (hierarchy.solve_compiled); fixed, fixed_dq and h (nv)
    are filled in place.
    bound_lower, bound_upper: QPHierarchy's bounds on dq (nv each; empty: none), with the
    damped 1-DoF joints (revolute_v: their v indices) bounded, not fixed (_damping_bounds).
    A solution whose
    levels leave them (first_level_out_of_bounds), or that starts outside them, is
    QPHierarchy's cascade (qp_hierarchy.cascade_compiled) when `cascades`, with
    cascade_state = (KeptActiveSets' four arrays, the hierarchy's counters, enforced
    (nv), cascade residuals (levels)) and the fixed and damped DoFs (`fixed`) as the key
    of its kept active sets, the next solution then a fresh one as after
    QPHierarchy.solve_stacked's cascade; the loop stops before the limit pass of a
    solution that leaves the bounds when not `cascades`, or when its cascade reaches a
    level whose hot start fails (ProxSuite's business).
    Returns (dq, level_steps, residuals, solutions kept, whether the last was kept and
    whether it was a cascade's, then the last solution's fixed joints, their variations,
    level bases, ranks and starts: hierarchy.restartable_solution's)."""
    nv, levels = jacobian.shape[1], len(offsets) - 1
    kept_keys, kept_sides, kept_known, kept_used, counters, enforced, cascade_residuals = \
        cascade_state
    level_bases = np.empty((levels, nv, nv))
    level_ranks = np.zeros(levels, dtype=np.int64)
    level_starts = np.empty((levels + 1, nv))
    level_steps, residuals = np.zeros((levels, nv)), np.zeros(levels)
    no_fixed, no_values = np.zeros(0, dtype=np.bool_), np.zeros(0)
    solved_fixed, solved_values = no_fixed, no_values   # none yet: a fresh solve
    solutions = 0
    lower, upper = bound_lower, bound_upper
    while True:
        if len(bound_lower):
            now_fixed, lower, upper = _damping_bounds(fixed, fixed_dq, h, revolute_v,
                                                      bound_lower, bound_upper)
        else:
            now_fixed = fixed.copy()
        values = np.where(now_fixed, fixed_dq, 0.0)
        dq = values
        if len(lower) and excludes_zero(now_fixed, lower, upper):
            first = -1              # QPHierarchy cascades at once, no unconstrained solve
        else:   # stops at the first level that leaves the bounds: the cascade's start
            dq, first = solve_compiled(jacobian, target, offsets, now_fixed, values,
                                       solved_fixed, solved_values, level_bases,
                                       level_ranks, level_starts, level_steps, residuals,
                                       damping, rank_tolerance, lower, upper)
        cascaded = first < levels
        if cascaded and cascades:
            enforced[:] = False
            cascade_residuals[:] = 0.0
            reached = cascade_compiled(
                jacobian, target, offsets, now_fixed, values, lower, upper, first,
                level_bases, level_ranks, level_starts, residuals, fixed, kept_keys,
                kept_sides, kept_known, kept_used, counters, True, enforced,
                cascade_residuals, damping, rank_tolerance)
            dq = reached[1]
        if cascaded and (not cascades or reached[0] < levels):
            if first >= 0:          # the rest of the unconstrained solution to restart from
                dq = solve_levels(jacobian, target, offsets, first,
                                  *level_start_state(first, now_fixed, values, level_bases,
                                                     level_ranks, level_starts,
                                                     rank_tolerance),
                                  level_steps, residuals, level_bases, level_ranks,
                                  level_starts, damping, rank_tolerance, now_fixed,
                                  no_values, no_values)[0]
            return (dq, level_steps, residuals, solutions, False, cascaded, now_fixed,
                    values, level_bases, level_ranks, level_starts)
        solutions += 1
        if not _fix_limits(q, dq, limit_indices, limit_table, groups, balls, progressive,
                           fixed, fixed_dq, h):
            return (dq, level_steps, cascade_residuals if cascaded else residuals, solutions,
                    True, cascaded, now_fixed, values, level_bases, level_ranks,
                    level_starts)
        solved_fixed, solved_values = (no_fixed, no_values) if cascaded else \
            (now_fixed, values)


@numba.njit(cache=True)
def _damping_bounds(fixed, fixed_dq, h, revolute_v, lower, upper):
    """(fixed as equalities, lower, upper) for the QP hierarchy: a 1-DoF joint the
    progressive clamping damped (0 < h < 1, revolute_v: the 1-DoF joints' v indices) is
    not fixed to its damped variation but bounded by it on the side it moves (the
    component toward its limit is damped, eq. 1-5): it may move less, or back, where the
    levels above need it to, which hard velocity bounds on the other joints could
    otherwise forbid (the CoM level then drifted with an arm stretched out of reach).
    Clamped joints (h = 1), and every other fixed DoF, stay equalities."""
    equal, low, high = fixed.copy(), lower.copy(), upper.copy()
    for v in revolute_v:
        if fixed[v] and 0.0 < h[v] < 1.0 and fixed_dq[v] != 0.0:
            equal[v] = False
            if fixed_dq[v] > 0.0:
                high[v] = min(high[v], fixed_dq[v])
            else:
                low[v] = max(low[v], fixed_dq[v])
    return equal, low, high


@numba.njit(cache=True)
def _fix_limits(q, dq, limit_indices, limit_table, groups, balls, progressive, fixed,
                fixed_dq, h):
    """The limit pass of PIKSolver._clamping, compiled: the 1-DoF joints', each joint
    group's and each spherical joint's decision written in place (fixed, fixed_dq, h: nv;
    the models' DoFs do not overlap, so the order is free); True if any DoF is fixed."""
    changed = fix_joints(q, dq, limit_indices, limit_table, progressive, fixed, fixed_dq,
                         h) > 0
    for group in groups:
        changed |= group_fix(group, q, dq, progressive, fixed, fixed_dq, h)
    for ball in balls:
        changed |= ball_fix(ball, q, dq, progressive, fixed, fixed_dq, h)
    return changed


@numba.njit(cache=True)
def _joint_dq_bounds(q, q_index, v_index, lower_limit, upper_limit, speed_bound, nv):
    """PIKSolver._dq_bounds in one compiled call: (lower, upper) on dq (nv each) from the
    1-DoF joints' limits (q_index, v_index, limits: per joint) at configuration q, 0 kept
    inside them, and |dq| <= speed_bound; +-inf for the other DoFs."""
    lower, upper = np.full(nv, -np.inf), np.full(nv, np.inf)
    for joint in range(len(q_index)):
        current = q[q_index[joint]]
        low = np.minimum(lower_limit[joint] - current, 0.0)
        high = np.maximum(upper_limit[joint] - current, 0.0)
        lower[v_index[joint]] = np.maximum(low, -speed_bound[joint])
        upper[v_index[joint]] = np.minimum(high, speed_bound[joint])
    return lower, upper


@numba.njit(cache=True)
def _velocity_saturation(dq, fixed_dq, level_steps, by_level, speed_index, inverse_speed_step):
    """PIKSolver._within_velocity_limits in one compiled call: (dq, factor) with
    |dq[speed_index]| * inverse_speed_step <= 1, levels (rows of level_steps, added to
    fixed_dq) saturated from the lowest when by_level, else dq scaled uniformly."""
    worst = np.max(np.abs(dq[speed_index] * inverse_speed_step))
    if worst <= 1.0:
        return dq, 1.0
    if not by_level or np.max(np.abs(fixed_dq[speed_index] * inverse_speed_step)) > 1.0:
        scale = 1.0 / worst
        return dq * scale, scale
    saturated = fixed_dq.copy()
    for level_step in level_steps:
        fraction = _largest_fraction(saturated[speed_index] * inverse_speed_step,
                                     level_step[speed_index] * inverse_speed_step)
        if fraction < 1.0:
            return saturated + fraction * level_step, fraction
        saturated += level_step
    return saturated, 1.0


@numba.njit(cache=True)
def _weighted_rows(jacobian, error, gain, group, cap, scale, target):
    """Scale the stacked Jacobian's rows by sqrt(weight) `scale` in place and write the
    scaled, capped steps of `error` into target (capped_steps)."""
    for row in range(len(scale)):
        if scale[row] != 1.0:
            for column in range(jacobian.shape[1]):
                jacobian[row, column] *= scale[row]
    capped_steps(error, gain, group, cap, scale, target)


@numba.njit(cache=True)
def _error_norms(error, task_starts, level_offsets, row_scale, norms):
    """norms = [|e| per task, |sqrt(w) e| per level] of the stacked error (task units), in
    place: numba boxes any returned array at a cost."""
    task_count = len(task_starts)
    norms[:] = 0.0
    task = -1
    for row in range(len(error)):
        while task + 1 < task_count and task_starts[task + 1] == row:
            task += 1
        norms[task] += error[row] * error[row]
    for level in range(len(level_offsets) - 1):
        for row in range(level_offsets[level], level_offsets[level + 1]):
            weighted = row_scale[row] * error[row]
            norms[task_count + level] += weighted * weighted
    for index in range(len(norms)):
        norms[index] = np.sqrt(norms[index])


@numba.njit(cache=True)
def _largest_fraction(used: np.ndarray, added: np.ndarray) -> float:
    """Largest s in [0, 1] with |used + s added| <= 1 everywhere, given |used| <= 1."""
    fraction = np.inf
    for i in range(len(used)):
        room = 1.0 - used[i] if added[i] > 0.0 else 1.0 + used[i]
        if abs(added[i]) > room:
            fraction = min(fraction, room / abs(added[i]))
    return min(fraction, 1.0)


@numba.njit(cache=True)
def _lm_scale_levels(jacobian, target, error, gain, row_scale, offsets, counted, damping,
                     lm_damping, returned, scale):
    """scale[k] = damping / lambda_k, lambda_k^2 = damping^2 + lm_damping |e_k|^2 with e_k
    level k's rows as `counted` says (LM_STEP: the target, LM_ERROR: sqrt(weight) x gain x
    error, uncapped) and the uncapped returns its inequality rows ask (returned[k]: the
    sum of their squares; empty: none; PIKSolver module docstring, step 2); level k's rows
    of jacobian and target multiplied by it (all in place)."""
    for level in range(len(offsets) - 1):
        square = returned[level] if len(returned) else 0.0
        for row in range(offsets[level], offsets[level + 1]):
            if counted[row] == LM_STEP:
                square += target[row] * target[row]
            elif counted[row] == LM_ERROR:
                uncapped = row_scale[row] * gain[row] * error[row]
                square += uncapped * uncapped
        scale[level] = 1.0 if square == 0.0 else \
            damping / math.sqrt(damping * damping + lm_damping * square)
        if scale[level] < 1.0:
            for row in range(offsets[level], offsets[level + 1]):
                target[row] *= scale[level]
                for column in range(jacobian.shape[1]):
                    jacobian[row, column] *= scale[level]


@numba.njit(cache=True)
def _level_residuals(jacobian, target, offsets, dq) -> np.ndarray:
    """|J dq - target| of each stacked level (task units)."""
    residuals = np.zeros(len(offsets) - 1)
    for level in range(len(residuals)):
        for row in range(offsets[level], offsets[level + 1]):
            residual = target[row]
            for joint in range(len(dq)):
                residual -= jacobian[row, joint] * dq[joint]
            residuals[level] += residual * residual
    return np.sqrt(residuals)


HIERARCHIES = ("svd", "qp")


def _with_shortfalls(step_residuals, inequalities, dq) -> np.ndarray:
    """Each level's step residual (of its rows as solved: scaled by its LM factor) with
    the shortfall its own inequality rows have after dq, max(0, rows dq - room) times
    their weight (the same factor), added in quadrature: a support level's CoM left
    outside its polygon is not met."""
    residuals = np.array(step_residuals, dtype=float)
    shortfalls = inequalities.row_weights() * np.maximum(
        inequalities.rows @ dq - inequalities.room, 0.0)
    squares = np.zeros(len(residuals))
    np.add.at(squares, inequalities.level, shortfalls ** 2)
    return np.sqrt(residuals ** 2 + squares)


def _with_violated_rows(jacobian, target, offsets, inequalities) -> tuple:
    """(jacobian, target, offsets) with each level's violated inequality rows (room < 0:
    the CoM outside an edge, asked back by -room this step) among its rows, as equalities
    rows dq = room times their weight (scaled as the level's rows are):
    _level_condition then judges a support level by what its step asks, as any other."""
    violated = inequalities.room < 0.0
    weight = inequalities.row_weights()
    weighted_rows = weight[:, None] * inequalities.rows
    weighted_room = weight * inequalities.room
    rows, targets, sizes = [], [], []
    for level in range(len(offsets) - 1):
        own = violated & (inequalities.level == level)
        rows += [jacobian[offsets[level]:offsets[level + 1]], weighted_rows[own]]
        targets += [target[offsets[level]:offsets[level + 1]], weighted_room[own]]
        sizes.append(offsets[level + 1] - offsets[level] + int(own.sum()))
    return (np.vstack(rows), np.concatenate(targets),
            np.concatenate([[0], np.cumsum(sizes)]).astype(offsets.dtype))


_NO_RETURNS = np.zeros(0)       # _lm_scale_levels' returns without inequality rows
# _clamping_loop's cascade_state (QPHierarchy.cascade_state) for a hierarchy without cascades
_NO_CASCADE_STATE = empty_cascade_state(0, 0, np.zeros(1, dtype=np.int64))


def _level_condition(problem, level, step_residual) -> str:
    """LevelReport.condition of a level of problem = (stacked rows and targets, each level
    scaled by its LM factor, level offsets, damping^2, the factors, held), which the
    hierarchy left with this step residual (of the scaled rows). held = (the DoFs the
    clamping loop fixed and their variations, the bounds on dq: (lower, upper) or the call
    that makes them (PIKSolver._dq_bounds), the step residuals before velocity saturation
    or None when nothing saturated)."""
    jacobian, target, offsets, damping_sq, scale, held = problem
    rows = jacobian[offsets[level]:offsets[level + 1]]
    wanted = target[offsets[level]:offsets[level + 1]]
    met = max(MET_RELATIVE * float(np.linalg.norm(wanted)), MET_ABSOLUTE)
    if step_residual <= met:
        return "met"
    factor = scale[level]
    alone = _damped_least_squares(rows, wanted, damping_sq * factor * factor)  # lambda: damping
    if float(np.linalg.norm(rows @ alone - wanted)) > met:
        return "singular"
    fixed, fixed_dq, bounds, unsaturated = held
    if factor == 1.0 or (unsaturated is not None and step_residual > unsaturated[level] + met):
        return "conflict"           # ... or the velocity limits took part of its step
    # LM damping on: would the levels above (as solved) and the fixed DoFs leave it its step
    # at lambda = damping, within the bounds on dq (joint and velocity limits)? Then its
    # own damping is what holds the step back, else they take it too
    index = np.flatnonzero(fixed)
    end = offsets[level + 1]
    prefix_jacobian, prefix_target = jacobian[:end].copy(), target[:end].copy()
    prefix_jacobian[offsets[level]:end] /= factor
    prefix_target[offsets[level]:end] /= factor
    prefix = DampedHierarchy(damping=math.sqrt(damping_sq)).solve_stacked(
        prefix_jacobian, prefix_target, offsets[:level + 2], index, fixed_dq[index])
    lower, upper = bounds() if callable(bounds) else bounds
    free = ~fixed
    within = np.all(prefix.dq[free] >= lower[free] - BINDING_TOLERANCE) and \
        np.all(prefix.dq[free] <= upper[free] + BINDING_TOLERANCE)
    return "damped" if within and prefix.step_residuals[level] <= met / factor else "conflict"


def make_hierarchy(hierarchy, robot, damping: float, dt: float | None):
    """A hierarchy object from its name (see PIKSolver; None = svd); objects pass through."""
    if hierarchy is not None and not isinstance(hierarchy, str):
        return hierarchy
    if hierarchy in (None, "svd"):
        return DampedHierarchy(damping=damping)
    if hierarchy == "qp":
        return QPHierarchy.for_robot(robot, dt=dt, damping=damping)
    raise ValueError(f"unknown hierarchy {hierarchy!r} (expected one of {', '.join(HIERARCHIES)})")


def _locked_dofs(robot, names) -> np.ndarray:
    """Velocity indices of the named joints (RobotModelError: unknown, repeated, or the
    free-flyer base)."""
    for position, name in enumerate(names):
        if not robot.model.existJointName(name):
            raise RobotModelError(f"locked_joints[{position}]: unknown joint {name!r}")
        if name in names[:position]:
            raise RobotModelError(f"locked_joints[{position}]: {name!r} named twice")
        if robot.model.getJointId(name) not in robot.actuated_joint_ids:
            raise RobotModelError(f"locked_joints[{position}]: {name!r} is the free-flyer "
                                  "base, which the IK always moves")
    return robot.velocity_indices(names)


def _append_levels(jacobian, target, offsets, levels):
    """Stacked arrays with `levels` appended as the lowest priorities."""
    jacobian = np.vstack([jacobian, *(level.jacobian for level in levels)])
    target = np.concatenate([target, *(level.target for level in levels)])
    ends = offsets[-1] + np.cumsum([len(level.target) for level in levels])
    return jacobian, target, np.concatenate([offsets, ends]).astype(np.int64)


DATA = Path(__file__).parent / "data"
DEMO_STACK_FILE = DATA / "talos_demo_stack.yaml"


def demo_stack_file(robot_name: str) -> Path | None:
    """The shipped demo stack of a robot (talos, mannequin), or None."""
    path = DATA / f"{robot_name}_demo_stack.yaml"
    return path if path.is_file() else None


def default_stack_specs() -> list:
    """The Talos demo stack: feet fixed > CoM over the feet > right hand > posture."""
    return parse_stack_yaml(DEMO_STACK_FILE.read_text())
