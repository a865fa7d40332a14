"""Task errors and step caps: the compiled frame error against Pinocchio's log3, and the
per-group norm caps of a task's step."""

import numpy as np
import pinocchio as pin
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from stance.stack import TaskSpec
from stance.tasks import capped_steps, frame_error, make_task, step_cap_groups

PROPERTY = settings(max_examples=300, deadline=None, derandomize=True, database=None)
ANGLES = st.one_of(st.floats(0.0, np.pi), st.floats(0.0, 1e-3), st.floats(np.pi - 2e-2, np.pi),
                   st.sampled_from([0.0, 1e-9, 1e-4, np.pi - 1e-2, np.pi - 1e-9, np.pi]))


@PROPERTY
@given(st.integers(0, 2**32 - 1), ANGLES)
def test_frame_error_is_pinocchios_log3(seed, angle):
    rng = np.random.default_rng(seed)
    current = Rotation.random(random_state=rng).as_matrix()
    axis = rng.normal(size=3)
    relative = pin.exp3(angle * axis / np.linalg.norm(axis))
    target = relative @ current
    translation, target_translation = rng.normal(size=3), rng.normal(size=3)
    error = np.empty(6)
    frame_error(pin.SE3(target, target_translation).homogeneous,
                pin.SE3(current, translation).homogeneous, error)
    np.testing.assert_allclose(error[:3], target_translation - translation, atol=1e-15)
    assert np.linalg.norm(error[3:]) <= np.pi + 1e-12
    # the same rotation (at exactly pi, +-axis are both right)
    np.testing.assert_allclose(pin.exp3(error[3:]), target @ current.T, atol=1e-9)
    if angle < np.pi - 1e-6:
        np.testing.assert_allclose(error[3:], pin.log3(target @ current.T), atol=1e-9)


@PROPERTY
@given(st.lists(st.floats(-10.0, 10.0), min_size=6, max_size=6), st.floats(0.01, 1.0))
def test_frame_task_caps_translation_and_rotation_separately(values, gain):
    task = make_task(TaskSpec("hand", "pose", frame="hand", gain=gain), _FakeRobot())
    error = np.array(values)
    step = np.empty(6)
    capped_steps(error, np.full(6, gain), *step_cap_groups([task]), np.ones(6), step)
    for part, cap in ((slice(0, 3), task.max_linear_step), (slice(3, 6), task.max_angular_step)):
        wanted = gain * error[part]
        norm = np.linalg.norm(wanted)
        expected = wanted * min(1.0, cap / norm) if norm > 0 else wanted
        np.testing.assert_allclose(step[part], expected, rtol=1e-12, atol=1e-15)


class _FakeRobot:
    """Just what a FrameTask's constructor asks of a robot."""

    def frame_id(self, frame):
        return 0
