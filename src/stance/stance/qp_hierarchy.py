"""Strict task priorities under bounds on dq: a cascade of small QPs (hot-started active
sets, ProxSuite as their fallback).

Same levels and damping as DampedHierarchy, plus bounds lower <= dq <= upper (rad or m:
joint limits, velocity limits over one step, progressive clamping's damped variations)
and, per level, inequality rows (Inequalities, e.g. a support polygon's edges: see
QPHierarchy._row_cascade; the rest of this docstring is the bounds-only cascade). Level i
works in the orthonormal basis Z (nv x k) of what the fixed DoFs and levels 0..i-1 leave
free, dq = dq_prev + Z y:

    minimize |P y - r|^2 + lambda^2 |y|^2
    subject to lower_b - dq_prev_b <= Z_b y <= upper_b - dq_prev_b   (bounded free DoFs b)

with P = J_i Z and r = t_i - J_i dq_prev. Lower levels then move in Z' = Z null(P)
(DampedHierarchy's nullspace update), so J_i dq, hence level i's residual, never changes:
the standard cascade's "keep J_i dq = J_i dq_i*" without equality rows, robust to
rank-deficient levels. The start (fixed variations, 0 elsewhere clipped into the bounds)
is feasible and y = 0 stays feasible, so no level is ever infeasible: a contradictory or
out-of-reach level is met in the least-squares sense within the bounds and its residual
is reported.

Per level, the unconstrained damped least squares y is kept when it respects the bounds:
the result is then DampedHierarchy's (to rounding). So DampedHierarchy's compiled solve
comes first, and when every level's dq respects the bounds (most steps: progressive
clamping keeps joints off their limits) its solution is the answer, restart state
included (a re-solve of the clamping loop then restarts where it can); the cascade below
runs only when a level crosses a bound, from that level on (the levels above are the
unconstrained solve's). It is compiled (numba: cascade_compiled) but for ProxSuite and the
exact active-set fallback, and PIKSolver's compiled clamping loop runs it in the same call
as long as the hot starts below find their KKT points.

A level that crosses a bound is first polished from its hot start, the active set it
ended with last time (kept by DoF, per level and per key, by default the fixed DoFs: the
clamping loop's solutions of one step fix or damp different joints, and each changes
little from the one that fixed and damped the same joints a step before). The polish
solves the problem with the active bounds as equalities exactly (nullspace method on a
pivoted QR of the active rows, Q kept as its reflections, the damped least squares in
their nullspace) and keeps the result when it is a KKT point: no bound violated (the
active ones to rounding), multipliers of the right sign (or, at a degenerate vertex where
more bounds are tight than the set's rank, the kept set's step or y = 0 certified by NNLS
over all of them).
Otherwise it corrects the set by Goldfarb and Idnani's dual method (the wrong-sign
bounds leave until the set is dual feasible, then the most violated bound joins by
partial steps that keep every multiplier's sign, a dependent one replacing the bound
their ratio rule names) a bounded number of times. The KKT point is unique (the
objective is strictly convex), so the result does not depend on where the polish
started, to within the multiplier tolerance (MULTIPLIER_SLACK); toward the bit, a
certified step is solved once more on every bound it is on (at a degenerate vertex several
active sets certify it, and each gives the point to rounding). Which bounds count as on
it can still follow the path in the last bits: a solver with a history and a fresh one
given the same input agree to rounding (Talos, a hand sent 0.6 m: 5 of 600 steps differed,
by at most 5e-14 rad), while the same input and the same kept sets give the same bits.

Where the hot start fails (or there is none) a persistent ProxSuite dense QP (one per
level and size) is updated and warm-started from its previous result, cold started when
that fails, to eps_abs 1e-9 within a bounded number of iterations (outer and inner:
ProxSuite's max_iter alone caps only the outer ones, and a warm start once ran 4,500 inner
iterations, 120 ms). Its duals seed the polish; where that finds no KKT point either, an
exact primal active-set method from y = 0 gives the level's step. The active set found is
kept for the next hot start, and the compiled cascade solves the level again from it, so
that a level's step comes out of the same code whichever way its active set was found
(where that re-solve finds no KKT point, the step found is kept).
"""

from __future__ import annotations

import weakref
from typing import NamedTuple

import numba
import numpy as np
from proxsuite import proxqp

from .hierarchy import (REORDERING, DampedHierarchy, HierarchySolution, Level,
                        _damped_least_squares, _free_axes, _nullspace_update,
                        _sparse_rows_product, _times, excludes_zero,
                        first_level_out_of_bounds, level_start_state, stack_levels)

QP_TOLERANCE = 1e-9          # ProxSuite eps_abs (eps_rel 0), task and dq units
# ProxSuite iterations: outer (max_iter) and inner per outer (max_iter_in). The polish only
# needs the active set, so a bounded solve costs less than waiting for 1e-9 on the
# degenerate bound sets of a clamped posture level (many bounds of zero width).
WARM_MAX_ITERATIONS = 10     # a warm start needing more is abandoned for a cold start
COLD_MAX_ITERATIONS = 100
INNER_MAX_ITERATIONS = 10
FEASIBILITY_SLACK = 1e-12    # rad or m: polished y may exceed a bound by this much
MULTIPLIER_SLACK = 1e-12     # relative to |gradient|: tolerated wrong-sign multiplier; it can
#                              move the optimum by up to itself / damping^2 where only the
#                              damping weighs (1e-9 let two certified answers differ by 6e-4)
POLISH_ROUNDS = 48           # active set corrections tried by the polish
ACTIVE_SET_ITERATIONS = 4    # x (variables + bound rows): cap of the exact active-set solve
STEP_TOLERANCE = 1e-13       # relative: an active-set step this small is a stationary point
BINDING_TOLERANCE = 1e-9     # rad or m: a dq this close to a bound is on it
RANK_RELATIVE = 1e-12        # active bound rows: a pivoted QR remainder (polish) or singular
#                              value (exact active-set solve) below this x the largest drops
MOVABLE_ROW_NORM = 1e-12     # a DoF whose basis row is below this cannot move any more
MAX_CACHED_QPS = 64          # persistent QPs kept (level, variables, bound rows)
MAX_KEPT_SETS = 16           # fixed-DoF patterns whose active sets are kept
NO_KKT_POINT, CERTIFIED, FREE = 0, 1, 2  # level outcomes: _polish's two, no bound crossed


def robot_dof_names(robot) -> list:
    """A name per velocity DoF: base_x .. base_rz for a free flyer, the joint name for a
    1-DoF joint, joint_0 .. joint_{n-1} for other multi-DoF joints."""
    model = robot.model
    names = [""] * model.nv
    for joint_id in range(1, model.njoints):
        joint, name = model.joints[joint_id], model.names[joint_id]
        if robot.floating_base and joint_id == 1:
            axes = [f"base_{axis}" for axis in ("x", "y", "z", "rx", "ry", "rz")]
        elif joint.nv == 1:
            axes = [name]
        else:
            axes = [f"{name}_{axis}" for axis in range(joint.nv)]
        names[joint.idx_v:joint.idx_v + joint.nv] = axes
    return names


def robot_velocity_steps(robot, dt: float | None) -> np.ndarray:
    """Largest |dq| per velocity DoF allowed by the URDF velocity limits over dt seconds
    (rad or m); inf where there is none or dt is None."""
    steps = np.full(robot.model.nv, np.inf)
    if dt is not None:
        usable = robot.velocity_limit > 0
        steps[robot.limited_v_index[usable]] = robot.velocity_limit[usable] * dt
    return steps


class Inequalities(NamedTuple):
    """Rows of the levels' inequalities rows @ dq <= room (task units, e.g. m), each
    declared by one level: that level meets it as well as it can (the square of its
    violation, times weight^2, joins the level's objective), and every level below keeps it
    as that level left it (no further out). Where the levels' damped least squares steps
    keep every row from its level on, they are the answer (QPHierarchy._row_cascade)."""

    rows: np.ndarray     # m x nv
    room: np.ndarray     # m
    level: np.ndarray    # m, int64: the level that declares the row
    labels: list         # m names for the binding report, e.g. "balance edge 0"
    weight: np.ndarray | None = None   # m, > 0: the violation's weight in its level's
    #                                    objective (None: 1; PIKSolver: the level's LM factor)

    def row_weights(self) -> np.ndarray:
        """weight, ones where it is None."""
        if self.weight is None:
            return np.ones(len(self.room))
        return np.asarray(self.weight, dtype=float)


