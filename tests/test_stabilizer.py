"""The stabilizer gate (stance.execution.stabilizer): the paper's switching rule on plan
stances, a continuous blend over the ramp time, and the coplanarity tolerances."""

import dataclasses
import math

import numpy as np
import pinocchio as pin
import pytest
from stance.execution.stabilizer import (COM_POLYGON, END, START, STATIC_EQUILIBRIUM,
                                         LearnedSurfaces, StabilizerGate, Transition)
from stance.planning.contacts import Contact
from stance.planning.scene import Surface, load_scene

RAMP = 0.5  # s
FEET = (Contact("left_sole", "floor", 0.0, 0.1, 0.0),
        Contact("right_sole", "floor", 0.0, -0.1, 0.0))
HAND = Contact("right_hand", "table", -0.3, -0.2, 0.0)


@pytest.fixture(scope="module")
def chair_table():
    return load_scene("chair_table")


@pytest.fixture
def gate(chair_table):
    return StabilizerGate(chair_table, ramp_time=RAMP)


def hand_on_table_stances():
    """feet -> feet + hand on the table -> feet (the hand kept geometric, as plans do)."""
    return [FEET, FEET + (HAND,), FEET + (HAND.with_stability(False),)]


def walking_stances():
    """Static steps on the floor: lift the right foot, put it ahead, the same with the left."""
    left, right = FEET
    right_ahead = dataclasses.replace(right, x=0.15)
    left_ahead = dataclasses.replace(left, x=0.3)
    return [FEET, (left, right.with_stability(False)), (left, right_ahead),
            (left.with_stability(False), right_ahead), (left_ahead, right_ahead)]


def execution(gate, stances, times):
    """Transitions of stances executed over times: (start, end) per transition after the
    first stance."""
    supports = [gate.support(index, contacts) for index, contacts in enumerate(stances)]
    return [Transition(supports[0], 0.0, 0.0)] + [
        Transition(support, start, end) for support, (start, end) in zip(supports[1:], times)]


def test_coplanar_steps_never_switch(gate):
    stances = walking_stances()
    assert gate.schedule(stances) == []
    transitions = execution(gate, stances, [(k, k + 0.5) for k in range(1, len(stances))])
    for t in np.linspace(-1.0, 6.0, 141):
        state = gate.state(t, transitions)
        assert (state.enabled, state.blend, state.balance_mode) == (True, 1.0, COM_POLYGON)
        assert state.coplanar


def test_hand_on_table_switches_off_before_it_and_on_after_its_release(gate):
    events = gate.schedule(hand_on_table_stances())
    assert [(e.stance_index, e.at, e.enabled) for e in events] == [(1, START, False),
                                                                  (2, END, True)]
    assert "right_hand on table" in events[0].reason and "non-coplanar" in events[0].reason
    assert "right_hand on table released" in events[1].reason

    transitions = execution(gate, hand_on_table_stances(), [(1.0, 3.0), (4.0, 6.0)])
    before = gate.state(0.99, transitions)
    assert (before.enabled, before.blend, before.stance_index) == (True, 1.0, 0)
    switching_off = gate.state(1.0 + RAMP / 2, transitions)
    assert not switching_off.enabled and 0.0 < switching_off.blend < 1.0
    assert switching_off.balance_mode == STATIC_EQUILIBRIUM        # never dropped
    on_table = gate.state(3.5, transitions)
    assert (on_table.enabled, on_table.blend, on_table.stance_index, on_table.coplanar) == \
        (False, 0.0, 1, False)
    releasing = gate.state(5.9, transitions)                       # in the release transition
    assert (releasing.enabled, releasing.blend, releasing.stance_index) == (False, 0.0, 2)
    assert releasing.coplanar
    switching_on = gate.state(6.0 + RAMP / 2, transitions)
    assert switching_on.enabled and 0.0 < switching_on.blend < 1.0
    assert switching_on.balance_mode == COM_POLYGON
    assert "released" in switching_on.reason
    assert gate.state(6.0 + RAMP, transitions).blend == 1.0


