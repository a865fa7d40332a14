"""Time scaling of a sampled configuration path (Escande et al. 2008, section 4).

The path through the samples q_0..q_{N-1} is cut at rest samples (contact events: the
robot stops when a contact is created or broken). Between two rest samples a and b the
samples are joined by a monotone cubic (scipy PchipInterpolator, C1) in the tangent
coordinates x(p) = difference(q_a, q_{a+p}), p in [0, b - a] (sample units), and
q(p) = integrate(q_a, x(p)): the 1-DoF joints are exact linear coordinates, and the
monotone cubic never overshoots the samples, so joints stay inside their limits between
samples; corners are passed without stopping (the paper's path is piecewise linear: its
joint speed jumps at each sample).

Two time laws p(t) per transition, both at rest at its two ends:
- `sinusoidal_trajectory` (the paper): p = m s(t / T), s(tau) = tau - sin(2 pi tau) / (2 pi)
  (speed (1 - cos 2 pi tau) / T: zero at both ends), T the least duration keeping every
  joint under scale * its velocity limit (evaluated on a dense grid of tau);
- `time_optimal_trajectory` (beyond the paper): the fastest p(t) under joint velocity and
  acceleration limits, by the reachability-analysis form of TOPP (Pham and Pham 2018) on a
  grid of p: backward pass of the largest controllable squared speed, forward pass of the
  largest admissible acceleration; piecewise-constant p'' between grid points, constraints
  enforced at the start of each grid interval (the acceleration error is O(grid step)).

Units: s, rad, m; velocities v are Pinocchio tangent velocities (nv).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq

from ..stopping import stop_if_asked

ACCELERATION_LIMIT = 4.0   # rad/s^2: default joint acceleration limit (Talos' URDF has none)
DENSE = 64                 # time-law grid points per sample interval
MAX_PATH_SPEED = 1e3       # samples/s: where no limited joint moves (identical samples)


class _PathPiece:
    """Path between two rest samples: q(p) = integrate(q_a, x(p)), p in [0, m]."""

    def __init__(self, model, samples: np.ndarray):
        self.model, self.origin = model, samples[0]
        self.steps = len(samples) - 1
        tangent = np.array([pin.difference(model, samples[0], q) for q in samples])
        self.x = PchipInterpolator(np.arange(len(samples)), tangent, axis=0)
        self.dx, self.ddx = self.x.derivative(1), self.x.derivative(2)

    def state(self, p: float, p_dot: float):
        """(q (nq), v (nv)) at path parameter p moving at p_dot (1/s)."""
        x = self.x(p)
        jacobian = pin.dIntegrate(self.model, self.origin, x, pin.ARG1)
        return pin.integrate(self.model, self.origin, x), jacobian @ self.dx(p) * p_dot


class _SinusoidalLaw:
    """p(t) = m s(t / T), s(tau) = tau - sin(2 pi tau) / (2 pi)."""

    def __init__(self, steps: int, duration: float):
        self.steps, self.duration = steps, duration

    def at(self, t: float):
        tau = min(max(t / self.duration, 0.0), 1.0)
        return (self.steps * (tau - math.sin(2 * math.pi * tau) / (2 * math.pi)),
                self.steps * (1.0 - math.cos(2 * math.pi * tau)) / self.duration)

    def time_of(self, p: float) -> float:
        if p <= 0.0 or p >= self.steps:
            return self.duration * min(max(p / self.steps, 0.0), 1.0)
        return self.duration * brentq(lambda tau: tau - math.sin(2 * math.pi * tau)
                                      / (2 * math.pi) - p / self.steps, 0.0, 1.0)


class _GridLaw:
    """p(t) with piecewise-constant p'' = u_i between grid points p_i (squared speeds
    x_i = p_dot_i^2, times t_i)."""

    def __init__(self, grid: np.ndarray, squared_speed: np.ndarray):
        self.grid, self.squared_speed = grid, np.maximum(squared_speed, 0.0)
        step = np.diff(grid)
        self.u = np.diff(self.squared_speed) / (2 * step)
        speeds = np.sqrt(self.squared_speed)
        self.times = np.concatenate([[0.0], np.cumsum(2 * step / (speeds[:-1] + speeds[1:]))])
        self.speeds, self.duration = speeds, float(self.times[-1])

    def at(self, t: float):
        i = int(np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.u) - 1))
        tau = min(max(t - self.times[i], 0.0), self.times[i + 1] - self.times[i])
        return (self.grid[i] + self.speeds[i] * tau + 0.5 * self.u[i] * tau * tau,
                self.speeds[i] + self.u[i] * tau)

    def time_of(self, p: float) -> float:
        return float(np.interp(p, self.grid, self.times))


@dataclass
class Trajectory:
    """A timed path: waypoint times (N,) of the samples (s), and `sample(t)`."""

    pieces: list          # _PathPiece per transition between rest samples
    laws: list            # their time laws
    starts: np.ndarray    # start time of each piece (s)
    times: np.ndarray     # time of each input sample (s)

    @property
    def duration(self) -> float:
        return float(self.starts[-1] + self.laws[-1].duration)

    def times_of(self, samples) -> np.ndarray:
        """Time (s) of each input sample index in `samples`, at most the duration (the
        summed laws may put the last sample a rounding error past it)."""
        return np.minimum(self.times[np.asarray(samples, dtype=int)], self.duration)

    def sample(self, t: float):
        """(q (nq), v (nv)) at time t (s), clamped to [0, duration]."""
        t = min(max(t, 0.0), self.duration)
        i = int(np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0,
                        len(self.pieces) - 1))
        p, p_dot = self.laws[i].at(t - self.starts[i])
        return self.pieces[i].state(min(max(p, 0.0), self.pieces[i].steps), p_dot)


def _rest_pieces(model, q: np.ndarray, rest_samples) -> list:
    """_PathPiece between consecutive rest samples (the first and last samples included);
    ValueError for fewer than two finite samples of size nq or a rest sample off the path."""
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != model.nq or len(q) < 2:
        raise ValueError(f"the path needs at least 2 samples of {model.nq} values, got an "
                         f"array of shape {q.shape}")
    if not np.isfinite(q).all():
        raise ValueError("the path has samples that are not finite")
    rest_samples = np.asarray(rest_samples, dtype=int)
    if np.any((rest_samples < 0) | (rest_samples >= len(q))):
        raise ValueError(f"rest samples must be in [0, {len(q) - 1}]")
    rest = np.unique(np.concatenate([[0, len(q) - 1], rest_samples]))
    return [_PathPiece(model, q[a:b + 1]) for a, b in zip(rest[:-1], rest[1:])]


def _assemble(pieces, laws) -> Trajectory:
    starts = np.concatenate([[0.0], np.cumsum([law.duration for law in laws])[:-1]])
    times = [0.0] + [start + law.time_of(k) for piece, law, start in zip(pieces, laws, starts)
                     for k in range(1, piece.steps + 1)]
    return Trajectory(pieces, laws, starts, np.array(times))


def sinusoidal_trajectory(robot, q: np.ndarray, rest_samples, velocity_scale: float = 0.5,
                          acceleration_limit=None) -> Trajectory:
    """The paper's sinusoidal speed profile per transition (module docstring): joint speeds
    at most velocity_scale * robot.velocity_limit; with acceleration_limit (rad/s^2, scalar
    or per limited joint; the paper has none) the duration also keeps
    |x' p'' + x'' p'^2| under it (to compare with time_optimal_trajectory)."""
    velocity = _velocity(robot, velocity_scale)
    acceleration = None if acceleration_limit is None else \
        _per_joint(acceleration_limit, velocity)
    pieces, laws = _rest_pieces(robot.model, q, rest_samples), []
    for piece in pieces:
        m = piece.steps
        tau = np.linspace(0.0, 1.0, DENSE * m + 1)
        p = m * (tau - np.sin(2 * np.pi * tau) / (2 * np.pi))
        # the samples themselves too: x'' jumps there (evaluated on both sides)
        unit = _SinusoidalLaw(m, 1.0)
        tau = np.sort(np.concatenate([tau, [unit.time_of(k) for k in range(m + 1)]]))
        p = m * (tau - np.sin(2 * np.pi * tau) / (2 * np.pi))
        first = piece.dx(p)[:, robot.limited_v_index]
        speed = m * (1.0 - np.cos(2 * np.pi * tau))           # T * p_dot
        duration = float(np.max(speed[:, None] * np.abs(first) / velocity))
        if acceleration is not None:
            push = m * 2 * np.pi * np.sin(2 * np.pi * tau)     # T^2 * p_ddot
            joint = [first * push[:, None] + piece.ddx(p + side)[:, robot.limited_v_index]
                     * (speed ** 2)[:, None] for side in (-1e-9, 1e-9)]  # T^2 * joint acc.
            duration = max(duration, math.sqrt(float(np.max(
                np.abs(joint) / acceleration))))
        laws.append(_SinusoidalLaw(m, max(duration, 1e-9)))
    return _assemble(pieces, laws)


def time_optimal_trajectory(robot, q: np.ndarray, rest_samples, velocity_scale: float = 0.5,
                            acceleration_limit=ACCELERATION_LIMIT, grid: int = 16,
                            should_stop=None) -> Trajectory:
    """Fastest timing under joint speeds <= velocity_scale * robot.velocity_limit and
    |joint accelerations| <= acceleration_limit (rad/s^2, scalar or per limited joint),
    at rest at every rest sample (module docstring); `grid` points per sample interval.
    stopping.Stopped once should_stop (a callable, asked before each transition: ~30 ms
    of work on Talos) answers True."""
    velocity = _velocity(robot, velocity_scale)
    acceleration = _per_joint(acceleration_limit, velocity)
    if not (isinstance(grid, (int, np.integer)) and grid >= 1):
        raise ValueError(f"grid must be an integer >= 1, got {grid!r}")
    pieces, laws = _rest_pieces(robot.model, q, rest_samples), []
    for index, piece in enumerate(pieces):
        stop_if_asked(should_stop, f"timing stopped at transition {index} -> {index + 1}")
        points = np.linspace(0.0, piece.steps, grid * piece.steps + 1)
        # derivatives at each grid interval's start, and at its end from the left (the
        # monotone cubic's second derivative jumps at the samples)
        ends = np.nextafter(points[1:], points[:-1])
        start = (piece.dx(points)[:, robot.limited_v_index],
                 piece.ddx(points)[:, robot.limited_v_index])
        end = (piece.dx(ends)[:, robot.limited_v_index],
               piece.ddx(ends)[:, robot.limited_v_index])
        laws.append(_GridLaw(points, _topp(points, start, end, velocity, acceleration)))
    return _assemble(pieces, laws)


def _per_joint(limit, like: np.ndarray) -> np.ndarray:
    """The acceleration limit (rad/s^2, scalar or per limited joint) per limited joint;
    ValueError unless every value is finite and > 0."""
    values = np.broadcast_to(np.asarray(limit, dtype=float), like.shape)
    if not (np.isfinite(values).all() and (values > 0.0).all()):
        raise ValueError(f"acceleration_limit must be finite and > 0, got {limit!r}")
    return values


def _velocity(robot, velocity_scale: float) -> np.ndarray:
    """velocity_scale * robot.velocity_limit; ValueError unless the scale is finite and
    > 0."""
    if not (math.isfinite(velocity_scale) and velocity_scale > 0.0):
        raise ValueError(f"velocity_scale must be finite and > 0, got {velocity_scale!r}")
    return velocity_scale * robot.velocity_limit


def _topp(points, start, end, velocity, acceleration) -> np.ndarray:
    """Squared path speeds x_i at the grid points (rest at both ends): TOPP-RA with
    x_{i+1} = x_i + 2 step_i u_i, the speed limits |x'(p_i)| x_i^0.5 <= velocity and the
    acceleration limits |x'(p) u_i + x''(p) x(p)| <= acceleration at both ends of each
    interval (start = (x', x'') at the grid points, end = at the interval ends)."""
    step = np.diff(points)
    with np.errstate(divide="ignore"):
        speed_bound = np.minimum(np.min((velocity / np.abs(start[0])) ** 2, axis=1),
                                 MAX_PATH_SPEED ** 2)
    count = len(points)

    def lines(i):
        # at the end: x'(u) + x'' (x_i + 2 step u) = (x' + 2 step x'') u + x'' x_i
        return _acceleration_lines(
            np.concatenate([start[0][i], end[0][i] + 2 * step[i] * end[1][i]]),
            np.concatenate([start[1][i], end[1][i]]), np.concatenate([acceleration] * 2))

    controllable = np.zeros(count)
    for i in range(count - 2, -1, -1):
        controllable[i] = _largest_controllable(lines(i), speed_bound[i],
                                                controllable[i + 1], step[i])
    squared = np.zeros(count)
    for i in range(count - 1):
        _, (e, f), _ = lines(i)
        u = min(np.min(e + f * squared[i], initial=np.inf),
                (controllable[i + 1] - squared[i]) / (2 * step[i]))
        squared[i + 1] = min(max(squared[i] + 2 * step[i] * u, 0.0), controllable[i + 1])
    return squared


def _acceleration_lines(first, second, acceleration):
    """|first u + second x| <= acceleration (per row) as ((c, d), (e, f), x_bound):
    c + d x <= u <= e + f x for the rows with first != 0, x <= x_bound for the others."""
    moving = np.abs(first) > 1e-12
    reach = acceleration[moving] / np.abs(first[moving])
    slope = -second[moving] / first[moving]
    with np.errstate(divide="ignore"):
        x_bound = float(np.min(acceleration[~moving] / np.abs(second[~moving]),
                               initial=np.inf))
    return (-reach, slope), (reach, slope), x_bound


def _largest_controllable(lines, speed_bound, next_bound, step):
    """Largest x <= speed_bound from which some u satisfying the acceleration lines
    reaches [0, next_bound]: a two-variable LP in (x, u), solved over all pairs of lower
    and upper lines ((d_l - f_m) x <= e_m - c_l)."""
    (c, d), (e, f), x_bound = lines
    c = np.append(c, 0.0)                      # -x / (2 step) <= u
    d = np.append(d, -1.0 / (2 * step))
    e = np.append(e, next_bound / (2 * step))  # u <= (next_bound - x) / (2 step)
    f = np.append(f, -1.0 / (2 * step))
    coefficient = d[:, None] - f[None, :]
    right = e[None, :] - c[:, None]
    positive = coefficient > 1e-15
    bound = min(speed_bound, x_bound)
    if np.any(positive):
        bound = min(bound, float(np.min(right[positive] / coefficient[positive])))
    return max(bound, 0.0)
