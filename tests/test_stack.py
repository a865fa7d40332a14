"""Stack validation: every malformed stack is rejected with a message naming the culprit,
and a rejected stack leaves the solver's previous stack and targets untouched."""

import math
from dataclasses import replace

import numpy as np
import pytest

from stance.pik import PIKSolver, default_stack_specs
from stance.robot import Robot
from stance.stack import (FRAME_KINDS, MAX_PRIORITY, StackError, TaskSpec, parse_stack_yaml,
                          validate_stack)
from stance.tasks import TargetError

FRAMES = {"left_sole_link", "gripper_right_base_link"}
HAND = TaskSpec("hand", "pose", frame="gripper_right_base_link")
COM_XY = TaskSpec("com", "com", priority=1, axes=("x", "y"))


@pytest.fixture(scope="module")
def talos():
    return Robot.from_example_robot_data("talos")


def rejects(specs, match: str) -> None:
    with pytest.raises(StackError, match=match):
        validate_stack(specs, FRAMES.__contains__)


def rejects_spec(match: str, **changes) -> None:
    """A one-task stack: HAND with `changes` applied (no frame for frameless kinds)."""
    spec = replace(HAND, **changes)
    if spec.kind not in FRAME_KINDS:
        spec = replace(spec, frame="")
    rejects([spec], match)


def test_valid_stack_is_accepted():
    assert validate_stack([HAND, COM_XY], FRAMES.__contains__) == [HAND, COM_XY]


def test_duplicate_names_are_rejected():
    rejects([HAND, TaskSpec("hand", "com")], "duplicate task name 'hand'")


def test_unknown_frame_is_rejected():
    rejects_spec("unknown frame 'no_such_link'", frame="no_such_link")


def test_empty_stack_is_rejected():
    rejects([], "empty")


@pytest.mark.parametrize("priority", [-1, MAX_PRIORITY + 1, True, 1.0, "0"])
def test_out_of_range_priority_is_rejected(priority):
    rejects_spec("priority", priority=priority)


@pytest.mark.parametrize("weight", [math.nan, math.inf, -math.inf, 0.0, -1.0, "1", 1e40,
                                    1e-30, 2e6, 5e-7])
def test_a_weight_outside_1e_6_to_1e6_is_rejected(weight):
    """1e40 on one foot let the other, on the same priority-0 level, slide 0.28 m while the
    level reported `met`; 1e-30 left a task 0.32 m off."""
    rejects_spec(r"weight must be a number in \[1e-06, 1e\+06\]", weight=weight)


@pytest.mark.parametrize("weight", [1e-6, 1e6])
def test_the_weight_bounds_are_accepted(weight):
    validate_stack([replace(HAND, weight=weight)])


def test_a_stack_of_more_than_64_tasks_is_rejected():
    """1000 one-axis CoM tasks took pik_node from 500 Hz to 40 Hz without a word."""
    tasks = [TaskSpec(f"com{index}", "com", axes=("x",)) for index in range(65)]
    validate_stack(tasks[:64])
    rejects(tasks, "the stack has 65 tasks, more than 64")


@pytest.mark.parametrize("gain", [0.0, -0.1, 1.5, math.nan, math.inf])
def test_gain_outside_zero_one_is_rejected(gain):
    rejects_spec("gain", gain=gain)


@pytest.mark.parametrize("kind, axes", [
    ("position", ("rx",)), ("orientation", ("x",)), ("com", ("rz",)), ("pose", ("w",)),
    ("pose", ("x", "x")),
])
def test_axes_invalid_for_the_kind_are_rejected(kind, axes):
    rejects_spec("axis", kind=kind, axes=axes)


def test_posture_takes_no_axes():
    rejects_spec("axis 'x' not valid for kind posture", kind="posture", axes=("x",))


@pytest.mark.parametrize("frame", [5, ["left_sole_link"]])
def test_frame_that_is_not_a_string_is_rejected(frame):
    rejects_spec("frame must be a string", frame=frame)


@pytest.mark.parametrize("enabled", ["false", 0, None])
def test_enabled_that_is_not_a_bool_is_rejected(enabled):
    rejects_spec("enabled", enabled=enabled)


@pytest.mark.parametrize("text", ["tasks: [", "- {name: a, kind: com", "\t- a"])
def test_malformed_yaml_is_rejected(text):
    with pytest.raises(StackError, match="not valid YAML"):
        parse_stack_yaml(text)


@pytest.mark.parametrize("text", ["42", "tasks: 3", "name: a"])
def test_yaml_that_is_not_a_task_list_is_rejected(text):
    with pytest.raises(StackError, match="list of tasks"):
        parse_stack_yaml(text)


def test_unknown_yaml_keys_are_rejected():
    with pytest.raises(StackError, match=r"task 'a': unknown keys \['frmae', 'prio'\]"):
        parse_stack_yaml("- {name: a, kind: com, prio: 1, frmae: x}")