def test_blend_is_continuous_bounded_and_takes_the_ramp_time(gate):
    transitions = execution(gate, hand_on_table_stances(), [(1.0, 3.0), (4.0, 6.0)])
    dt = 1e-3
    times = np.arange(0.0, 8.0, dt)
    blend = np.array([gate.state(t, transitions).blend for t in times])
    assert blend.min() == 0.0 and blend.max() == 1.0
    # Cubic ramp: slope at most 1.5 / RAMP, zero at both ends (C1).
    assert np.abs(np.diff(blend)).max() <= 1.5 / RAMP * dt * 1.01
    moving = times[1:][np.diff(blend) != 0.0]
    off = moving[moving < 3.0]
    on = moving[moving > 3.0]
    assert (off.min(), off.max()) == pytest.approx((1.0, 1.0 + RAMP), abs=2 * dt)
    assert (on.min(), on.max()) == pytest.approx((6.0, 6.0 + RAMP), abs=2 * dt)


def test_on_switch_waits_for_the_robot_to_reach_the_release_stance(gate):
    planned = execution(gate, hand_on_table_stances(), [(1.0, 3.0), (4.0, 6.0)])
    pending = planned[:2] + [dataclasses.replace(planned[2], reached=math.inf)]
    for t in (6.0, 6.5, 60.0):       # the planned end is past, the robot not known there
        state = gate.state(t, pending)
        assert (state.enabled, state.blend, state.balance_mode, state.stance_index) == \
            (False, 0.0, STATIC_EQUILIBRIUM, 2)
    assert gate.prune(pending, 60.0) == pending     # a pending switch is never pruned
    late = planned[:2] + [dataclasses.replace(planned[2], reached=6.8)]
    assert gate.state(6.79, late).blend == 0.0
    switching_on = gate.state(6.8 + RAMP / 2, late)
    assert switching_on.enabled and 0.0 < switching_on.blend < 1.0
    assert gate.state(6.8 + RAMP, late).blend == 1.0
    # reached before the planned end: the switch keeps the planned end
    early = planned[:2] + [dataclasses.replace(planned[2], reached=5.0)]
    times = np.arange(4.0, 7.0, 1e-3)
    assert [gate.state(t, early) for t in times] == [gate.state(t, planned) for t in times]


def test_off_ramp_ends_before_a_short_transition_creates_the_contact(gate):
    transitions = execution(gate, hand_on_table_stances(), [(1.0, 1.2), (4.0, 6.0)])
    assert 0.0 < gate.state(1.1, transitions).blend < 1.0
    assert gate.state(1.2, transitions).blend == 0.0


def test_switch_during_a_ramp_keeps_the_blend_continuous(gate):
    stances = hand_on_table_stances() + [FEET + (HAND,)]            # the hand comes back
    transitions = execution(gate, stances, [(1.0, 2.0), (3.0, 4.0), (4.1, 5.0)])
    times = np.arange(3.9, 5.0, 1e-3)
    blend = np.array([gate.state(t, transitions).blend for t in times])
    assert np.abs(np.diff(blend)).max() < 0.01
    assert 0.0 < blend[times < 4.1].max() < 1.0     # the on ramp was under way...
    assert blend[-1] == 0.0                         # ...and is undone before the new contact