class KeptActiveSets(NamedTuple):
    """The active sets cascades ended with, per level, for up to MAX_KEPT_SETS keys (slots):
    a key is a pattern of DoFs, by default the fixed ones. The clamping loop's solutions of
    one step fix or damp different joints, and each is most like the one that fixed and
    damped the same joints a step before: it keys its solves by both (on the QP hierarchy
    a damped joint is bounded, not fixed, so its fixed DoFs alone do not tell the step's
    solutions apart, and each started from the other's set)."""

    keys: np.ndarray     # slots x nv, bool: the key of the slot's solves
    sides: np.ndarray    # slots x levels x nv, int8: +1 upper, -1 lower, 0 inactive
    known: np.ndarray    # slots x levels, bool: whether the level has one
    used: np.ndarray     # slots, int64: when the slot was last used (0: empty), later larger

    @classmethod
    def empty(cls, level_count: int, nv: int) -> KeptActiveSets:
        return cls(np.zeros((MAX_KEPT_SETS, nv), dtype=np.bool_),
                   np.zeros((MAX_KEPT_SETS, level_count, nv), dtype=np.int8),
                   np.zeros((MAX_KEPT_SETS, level_count), dtype=np.bool_),
                   np.zeros(MAX_KEPT_SETS, dtype=np.int64))


def empty_cascade_state(level_count: int, nv: int, counters) -> tuple:
    """QPHierarchy.cascade_state's tuple for problems of this shape, no active set kept:
    KeptActiveSets' four arrays, the counters, enforced (bool, nv), residuals (levels)."""
    return (*KeptActiveSets.empty(level_count, nv), counters, np.zeros(nv, dtype=np.bool_),
            np.zeros(level_count))


# cascade_compiled's unconstrained solution state when there is none
_NO_LEVEL_BASES, _NO_LEVEL_STARTS = np.zeros((0, 0, 0)), np.zeros((0, 0))
_NO_LEVEL_RANKS, _NO_RESIDUALS = np.zeros(0, dtype=np.int64), np.zeros(0)


