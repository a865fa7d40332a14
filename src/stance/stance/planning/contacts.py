"""Contacts, stances and plans (the planner's output), and their files.

A contact places a robot contact spot on an environment surface at (x, y, theta) in the
surface frame: the spot frame's origin goes to the surface point (x, y, 0) and the spot's
z axis points against the surface normal, rotated by theta (rad) about the normal.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace

import numpy as np
import pinocchio as pin

# Spot frame relative to the contact frame on the surface: z flipped (rotation of pi about x).
SPOT_IN_CONTACT = pin.SE3(np.diag([1.0, -1.0, -1.0]), np.zeros(3))


@dataclass(frozen=True)
class Contact:
    """Spot `spot` on surface `surface` at (x, y) m and theta rad in the surface frame.

    in_stability: False while the contact is only geometric (being broken, or new and not
    yet trusted for support: Escande et al. section 2.3).
    """

    spot: str
    surface: str
    x: float
    y: float
    theta: float
    in_stability: bool = True

    @property
    def pair(self) -> tuple:
        return (self.spot, self.surface)

    def contact_frame(self, surface) -> pin.SE3:
        """Contact frame in the world: on the surface, z = the surface's outward normal."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        local = pin.SE3(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]),
                        np.array([self.x, self.y, 0.0]))
        return surface.pose * local

    def spot_target(self, surface) -> pin.SE3:
        """Where the robot's spot frame must be in the world (z against the normal)."""
        return self.contact_frame(surface) * SPOT_IN_CONTACT

    def with_stability(self, in_stability: bool) -> Contact:
        return replace(self, in_stability=in_stability)


@dataclass
class Stance:
    """A set of contacts with a witness posture q (size nq) that realises it."""

    contacts: tuple
    q: np.ndarray
    potential: float = float("nan")

    def supporting(self) -> tuple:
        return tuple(c for c in self.contacts if c.in_stability)


@dataclass
class Plan:
    """A sequence of stances, consecutive ones differing by one contact, and how the search
    went (nodes expanded, posture generations, seconds)."""

    scene: str
    robot: str
    stances: list
    statistics: dict = field(default_factory=dict)


def contact_to_dict(contact: Contact) -> dict:
    return {"spot": contact.spot, "surface": contact.surface, "x": contact.x, "y": contact.y,
            "theta": contact.theta, "in_stability": contact.in_stability}


def contact_from_dict(entry: dict) -> Contact:
    return Contact(str(entry["spot"]), str(entry["surface"]), float(entry["x"]),
                   float(entry["y"]), float(entry["theta"]), bool(entry.get("in_stability", True)))


def save_plan(plan: Plan, path: str) -> None:
    """Write a plan as JSON (configurations as lists, nq values each)."""
    document = {
        "scene": plan.scene, "robot": plan.robot, "statistics": plan.statistics,
        "stances": [{"contacts": [contact_to_dict(c) for c in stance.contacts],
                     "q": [float(v) for v in stance.q], "potential": stance.potential}
                    for stance in plan.stances],
    }
    with open(path, "w") as stream:
        json.dump(document, stream, indent=1)


def load_plan(path: str) -> Plan:
    with open(path) as stream:
        document = json.load(stream)
    stances = [Stance(tuple(contact_from_dict(c) for c in entry["contacts"]),
                      np.array(entry["q"], dtype=float), float(entry.get("potential", "nan")))
               for entry in document["stances"]]
    return Plan(document["scene"], document["robot"], stances, document.get("statistics", {}))
