"""Strict task priorities under per-DoF bounds on dq: a cascade of small ProxSuite QPs.

Same levels and damping as DampedHierarchy, plus bounds lower <= dq <= upper (rad or m:
joint limits and velocity limits over one step). Level i works in the orthonormal basis Z
(nv x k) of what the fixed DoFs and levels 0..i-1 leave free, dq = dq_prev + Z y:

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
runs only when a level crosses a bound. Otherwise a persistent ProxSuite dense
QP (one per level and size) is updated and warm-started from its previous result, cold
started when that fails, to eps_abs 1e-9 within a bounded number of iterations (outer and
inner: ProxSuite's max_iter alone caps only the outer ones, and a warm start once ran
4,500 inner iterations, 120 ms). Its duals then seed the polish: the problem with the
active bounds they show as equalities is solved exactly and kept when nonnegative
multipliers exist (a KKT certificate that makes the result independent of the warm start
and of how far ProxSuite got; a few active set corrections are tried). Where the polish
finds no KKT point, an exact primal active-set method from y = 0 gives the level's step.
"""

from __future__ import annotations

import weakref

import numpy as np
import scipy.optimize
from proxsuite import proxqp

from .hierarchy import (DampedHierarchy, HierarchySolution, _damped_least_squares,
                        _nullspace_update, stack_levels)

QP_TOLERANCE = 1e-9          # ProxSuite eps_abs (eps_rel 0), task and dq units
# ProxSuite iterations: outer (max_iter) and inner per outer (max_iter_in). The polish only
# needs the active set, so a bounded solve costs less than waiting for 1e-9 on the
# degenerate bound sets of a clamped posture level (many bounds of zero width).
WARM_MAX_ITERATIONS = 10     # a warm start needing more is abandoned for a cold start
COLD_MAX_ITERATIONS = 100
INNER_MAX_ITERATIONS = 10
FEASIBILITY_SLACK = 1e-12    # rad or m: polished y may exceed a bound by this much
MULTIPLIER_SLACK = 1e-9      # relative to |gradient|: tolerated wrong-sign multiplier
POLISH_ROUNDS = 8            # active set corrections tried by the polish
ACTIVE_SET_ITERATIONS = 4    # x (variables + bound rows): cap of the exact active-set solve
STEP_TOLERANCE = 1e-13       # relative: an active-set step this small is a stationary point
BINDING_TOLERANCE = 1e-9     # rad or m: a dq this close to a bound is on it
RANK_RELATIVE = 1e-12        # active bound rows: singular values below this x largest drop
MOVABLE_ROW_NORM = 1e-12     # a DoF whose basis row is below this cannot move any more
MAX_CACHED_QPS = 64          # persistent QPs kept (level, variables, bound rows)


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