class QPHierarchy:
    """Prioritized damped least squares with inequality bounds on dq (see module docstring).

    damping, rank_tolerance: as DampedHierarchy's (the two agree when no bound binds).
    dof_names: a name per velocity DoF for the binding constraint report (default dof<i>).
    velocity_steps: |dq| bound per DoF from velocity limits (rad or m, inf if none); a bound
        equal to it is reported as "<dof> velocity" rather than "<dof> lower/upper".
    hot_start: a level whose bounds cross first tries the active set it ended with last
        time (certified by its KKT conditions, so the answer does not depend on it beyond
        MULTIPLIER_SLACK); off, every such level starts from ProxSuite.
    """

    uses_bounds = True
    uses_inequalities = True   # solve_stacked takes the levels' Inequalities

    def __init__(self, damping: float = 1e-3, rank_tolerance: float = 1e-9, dof_names=None,
                 velocity_steps=None, hot_start: bool = True):
        self.hot_start = hot_start
        self.damping = damping
        self.rank_tolerance = rank_tolerance
        self.dof_names = None if dof_names is None else list(dof_names)
        self.velocity_steps = None if velocity_steps is None else np.asarray(velocity_steps,
                                                                             dtype=float)
        self.unconstrained = DampedHierarchy(damping, rank_tolerance)  # kept where it fits
        self._qps = {}
        # ProxSuite objects still alive when the interpreter exits make nanobind report
        # them as leaks: drop them first (atexit runs before modules are torn down)
        weakref.finalize(self, self._qps.clear)
        self.qp_solves = 0        # levels ProxSuite solved (hot start failed or off)
        self.cold_starts = 0      # of which warm start failed or no QP of that size existed
        self.unpolished = 0       # of which the polish found no KKT point (solved exactly)
        self.unconverged = 0      # of which the exact solve ran out of iterations: its step
        #                           is feasible but not shown optimal
        self.qp_iterations = 0    # ProxSuite's inner iterations, warm and cold solves
        self._counters = np.zeros(2, dtype=np.int64)  # [hot starts, polish solves], filled
        #                                               when compiled
        self._bound_labels = []   # "<dof> lower|upper|velocity", 3 per DoF (_binding_codes)
        self.forget_starts()      # no kept start yet

    @classmethod
    def for_robot(cls, robot, dt: float | None = None, **options) -> QPHierarchy:
        """A QPHierarchy naming the robot's DoFs and its velocity bounds over dt (s)."""
        return cls(dof_names=robot_dof_names(robot),
                   velocity_steps=robot_velocity_steps(robot, dt), **options)

    def solve(self, levels, nv: int, fixed_index=(), fixed_dq=(), bounds=None):
        """Solve Level objects in order (see DampedHierarchy.solve); bounds: (lower, upper)."""
        return self.solve_stacked(*stack_levels(levels, nv), fixed_index, fixed_dq, bounds)

    def solve_stacked(self, jacobian, target, offsets, fixed_index=(), fixed_dq=(),
                      bounds=None, previous=None, inequalities=None,
                      kept_key=None) -> HierarchySolution:
        """Levels stacked by stack_levels(); fixed DoFs dq[fixed_index] = fixed_dq come first,
        then bounds = (lower, upper) per DoF (nv each, +-inf where unbounded) on the others
        (a free DoF whose bounds exclude 0 starts on the nearer one) and the levels'
        Inequalities, if any. previous: as for DampedHierarchy.solve_stacked (used when it
        came from the unconstrained solve). kept_key: bool (nv), which kept active sets a
        cascade hot-starts from and keeps (KeptActiveSets; default: the fixed DoFs)."""
        nv = jacobian.shape[1]
        free = np.ones(nv, dtype=bool)
        free[np.asarray(fixed_index, dtype=int)] = False
        lower, upper = _checked_bounds(bounds, nv)
        level_count, fixed = len(offsets) - 1, ~free
        key = fixed if kept_key is None else np.asarray(kept_key, dtype=bool).reshape(nv)
        if inequalities is not None and not len(inequalities.room):
            inequalities = None
        if inequalities is not None:
            _check_inequalities(inequalities, nv, level_count)
        if excludes_zero(fixed, lower, upper):  # 0 is out: no level is kept
            if inequalities is not None:
                return self._row_cascade(jacobian, target, offsets, fixed_index, fixed_dq,
                                         lower, upper, inequalities, key)
            return self._cascade(jacobian, target, offsets, fixed_index, fixed_dq, free,
                                 lower, upper, key)
        # a restart keeps the previous solution's levels above its restart level (their
        # starts without the newly fixed joints' values, which their rows ignore): the
        # first level out is sought among them too, since the bounds may be new
        solution = self.unconstrained.solve_stacked(jacobian, target, offsets, fixed_index,
                                                    fixed_dq, previous=previous)
        first = self._first_level_out(solution.restart.level_starts, fixed, lower, upper,
                                      inequalities)
        if first == level_count:
            return solution
        if inequalities is not None:
            return self._row_cascade(jacobian, target, offsets, fixed_index, fixed_dq, lower,
                                     upper, inequalities, key, solution, first)
        return self._cascade(jacobian, target, offsets, fixed_index, fixed_dq, free, lower,
                             upper, key, solution, first)

    @staticmethod
    def _first_level_out(level_starts, fixed, lower, upper, inequalities):
        """The first level whose dq leaves the bounds or an inequality row
        (first_level_out_of_bounds, _first_level_out_of_rows), the level count if none."""
        first = first_level_out_of_bounds(level_starts, fixed, lower, upper)
        if inequalities is None:
            return first
        return min(first, _first_level_out_of_rows(level_starts, inequalities))

    def _row_cascade(self, jacobian, target, offsets, fixed_index, fixed_dq, lower, upper,
                     inequalities, key, unconstrained=None, first=0) -> HierarchySolution:
        """The cascade with inequality rows: from level 0, or from `first` of the
        unconstrained solution, whose levels above it keep the bounds and rows. Compiled
        (_row_levels), but for the levels whose hot start fails, which ProxSuite solves
        here (_qp_rows_step); active sets kept per level and key (bool, nv), by DoF and by
        row, as the bounds-only cascade keeps them."""
        nv, level_count = jacobian.shape[1], len(offsets) - 1
        fixed, values = np.zeros(nv, dtype=bool), np.zeros(nv)
        fixed[np.asarray(fixed_index, dtype=int)] = True
        values[np.asarray(fixed_index, dtype=int)] = fixed_dq
        residuals = np.zeros(level_count)
        if unconstrained is None:
            first = 0
            dq = np.where(fixed, values, np.minimum(np.maximum(0.0, lower), upper))
            basis = _free_axes(fixed)
        else:
            state = unconstrained.restart
            dq, basis = level_start_state(first, fixed, values, state.level_bases,
                                          state.level_ranks, state.level_starts,
                                          self.rank_tolerance)
            dq = dq.copy()
            residuals[:first] = unconstrained.step_residuals[:first]
        bounded = np.flatnonzero(~fixed & (np.isfinite(lower) | np.isfinite(upper)))
        enforced = np.zeros(nv, dtype=bool)
        room = inequalities.room.copy()   # relaxed to what each declaring level left
        row_level = inequalities.level.copy()   # a row out of reach leaves the inequalities
        kept = self._kept_row_sets(level_count, nv, len(room))
        slot = _kept_slot(key, *kept)
        sides, known = kept.sides[slot], kept.known[slot]
        if not self.hot_start:
            known[:] = False
        weight = inequalities.row_weights()
        level, given_step = first, np.zeros(0)
        while True:
            level, basis, problem = _row_levels(
                jacobian, target, offsets, level, dq, basis, bounded, lower, upper,
                inequalities.rows, room, weight, row_level, sides, known, enforced,
                residuals, self._counters, self.damping, self.rank_tolerance, given_step)
            if level == level_count:
                break
            design, goal, constraint, low, high, dofs, declared = problem
            given_step, active, upper_side = self._qp_rows_step(level, design, goal,
                                                                constraint, low, high)
            _remember_rows(sides[level], nv, dofs, declared, active, upper_side)
            known[level] = True
        reach = inequalities.rows @ dq
        binding = self._binding_names(dq, enforced, lower, upper) + [
            label for label, row_reach, row_room in zip(inequalities.labels, reach,
                                                        inequalities.room)
            if row_reach >= row_room - BINDING_TOLERANCE]
        return HierarchySolution(dq=dq, step_residuals=residuals, binding=binding)

    def _kept_row_sets(self, level_count: int, nv: int, row_count: int) -> KeptActiveSets:
        """The row cascade's kept active sets: sides per DoF, then per inequality row
        (emptied when the shape changes: a new stack or polygon)."""
        kept = self._row_kept
        if kept is None or kept.sides.shape[1:] != (level_count, nv + row_count) or \
                kept.keys.shape[1] != nv:
            kept = self._row_kept = KeptActiveSets(
                np.zeros((MAX_KEPT_SETS, nv), dtype=np.bool_),
                np.zeros((MAX_KEPT_SETS, level_count, nv + row_count), dtype=np.int8),
                np.zeros((MAX_KEPT_SETS, level_count), dtype=np.bool_),
                np.zeros(MAX_KEPT_SETS, dtype=np.int64))
        return kept

    def _cascade(self, jacobian, target, offsets, fixed_index, fixed_dq, free, lower, upper,
                 key, unconstrained=None, first=0):
        """The level by level solve of the module docstring (free: bool (nv), the DoFs not
        in fixed_index; lower, upper: bounds (nv each); key: the kept active sets' (bool,
        nv)): compiled (cascade_compiled), but
        for the levels whose hot start fails, which ProxSuite solves here. unconstrained:
        DampedHierarchy's solution of the same problem, whose levels before `first` stay
        within the bounds (first_level_out_of_bounds): the cascade keeps them and starts
        at `first` from that solution's state."""
        nv, level_count = jacobian.shape[1], len(offsets) - 1
        values = np.zeros(nv)
        values[np.asarray(fixed_index, dtype=int)] = fixed_dq
        cascade_state = self.cascade_state(level_count, nv)
        enforced, residuals = np.zeros(nv, dtype=bool), np.zeros(level_count)
        state = None if unconstrained is None else unconstrained.restart
        level, dq, basis, projected, residual, bounded, slot = cascade_compiled(
            jacobian, target, offsets, ~free, values, lower, upper,
            -1 if state is None else first,
            *((_NO_LEVEL_BASES, _NO_LEVEL_RANKS, _NO_LEVEL_STARTS, _NO_RESIDUALS)
              if state is None else (state.level_bases, state.level_ranks,
                                     state.level_starts, unconstrained.step_residuals)),
            key, *cascade_state[:5], self.hot_start, enforced, residuals, self.damping,
            self.rank_tolerance)
        kept = KeptActiveSets(*cascade_state[:4])
        self._active_sides, self._known_sides = kept.sides[slot], kept.known[slot]
        while level < level_count:
            given_step, given_dofs = self._qp_level_step(level, projected, residual, basis,
                                                         dq, bounded, lower, upper)
            level, basis, projected, residual = _cascade_levels(
                jacobian, target, offsets, level, dq, basis, bounded, lower, upper,
                self._active_sides, self._known_sides, enforced, residuals, self._counters,
                self.damping, self.rank_tolerance, given_step, given_dofs)
        return self.cascade_solution(dq, residuals, enforced, lower, upper)

    def cascade_solution(self, dq, residuals, enforced, lower, upper) -> HierarchySolution:
        """The HierarchySolution of a cascade that ended with dq and these level residuals,
        naming the bounds of the `enforced` DoFs (bool, nv) that dq is on."""
        return HierarchySolution(dq=dq, step_residuals=residuals,
                                 binding=self._binding_names(dq, enforced, lower, upper))

    def cascade_state(self, level_count: int, nv: int) -> tuple:
        """What cascade_compiled reads and updates in place for problems of this shape:
        the KeptActiveSets' four arrays (emptied when the shape changes: a new stack), the
        counters, then scratch arrays for a compiled caller's cascades: enforced DoFs
        (bool, nv) and level residuals (levels)."""
        if KeptActiveSets(*self._cascade_state[:4]).sides.shape[1:] != (level_count, nv):
            self._cascade_state = empty_cascade_state(level_count, nv, self._counters)
        return self._cascade_state

    def warm_up(self) -> None:
        """Compile (or load from numba's disk cache) the cascade's kernels, by a throwaway
        hierarchy solving a small problem whose bounds bind (first through ProxSuite, then
        hot-started): compiling takes seconds, which a real-time loop must not pay at the
        first step where a bound binds."""
        scratch = QPHierarchy(self.damping, self.rank_tolerance)
        levels = [Level(np.eye(2), np.ones(2)), Level(np.ones((1, 2)), np.full(1, -1.0))]
        bounds = (np.full(2, -0.1), np.full(2, 0.1))
        for _ in range(2):
            scratch.solve(levels, 2, fixed_index=np.zeros(0, dtype=np.int64),
                          fixed_dq=np.zeros(0), bounds=bounds)

    def forget_starts(self) -> None:
        """Drop every kept start (the active sets of every key, the row cascade's, and
        ProxSuite's QPs): the next solves start as a fresh hierarchy's, e.g. after a step
        the caller discarded. The counters go on counting."""
        self._qps.clear()
        self._cascade_state = empty_cascade_state(0, 0, self._counters)
        self._active_sides = np.zeros((0, 0), dtype=np.int8)  # levels x nv: the cascade's
        self._known_sides = np.zeros(0, dtype=np.bool_)       # slot of the kept sets
        self._row_kept = None     # KeptActiveSets of the row cascade (_kept_row_sets)

    @property
    def hot_starts(self) -> int:
        """Levels whose bounds crossed, solved from the level's previous active set."""
        return int(self._counters[0])

    @property
    def polish_solves(self) -> int:
        """Equality-constrained solves of the polish (_polish: one per active set it
        tries), from hot starts and ProxSuite's duals alike: 1 per polish where the kept
        set is the answer."""
        return int(self._counters[1])

    def _qp_level_step(self, level, projected, residual, basis, dq, bounded, lower, upper):
        """(y, DoFs of the active bounds) of a level whose hot start failed
        (_qp_rows_step); the active set is kept."""
        dofs, rows, low, high = _level_bounds(basis, dq, bounded, lower, upper)
        step, active, upper_side = self._qp_rows_step(level, projected, residual, rows, low,
                                                      high)
        _remember(self._active_sides[level], dofs, active, upper_side)
        self._known_sides[level] = True
        return step, dofs[active]

    def _qp_rows_step(self, level, projected, residual, rows, low, high):
        """(y, active row mask, upper-side mask) minimizing |P y - r|^2 + lambda^2 |y|^2
        subject to low <= rows y <= high (0 feasible): ProxSuite's QP, its duals polished,
        or the exact active-set method where the polish certifies no KKT point."""
        slack = _multiplier_slack(projected, residual)
        hessian = projected.T @ projected
        hessian[np.diag_indices_from(hessian)] += self.damping * self.damping
        dual = self._qp_solve(level, hessian, -(projected.T @ residual), rows, low,
                              high).results.z
        step, active, upper_side, status = _polish(
            projected, residual, self.damping, rows, low, high,
            *_signed_start(dual, slack, low, high), slack, self._counters)
        if status != CERTIFIED:  # ProxSuite's answer is not certified: solve exactly instead
            self.unpolished += 1
            step, active, upper_side, converged = _active_set_solve(
                projected, residual, self.damping, rows, low, high)
            self.unconverged += not converged
        return step, active, upper_side

    def _qp_solve(self, level, hessian, gradient, rows, low, high):
        """The level's persistent ProxSuite QP of this size, solved: warm start from its
        previous result, cold start if there is none or it fails."""
        self.qp_solves += 1
        key = (level, *rows.shape)
        qp = self._qps.get(key)
        if qp is not None:
            qp.update(H=hessian, g=gradient, C=rows, l=low, u=high)
            qp.solve()
            self.qp_iterations += qp.results.info.iter
            if qp.results.info.status == proxqp.QPSolverOutput.PROXQP_SOLVED:
                return qp
        self.cold_starts += 1
        if len(self._qps) >= MAX_CACHED_QPS:
            self._qps.clear()
        qp = self._qps[key] = _new_qp(rows.shape)
        qp.init(hessian, gradient, None, None, rows, low, high)
        qp.solve()
        self.qp_iterations += qp.results.info.iter
        qp.settings.initial_guess = proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
        qp.settings.max_iter = WARM_MAX_ITERATIONS
        return qp

    def with_damping_bounds(self, names: list, dofs) -> list:
        """names (a solution's binding) with '<dof> lower|upper' of these DoFs renamed
        '<dof> damped': their bound was a damped variation of progressive clamping
        (pik._damping_bounds), not a joint or velocity limit."""
        labels = self._bound_labels
        if not len(labels):
            return names            # no DoF bound named yet: none to rename
        renamed = {labels[3 * dof + side]: labels[3 * dof].rsplit(" ", 1)[0] + " damped"
                   for dof in dofs for side in (0, 1)}
        return [renamed.get(name, name) for name in names]

    def _binding_names(self, dq, enforced, lower, upper) -> list:
        """'<dof> lower|upper|velocity' for each bound a level's QP enforced that dq is on."""
        nv = len(dq)
        steps = np.full(nv, np.nan) if self.velocity_steps is None else self.velocity_steps
        if len(self._bound_labels) != 3 * nv:
            names = self.dof_names or [f"dof{dof}" for dof in range(nv)]
            self._bound_labels = [f"{name} {kind}" for name in names
                                  for kind in ("lower", "upper", "velocity")]
        return [self._bound_labels[code]
                for code in _binding_codes(dq, enforced, lower, upper, steps).tolist()]


