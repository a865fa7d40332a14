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

The level loop is compiled with numba (cached on disk): at nv ~ 40, interpreter and LAPACK
call overheads, not arithmetic, would otherwise dominate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np


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
                      bounds=None):
        """Same as solve() on levels already stacked by stack_levels()."""
        nv = jacobian.shape[1]
        free = np.ones(nv, dtype=np.bool_)
        start = np.zeros(nv)
        if len(fixed_index):
            free[fixed_index] = False
            start[fixed_index] = fixed_dq
        dq, residuals, level_steps = _solve_levels(jacobian, target, offsets, free, start,
                                                   self.damping, self.rank_tolerance)
        return HierarchySolution(dq=dq, step_residuals=residuals, level_steps=level_steps)


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


@numba.njit(cache=True)
def _solve_levels(jacobian, target, offsets, free, start, damping, rank_tolerance):
    nv = jacobian.shape[1]
    dq = start.copy()
    basis = np.zeros((nv, int(free.sum())))
    column = 0
    for joint in range(nv):
        if free[joint]:
            basis[joint, column] = 1.0
            column += 1
    level_count = len(offsets) - 1
    residuals = np.zeros(level_count)
    level_steps = np.zeros((level_count, nv))
    damping_sq = damping * damping
    for level in range(level_count):
        rows = jacobian[offsets[level]:offsets[level + 1]]
        wanted = target[offsets[level]:offsets[level + 1]]
        residual = wanted - rows @ dq
        if basis.shape[1] > 0 and rows.shape[0] > 0:
            projected = rows @ basis
            level_steps[level] = basis @ _damped_least_squares(projected, residual, damping_sq)
            dq += level_steps[level]
            if level < level_count - 1:
                basis = _nullspace_update(projected, basis, rank_tolerance)
            residual = wanted - rows @ dq
        residuals[level] = np.sqrt(residual @ residual)
    return dq, residuals, level_steps


@numba.njit(cache=True)
def _spd_solve(gram, rhs):
    """x with gram x = rhs, gram symmetric positive definite (Cholesky, small sizes)."""
    n = gram.shape[0]
    low = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = gram[i, j]
            for p in range(j):
                acc -= low[i, p] * low[j, p]
            if i == j:
                low[i, i] = np.sqrt(acc)
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

@numba.njit(cache=True)
def _damped_least_squares(projected, residual, damping_sq):
    """argmin |P y - r|^2 + lambda^2 |y|^2 through the smaller Gram matrix of P."""
    rows, cols = projected.shape
    if rows <= cols:
        gram = projected @ projected.T
        for i in range(rows):
            gram[i, i] += damping_sq
        return projected.T @ _spd_solve(gram, residual)
    gram = projected.T @ projected
    for i in range(cols):
        gram[i, i] += damping_sq
    return _spd_solve(gram, projected.T @ residual)

@numba.njit(cache=True)
def _nullspace_update(projected, basis, tolerance):
    """basis @ Q2, Q2 an orthonormal basis of null(projected): column-pivoted Householder
    QR of projected^T (pivots <= tolerance end the rank), reflections applied to basis."""
    a = projected.T.copy()          # k x m
    k, m = a.shape
    b = basis.copy()                # nv x k
    nv = b.shape[0]
    norms = np.zeros(m)
    rank = 0
    for j in range(min(k, m)):
        for c in range(j, m):
            acc = 0.0
            for r in range(j, k):
                acc += a[r, c] * a[r, c]
            norms[c] = acc
        pivot = j
        for c in range(j + 1, m):
            if norms[c] > norms[pivot]:
                pivot = c
        if np.sqrt(norms[pivot]) <= tolerance:
            break
        if pivot != j:
            for r in range(k):
                a[r, j], a[r, pivot] = a[r, pivot], a[r, j]
        length = np.sqrt(norms[pivot])
        alpha = -length if a[j, j] >= 0 else length
        v = a[j:, j].copy()
        v[0] -= alpha
        v_sq = 0.0
        for r in range(k - j):
            v_sq += v[r] * v[r]
        rank += 1
        if v_sq == 0.0:
            continue
        scale = 2.0 / v_sq
        for c in range(j, m):
            acc = 0.0
            for r in range(k - j):
                acc += v[r] * a[j + r, c]
            acc *= scale
            for r in range(k - j):
                a[j + r, c] -= acc * v[r]
        for row in range(nv):
            acc = 0.0
            for r in range(k - j):
                acc += b[row, j + r] * v[r]
            acc *= scale
            for r in range(k - j):
                b[row, j + r] -= acc * v[r]
    return np.ascontiguousarray(b[:, rank:])