def test_unsupported_stance_and_unknown_surface_are_refused(gate):
    with pytest.raises(ValueError, match="no supporting contact"):
        gate.support(3, (HAND.with_stability(False),))
    # a bare KeyError before; a NaN contact on the flat floor was classed non-coplanar
    with pytest.raises(ValueError, match="stance 0: contact .*@no_such_surface: unknown "
                                         "surface"):
        gate.support(0, (dataclasses.replace(HAND, surface="no_such_surface"),))
    with pytest.raises(ValueError, match="unknown spot"):
        gate.support(0, (dataclasses.replace(HAND, spot="nose"),))
    with pytest.raises(ValueError, match="x, y or theta not finite"):
        gate.support(0, FEET[:1] + (dataclasses.replace(FEET[1], x=math.nan),))
    with pytest.raises(ValueError, match="ramp_time"):
        StabilizerGate(None, ramp_time=0.0)
    with pytest.raises(ValueError, match="angle_tolerance"):
        StabilizerGate(None, angle_tolerance=math.nan)


def floors(tilt_deg=0.0, height=0.0):
    """flat_steps' floor plus a second floor beside it, tilted by tilt_deg about x and
    raised by height (m)."""
    scene = load_scene("flat_steps")
    rotation = pin.utils.rotate("x", math.radians(tilt_deg))
    second = Surface("second_floor", pin.SE3(rotation, np.array([0.0, -0.3, height])),
                     scene.surfaces["floor"].polygon, 0.7)
    return dataclasses.replace(scene, surfaces={**scene.surfaces, "second_floor": second})


def across_floors():
    return (Contact("left_sole", "floor", 0.0, 0.1, 0.0),
            Contact("right_sole", "second_floor", 0.0, 0.0, 0.0))


@pytest.mark.parametrize("tilt_deg, height, tolerances, coplanar", [
    (1.0, 0.0, {}, True),
    (5.0, 0.0, {}, False),
    (1.0, 0.0, {"angle_tolerance": math.radians(0.5)}, False),
    (0.0, 0.01, {}, False),
    (0.0, 0.01, {"distance_tolerance": 0.02}, True),
], ids=["1 deg within 2 deg", "5 deg", "1 deg beyond 0.5 deg", "1 cm step",
        "1 cm step within 2 cm"])
def test_tolerances_decide_coplanarity(tilt_deg, height, tolerances, coplanar):
    gate = StabilizerGate(floors(tilt_deg, height), **tolerances)
    assert gate.support(0, across_floors()).coplanar is coplanar
    stances = [across_floors()[:1], across_floors()]
    assert len(gate.schedule(stances)) == (0 if coplanar else 1)


def test_learned_surfaces_judge_contact_frames():
    lookup = LearnedSurfaces()
    floor = pin.SE3(np.eye(3), np.array([0.0, 0.1, 0.0]))
    table = pin.SE3(np.eye(3), np.array([0.5, 0.0, 0.75]))
    lookup.learn("left_sole", "floor", floor, 0.7)
    lookup.learn("right_hand", "table", table, 0.6)
    gate = StabilizerGate(lookup)
    assert gate.support(0, [Contact("left_sole", "floor", 0.0, 0.0, 0.0),
                            Contact("right_hand", "table", 0.0, 0.0, 0.0)]).coplanar is False
    lookup.learn("right_sole", "floor", table, 0.7)   # floor known: its first frame stays
    assert gate.support(1, [Contact("left_sole", "floor", 0.0, 0.0, 0.0),
                            Contact("right_sole", "floor", 0.3, -0.2, 0.0)]).coplanar


def test_pruned_history_gives_the_same_states_from_then_on(gate):
    stances = (hand_on_table_stances() + [FEET + (HAND,), FEET + (HAND.with_stability(False),)]
               + walking_stances()[1:])
    times = [(2.0 * k, 2.0 * k + 1.0) for k in range(1, len(stances))]
    transitions = execution(gate, stances, times)
    now = 9.2                   # the second release ended at 9 s: its on ramp is under way
    pruned = gate.prune(transitions, now)
    assert pruned == transitions[2:]   # from the stance before the second switch (off, at 6 s)
    for t in np.arange(now, 16.0, 0.01):
        assert gate.state(t, pruned) == gate.state(t, transitions)
    assert gate.prune(transitions, 9.0 + RAMP) == transitions[3:]