@numba.njit(cache=True)
def _binding_codes(dq, enforced, lower, upper, velocity_steps):
    """3 dof + (0 lower, 1 upper, 2 velocity: |bound| is the DoF's velocity step) for each
    bound of an enforced DoF that dq is on (within BINDING_TOLERANCE), lower first."""
    codes = np.empty(2 * len(dq), dtype=np.int64)
    count = 0
    for dof in range(len(dq)):
        if not enforced[dof]:
            continue
        for side in range(2):
            bound = upper[dof] if side else lower[dof]
            if abs(dq[dof] - bound) > BINDING_TOLERANCE:
                continue
            codes[count] = 3 * dof + (2 if abs(bound) == velocity_steps[dof] else side)
            count += 1
    return codes[:count]


def _check_inequalities(inequalities, nv: int, level_count: int) -> None:
    """ValueError unless the Inequalities fit nv DoFs and level_count levels, finite."""
    rows, room, level = inequalities.rows, inequalities.room, inequalities.level
    count = len(room)
    if rows.shape != (count, nv) or level.shape != (count,) or \
            len(inequalities.labels) != count:
        raise ValueError(f"inequalities: {count} rows need rows {count} x {nv}, one level "
                         "and one label each")
    if not (np.all(np.isfinite(rows)) and np.all(np.isfinite(room))):
        raise ValueError("inequalities contain NaN or infinite values")
    weight = inequalities.weight
    if weight is not None and (np.shape(weight) != (count,) or
                               not np.all(np.isfinite(weight) & (weight > 0.0))):
        raise ValueError(f"inequalities: {count} rows need one finite weight > 0 each")
    if np.any((level < 0) | (level >= level_count)):
        raise ValueError(f"inequality levels must be in 0..{level_count - 1}")


def _first_level_out_of_rows(level_starts, inequalities) -> int:
    """The first level whose dq (level_starts: (levels + 1) x nv, the start then each
    level's result) leaves an inequality row of its own or of a level above, the level
    count if none: each row must hold at the end of its level and of every level after."""
    outside = inequalities.rows @ level_starts.T > inequalities.room[:, None]
    outside &= np.arange(level_starts.shape[0]) > inequalities.level[:, None]
    found = outside.any(axis=1)
    if not found.any():
        return level_starts.shape[0] - 1
    return int(np.argmax(outside[found], axis=1).min()) - 1   # the level that left it


def _checked_bounds(bounds, nv: int):
    """(lower, upper) as float arrays, +-inf without bounds; lower <= upper required."""
    if bounds is None:
        return np.full(nv, -np.inf), np.full(nv, np.inf)
    lower, upper = (np.asarray(side, dtype=float).reshape(nv) for side in bounds)
    if not _ordered(lower, upper):
        raise ValueError("dq bounds need lower <= upper (no NaN)")
    return lower, upper


@numba.njit(cache=True)
def _ordered(lower, upper):
    """lower <= upper everywhere (False where either is NaN)."""
    for dof in range(len(lower)):
        if not lower[dof] <= upper[dof]:
            return False
    return True


@numba.njit(cache=True, fastmath=REORDERING)
def cascade_compiled(jacobian, target, offsets, fixed, values, lower, upper, first,
                     level_bases, level_ranks, level_starts, unconstrained_residuals, key,
                     kept_keys, kept_sides, kept_known, kept_used, counters, hot_start,
                     enforced, residuals, damping, rank_tolerance):
    """QPHierarchy._cascade in one compiled call, up to the first level whose hot start
    fails (no kept active set, or no KKT point from it), with the fixed DoFs (bool, nv)
    at `values` (nv, 0 where free): from level 0 when first < 0, else from level `first`
    of an unconstrained solution (solve_compiled's level_bases, level_ranks and
    level_starts, its residuals), whose levels before it are kept. The kept active sets
    (KeptActiveSets' arrays; those of `key`, bool nv, hot-start), the counters,
    `enforced` (bool, nv: DoFs whose bounds a level enforced) and `residuals` (levels)
    are updated in place.
    Returns (the level reached, the level count when all are solved; dq, and the basis,
    P and r that level starts from; the bounded free DoFs; the kept set's slot)."""
    if first < 0:
        first = 0
        dq = np.minimum(np.maximum(0.0, lower), upper)
        for dof in range(len(fixed)):
            if fixed[dof]:
                dq[dof] = values[dof]
        basis = _free_axes(fixed)
    else:
        dq, basis = level_start_state(first, fixed, values, level_bases, level_ranks,
                                      level_starts, rank_tolerance)
        residuals[:first] = unconstrained_residuals[:first]
    bounded = np.flatnonzero(~fixed & (np.isfinite(lower) | np.isfinite(upper)))
    slot = _kept_slot(key, kept_keys, kept_sides, kept_known, kept_used)
    if not hot_start:
        kept_known[slot] = False
    level, basis, projected, residual = _cascade_levels(
        jacobian, target, offsets, first, dq, basis, bounded, lower, upper, kept_sides[slot],
        kept_known[slot], enforced, residuals, counters, damping, rank_tolerance, np.zeros(0),
        np.zeros(0, dtype=np.int64))
    return level, dq, basis, projected, residual, bounded, slot


@numba.njit(cache=True)
def _kept_slot(key, kept_keys, kept_sides, kept_known, kept_used):
    """The slot of KeptActiveSets (its arrays, updated in place) for solves with this key
    (bool, nv), marked as the one used last. A new key takes an empty slot, else the least
    recently used one, and starts from a copy of the sets used last."""
    last = np.argmax(kept_used)
    for slot in range(len(kept_used)):
        if kept_used[slot] > 0 and np.array_equal(kept_keys[slot], key):
            if slot != last:
                kept_used[slot] = kept_used[last] + 1
            return slot
    slot = np.argmin(kept_used)
    if kept_used[last] > 0:
        kept_sides[slot] = kept_sides[last]
        kept_known[slot] = kept_known[last]
    kept_keys[slot] = key
    kept_used[slot] = kept_used[last] + 1
    return slot


def _new_qp(shape):
    """A dense ProxSuite QP with inequality rows only, set for a cold solve."""
    bound_rows, variables = shape
    qp = proxqp.dense.QP(variables, 0, bound_rows)
    qp.settings.eps_abs = QP_TOLERANCE
    qp.settings.eps_rel = 0.0
    qp.settings.max_iter = COLD_MAX_ITERATIONS
    qp.settings.max_iter_in = INNER_MAX_ITERATIONS
    qp.settings.verbose = False
    return qp