@pytest.mark.parametrize("entry, match", [
    ("{name: a, kind: com, axes: 5}", "axis 5"),
    ("{name: a, kind: pose, frame: 5}", "frame must be a string"),
    ("{name: a, kind: com, enabled: maybe}", "enabled must be true or false"),
])
def test_yaml_values_of_the_wrong_type_are_rejected(talos, entry, match):
    """Checked against the robot's own frame lookup, as pik_node does."""
    with pytest.raises(StackError, match=match):
        parse_stack_yaml(f"- {entry}", talos.model.existFrame)


def test_yaml_stack_parses_to_specs():
    specs = parse_stack_yaml("tasks:\n  - {name: hand, kind: pose, frame: gripper_right_base_link}"
                             "\n  - {name: com, kind: com, priority: 1, axes: [x, y]}")
    assert specs == [HAND, COM_XY]


def test_exponents_without_a_dot_are_numbers():
    """YAML 1.1 (PyYAML) read 5e-1 as a string, refused as a gain of the wrong type."""
    spec, = parse_stack_yaml("- {name: com, kind: com, gain: 5e-1, weight: 2E0}")
    assert (spec.gain, spec.weight) == (0.5, 2.0)


# set_stack is atomic: a failure keeps the previous stack and its targets.

@pytest.fixture
def solver(talos):
    """The demo stack with a right-hand target moved away from its held value."""
    solver = PIKSolver(talos)
    solver.set_stack(default_stack_specs(), talos.initial_configuration())
    target = solver.task("right_hand").target
    target.translation += [0.1, 0.0, 0.2]
    solver.task("right_hand").set_target(target)
    return solver


def targets(solver) -> dict:
    """Every task's target as an array (a frame target as its 4x4 matrix)."""
    return {name: np.array(getattr(task.target, "homogeneous", task.target))
            for name, task in solver.tasks.items()}


@pytest.mark.parametrize("bad_stack, bad_q", [
    ([TaskSpec("com", "com"), TaskSpec("com", "com", priority=1)], False),
    ([TaskSpec("hand", "pose", frame="no_such_link")], False),
    ([TaskSpec("com", "com")], True),
], ids=["duplicate", "unknown_frame", "wrong_size_q"])
def test_failed_set_stack_keeps_previous_stack_and_targets(talos, solver, bad_stack, bad_q):
    q = talos.initial_configuration()
    specs_before, targets_before = solver.stack(), targets(solver)
    expected_step = solver.step(q).q

    with pytest.raises((StackError, ValueError)):
        solver.set_stack(bad_stack, q[:-1] if bad_q else q)

    assert solver.stack() == specs_before
    targets_after = targets(solver)
    assert targets_after.keys() == targets_before.keys()
    assert all(np.array_equal(targets_after[name], targets_before[name])
               for name in targets_before)
    assert np.array_equal(solver.step(q).q, expected_step)


def test_a_target_read_from_a_task_is_a_copy(solver):
    """Mutating what `target` returned must not desynchronize the tracked target."""
    task = solver.task("right_hand")
    before = task.target
    task.target.translation[:] = 0.0
    assert np.array_equal(task.target.homogeneous, before.homogeneous)


@pytest.mark.parametrize("name", ["hand\n", "hand\nfoot", "1hand", "a" * 65])
def test_a_name_that_cannot_name_its_target_topic_is_rejected(name):
    rejects_spec("task name", name=name)


def test_a_name_of_the_longest_length_is_accepted():
    spec = replace(HAND, name="a" * 64)
    assert validate_stack([spec], FRAMES.__contains__) == [spec]


@pytest.mark.parametrize("joint, message", [("universe", "the world"),
                                            ("root_joint", "not a one-coordinate joint"),
                                            ("no_such_joint", "unknown joint")])
def test_a_posture_target_names_only_the_robots_one_coordinate_joints(talos, solver, joint,
                                                                      message):
    task = solver.task("posture")
    before = task.target.copy()
    with pytest.raises(TargetError, match=message):
        task.set_joint_targets(talos, {joint: 0.1})
    assert np.array_equal(task.target, before)


@pytest.mark.parametrize("task_name", ["right_hand", "com"])
@pytest.mark.parametrize("coordinate", [1e7, -1e300])
def test_a_position_target_beyond_the_bound_is_refused(solver, task_name, coordinate):
    """Finite but absurd: at 1e300 m the capped step overflowed to 0 and the level said
    'met' with an infinite error."""
    task = solver.task(task_name)
    before = task.target
    target = before.copy()
    if task_name == "com":
        target[0] = coordinate
    else:
        target.translation[0] = coordinate
    with pytest.raises(TargetError, match="beyond 1e\\+06 m"):
        task.set_target(target)
    after = task.target
    assert np.array_equal(getattr(after, "homogeneous", after),
                          getattr(before, "homogeneous", before))
