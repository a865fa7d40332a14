"""Strict task priorities by damped least squares in successive nullspaces.

This is the inner loop of Baerlocher and Boulic's Prioritized Inverse Kinematics (the
recursive Siciliano-Slotine formulation). Level i is solved inside the nullspace of levels
0..i-1 and of the fixed joint variations, so it can never disturb them. Nullspaces are kept
as orthonormal bases Z (nv x k) rather than projectors: each level then works on a k-column
problem that shrinks as levels consume freedom.

Per level, with P = J Z (m x k) and r the level's residual:
  - damped least squares y = P^T (P P^T + lambda^2 I)^-1 r, by Cholesky on the smaller side
    of P (the same y as the damped SVD pseudo-inverse sigma / (sigma^2 + lambda^2));
  - the next basis Z' = Z Q2, Q2 spanning null(P), from a column-pivoted Householder QR of
    P^T whose reflections are applied to Z directly; rank = pivots above rank_tolerance.

Re-solving after more joints are fixed (the clamping loop) restarts at the highest level
whose rows involve a newly fixed joint: a level whose Jacobian columns of those joints are
zero neither sees their variations nor loses freedom to them (the nullspace above still
contains their axes, and removing an axis from the basis leaves J Z Z^T J^T and Z Z^T J^T
unchanged), so its share of dq is the same. The restart removes the new joints' axes from
that level's stored basis and solves the levels from there on.

The level loop is compiled with numba (cached on disk): at nv ~ 40, interpreter and LAPACK
call overheads, not arithmetic, would otherwise dominate. Products with a level's rows skip
their zero entries (a foot moves with 12 of Talos' 38 DoFs, a posture row with one).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np


# Let LLVM reorder sums (vectorized dot products); unlike full fastmath, NaN and infinity
# keep their meaning. Results are bitwise deterministic for a given input and compiled code;
# LLVM may reorder an inlined copy differently, so a fresh compile and a cached one can
# differ in the last bits.
REORDERING = {"reassoc", "contract", "nsz"}


@dataclass
class Level:
    """Rows of one priority level: find dq with jacobian @ dq = target (task units)."""

    jacobian: np.ndarray
    target: np.ndarray


@dataclass
class HierarchySolution:
    dq: np.ndarray                # joint variation (nv), rad or m
    step_residuals: np.ndarray    # |J dq - target| per level, task units
    binding: list = field(default_factory=list)  # binding bounds, e.g. "<joint> upper"
    level_steps: np.ndarray | None = None  # levels x nv: each level's share of dq (the
    #                                        fixed variations are the rest), if known
    restart: _RestartState | None = None  # what a re-solve with more fixed joints reuses


@dataclass
class _RestartState:
    """Per level of one solution: the nullspace basis (nv x rank) and dq it started from."""

    jacobian: np.ndarray          # the stacked problem solved (identity checked on restart)
    target: np.ndarray
    fixed: np.ndarray             # bool (nv): fixed joints of that solution
    fixed_dq: np.ndarray          # (nv): their variations, 0 elsewhere
    level_bases: np.ndarray       # levels x nv x nv, level i's basis in [i, :, :ranks[i]]
    level_ranks: np.ndarray       # levels
    level_starts: np.ndarray      # (levels + 1) x nv: dq before each level, then the final dq
    #                               (after a restart, the levels before the restart level
    #                               keep the earlier solution's starts and bases)


class DampedHierarchy:
    """Prioritized damped least squares.

    damping: lambda of the damped pseudo-inverse sigma / (sigma^2 + lambda^2), per level.
    rank_tolerance: singular values at or below it leave their direction to lower levels.
    """

    def __init__(self, damping: float = 1e-3, rank_tolerance: float = 1e-9):
        self.damping = damping
        self.rank_tolerance = rank_tolerance

    def solve(self, levels, nv: int, fixed_index=(), fixed_dq=()) -> HierarchySolution:
        """Solve the levels in order. `fixed_index` entries of dq are imposed as the highest
        priority equality dq[fixed_index] = fixed_dq (clamped or damped joints)."""
        return self.solve_stacked(*stack_levels(levels, nv), fixed_index, fixed_dq)

    uses_bounds = False  # inequality bounds on dq are the QP hierarchy's business

    def solve_stacked(self, jacobian, target, offsets, fixed_index=(), fixed_dq=(),
                      bounds=None, previous=None):
        """Same as solve() on levels already stacked by stack_levels().

        previous: a solution of this same stacked problem (same arrays, unchanged) whose
        fixed joints are among these with the same variations; the solve then restarts at
        the highest level involving a newly fixed joint (module docstring). `previous`
        gives its restart state up to the new solution.
        """
        nv = jacobian.shape[1]
        fixed = np.zeros(nv, dtype=np.bool_)
        values = np.zeros(nv)
        if len(fixed_index):
            fixed[fixed_index] = True
            values[fixed_index] = fixed_dq
        level_count = len(offsets) - 1
        state = getattr(previous, "restart", None)
        if state is not None and state.jacobian is jacobian and state.target is target:
            previous.restart = None
            level_steps = previous.level_steps.copy()
            residuals = previous.step_residuals.copy()
            old_fixed, old_values = state.fixed, state.fixed_dq
            state.fixed, state.fixed_dq = fixed, values
        else:
            state = _RestartState(jacobian, target, fixed, values,
                                  np.empty((level_count, nv, nv)),
                                  np.zeros(level_count, dtype=np.int64),
                                  np.empty((level_count + 1, nv)))
            level_steps = np.zeros((level_count, nv))
            residuals = np.zeros(level_count)
            # empty: a fresh solve (arrays rather than None keep solve_compiled to one
            # compiled signature, so its first call compiles the restart path too)
            old_fixed, old_values = np.zeros(0, dtype=np.bool_), np.zeros(0)
        dq = solve_compiled(jacobian, target, offsets, fixed, values, old_fixed, old_values,
                            state.level_bases, state.level_ranks, state.level_starts,
                            level_steps, residuals, self.damping, self.rank_tolerance,
                            _NO_BOUNDS, _NO_BOUNDS)[0]
        return HierarchySolution(dq=dq, step_residuals=residuals, level_steps=level_steps,
                                 restart=state)


def restartable_solution(jacobian, target, fixed, values, dq, residuals, level_steps,
                         level_bases, level_ranks, level_starts) -> HierarchySolution:
    """A solution that solve_compiled left in these arrays (fixed, values: its fixed joints
    and their variations, nv each), with the state a later solve_stacked(previous=...)
    restarts from."""
    return HierarchySolution(dq=dq, step_residuals=residuals, level_steps=level_steps,
                             restart=_RestartState(jacobian, target, fixed, values,
                                                   level_bases, level_ranks, level_starts))


def stack_levels(levels, nv: int):
    """Stack levels into one Jacobian (rows x nv), one target and row offsets per level."""
    offsets = np.zeros(len(levels) + 1, dtype=np.int64)
    for index, level in enumerate(levels):
        offsets[index + 1] = offsets[index] + len(level.target)
    if not levels:
        return np.zeros((0, nv)), np.zeros(0), offsets
    jacobian = np.ascontiguousarray(np.vstack([level.jacobian for level in levels]), dtype=float)
    target = np.concatenate([level.target for level in levels]).astype(float)
    return jacobian, target, offsets


_NO_BOUNDS = np.zeros(0)      # solve_compiled's lower and upper: solve every level


@numba.njit(cache=True, fastmath=REORDERING)
def solve_compiled(jacobian, target, offsets, fixed, values, old_fixed, old_values,
                   level_bases, level_ranks, level_starts, level_steps, residuals, damping,
                   rank_tolerance, lower, upper):
    """DampedHierarchy.solve_stacked in one compiled call (one dispatch instead of several):
    restart from the state of a solution with old_fixed / old_values when they are given
    (non-empty) and allow it (level_steps and residuals are then that solution's copies),
    else solve from the first level; arrays filled in place as by solve_levels, which
    stops at a level whose dq leaves the bounds lower, upper on dq (nv each; empty: none).
    Returns (dq, that level or the level count: first_level_out_of_bounds of the solution,
    the levels kept by a restart included, since the bounds may have changed since)."""
    first = -1
    if len(old_fixed):
        first, dq, basis = _restart_point(jacobian, offsets, old_fixed, old_values, fixed,
                                          values, level_bases, level_ranks, level_starts,
                                          level_steps, rank_tolerance)
    if first < 0:
        first, dq, basis = 0, values.copy(), _free_axes(fixed)
        level_steps[:] = 0.0
        residuals[:] = 0.0
    dq, level = solve_levels(jacobian, target, offsets, first, dq, basis, level_steps,
                             residuals, level_bases, level_ranks, level_starts, damping,
                             rank_tolerance, fixed, lower, upper)
    if len(lower) and first > 0:    # the kept levels against these bounds
        kept = first_level_out_of_bounds(level_starts[:first + 1], fixed, lower, upper)
        if kept < first:
            return level_starts[kept + 1].copy(), kept
    return dq, level


@numba.njit(cache=True)
def first_level_out_of_bounds(level_starts, fixed, lower, upper):
    """The first level of a solution whose dq leaves per-DoF bounds on dq (nv each), the
    level count if none does (QPHierarchy then keeps the unconstrained solution exactly):
    for every DoF not fixed, each level's dq (level_starts: (levels + 1) x nv, the start
    then each level's result) must stay inside them or not go further out than the level
    before left it (_leaves_bounds); 0 when a free DoF's bounds exclude 0. The levels
    before it are what QPHierarchy's cascade would keep."""
    if excludes_zero(fixed, lower, upper):
        return 0
    for level in range(level_starts.shape[0] - 1):
        if _leaves_bounds(level_starts[level], level_starts[level + 1], fixed, lower, upper):
            return level
    return level_starts.shape[0] - 1


@numba.njit(cache=True)
def excludes_zero(fixed, lower, upper):
    """Whether a free DoF's bounds on dq (nv each) exclude 0."""
    for dof in range(len(fixed)):
        if not fixed[dof] and (lower[dof] > 0.0 or upper[dof] < 0.0):
            return True
    return False


@numba.njit(cache=True)
def _leaves_bounds(before, after, fixed, lower, upper):
    """Whether a level's dq, from `before` to `after` (nv each), takes a free DoF outside
    its bounds (lower, upper: nv each), or further out than `before` was."""
    for dof in range(len(fixed)):
        if not fixed[dof] and (after[dof] < min(lower[dof], before[dof])
                               or after[dof] > max(upper[dof], before[dof])):
            return True
    return False


@numba.njit(cache=True)
def _free_axes(fixed):
    """nv x (free joints) basis of the free joints' axes."""
    basis = np.zeros((len(fixed), len(fixed) - int(fixed.sum())))
    column = 0
    for joint in range(len(fixed)):
        if not fixed[joint]:
            basis[joint, column] = 1.0
            column += 1
    return basis


@numba.njit(cache=True, fastmath=REORDERING)
def _restart_point(jacobian, offsets, old_fixed, old_values, fixed, values, level_bases,
                   level_ranks, level_starts, level_steps, tolerance):
    """(first level to solve again, dq and basis to start it from) after fixing more joints,
    from the state of a solution with old_fixed (its level_steps updated in place); first
    is -1 when that solution's fixed joints are not all among these at the same values."""
    nv = len(fixed)
    added = np.zeros(nv, dtype=np.bool_)
    for joint in range(nv):
        if old_fixed[joint] and (not fixed[joint] or values[joint] != old_values[joint]):
            return -1, values, np.zeros((nv, 0))
        added[joint] = fixed[joint] and not old_fixed[joint]
    axes = np.flatnonzero(added)
    level_count = len(offsets) - 1
    first = level_count
    for row in range(offsets[level_count]):
        if first < level_count:
            break
        for joint in axes:
            if jacobian[row, joint] != 0.0:
                first = np.searchsorted(offsets, row, side="right") - 1
                break
    for joint in axes:
        for level in range(first):
            level_steps[level, joint] = 0.0  # zero but for rounding: those rows ignore it
    if first == level_count:
        dq = level_starts[first].copy()
        for joint in axes:
            dq[joint] = values[joint]
        return first, dq, np.zeros((nv, 0))
    dq, basis = level_start_state(first, fixed, values, level_bases, level_ranks,
                                  level_starts, tolerance)
    return first, dq, basis


@numba.njit(cache=True, fastmath=REORDERING)
def level_start_state(level, fixed, values, level_bases, level_ranks, level_starts,
                      tolerance):
    """(dq, basis) that `level` of a solution starts from with these fixed joints (bool,
    nv) at `values`: its stored start and basis with every fixed joint at its value and
    its axis removed. A level above the restart point of a later re-solve keeps what was
    stored when fewer joints were fixed (a chain of restarts, the second one higher than
    the first); the joints fixed since are absent from its rows and those above, so their
    values and axes are all that changed. An axis is still in a basis where its row is
    non-zero: a fixed joint's row is zeroed, and reflections keep zero rows zero."""
    dq = level_starts[level].copy()
    basis = np.ascontiguousarray(level_bases[level, :, :level_ranks[level]])
    stale = np.zeros(len(fixed), dtype=np.bool_)
    for joint in range(len(fixed)):
        if fixed[joint]:
            dq[joint] = values[joint]
            for column in range(basis.shape[1]):
                if basis[joint, column] != 0.0:
                    stale[joint] = True
                    break
    axes = np.flatnonzero(stale)
    if len(axes) == 0:
        return dq, basis
    selected = np.zeros((len(axes), basis.shape[1]))
    for index in range(len(axes)):
        selected[index] = basis[axes[index]]
    basis = _nullspace_update(selected, basis, tolerance)
    for joint in axes:
        basis[joint] = 0.0
    return dq, basis


@numba.njit(cache=True, fastmath=REORDERING)
def solve_levels(jacobian, target, offsets, first, dq, basis, level_steps, residuals,
                 level_bases, level_ranks, level_starts, damping, rank_tolerance, fixed,
                 lower, upper):
    """Solve levels first, first + 1, ... from dq and the nullspace basis left by the levels
    above; fill their level_steps and residuals, and per level the basis and dq it started
    from (all in place), then the final dq. With bounds lower, upper on dq (nv each; empty:
    none), stop after the dq of a level that leaves them (_leaves_bounds; the DoFs fixed
    are exempt): its residual and the levels below are left unsolved. Returns (dq, that
    level or the level count)."""
    level_count = len(offsets) - 1
    damping_sq = damping * damping
    for level in range(first, level_count):
        rank = basis.shape[1]
        level_bases[level, :, :rank] = basis
        level_ranks[level] = rank
        level_starts[level] = dq
        rows = jacobian[offsets[level]:offsets[level + 1]]
        wanted = target[offsets[level]:offsets[level + 1]]
        level_steps[level] = 0.0
        if rank > 0 and rows.shape[0] > 0:
            projected = _sparse_rows_product(rows, basis)
            level_steps[level] = _times(basis, _damped_least_squares(
                projected, wanted - _times(rows, dq), damping_sq))
            dq += level_steps[level]
            if len(lower) and _leaves_bounds(level_starts[level], dq, fixed, lower, upper):
                level_starts[level + 1] = dq
                return dq, level
            if level < level_count - 1:
                basis = _nullspace_update(projected, basis, rank_tolerance)
        square = 0.0
        for value in wanted - _times(rows, dq):
            square += value * value
        residuals[level] = np.sqrt(square)
    level_starts[level_count] = dq
    return dq, level_count


@numba.njit(cache=True, fastmath=REORDERING)
def _times(matrix, vector):
    """matrix @ vector (rows contiguous) by dot products: no BLAS call at these sizes."""
    product = np.zeros(matrix.shape[0])
    for i in range(matrix.shape[0]):
        acc = 0.0
        for j in range(matrix.shape[1]):
            acc += matrix[i, j] * vector[j]
        product[i] = acc
    return product


@numba.njit(cache=True, fastmath=REORDERING)
def _sparse_rows_product(rows, matrix):
    """rows @ matrix, skipping the zero entries of rows."""
    product = np.zeros((rows.shape[0], matrix.shape[1]))
    for i in range(rows.shape[0]):
        for c in range(rows.shape[1]):
            value = rows[i, c]
            if value != 0.0:
                for j in range(matrix.shape[1]):
                    product[i, j] += value * matrix[c, j]
    return product


# relative to the largest diagonal entry: the smallest Cholesky pivot kept (below it the
# matrix is singular to rounding)
PIVOT_EPSILON = 1e-15


@numba.njit(cache=True, fastmath=REORDERING)
def _spd_solve(gram, rhs, smallest_eigenvalue):
    """x with gram x = rhs, gram symmetric positive definite with no eigenvalue below
    smallest_eigenvalue (Cholesky, small sizes). No exact pivot is below it either (nor
    below PIVOT_EPSILON x the largest diagonal entry); one that rounding took there is
    raised to it: rows of weight 1e10 (Gram entries ~1e10 against lambda^2 = 1e-6) gave a
    pivot of 0 or below, a division by zero or a NaN step."""
    n = gram.shape[0]
    largest = 0.0
    for i in range(n):
        largest = max(largest, gram[i, i])
    floor = max(smallest_eigenvalue, PIVOT_EPSILON * largest)
    low = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = gram[i, j]
            for p in range(j):
                acc -= low[i, p] * low[j, p]
            if i == j:
                low[i, i] = np.sqrt(max(acc, floor))
            else:
                low[i, j] = acc / low[j, j]
    x = rhs.copy()
    for i in range(n):
        acc = x[i]
        for p in range(i):
            acc -= low[i, p] * x[p]
        x[i] = acc / low[i, i]
    for i in range(n - 1, -1, -1):
        acc = x[i]
        for p in range(i + 1, n):
            acc -= low[p, i] * x[p]
        x[i] = acc / low[i, i]
    return x


@numba.njit(cache=True, fastmath=REORDERING)
def _damped_least_squares(projected, residual, damping_sq):
    """argmin |P y - r|^2 + lambda^2 |y|^2 through the smaller Gram matrix of P."""
    rows, cols = projected.shape
    if rows <= cols:
        x = _spd_solve(_damped_gram(projected, damping_sq), residual, damping_sq)
        y = np.zeros(cols)
        for i in range(rows):
            for c in range(cols):
                y[c] += projected[i, c] * x[i]
        return y
    transposed = np.ascontiguousarray(projected.T)
    return _spd_solve(_damped_gram(transposed, damping_sq), _times(transposed, residual),
                      damping_sq)


@numba.njit(cache=True, fastmath=REORDERING)
def _damped_gram(a, damping_sq):
    """Lower triangle of a a^T + damping_sq I, all _spd_solve reads (upper left zero): dot
    products of contiguous rows, cheaper than a BLAS call at these sizes."""
    n = a.shape[0]
    gram = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = 0.0
            for c in range(a.shape[1]):
                acc += a[i, c] * a[j, c]
            gram[i, j] = acc
        gram[i, i] += damping_sq
    return gram


@numba.njit(cache=True, fastmath=REORDERING)
def _nullspace_update(projected, basis, tolerance):
    """basis @ Q2, Q2 an orthonormal basis of null(projected): column-pivoted Householder
    QR of projected^T (pivots <= tolerance end the rank), reflections applied to basis.
    Basis columns the level does not see (zero columns of projected) are moved last and
    kept as they are: no reflection involves them. Both factors are stored transposed
    (rows of projected, columns of basis as contiguous rows), so that every reflection
    runs over contiguous memory."""
    m, k = projected.shape
    nv = basis.shape[0]
    seen = np.zeros(k, dtype=np.bool_)
    for c in range(k):
        for r in range(m):
            if projected[r, c] != 0.0:
                seen[c] = True
                break
    involved = int(seen.sum())      # leading columns of a the reflections work on
    a = np.empty((m, k))            # projected, seen columns first
    b = np.empty((k, nv))           # basis^T in the same order
    seen_count, unseen_count = 0, 0
    for c in range(k):
        if seen[c]:
            column = seen_count
            seen_count += 1
        else:
            column = involved + unseen_count
            unseen_count += 1
        for r in range(m):
            a[r, column] = projected[r, c]
        for dof in range(nv):
            b[column, dof] = basis[dof, c]
    norms = np.zeros(m)
    v = np.empty(involved)
    combination = np.empty(nv)
    rank = 0
    for j in range(min(involved, m)):
        for c in range(j, m):
            acc = 0.0
            for r in range(j, involved):
                acc += a[c, r] * a[c, r]
            norms[c] = acc
        pivot = j
        for c in range(j + 1, m):
            if norms[c] > norms[pivot]:
                pivot = c
        if np.sqrt(norms[pivot]) <= tolerance:
            break
        if pivot != j:
            for r in range(involved):
                a[j, r], a[pivot, r] = a[pivot, r], a[j, r]
        length = np.sqrt(norms[pivot])
        alpha = -length if a[j, j] >= 0 else length
        size = involved - j
        for r in range(size):
            v[r] = a[j, j + r]
        v[0] -= alpha
        v_sq = 0.0
        for r in range(size):
            v_sq += v[r] * v[r]
        rank += 1
        if v_sq == 0.0:
            continue
        scale = 2.0 / v_sq
        for c in range(j, m):
            acc = 0.0
            for r in range(size):
                acc += v[r] * a[c, j + r]
            acc *= scale
            for r in range(size):
                a[c, j + r] -= acc * v[r]
        combination[:] = 0.0        # v^T b over the reflected rows, per DoF
        for r in range(size):
            for dof in range(nv):
                combination[dof] += v[r] * b[j + r, dof]
        for dof in range(nv):
            combination[dof] *= scale
        for r in range(size):
            for dof in range(nv):
                b[j + r, dof] -= combination[dof] * v[r]
    return np.ascontiguousarray(b[rank:].T)