@numba.njit(cache=True, fastmath=REORDERING)
def _cascade_levels(jacobian, target, offsets, level, dq, basis, bounded, lower, upper,
                    active_sides, known_sides, enforced, residuals, counters, damping,
                    rank_tolerance, given_step, given_dofs):
    """QPHierarchy._cascade's levels from `level` on, dq, enforced, residuals, the kept
    active sets and counters (hot starts, polish solves) updated in place, until a level's
    hot start fails (no kept active set, or no KKT point from it). given_step: `level`'s step when
    QPHierarchy solved it (empty otherwise), given_dofs: the DoFs of its active bounds;
    the level is solved again from the active set kept then, so that its step is computed
    by the same code whether it came from ProxSuite or from a hot start (the same bits for
    the same input), and given_step is the fallback.
    Returns (that level, or the level count when all are solved; the basis it starts
    from, its projected rows P and residual r: what QPHierarchy solves it from)."""
    level_count = len(offsets) - 1
    while level < level_count:
        rows = jacobian[offsets[level]:offsets[level + 1]]
        wanted = target[offsets[level]:offsets[level + 1]]
        if basis.shape[1] > 0 and rows.shape[0] > 0:
            projected = _sparse_rows_product(rows, basis)
            residual = wanted - _times(rows, dq)
            step, status = _level_step(projected, residual, basis, dq, bounded, lower, upper,
                                       active_sides[level], known_sides[level], enforced,
                                       damping, counters)
            if status == NO_KKT_POINT:
                if not len(given_step):   # the caller's ProxSuite keeps a new set: the
                    known_sides[level] = False   # failed one is not polished again first
                    return level, basis, projected, residual
                step = given_step
                enforced[given_dofs] = True
            elif status == CERTIFIED and not len(given_step):
                counters[0] += 1
            given_step = given_step[:0]
            dq += _times(basis, step)
            if level < level_count - 1:
                basis = _nullspace_update(projected, basis, rank_tolerance)
        missed = wanted - _times(rows, dq)
        residuals[level] = np.sqrt(np.sum(missed * missed))
        level += 1
    return level, basis, np.zeros((0, 0)), np.zeros(0)


@numba.njit(cache=True, fastmath=REORDERING)
def _row_levels(jacobian, target, offsets, level, dq, basis, bounded, lower, upper, rows,
                room, weight, row_level, sides, known, enforced, residuals, counters, damping,
                rank_tolerance, given_step):
    """QPHierarchy._row_cascade's levels from `level` on, dq, room (own rows relaxed to
    what their level left), the kept sides (levels x (nv + rows): +1 upper, -1 lower, 0)
    and known flags, enforced, residuals and counters updated in place, until a level's
    hot start fails. Per level, variables y and a slack w per own row (w = shortfall + w',
    0 feasible) minimize |P y - r|^2 + |weight w|^2 + lambda^2 (|y|^2 + |w'|^2) subject to the
    DoF bounds, the rows of the levels above within their room and the own rows minus w
    within theirs: the damped least squares step where it keeps them all (DampedHierarchy's
    step), else the polish from the kept active set. given_step: `level`'s step when
    QPHierarchy solved it, polished again from the set kept then (the same code either
    way), else kept as it is.
    An own row the level leaves beyond its room (out of reach, by more than
    BINDING_TOLERANCE) becomes an equality of the levels below, as the level's equality
    rows do (the basis loses its direction; row_level is set past the last level): every
    dq keeping the level's optimum has the same shortfall on it, and as an inequality kept
    exactly tight it made the levels below degenerate (a polygon out of reach: ProxSuite
    solved 1.6-2 levels per step, cold, where the hot starts now hold).
    Returns (that level, or the level count when all are solved; the basis it starts
    from; its problem (_row_level_problem) for QPHierarchy to solve)."""
    level_count, nv = len(offsets) - 1, len(dq)
    while level < level_count:
        equalities = jacobian[offsets[level]:offsets[level + 1]]
        wanted = target[offsets[level]:offsets[level + 1]]
        variables = basis.shape[1]
        if variables > 0:
            projected = _sparse_rows_product(equalities, basis) if equalities.shape[0] > 0 \
                else np.zeros((0, variables))
            problem = _row_level_problem(projected, wanted - _times(equalities, dq), basis,
                                         dq, bounded, lower, upper, rows, room, weight,
                                         row_level, level)
            design, goal, constraint, low, high, dofs, declared = problem
            step = _damped_least_squares(design, goal, damping * damping) \
                if design.shape[0] > 0 else np.zeros(design.shape[1])
            reach = _times(constraint, step)
            if not np.all((reach >= low) & (reach <= high)):
                side = sides[level]
                signs = np.empty(len(dofs) + len(declared), dtype=np.int8)
                for index in range(len(dofs)):
                    signs[index] = side[dofs[index]]
                for index in range(len(declared)):
                    signs[len(dofs) + index] = side[nv + declared[index]]
                active, upper_side = _signed_start(signs, 0, low, high)
                status = NO_KKT_POINT
                if known[level]:
                    polished, active, upper_side, status = _polish(
                        design, goal, damping, constraint, low, high, active, upper_side,
                        _multiplier_slack(design, goal), counters)
                if status == CERTIFIED:
                    step = polished
                    _remember_rows(side, nv, dofs, declared, active, upper_side)
                    if not len(given_step):
                        counters[0] += 1
                elif len(given_step):
                    step = given_step
                else:
                    known[level] = False
                    return level, basis, problem
                for index in range(len(dofs)):
                    if active[index]:
                        enforced[dofs[index]] = True
            given_step = given_step[:0]
            dq += _times(basis, step[:variables])
            if level < level_count - 1 and equalities.shape[0] > 0:
                basis = _nullspace_update(projected, basis, rank_tolerance)
        out_of_reach = np.zeros(len(room), dtype=np.bool_)
        for row in range(len(room)):
            if row_level[row] == level:
                reach = 0.0
                for dof in range(nv):
                    reach += rows[row, dof] * dq[dof]
                out_of_reach[row] = reach > room[row] + BINDING_TOLERANCE
                room[row] = max(room[row], reach)
        if np.any(out_of_reach) and level < level_count - 1 and basis.shape[1] > 0:
            frozen = np.flatnonzero(out_of_reach)
            basis = _nullspace_update(_sparse_rows_product(rows[frozen], basis), basis,
                                      rank_tolerance)
            row_level[frozen] = level_count     # equalities now: in no lower level's rows
        missed = wanted - _times(equalities, dq)
        residuals[level] = np.sqrt(np.sum(missed * missed))
        level += 1
    return level, basis, (np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0)), np.zeros(0),
                          np.zeros(0), np.zeros(0, dtype=np.int64),
                          np.zeros(0, dtype=np.int64))


@numba.njit(cache=True, fastmath=REORDERING)
def _row_level_problem(projected, residual, basis, dq, bounded, lower, upper, rows, room,
                       weight, row_level, level):
    """One level of _row_levels as (design, goal, constraint, low, high, dofs, declared):
    minimize |design x - goal|^2 + lambda^2 |x|^2, x = (y, w'), subject to low <=
    constraint x <= high; constraint rows: the movable bounded DoFs (dofs), then the rows
    declared by this level or above (declared, row indices), own rows with -1 on their
    slack."""
    dofs, bound_rows, bound_low, bound_high = _level_bounds(basis, dq, bounded, lower, upper)
    declared = np.flatnonzero(row_level <= level)
    slacks = int(np.sum(row_level == level))
    equalities, variables, nv = projected.shape[0], basis.shape[1], len(dq)
    design = np.zeros((equalities + slacks, variables + slacks))
    design[:equalities, :variables] = projected
    goal = np.zeros(equalities + slacks)
    goal[:equalities] = residual
    count = len(dofs) + len(declared)
    constraint = np.zeros((count, variables + slacks))
    constraint[:len(dofs), :variables] = bound_rows
    low, high = np.full(count, -np.inf), np.empty(count)
    low[:len(dofs)] = bound_low
    high[:len(dofs)] = bound_high
    slack = 0
    for index in range(len(declared)):
        row, position = declared[index], len(dofs) + index
        reach = 0.0
        for dof in range(nv):
            if rows[row, dof] != 0.0:
                reach += rows[row, dof] * dq[dof]
                for column in range(variables):
                    constraint[position, column] += rows[row, dof] * basis[dof, column]
        left = room[row] - reach
        high[position] = max(left, 0.0)
        if row_level[row] == level:
            constraint[position, variables + slack] = -1.0
            design[equalities + slack, variables + slack] = weight[row]
            goal[equalities + slack] = -weight[row] * max(-left, 0.0)
            slack += 1
    return design, goal, constraint, low, high, dofs, declared


@numba.njit(cache=True)
def _remember_rows(side, nv, dofs, declared, active, upper_side):
    """Keep a row cascade level's active set in `side` (nv sides per DoF, then one per
    inequality row: +1 upper, -1 lower, 0 inactive) from the masks over its constraint
    rows (dofs, then the declared rows)."""
    side[:] = 0
    for index in range(len(dofs)):
        if active[index]:
            side[dofs[index]] = 1 if upper_side[index] else -1
    for index in range(len(declared)):
        position = len(dofs) + index
        if active[position]:
            side[nv + declared[index]] = 1 if upper_side[position] else -1

@numba.njit(cache=True, fastmath=REORDERING)
def _level_step(projected, residual, basis, dq, bounded, lower, upper, active_side, known,
                enforced, damping, counters):
    """(y, FREE) when the level's damped least squares step keeps within the bounds (the
    ones a QP left a hair outside not further out), (y, CERTIFIED) when the polish from the
    level's kept active set (active_side: +1 upper, -1 lower, 0 inactive per DoF; known:
    whether there is one) finds the KKT point, which is then kept; else (_, NO_KKT_POINT).
    counters: the hierarchy's (the polish counts its solves)."""
    step = _damped_least_squares(projected, residual, damping * damping)
    dofs, rows, low, high = _level_bounds(basis, dq, bounded, lower, upper)
    reach = rows @ step
    if np.all((reach >= low) & (reach <= high)):
        return step, FREE
    if not known:
        return step, NO_KKT_POINT
    step, active, upper_side, status = _polish(projected, residual, damping, rows, low, high,
                                               *_signed_start(active_side[dofs], 0, low, high),
                                               _multiplier_slack(projected, residual), counters)
    if status == CERTIFIED:
        _remember(active_side, dofs, active, upper_side)
        enforced[dofs[active]] = True
    return step, status