class QPHierarchy:
    """Prioritized damped least squares with inequality bounds on dq (see module docstring).

    damping, rank_tolerance: as DampedHierarchy's (the two agree when no bound binds).
    dof_names: a name per velocity DoF for the binding constraint report (default dof<i>).
    velocity_steps: |dq| bound per DoF from velocity limits (rad or m, inf if none); a bound
        equal to it is reported as "<dof> velocity" rather than "<dof> lower/upper".
    """

    uses_bounds = True

    def __init__(self, damping: float = 1e-3, rank_tolerance: float = 1e-9, dof_names=None,
                 velocity_steps=None):
        self.damping = damping
        self.rank_tolerance = rank_tolerance
        self.dof_names = None if dof_names is None else list(dof_names)
        self.velocity_steps = None if velocity_steps is None else np.asarray(velocity_steps,
                                                                             dtype=float)
        self._unconstrained = DampedHierarchy(damping, rank_tolerance)
        self._qps = {}
        # ProxSuite objects still alive when the interpreter exits make nanobind report
        # them as leaks: drop them first (atexit runs before modules are torn down)
        weakref.finalize(self, self._qps.clear)
        self.qp_solves = 0        # levels that needed a QP, since construction
        self.cold_starts = 0      # of which warm start failed or no QP of that size existed
        self.unpolished = 0       # of which the polish found no KKT point (solved exactly)
        self.qp_iterations = 0    # ProxSuite's inner iterations, warm and cold solves

    @classmethod
    def for_robot(cls, robot, dt: float | None = None, **options) -> QPHierarchy:
        """A QPHierarchy naming the robot's DoFs and its velocity bounds over dt (s)."""
        return cls(dof_names=robot_dof_names(robot),
                   velocity_steps=robot_velocity_steps(robot, dt), **options)

    def solve(self, levels, nv: int, fixed_index=(), fixed_dq=(), bounds=None):
        """Solve Level objects in order (see DampedHierarchy.solve); bounds: (lower, upper)."""
        return self.solve_stacked(*stack_levels(levels, nv), fixed_index, fixed_dq, bounds)

    def solve_stacked(self, jacobian, target, offsets, fixed_index=(), fixed_dq=(),
                      bounds=None, previous=None) -> HierarchySolution:
        """Levels stacked by stack_levels(); fixed DoFs dq[fixed_index] = fixed_dq come first,
        then bounds = (lower, upper) per DoF (nv each, +-inf where unbounded) on the others
        (a free DoF whose bounds exclude 0 starts on the nearer one). previous: as for
        DampedHierarchy.solve_stacked (used when it came from the unconstrained solve)."""
        nv = jacobian.shape[1]
        free = np.ones(nv, dtype=bool)
        free[np.asarray(fixed_index, dtype=int)] = False
        lower, upper = _checked_bounds(bounds, nv)
        if np.all((lower[free] <= 0.0) & (upper[free] >= 0.0)):
            solution = self._unconstrained.solve_stacked(jacobian, target, offsets,
                                                         fixed_index, fixed_dq,
                                                         previous=previous)
            if _levels_within(solution.restart.level_starts, free, lower, upper):
                return solution
        return self._cascade(jacobian, target, offsets, fixed_index, fixed_dq, free, lower,
                             upper)

    def _cascade(self, jacobian, target, offsets, fixed_index, fixed_dq, free, lower, upper):
        """The level by level solve of the module docstring (free: bool (nv), the DoFs not
        in fixed_index; lower, upper: bounds (nv each))."""
        nv = jacobian.shape[1]
        dq = np.clip(np.zeros(nv), lower, upper)
        dq[np.asarray(fixed_index, dtype=int)] = fixed_dq
        bounded = np.flatnonzero(free & (np.isfinite(lower) | np.isfinite(upper)))
        basis = np.eye(nv)[:, free]
        level_count = len(offsets) - 1
        residuals = np.zeros(level_count)
        enforced = np.zeros(nv, dtype=bool)
        damping_sq = self.damping * self.damping
        for level in range(level_count):
            rows = jacobian[offsets[level]:offsets[level + 1]]
            wanted = target[offsets[level]:offsets[level + 1]]
            if basis.shape[1] and len(rows):
                projected = rows @ basis
                step, active = self._level_step(level, projected, wanted - rows @ dq, basis,
                                                dq, bounded, lower, upper, damping_sq)
                dq += basis @ step
                enforced[active] = True
                if level < level_count - 1:
                    basis = _nullspace_update(projected, basis, self.rank_tolerance)
            residuals[level] = np.linalg.norm(wanted - rows @ dq)
        return HierarchySolution(dq=dq, step_residuals=residuals,
                                 binding=self._binding_names(dq, enforced, lower, upper))

    def _level_step(self, level, projected, residual, basis, dq, bounded, lower, upper,
                    damping_sq):
        """(y, DoFs whose bounds the level's QP enforced) for one level."""
        step = _damped_least_squares(projected, residual, damping_sq)
        if not len(bounded):
            return step, bounded
        moving = np.linalg.norm(basis[bounded], axis=1) > MOVABLE_ROW_NORM
        dofs = bounded[moving]
        rows = basis[dofs]
        # y = 0 stays feasible: a DoF a QP left a hair outside may not go further out
        low = np.minimum(lower[dofs] - dq[dofs], 0.0)
        high = np.maximum(upper[dofs] - dq[dofs], 0.0)
        reach = rows @ step
        if np.all((reach >= low) & (reach <= high)):
            return step, dofs[:0]
        hessian = projected.T @ projected
        hessian[np.diag_indices_from(hessian)] += damping_sq
        qp = self._qp_solve(level, hessian, -(projected.T @ residual), rows, low, high)
        polished = _polish(projected, residual, self.damping, rows, low, high, qp.results.z)
        if polished is not None:
            step, active = polished
            return step, dofs[active]
        self.unpolished += 1  # ProxSuite's answer is not certified: solve exactly instead
        step, active = _active_set_solve(projected, residual, self.damping, rows, low, high)
        return step, dofs[active]

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

    def _binding_names(self, dq, enforced, lower, upper) -> list:
        """'<dof> lower|upper|velocity' for each bound a level's QP enforced that dq is on."""
        names = []
        for dof in np.flatnonzero(enforced):
            for side, bound in (("lower", lower[dof]), ("upper", upper[dof])):
                if abs(dq[dof] - bound) > BINDING_TOLERANCE:
                    continue
                velocity = (self.velocity_steps is not None
                            and abs(bound) == self.velocity_steps[dof])
                dof_name = self.dof_names[dof] if self.dof_names else f"dof{dof}"
                names.append(f"{dof_name} {'velocity' if velocity else side}")
        return names


