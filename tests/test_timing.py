"""Time scaling of a sampled path: the paper's sinusoidal profile and the time-optimal one
(joint speed and acceleration limits, rest at contact events), checked by sampling and
finite differences on a Talos path with corners and a joint driven onto its limit."""

import math

import numpy as np
import pinocchio as pin
import pytest

from stance.execution.timing import sinusoidal_trajectory, time_optimal_trajectory
from stance.robot import Robot
from stance.stopping import Stopped

SCALE = 0.5
ACCELERATION = 3.0       # rad/s^2
REST = [20, 35]          # contact events (the first and last samples rest too)


@pytest.fixture(scope="module")
def robot():
    return Robot.load("talos")


@pytest.fixture(scope="module")
def samples(robot):
    """51 samples: smooth joint motions plus noise (corners), the base drifting and
    turning, one joint held at its upper limit over several samples."""
    generator = np.random.default_rng(3)
    q0 = robot.initial_configuration()
    count = len(robot.limited_q_index)
    amplitude = generator.uniform(0.05, 0.3, count)
    frequency = generator.uniform(0.5, 2.0, count)
    k = np.arange(51)[:, None]
    joints = q0[robot.limited_q_index] + amplitude * np.sin(np.pi * frequency * k / 50) \
        + generator.normal(0.0, 0.005, (51, count))
    joints[:, 3] = np.minimum(q0[robot.limited_q_index[3]] + 0.02 * k[:, 0],
                              robot.upper[3])
    joints = np.clip(joints, robot.lower, robot.upper)
    q = np.tile(q0, (51, 1))
    q[:, robot.limited_q_index] = joints
    for i in range(51):
        base = pin.exp6(np.array([0.004 * i, 0.0, 0.0, 0.0, 0.0, 0.003 * i]))
        placement = pin.XYZQUATToSE3(q0[:7]) * base
        q[i, :7] = pin.SE3ToXYZQUAT(placement)
    return q


def sampled(robot, trajectory, step=5e-4):
    times = np.arange(0.0, trajectory.duration, step)
    states = [trajectory.sample(t) for t in times]
    q = np.array([s[0] for s in states])
    v = np.array([s[1] for s in states])
    return times, q, v[:, robot.limited_v_index]


@pytest.fixture(scope="module")
def trajectories(robot, samples):
    return {"sinusoidal": sinusoidal_trajectory(robot, samples, REST, SCALE),
            "bounded": sinusoidal_trajectory(robot, samples, REST, SCALE, ACCELERATION),
            "optimal": time_optimal_trajectory(robot, samples, REST, SCALE, ACCELERATION)}


@pytest.mark.parametrize("name", ["sinusoidal", "bounded", "optimal"])
def test_waypoints_speed_limits_and_rest_at_events(robot, samples, trajectories, name):
    trajectory = trajectories[name]
    times = trajectory.times
    assert len(times) == len(samples) and np.all(np.diff(times) > 0) and times[0] == 0.0
    assert times[-1] == pytest.approx(trajectory.duration)
    for time, q in zip(times, samples):
        assert np.allclose(pin.difference(robot.model, trajectory.sample(time)[0], q), 0.0,
                           atol=1e-9)
    _, q, v = sampled(robot, trajectory)
    ratio = np.max(np.abs(v) / (SCALE * robot.velocity_limit))
    assert ratio <= 1.0 + 1e-3
    for event in [0, *REST, len(samples) - 1]:
        assert np.max(np.abs(trajectory.sample(times[event])[1])) < 1e-9
    middle = trajectory.sample(0.5 * (times[0] + times[REST[0]]))[1]
    assert np.max(np.abs(middle)) > 1e-3
    joints = q[:, robot.limited_q_index]
    assert np.all(joints >= robot.lower - 1e-12) and np.all(joints <= robot.upper + 1e-12)


def test_sinusoidal_duration_is_set_by_a_speed_limit(robot, trajectories):
    _, _, v = sampled(robot, trajectories["sinusoidal"])
    assert np.max(np.abs(v) / (SCALE * robot.velocity_limit)) > 0.99


def test_time_optimal_respects_accelerations_and_is_not_longer(robot, trajectories):
    optimal, bounded = trajectories["optimal"], trajectories["bounded"]
    step = 5e-4
    _, _, v = sampled(robot, optimal, step)
    acceleration = np.diff(v, axis=0) / step
    assert np.max(np.abs(acceleration)) <= ACCELERATION * 1.02
    assert optimal.duration <= bounded.duration
    # time-optimal: some limit is nearly active (speed or acceleration) most of the time
    active = np.maximum(np.max(np.abs(v[1:]) / (SCALE * robot.velocity_limit), axis=1),
                        np.max(np.abs(acceleration), axis=1) / ACCELERATION)
    assert np.mean(active > 0.9) > 0.8
    _, _, v_bounded = sampled(robot, bounded, step)
    assert np.max(np.abs(np.diff(v_bounded, axis=0) / step)) <= ACCELERATION * 1.02


@pytest.mark.parametrize("timing", [sinusoidal_trajectory, time_optimal_trajectory])
@pytest.mark.parametrize("keywords, message", [
    ({"velocity_scale": 0.0}, "velocity_scale must be finite and > 0"),
    ({"velocity_scale": -0.5}, "velocity_scale must be finite and > 0"),
    ({"velocity_scale": math.nan}, "velocity_scale must be finite and > 0"),
    ({"velocity_scale": math.inf}, "velocity_scale must be finite and > 0"),
    ({"acceleration_limit": 0.0}, "acceleration_limit must be finite and > 0"),
    ({"acceleration_limit": -4.0}, "acceleration_limit must be finite and > 0"),
    ({"acceleration_limit": math.nan}, "acceleration_limit must be finite and > 0"),
])
def test_limits_that_mean_nothing_are_refused(robot, samples, timing, keywords, message):
    """They used to give durations of 2e-9 s, NaN or inf, or be ignored."""
    with pytest.raises(ValueError, match=message):
        timing(robot, samples, [25], **keywords)


@pytest.mark.parametrize("timing", [sinusoidal_trajectory, time_optimal_trajectory])
def test_a_path_of_one_sample_or_not_finite_is_refused(robot, samples, timing):
    """One sample (a plan of one stance) raised an IndexError; NaN went through."""
    with pytest.raises(ValueError, match="at least 2 samples"):
        timing(robot, samples[:1], [])
    broken = samples.copy()
    broken[10, 8] = math.nan
    with pytest.raises(ValueError, match="not finite"):
        timing(robot, broken, [25])
    with pytest.raises(ValueError, match="rest samples must be in"):
        timing(robot, samples, [len(samples)])


def test_a_time_optimal_grid_below_one_is_refused(robot, samples):
    with pytest.raises(ValueError, match="grid must be an integer >= 1"):
        time_optimal_trajectory(robot, samples, [25], grid=0)


def test_a_time_optimal_timing_stops_when_asked_before_a_transition(robot, samples):
    """should_stop is asked before each transition (rest to rest): the first True
    abandons the timing."""
    asked = []
    with pytest.raises(Stopped, match="timing stopped at transition 1 -> 2"):
        time_optimal_trajectory(robot, samples, [25],
                                should_stop=lambda: asked.append(True) or len(asked) > 1)
    assert len(asked) == 2
    asked.clear()
    time_optimal_trajectory(robot, samples, [25], should_stop=lambda: asked.append(True))
    assert len(asked) == 2      # never True: both transitions timed