@numba.njit(cache=True, fastmath=REORDERING)
def _level_bounds(basis, dq, bounded, lower, upper):
    """(dofs, rows, low, high): the bounded DoFs the level can still move (basis row above
    MOVABLE_ROW_NORM), their basis rows and the room left to their bounds, never
    excluding 0 (y = 0 stays feasible: a DoF a QP left a hair outside may not go further
    out)."""
    count = 0
    dofs = np.empty(len(bounded), dtype=np.int64)
    for dof in bounded:             # scalar loops: no temporary array per DoF
        square = 0.0
        for column in range(basis.shape[1]):
            square += basis[dof, column] * basis[dof, column]
        if np.sqrt(square) > MOVABLE_ROW_NORM:
            dofs[count] = dof
            count += 1
    dofs = dofs[:count]
    rows = np.empty((count, basis.shape[1]))
    low, high = np.empty(count), np.empty(count)
    for index in range(count):
        dof = dofs[index]
        rows[index] = basis[dof]
        low[index] = min(lower[dof] - dq[dof], 0.0)
        high[index] = max(upper[dof] - dq[dof], 0.0)
    return dofs, rows, low, high


@numba.njit(cache=True)
def _multiplier_slack(projected, residual):
    """Tolerated wrong-sign multiplier: MULTIPLIER_SLACK x (1 + |P^T r|_inf)."""
    gradient = np.ascontiguousarray(projected.T) @ residual
    return MULTIPLIER_SLACK * (1.0 + (np.max(np.abs(gradient)) if len(gradient) else 0.0))


@numba.njit(cache=True)
def _signed_start(signs, threshold, low, high):
    """(active, upper side) row masks a polish starts from: the rows whose sign estimate
    (ProxSuite's multiplier, or a kept side +-1) is above threshold with a finite upper
    bound, or below -threshold with a finite lower one."""
    upper_side = (signs > threshold) & np.isfinite(high)
    return upper_side | ((signs < -threshold) & np.isfinite(low)), upper_side


@numba.njit(cache=True)
def _remember(active_side, dofs, active, upper_side):
    """Keep a level's active set by DoF (+1 upper, -1 lower, 0 inactive): the next
    problem of that level may have other rows."""
    active_side[:] = 0
    for index in range(len(dofs)):
        if active[index]:
            active_side[dofs[index]] = 1 if upper_side[index] else -1


@numba.njit(cache=True, fastmath=REORDERING)
def _polish(projected, residual, damping, rows, low, high, active, upper_side, slack,
            counters):
    """Exact solution of the level's QP from an active set of bounds: (y, active row mask,
    upper-side mask, status), status CERTIFIED when the KKT conditions hold (no bound
    violated, multipliers of the right sign within `slack`, by NNLS on a degenerate
    vertex), else NO_KKT_POINT. Goldfarb and Idnani's dual method, started from `active`
    / `upper_side`: the bounds whose multipliers have the wrong sign (or that dependent
    active rows make miss their value) leave, one at a time, until the set is dual
    feasible; then the most violated bound joins, by partial steps along which every
    multiplier keeps its sign (a bound whose multiplier reaches zero first leaves; where
    the joining row depends on the active ones, the bound _leaving_bound names). The
    objective rises at every step, so no set repeats (swapping the most violated bound
    and the worst multiplier in turn cycled: 9 in 10 hot starts failed on Talos' hands
    reaching out, some from the very optimal set). Each solve minimizes in the nullspace
    of its rows, in index order (_on_active_rows), at most POLISH_ROUNDS of them, each
    counted in counters[1] (the hierarchy's polish solves)."""
    active, upper_side = active.copy(), upper_side.copy()
    signed = np.zeros(len(low))     # multipliers, positive when right (active rows' only)
    step, solves = np.zeros(projected.shape[1]), 0
    while True:                     # a dual feasible start: wrong-sign bounds leave
        if solves == POLISH_ROUNDS:
            return step, active, upper_side, NO_KKT_POINT
        solves += 1
        counters[1] += 1
        index = np.flatnonzero(active)
        value = np.where(upper_side[index], high[index], low[index])
        active_rows = np.ascontiguousarray(rows[index])
        step, multiplier, factorization, _ = _on_active_rows(projected, residual, damping,
                                                             active_rows, value, -1)
        dependent = factorization[3][factorization[4]:]   # the rows past the rank, which
        missed = dependent[np.abs(active_rows[dependent] @ step - value[dependent])
                           > FEASIBILITY_SLACK]           # the solve did not impose
        if len(missed):             # dependent active rows that disagree: not a vertex
            active[index[missed]] = False
            continue
        side = np.where(upper_side[index], 1.0, -1.0)
        signed[:] = 0.0
        signed[index] = multiplier * side
        if len(index) == 0 or np.min(signed[index]) >= -slack:
            break
        rank = factorization[4]
        if solves == 1:             # the kept set's multipliers are not all right: its step
            #                         may be a degenerate vertex all the same, or y = 0
            #                         (always feasible) may be the optimum
            for trial, reach, trial_rank in ((step, rows @ step, rank),
                                             (np.zeros_like(step), np.zeros(len(low)), 0)):
                if not _within_bounds(reach, low, high):
                    continue
                certified, on, on_upper = _certifying_tight_rows(
                    projected, residual, damping, rows, low, high, reach, trial, trial_rank,
                    slack)
                if certified:
                    return _on_tight_rows(projected, residual, damping, rows, low, high,
                                          reach, trial, on, on_upper)
        if rank < len(index):       # dependent rows that agree leave: y stays, and the
            active[index[factorization[3][rank:]]] = False   # set is independent
            continue
        active[index[np.argmin(signed[index])]] = False
    while True:                     # the most violated bound joins, until none is
        reach = rows @ step
        excess = np.maximum(reach - high, low - reach)
        rounding = FEASIBILITY_SLACK * (1.0 + np.max(np.abs(step)))
        for row in range(len(excess)):  # the rows solved on miss theirs by rounding only
            if active[row] and excess[row] <= rounding:     # (1e-11 on a step of 1e5)
                excess[row] = -np.inf
        joining = np.argmax(excess)
        if excess[joining] <= FEASIBILITY_SLACK:
            return _on_tight_rows(projected, residual, damping, rows, low, high, reach,
                                  step, active, upper_side)
        if active[joining]:
            return step, active, upper_side, NO_KKT_POINT  # active rows in conflict
        upper_side[joining] = reach[joining] > high[joining]
        normal = (1.0 if upper_side[joining] else -1.0) * rows[joining]   # outward
        while True:                 # steps toward the joining bound
            if solves == POLISH_ROUNDS:
                return step, active, upper_side, NO_KKT_POINT
            solves += 1
            counters[1] += 1
            index = np.flatnonzero(active)
            active[joining] = True  # solved with it, in index order
            members = np.flatnonzero(active)
            active[joining] = False
            position = np.searchsorted(members, joining)
            value = np.where(upper_side[members], high[members], low[members])
            target, multiplier, _, target_led = _on_active_rows(
                projected, residual, damping, np.ascontiguousarray(rows[members]), value,
                position)
            others = members != joining
            side = np.where(upper_side[index], 1.0, -1.0)
            if target_led:          # the joining row depends on the (independent) active
                #                     ones, which keep it violated: a dual step
                own = _pivoted_qr(np.ascontiguousarray(rows[index].T), -1)
                leaving, share = _leaving_bound(own, normal, signed[index] * side, side)
                if leaving < 0:
                    return step, active, upper_side, NO_KKT_POINT
                signed[index] -= signed[index[leaving]] / share[leaving] * share
                signed[index[leaving]] = 0.0
                active[index[leaving]] = False
                continue
            target_signed = multiplier[others] * side
            fraction, leaving = 1.0, -1       # the largest step keeping every sign
            for i in range(len(index)):
                falling = signed[index[i]] - target_signed[i]
                if target_signed[i] < 0.0 and falling > 0.0:
                    ratio = signed[index[i]] / falling
                    if ratio < fraction:
                        fraction, leaving = ratio, i
            if leaving < 0:         # a full step: the joining bound holds
                step = target
                signed[members] = multiplier * np.where(upper_side[members], 1.0, -1.0)
                active[joining] = True
                break
            step = step + fraction * (target - step)
            signed[index] += fraction * (target_signed - signed[index])
            signed[index[leaving]] = 0.0
            active[index[leaving]] = False


