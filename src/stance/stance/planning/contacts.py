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


class PlanFileError(ValueError):
    """A plan file that is not a plan; the message names the file and the field."""


def contact_from_dict(entry: dict, where: str = "contact") -> Contact:
    """A Contact from its dictionary (contact_to_dict's); PlanFileError naming `where` and
    the field for a missing key, a wrong type or a number that is not finite."""
    if not isinstance(entry, dict):
        raise PlanFileError(f"{where}: expected a mapping, got {type(entry).__name__}")
    missing = [key for key in ("spot", "surface", "x", "y", "theta") if key not in entry]
    if missing:
        raise PlanFileError(f"{where}.{missing[0]}: missing")
    for key in ("spot", "surface"):
        if not isinstance(entry[key], str):
            raise PlanFileError(f"{where}.{key}: expected a string")
    numbers = [_finite(entry[key], f"{where}.{key}") for key in ("x", "y", "theta")]
    in_stability = entry.get("in_stability", True)
    if not isinstance(in_stability, bool):     # bool("false") is True
        raise PlanFileError(f"{where}.in_stability: expected true or false")
    return Contact(entry["spot"], entry["surface"], *numbers, in_stability)


def _finite(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not math.isfinite(value):
        raise PlanFileError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


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
    """The plan save_plan wrote; PlanFileError naming the file and the field when it is not
    one (the witnesses' size is the verifier's business: it knows the robot)."""
    try:
        with open(path, encoding="utf-8") as stream:
            document = json.load(stream)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise PlanFileError(f"{path}: not a JSON plan file ({error})") from None
    try:
        return _plan_from_document(document)
    except PlanFileError as error:
        raise PlanFileError(f"{path}: {error}") from None


def _plan_from_document(document) -> Plan:
    if not isinstance(document, dict):
        raise PlanFileError(f"expected a mapping, got {type(document).__name__}")
    for key in ("scene", "robot", "stances"):
        if key not in document:
            raise PlanFileError(f"{key}: missing")
    for key in ("scene", "robot"):
        if not isinstance(document[key], str):
            raise PlanFileError(f"{key}: expected a string")
    if not isinstance(document["stances"], list):
        raise PlanFileError("stances: expected a list")
    stances = []
    for index, entry in enumerate(document["stances"]):
        where = f"stances[{index}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("contacts"), list):
            raise PlanFileError(f"{where}: expected a mapping with a contacts list")
        q = entry.get("q")
        if not isinstance(q, list) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in q):
            raise PlanFileError(f"{where}.q: expected a list of numbers")
        contacts = tuple(contact_from_dict(c, f"{where}.contacts[{k}]")
                         for k, c in enumerate(entry["contacts"]))
        potential = entry.get("potential")
        if potential is not None and (isinstance(potential, bool)
                                      or not isinstance(potential, (int, float))):
            raise PlanFileError(f"{where}.potential: expected a number")
        stances.append(Stance(contacts, np.array(q, dtype=float),
                              math.nan if potential is None else float(potential)))
    statistics = document.get("statistics", {})
    return Plan(document["scene"], document["robot"], stances,
                statistics if isinstance(statistics, dict) else {})
