"""The stabilizer gate: when the foot stabilizer may run along a contact plan (Escande et
al. 2008, section 4).

HRP-2's stabilizer "has been designed to deal only with planar contacts and must be
switched off when this is not the case"; "one needs to switch it off just before a
non-coplanar contact is created", and "switch it on just after the contact is released and
only coplanar contacts remain in the stance". The paper notes that "the stabilizer on-off
transitions result in discontinuities in the posture configurations"; here the switch
ramps a blend instead.

The rule, on the supporting contacts (in_stability) of consecutive stances:
- transition into stance k whose support is non-coplanar while stance k-1's was coplanar
  (a contact is created off the plane): OFF at the START of that transition, so the ramp
  is over before the contact is made (shortened to the transition if that is shorter);
- transition into stance k whose support is coplanar while stance k-1's was not (the last
  off-plane contact leaves the support): ON at the END of that transition, and not before
  the robot is known to be at stance k (Transition.reached: a robot late on its plan is
  still moving its weight off the released contact at the planned end);
- every other transition: no switch.
"Released" is taken as out of the support: a plan stance keeps a removed contact as
geometric (in_stability False) while its witness still touches it, and the next transition
lifts it (stance.planning.planner).

While ON the kinematic balance constraint is the CoM over the support polygon
(`com_polygon`, equilibrium.support_polygon); while OFF it is static equilibrium on all
supporting contacts (`static_equilibrium`, equilibrium.contacts_equilibrium): balance is
switched, never dropped. Times in s, lengths in m, angles in rad, world frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ..limits import cubic_step
from ..planning.equilibrium import are_coplanar
from ..planning.scene import ContactSpot, Surface

# The plain Python smoothstep: a first JIT call would stall a publishing loop (~0.2 s).
# (cubic_step is that function already where NUMBA_DISABLE_JIT is set.)
_smoothstep = getattr(cubic_step, "py_func", cubic_step)

START, END = "start", "end"        # which end of the transition into a stance a switch is at
# Transition.reached: not known yet (an END switch waits), or the planned end is trusted
NOT_YET_REACHED, PLANNED_END_TRUSTED = math.inf, -math.inf
COM_POLYGON = "com_polygon"                  # balance mode while the stabilizer is on
STATIC_EQUILIBRIUM = "static_equilibrium"    # balance mode while it is off


@dataclass(frozen=True)
class Support:
    """The supporting contacts of stance `index`: coplanar or not, their (spot, surface)
    pairs."""

    index: int
    coplanar: bool
    pairs: frozenset


@dataclass(frozen=True)
class SwitchEvent:
    """Switch the stabilizer to `enabled` at the start or end (`at`) of the transition into
    stance `stance_index`."""

    stance_index: int
    at: str
    enabled: bool
    reason: str


@dataclass(frozen=True)
class Transition:
    """The motion into `support`'s stance over [start, end] (s, `end` as planned). The first
    transition of an execution stands for the stance it starts in: its times are not used.

    reached: when the robot was known to be at the stance (s). A switch at the END of the
    transition waits for it (at max(end, reached)): a robot late on its plan is still
    releasing the contact at the planned end. NOT_YET_REACHED: the switch is pending (only
    the last transition of a list may be); PLANNED_END_TRUSTED (default): at the planned
    end.
    """

    support: Support
    start: float
    end: float
    reached: float = PLANNED_END_TRUSTED

    def switch_time(self, at: str) -> float:
        """When a switch at the START or END (`at`) of this transition happens (s)."""
        return self.start if at == START else max(self.end, self.reached)


@dataclass(frozen=True)
class GateState:
    """The gate at one instant: enabled (commanded), blend in [0, 1] (0 off, 1 on), the
    balance mode to enforce, the reason of the last switch, and the current stance."""

    enabled: bool
    blend: float
    balance_mode: str
    reason: str
    stance_index: int
    coplanar: bool


class StabilizerGate:
    """Decides coplanarity of supports and when the stabilizer switches.

    scene: the surface lookup the contacts name (a Scene, or LearnedSurfaces); coplanar:
    surface normals within angle_tolerance (rad) and every patch vertex within
    distance_tolerance (m) of the first contact's plane (equilibrium.are_coplanar).
    ramp_time: s for the blend to go from 0 to 1 or back (cubic, C1 at both ends).
    """

    def __init__(self, scene, angle_tolerance: float = math.radians(2.0),
                 distance_tolerance: float = 0.005, ramp_time: float = 0.5):
        for name, value in (("angle_tolerance", angle_tolerance),
                            ("distance_tolerance", distance_tolerance)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        if not (math.isfinite(ramp_time) and ramp_time > 0.0):
            raise ValueError(f"ramp_time must be finite and > 0 s, got {ramp_time}")
        self.scene = scene
        self.angle_tolerance = angle_tolerance
        self.distance_tolerance = distance_tolerance
        self.ramp_time = ramp_time

    def support(self, index: int, contacts) -> Support:
        """Support of stance `index` from all its contacts (only in_stability ones count).
        Raises ValueError when none supports, or for a contact on a surface or spot the
        scene lacks or with numbers that are not finite (a NaN contact on a flat floor was
        classed non-coplanar: the stabilizer would have switched off)."""
        supporting = [c for c in contacts if c.in_stability]
        if not supporting:
            raise ValueError(f"stance {index} has no supporting contact")
        for contact in supporting:
            where = f"stance {index}: contact {contact.spot}@{contact.surface}"
            if contact.surface not in self.scene.surfaces:
                raise ValueError(f"{where}: unknown surface")
            if contact.spot not in self.scene.spots:
                raise ValueError(f"{where}: unknown spot")
            if not all(math.isfinite(value) for value in (contact.x, contact.y,
                                                          contact.theta)):
                raise ValueError(f"{where}: x, y or theta not finite")
        coplanar = are_coplanar(supporting, self.scene, self.angle_tolerance,
                                self.distance_tolerance)
        return Support(index, coplanar, frozenset(c.pair for c in supporting))

    def schedule(self, stances) -> list[SwitchEvent]:
        """The switches along a plan; stances: each stance's contacts, in plan order
        (e.g. [s.contacts for s in plan.stances])."""
        supports = [self.support(index, contacts) for index, contacts in enumerate(stances)]
        events = (switch(before, after) for before, after in zip(supports, supports[1:]))
        return [event for event in events if event is not None]

    def state(self, t: float, transitions) -> GateState:
        """The gate at time t (s) along `transitions` (Transition, in execution order; the
        first is the start stance). Transitions starting after t are not entered yet."""
        if not transitions:
            raise ValueError("state needs at least the start stance")
        current = transitions[0].support
        enabled = current.coplanar
        reason = (f"stance {current.index}: "
                  f"{'coplanar' if current.coplanar else 'non-coplanar'} support")
        ramp = _Ramp(-math.inf, float(enabled), float(enabled), self.ramp_time)
        for previous, transition in zip(transitions, transitions[1:]):
            if transition.start > t:
                break
            current = transition.support
            event = switch(previous.support, current)
            if event is None:
                continue
            at = max(transition.switch_time(event.at), ramp.origin)
            if at > t:
                break
            duration = self.ramp_time
            if event.at == START and transition.end > transition.start:
                duration = min(duration, transition.end - transition.start)
            ramp = _Ramp(at, ramp.value(at), float(event.enabled), duration)
            enabled, reason = event.enabled, event.reason
        return GateState(enabled, ramp.value(t), COM_POLYGON if enabled else STATIC_EQUILIBRIUM,
                         reason, current.index, current.coplanar)

    def prune(self, transitions, t: float) -> list:
        """The tail of `transitions` that gives the same states at t (s) and later: from the
        stance before the last switch whose ramp is over by t (all of them if none is)."""
        for index in range(len(transitions) - 1, 0, -1):
            transition = transitions[index]
            event = switch(transitions[index - 1].support, transition.support)
            if event is not None:
                if transition.switch_time(event.at) + self.ramp_time <= t:
                    return list(transitions[index - 1:])
        return list(transitions)


def switch(before: Support, after: Support) -> SwitchEvent | None:
    """The paper's rule for the transition from `before`'s stance to `after`'s (module
    docstring); None when the stabilizer keeps its state."""
    if before.coplanar and not after.coplanar:
        created = _names(after.pairs - before.pairs)
        return SwitchEvent(after.index, START, False,
                           f"stance {after.index}: {created} makes the support non-coplanar: "
                           "off before the contact is created")
    if after.coplanar and not before.coplanar:
        released = _names(before.pairs - after.pairs)
        return SwitchEvent(after.index, END, True,
                           f"stance {after.index}: {released} released, only coplanar "
                           "contacts remain: on after the release")
    return None


@dataclass(frozen=True)
class _Ramp:
    """Blend going from `start_value` at `origin` (s) to `target`; a full 0-1 swing takes
    `duration` s, a partial one (a switch during a ramp) proportionally less."""

    origin: float
    start_value: float
    target: float
    duration: float

    def value(self, t: float) -> float:
        swing = self.target - self.start_value
        if swing == 0.0 or t <= self.origin:
            return self.start_value
        progress = (t - self.origin) / (self.duration * abs(swing))
        return self.start_value + swing * _smoothstep(progress)


def _names(pairs) -> str:
    return ", ".join(f"{spot} on {surface}" for spot, surface in sorted(pairs)) or "no contact"


class LearnedSurfaces:
    """A surface lookup for contacts known only by their contact frames (no scene).

    The first contact seen on a surface name defines that surface: its contact frame
    (z = outward normal). Spots are points at their frame origins, so coplanarity is judged
    on the contact frames' origins and normals, not on patches.
    """

    def __init__(self):
        self.surfaces = {}
        self.spots = {}

    def copy(self) -> LearnedSurfaces:
        """A lookup knowing what this one knows, learning on its own from now on."""
        other = LearnedSurfaces()
        other.surfaces, other.spots = dict(self.surfaces), dict(self.spots)
        return other

    def learn(self, spot: str, surface: str, contact_frame: pin.SE3, friction: float) -> None:
        """Remember `surface` at contact_frame (world) and `spot` as a point, if unknown."""
        if surface not in self.surfaces:
            self.surfaces[surface] = Surface(surface, contact_frame, np.zeros((0, 2)),
                                             float(friction))
        if spot not in self.spots:
            self.spots[spot] = ContactSpot(spot, "", pin.SE3.Identity(), np.zeros((1, 2)))