@numba.njit(cache=True)
def _within_bounds(reach, low, high):
    """Whether every bound holds within FEASIBILITY_SLACK."""
    return np.all((reach - high <= FEASIBILITY_SLACK) & (low - reach <= FEASIBILITY_SLACK))


@numba.njit(cache=True)
def _tight(reach, low, high):
    """(tight, on the upper side) row masks: the bounds that rows reaching `reach` are on,
    within FEASIBILITY_SLACK (the upper one first)."""
    on_upper = (np.abs(reach - high) <= FEASIBILITY_SLACK) & np.isfinite(high)
    return on_upper | ((np.abs(reach - low) <= FEASIBILITY_SLACK) & np.isfinite(low)), on_upper


@numba.njit(cache=True, fastmath=REORDERING)
def _certifying_tight_rows(projected, residual, damping, rows, low, high, reach, step,
                           rank, slack):
    """(certified, active, upper_side) for a feasible step (reaching `reach`) that the set
    it was solved on (of this rank; 0 for y = 0) does not certify: at a degenerate vertex,
    more bounds tight than that rank (a level held at y = 0 by more bounds than it has
    variables, or dependent rows), the multipliers are not unique, and the descent g - H y
    may be a nonnegative combination of the tight bounds' outward normals (NNLS within
    `slack`) although the set's own multipliers have a wrong sign; active, upper_side: the
    row masks of its bounds of positive multiplier, the set that certifies it. With no
    more bounds tight than the rank, the multipliers are unique: not certified. A nearly
    dependent kept set (smallest singular value 1e-6) gave multipliers of 1e9 and a step
    of 1e4 where y = 0 was the optimum, and the dual method dropped and added back its 19
    bounds one by one."""
    tight, on_upper = _tight(reach, low, high)
    index = np.flatnonzero(tight)
    fitting = np.zeros(len(low), dtype=np.bool_)
    if len(index) <= rank:
        return False, fitting, on_upper
    normals = np.empty((rows.shape[1], len(index)))   # outward, as columns
    for column in range(len(index)):
        sign = 1.0 if on_upper[index[column]] else -1.0
        for variable in range(rows.shape[1]):
            normals[variable, column] = sign * rows[index[column], variable]
    multipliers, missed = _nonnegative_fit(normals, _descent(projected, residual, damping,
                                                             step), slack)
    fitting[index[multipliers > 0.0]] = True
    return missed <= slack, fitting, on_upper & fitting


@numba.njit(cache=True, fastmath=REORDERING)
def _on_tight_rows(projected, residual, damping, rows, low, high, reach, step, active,
                   upper_side):
    """The certified step of _polish, made independent of the active set that certified
    it: at a degenerate vertex several sets do (ProxSuite's duals gave two fresh solvers
    two of them, and steps 3e-14 apart). Every bound the step is on (within
    FEASIBILITY_SLACK; the upper one first) holds at the optimum, so the optimum on all
    of them as equalities is the same point: solved again on them, unless they are the
    set the step already came from. The active bounds count as tight however far rounding
    left the step from them (1e-11 on a step of 1e5). Returns _polish's tuple with the
    certifying set (the better hot start: the tight set's extra rows would only have to
    leave again)."""
    tight, on_upper = _tight(reach, low, high)
    on_upper |= active & upper_side & ~tight
    tight |= active
    if np.array_equal(tight, active) and \
            np.array_equal(on_upper, upper_side & active):
        return step, active, upper_side, CERTIFIED
    index = np.flatnonzero(tight)
    value = np.where(on_upper[index], high[index], low[index])
    step = _on_active_rows(projected, residual, damping, np.ascontiguousarray(rows[index]),
                           value, -1)[0]
    return step, active, upper_side, CERTIFIED


@numba.njit(cache=True, fastmath=REORDERING)
def _on_active_rows(projected, residual, damping, active_rows, value, leading):
    """argmin |P y - r|^2 + damping^2 |y|^2 subject to active_rows y = value (least squares
    on dependent rows), by the nullspace method on a pivoted QR of active_rows^T (row
    `leading` pivoted first if >= 0 and the rows are dependent: the ones it conflicts
    with are then the dependent ones; independent rows give the same point either way):
    y = Q (t, z), t from R11^T t = the kept rows' values, z the damped least squares of
    (P Q)_2 z = r - (P Q)_1 t (_damped_least_squares; Q applied by its reflectors, never
    formed). Returns (y, one set of multipliers mu with active_rows^T mu = g - H y,
    H = P^T P + damping^2 I and g = P^T r, the factorization of _pivoted_qr, whether
    `leading` led it)."""
    variables = projected.shape[1]
    transposed = np.ascontiguousarray(active_rows.T)
    factorization = _pivoted_qr(transposed, -1)
    led = leading >= 0 and factorization[4] < len(value)
    if led:
        factorization = _pivoted_qr(transposed, leading)
    triangular, order, rank = factorization[2], factorization[3], factorization[4]
    kept = value[order[:rank]]
    coordinates = np.zeros(variables)   # (t, z): y in the basis of Q's columns
    for i in range(rank):               # R11^T t = kept
        acc = kept[i]
        for p in range(i):
            acc -= triangular[p, i] * coordinates[p]
        coordinates[i] = acc / triangular[i, i]
    if rank < variables:
        rotated = _transposed_q_rows(factorization, projected)    # (P Q)^T
        wanted = residual.copy()
        for i in range(rank):
            for row in range(len(wanted)):
                wanted[row] -= rotated[i, row] * coordinates[i]
        coordinates[rank:] = _damped_least_squares(np.ascontiguousarray(rotated[rank:].T),
                                                   wanted, damping * damping)
    step = _q_times(factorization, coordinates)
    multiplier = np.zeros(len(value))
    multiplier[order[:rank]] = _basic_solution(factorization,
                                               _descent(projected, residual, damping, step))
    return step, multiplier, factorization, led


@numba.njit(cache=True, fastmath=REORDERING)
def _descent(projected, residual, damping, step):
    """g - H y of the level's QP (H = P^T P + damping^2 I, g = P^T r) at y = step: what the
    active rows' multipliers must balance."""
    descent = -damping * damping * step
    for row in range(projected.shape[0]):
        missed = residual[row]
        for c in range(len(step)):
            missed -= projected[row, c] * step[c]
        for c in range(len(step)):
            descent[c] += projected[row, c] * missed
    return descent


@numba.njit(cache=True, fastmath=REORDERING)
def _leaving_bound(factorization, joining, multiplier, side):
    """(index, share): index (into the active rows of a _pivoted_qr factorization, their
    multipliers and sides +-1) of the bound that a joining one replaces when its outward
    normal `joining` depends on the active rows (Goldfarb and Idnani's dual step): with joining =
    sum_i c_i side_i (side_i row_i), the one of least lambda_i / (c_i side_i) over
    c_i side_i > 0, lambda_i = multiplier_i side_i (the first multiplier that raising the
    joining one's drives to 0); -1 when joining is independent of the active rows (none
    has to leave) or no c_i side_i is positive; share: the c_i side_i, by which the dual
    step moves the multipliers. Without it, two dependent bounds that cannot both hold
    replace each other in turn until the polish gives up."""
    order, rank = factorization[3], factorization[4]
    outside = _transposed_q_times(factorization, joining)[rank:]
    if np.sqrt(np.sum(outside * outside)) > RANK_RELATIVE * np.sqrt(np.sum(joining * joining)):
        return -1, np.zeros(len(side))
    coefficients = np.zeros(len(side))
    coefficients[order[:rank]] = _basic_solution(factorization, joining)
    share = coefficients * side
    threshold = RANK_RELATIVE * np.max(np.abs(share)) if len(share) else 0.0
    leaving, least = -1, np.inf
    for i in range(len(side)):
        if share[i] > threshold:
            ratio = multiplier[i] * side[i] / share[i]
            if ratio < least:
                leaving, least = i, ratio
    return leaving, share