def _levels_within(level_starts, free, lower, upper) -> bool:
    """Whether each level's dq (level_starts: (levels + 1) x nv, the start then each level's
    result) keeps the free DoFs inside [lower, upper], or not further out than the level
    before left them: the cascade's test for keeping a level's unconstrained step."""
    before = level_starts[:-1, free]
    after = level_starts[1:, free]
    return bool(np.all((after >= np.minimum(lower[free], before))
                       & (after <= np.maximum(upper[free], before))))


def _checked_bounds(bounds, nv: int):
    """(lower, upper) as float arrays, +-inf without bounds; lower <= upper required."""
    if bounds is None:
        return np.full(nv, -np.inf), np.full(nv, np.inf)
    lower, upper = (np.asarray(side, dtype=float).reshape(nv) for side in bounds)
    if np.any(lower > upper) or np.any(np.isnan(lower)) or np.any(np.isnan(upper)):
        raise ValueError("dq bounds need lower <= upper (no NaN)")
    return lower, upper


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


def _polish(projected, residual, damping, rows, low, high, dual):
    """Exact solution of the level's QP on an active set of bounds, (y, active row mask),
    or None. The set starts from ProxSuite's duals and is corrected a few times (violated
    bounds join it, the bound with the worst wrong-sign multiplier leaves it) until the KKT
    conditions hold (nonnegative multipliers, by NNLS on a degenerate vertex). Each try is a
    least-squares problem in the nullspace of the active rows (SVD), never the normal
    equations, whose condition number is squared."""
    variables = projected.shape[1]
    design = np.vstack([projected, damping * np.eye(variables)])
    wanted = np.concatenate([residual, np.zeros(variables)])
    slack = MULTIPLIER_SLACK * (1.0 + np.abs(projected.T @ residual).max(initial=0.0))
    upper_side = (dual > slack) & np.isfinite(high)
    active = upper_side | ((dual < -slack) & np.isfinite(low))
    for _ in range(POLISH_ROUNDS):
        index = np.flatnonzero(active)
        value = np.where(upper_side[index], high[index], low[index])
        step = _equality_least_squares(design, wanted, rows[index], value)
        reach = rows @ step
        if np.any(np.abs(reach[index] - value) > FEASIBILITY_SLACK):
            return None  # the active bounds cannot all hold: not a vertex, no KKT point
        above, below = reach > high + FEASIBILITY_SLACK, reach < low - FEASIBILITY_SLACK
        if np.any(above | below):
            if np.all(active[above | below]):
                return None  # active rows in conflict: no vertex of this set is feasible
            active |= above | below
            upper_side = (upper_side | above) & ~below
            continue
        if not len(index):
            return step, active
        gradient = design.T @ (design @ step - wanted)
        outward = rows[index].T * np.where(upper_side[index], 1.0, -1.0)
        multiplier = np.linalg.lstsq(outward, -gradient, rcond=None)[0]
        if np.all(multiplier >= -slack) or scipy.optimize.nnls(outward, -gradient)[1] <= slack:
            return step, active
        active[index[np.argmin(multiplier)]] = False
    return None


def _active_set_solve(projected, residual, damping, rows, low, high):
    """Exact minimizer of |P y - r|^2 + damping^2 |y|^2 subject to low <= rows y <= high, and
    its active row mask, by a primal active-set method from y = 0 (feasible: low <= 0 <=
    high by construction). The objective is strictly convex, so the optimum is unique and
    does not depend on any solver history; used where ProxSuite's answer is not certified."""
    variables = projected.shape[1]
    design = np.vstack([projected, damping * np.eye(variables)])
    wanted = np.concatenate([residual, np.zeros(variables)])
    y = np.zeros(variables)
    working, side = [], []          # active rows and their side: +1 upper, -1 lower
    scale = 1.0 + np.abs(projected.T @ residual).max(initial=0.0)
    for _ in range(ACTIVE_SET_ITERATIONS * (variables + len(rows))):
        step = _equality_least_squares(design, wanted - design @ y, rows[working],
                                       np.zeros(len(working))) if working else \
            np.linalg.lstsq(design, wanted - design @ y, rcond=None)[0]
        if np.linalg.norm(step) <= STEP_TOLERANCE * (1.0 + np.linalg.norm(y)):
            if not working:
                break
            gradient = design.T @ (design @ y - wanted)
            outward = rows[working].T * np.array(side, dtype=float)
            multiplier = np.linalg.lstsq(outward, -gradient, rcond=None)[0]
            if np.all(multiplier >= -MULTIPLIER_SLACK * scale):
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
    active = np.zeros(len(rows), dtype=bool)
    active[working] = True
    return y, active


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
