"""Strict task priorities by damped least squares in successive nullspaces.

This is the inner loop of Baerlocher and Boulic's Prioritized Inverse Kinematics (the
recursive Siciliano-Slotine formulation). Level i is solved inside the nullspace of levels
0..i-1 and of the fixed joint variations, so it can never disturb them. Nullspaces are kept
as orthonormal bases Z (nv x k) rather than projectors: each level then works on a k-column
problem that shrinks as levels consume freedom.

The level loop is compiled with numba (cached on disk): the problems are small (nv ~ 40),
so interpreter overhead, not arithmetic, would otherwise dominate.
"""

from __future__ import annotations

from dataclasses import dataclass

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


class DampedHierarchy:
    """Prioritized damped least squares (SVD).

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

    def solve_stacked(self, jacobian, target, offsets, fixed_index=(), fixed_dq=()):
        """Same as solve() on levels already stacked by stack_levels()."""
        nv = jacobian.shape[1]
        free = np.ones(nv, dtype=np.bool_)
        start = np.zeros(nv)
        if len(fixed_index):
            free[fixed_index] = False
            start[fixed_index] = fixed_dq
        dq, residuals = _solve_levels(jacobian, target, offsets, free, start,
                                      self.damping, self.rank_tolerance)
        return HierarchySolution(dq=dq, step_residuals=residuals)


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
    damping_sq = damping * damping
    for level in range(level_count):
        rows = jacobian[offsets[level]:offsets[level + 1]]
        wanted = target[offsets[level]:offsets[level + 1]]
        residual = wanted - rows @ dq
        if basis.shape[1] > 0 and rows.shape[0] > 0:
            projected = rows @ basis
            if level == level_count - 1:
                y = _damped_least_squares(projected, residual, damping_sq)
                dq += basis @ y
            else:
                u, sigma, vt = np.linalg.svd(projected)
                y = np.zeros(basis.shape[1])
                rank = 0
                for mode in range(len(sigma)):
                    coefficient = sigma[mode] / (sigma[mode] ** 2 + damping_sq)
                    y += coefficient * (u[:, mode] @ residual) * vt[mode]
                    if sigma[mode] > rank_tolerance:
                        rank += 1
                dq += basis @ y
                basis = basis @ np.ascontiguousarray(vt[rank:].T)
            residual = wanted - rows @ dq
        residuals[level] = np.sqrt(residual @ residual)
    return dq, residuals


@numba.njit(cache=True)
def _damped_least_squares(matrix, rhs, damping_sq):
    """argmin |A y - b|^2 + lambda^2 |y|^2 by normal equations on the smaller side of A.

    Used for the last level, which needs no nullspace: the same solution as the damped
    SVD pseudo-inverse at a fraction of the cost."""
    rows, cols = matrix.shape
    if rows >= cols:
        gram = matrix.T @ matrix
        for i in range(cols):
            gram[i, i] += damping_sq
        return np.linalg.solve(gram, matrix.T @ rhs)
    gram = matrix @ matrix.T
    for i in range(rows):
        gram[i, i] += damping_sq
    return matrix.T @ np.linalg.solve(gram, rhs)