@numba.njit(cache=True, fastmath=REORDERING)
def _pivoted_qr(matrix, leading):
    """Householder QR with column pivoting, matrix[:, order] = Q R, Q = H_0 ... H_{rank-1}
    kept as its reflections H_j = I - scale_j v_j v_j^T: (reflectors (rank x n, v_j zero
    before entry j), scales, R (n x s, upper triangular in its first rank rows), order,
    rank); column `leading` first if >= 0, then the largest remaining; a column whose
    remaining norm is at most RANK_RELATIVE x the largest column norm ends the rank."""
    n, columns = matrix.shape
    factor = matrix.copy()
    order = np.arange(columns)
    norms = np.zeros(columns)
    largest = 0.0
    for c in range(columns):
        acc = 0.0
        for i in range(n):
            acc += factor[i, c] * factor[i, c]
        largest = max(largest, acc)
    reflectors = np.zeros((min(n, columns), n))
    scales = np.zeros(min(n, columns))
    rank = 0
    for j in range(min(n, columns)):
        for c in range(j, columns):
            acc = 0.0
            for i in range(j, n):
                acc += factor[i, c] * factor[i, c]
            norms[c] = acc
        pivot = j + np.argmax(norms[j:])
        if j == 0 and leading >= 0 and norms[leading] > RANK_RELATIVE ** 2 * largest:
            pivot = leading
        if norms[pivot] == 0.0 or norms[pivot] <= RANK_RELATIVE * RANK_RELATIVE * largest:
            break
        if pivot != j:
            for i in range(n):
                factor[i, j], factor[i, pivot] = factor[i, pivot], factor[i, j]
            order[j], order[pivot] = order[pivot], order[j]
        length = np.sqrt(norms[pivot])
        alpha = -length if factor[j, j] >= 0.0 else length
        reflector = reflectors[j]
        reflector[j:] = factor[j:, j]
        reflector[j] -= alpha
        scale = 2.0 / (norms[pivot] - 2.0 * alpha * factor[j, j] + alpha * alpha)
        scales[j] = scale
        for c in range(j, columns):
            acc = 0.0
            for i in range(j, n):
                acc += reflector[i] * factor[i, c]
            acc *= scale
            for i in range(j, n):
                factor[i, c] -= acc * reflector[i]
        rank += 1
    return reflectors[:rank], scales[:rank], factor, order, rank


@numba.njit(cache=True, fastmath=REORDERING)
def _q_times(factorization, vector):
    """Q vector for a _pivoted_qr factorization: its reflections, the last first."""
    reflectors, scales = factorization[0], factorization[1]
    result = vector.copy()
    for j in range(len(scales) - 1, -1, -1):
        _reflect(reflectors[j], scales[j], j, result)
    return result


@numba.njit(cache=True, fastmath=REORDERING)
def _transposed_q_times(factorization, vector):
    """Q^T vector for a _pivoted_qr factorization: its reflections, the first first."""
    reflectors, scales = factorization[0], factorization[1]
    result = vector.copy()
    for j in range(len(scales)):
        _reflect(reflectors[j], scales[j], j, result)
    return result


@numba.njit(cache=True, fastmath=REORDERING)
def _transposed_q_rows(factorization, matrix):
    """Q^T matrix^T (n x rows) for a _pivoted_qr factorization: each reflection a rank-one
    update over contiguous rows, on a copy (ascontiguousarray returns the caller's memory
    where matrix.T is C-contiguous already: a one-row or a Fortran-ordered matrix)."""
    reflectors, scales = factorization[0], factorization[1]
    result = matrix.T.copy()
    combination = np.empty(result.shape[1])
    for j in range(len(scales)):
        reflector = reflectors[j]
        combination[:] = 0.0
        for i in range(j, result.shape[0]):
            for column in range(result.shape[1]):
                combination[column] += reflector[i] * result[i, column]
        for i in range(j, result.shape[0]):
            weight = scales[j] * reflector[i]
            for column in range(result.shape[1]):
                result[i, column] -= weight * combination[column]
    return result


@numba.njit(cache=True, fastmath=REORDERING)
def _reflect(reflector, scale, start, vector):
    """vector <- (I - scale v v^T) vector in place, v = reflector (zero before `start`)."""
    acc = 0.0
    for i in range(start, len(vector)):
        acc += reflector[i] * vector[i]
    acc *= scale
    for i in range(start, len(vector)):
        vector[i] -= acc * reflector[i]


@numba.njit(cache=True, fastmath=REORDERING)
def _basic_solution(factorization, rhs):
    """x (rank) with R11 x = Q1^T rhs: the least-squares coefficients of rhs on the first
    `rank` pivoted columns of a _pivoted_qr factorization."""
    triangular, rank = factorization[2], factorization[4]
    x = _transposed_q_times(factorization, rhs)[:rank].copy()
    for i in range(rank - 1, -1, -1):
        acc = x[i]
        for p in range(i + 1, rank):
            acc -= triangular[i, p] * x[p]
        x[i] = acc / triangular[i, i]
    return x


@numba.njit(cache=True, fastmath=REORDERING)
def _nonnegative_fit(matrix, rhs, tolerance):
    """(x, |matrix x - rhs|) minimizing |matrix x - rhs| over x >= 0 (Lawson-Hanson NNLS;
    iterations capped)."""
    columns = matrix.shape[1]
    x = np.zeros(columns)
    passive = np.zeros(columns, dtype=np.bool_)
    for _ in range(3 * columns):
        dual = np.ascontiguousarray(matrix.T) @ (rhs - matrix @ x)
        entering, best = -1, tolerance
        for c in range(columns):
            if not passive[c] and dual[c] > best:
                entering, best = c, dual[c]
        if entering < 0:
            break
        passive[entering] = True
        for _ in range(3 * columns):
            index = np.flatnonzero(passive)
            factorization = _pivoted_qr(np.ascontiguousarray(matrix[:, index]), -1)
            trial = np.zeros(len(index))
            trial[factorization[3][:factorization[4]]] = _basic_solution(factorization, rhs)
            if np.all(trial > 0.0):
                x[:] = 0.0
                x[index] = trial
                break
            fraction = 1.0
            for i in range(len(index)):
                if trial[i] <= 0.0:     # x >= 0, so x - trial > 0 unless both are 0
                    current = x[index[i]]
                    gap = current - trial[i]
                    fraction = min(fraction, current / gap if gap > 0.0 else 0.0)
            for i in range(len(index)):
                x[index[i]] += fraction * (trial[i] - x[index[i]])
                if x[index[i]] <= 0.0:
                    x[index[i]] = 0.0
                    passive[index[i]] = False
    return x, np.sqrt(np.sum((matrix @ x - rhs) ** 2))


def _active_set_solve(projected, residual, damping, rows, low, high):
    """Exact minimizer of |P y - r|^2 + damping^2 |y|^2 subject to low <= rows y <= high, its
    active row mask, which of those rows are on their upper bound, and whether it converged,
    by a primal active-set method from y = 0 (feasible: low <= 0 <= high by construction).
    The objective is strictly convex, so the optimum is unique and does not depend on any
    solver history; used where ProxSuite's answer is not certified. Out of iterations
    (ACTIVE_SET_ITERATIONS x (variables + rows)), y is feasible and no worse than 0, but
    not shown optimal: converged is then False."""
    variables = projected.shape[1]
    design = np.vstack([projected, damping * np.eye(variables)])
    wanted = np.concatenate([residual, np.zeros(variables)])
    y = np.zeros(variables)
    working, side = [], []          # active rows and their side: +1 upper, -1 lower
    scale = 1.0 + np.abs(projected.T @ residual).max(initial=0.0)
    converged = False
    for _ in range(ACTIVE_SET_ITERATIONS * (variables + len(rows))):
        step = _equality_least_squares(design, wanted - design @ y, rows[working],
                                       np.zeros(len(working))) if working else \
            np.linalg.lstsq(design, wanted - design @ y, rcond=None)[0]
        if np.linalg.norm(step) <= STEP_TOLERANCE * (1.0 + np.linalg.norm(y)):
            if not working:
                converged = True
                break
            gradient = design.T @ (design @ y - wanted)
            outward = rows[working].T * np.array(side, dtype=float)
            multiplier = np.linalg.lstsq(outward, -gradient, rcond=None)[0]
            if np.all(multiplier >= -MULTIPLIER_SLACK * scale):
                converged = True
                break
            drop = int(np.argmin(multiplier))
            del working[drop], side[drop]
            continue
        reach, change = rows @ y, rows @ step
        fraction, blocking = 1.0, None
        for row in range(len(rows)):
            if row in working or abs(change[row]) <= STEP_TOLERANCE:
                continue
            bound = high[row] if change[row] > 0 else low[row]
            if np.isfinite(bound):
                limit = max(0.0, (bound - reach[row]) / change[row])
                if limit < fraction:
                    fraction, blocking = limit, (row, 1 if change[row] > 0 else -1)
        y = y + fraction * step
        if blocking is not None:
            working.append(blocking[0])
            side.append(blocking[1])
    active, upper_side = np.zeros(len(rows), dtype=bool), np.zeros(len(rows), dtype=bool)
    active[working] = True
    upper_side[[row for row, row_side in zip(working, side) if row_side > 0]] = True
    return y, active, upper_side, converged


def _equality_least_squares(design, wanted, equality_rows, equality_value):
    """argmin |design y - wanted| subject to equality_rows y = equality_value (least
    squares on dependent equality rows), through the SVD of the equality rows."""
    if not len(equality_rows):
        return np.linalg.lstsq(design, wanted, rcond=None)[0]
    left, singular, right_t = np.linalg.svd(equality_rows)
    rank = int(np.sum(singular > RANK_RELATIVE * singular[0]))
    particular = right_t[:rank].T @ ((left[:, :rank].T @ equality_value) / singular[:rank])
    null = right_t[rank:].T
    if not null.shape[1]:
        return particular
    free = np.linalg.lstsq(design @ null, wanted - design @ particular, rcond=None)[0]
    return particular + null @ free
