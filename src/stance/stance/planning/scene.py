"""Scenes for contact planning: environment contact surfaces, collision obstacles, robot
contact spots, the start stance, key postures of the rough trajectory and the goal.

Frames: everything is in the world frame (z up, m, rad). A surface's frame has its z axis
along the outward normal; its polygon lies in the frame's xy-plane. A robot contact spot is
a frame fixed on a robot body whose z axis points out of the body; in contact, the spot
frame's z is opposite to the surface normal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from ..robot import Robot, RobotModelError, is_urdf_path
from ..tasks import MAX_COORDINATE
from ..yaml_file import load_yaml_file
from .potential import RoughTrajectory

DEFAULT_POTENTIAL_SLOPE = 10.0
MAX_NUMBER = MAX_COORDINATE   # m, rad or unitless: a scene's numbers stay below it in magnitude


class SceneError(ValueError):
    """A scene file is malformed; the message names the offending field."""


@dataclass(frozen=True)
class Surface:
    """A convex planar contact surface of the environment.

    pose: surface frame in the world (z = outward normal).
    polygon: (N, 2) convex vertices, counter-clockwise, in the surface frame's xy (m).
    friction: Coulomb coefficient.
    obstacle: name of the obstacle the surface lies on: collisions between that obstacle
        and a body in contact with the surface are not counted, or None.
    """

    name: str
    pose: pin.SE3
    polygon: np.ndarray
    friction: float
    obstacle: str | None = None


@dataclass(frozen=True)
class Obstacle:
    """A collision obstacle: a box (size = full extents, m) or a mesh (path, scale)."""

    name: str
    shape: str                      # "box" or "mesh"
    pose: pin.SE3                   # box centre or mesh origin in the world
    size: np.ndarray | None = None  # box extents (m)
    mesh: str | None = None         # absolute path of a mesh file
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))


@dataclass(frozen=True)
class ContactSpot:
    """A place on the robot that may take contact.

    frame: a frame of the robot model (its parent joint moves the spot).
    placement: spot frame relative to `frame` (z points out of the body).
    patch: (M, 2) convex contact patch vertices in the spot frame's xy (m).
    surfaces: names of the surfaces this spot may touch (empty: all).
    """

    name: str
    frame: str
    placement: pin.SE3
    patch: np.ndarray
    surfaces: tuple = ()


@dataclass(frozen=True)
class ContactSpec:
    """A fixed contact in a scene file: spot on surface at (x, y, theta) in the surface
    frame (m, m, rad)."""

    spot: str
    surface: str
    x: float
    y: float
    theta: float


@dataclass(frozen=True)
class Goal:
    """Goal condition: the world coordinate `axis` (x, y or z) of `frame`'s origin passes
    `threshold` (m) in direction `sense` (+1: greater than, -1: less than)."""

    frame: str
    axis: str
    threshold: float
    sense: int = 1

    def reached(self, position: np.ndarray) -> bool:
        value = float(position["xyz".index(self.axis)])
        return (value - self.threshold) * self.sense > 0.0


@dataclass
class Scene:
    """Everything the planner needs besides the robot model.

    robot: robot spec for stance.robot.Robot.load (e.g. "talos").
    surfaces, obstacles, spots: Surface, Obstacle and ContactSpot by name.
    start: the start stance's contacts (ContactSpec list, all in stability).
    start_configuration: q (size nq) near which the start posture is sought.
    key_postures: (K, nq) configurations of the rough trajectory, K >= 2.
    """

    name: str
    robot: str
    surfaces: dict
    obstacles: dict
    spots: dict
    start: list
    start_configuration: np.ndarray
    key_postures: np.ndarray
    goal: Goal
    potential_slope: float = 10.0   # k of the potential f_T (f units per m along T')
    locked_joints: tuple = ()       # joint names the posture generator never moves
    source: str = ""                # path of the scene file, for messages


SCENE_DIRECTORY = Path(__file__).resolve().parent.parent / "data" / "scenes"

# Relative tolerance of the convexity tests on polygons (cross products, in m^2).
_CONVEXITY_EPSILON = 1e-12


def scene_names() -> list[str]:
    """Names of the scenes shipped in stance/data/scenes."""
    return sorted(path.stem for path in SCENE_DIRECTORY.glob("*.yaml"))


def load_scene(spec: str, robot=None) -> Scene:
    """Load a shipped scene by name (see scene_names) or a scene YAML file by path.

    robot: a stance.robot.Robot to check frame and joint names against; default the
    scene's own `robot` field, loaded with Robot.load.
    """
    path = SCENE_DIRECTORY / f"{spec}.yaml" if spec in scene_names() else Path(spec)
    if not path.is_file():
        raise SceneError(f"unknown scene {spec!r}: neither a shipped scene "
                         f"({', '.join(scene_names())}) nor a file")
    document = load_yaml_file(path, SceneError)
    return parse_scene(document, str(path), robot)


def parse_scene(document: dict, source: str, robot=None) -> Scene:
    """Build and validate a Scene from a parsed YAML document (format: docs/scenes.md).

    source: the file the document came from (relative mesh paths are resolved against its
    directory; other sources resolve them against the current directory), or a label such
    as "<goal>", used in messages.
    """
    return _SceneParser(source, robot).scene(document)


class _SceneParser:
    """Validation with field paths such as `surfaces[2].polygon` in every error."""

    def __init__(self, source: str, robot):
        self.source = source
        self.robot = robot
        source_path = Path(source)
        self.directory = source_path.parent if source_path.is_file() else Path.cwd()

    def fail(self, path: str, reason: str):
        raise SceneError(f"{path or 'document'}: {reason} (scene {self.source})")

    def scene(self, document) -> Scene:
        fields = self.mapping(document, "", ("name", "robot", "surfaces", "obstacles", "spots",
                                             "start", "key_postures", "goal"),
                              ("potential_slope", "locked_joints"))
        name = self.string(fields["name"], "name")
        robot_spec = self.string(fields["robot"], "robot")
        given = getattr(self.robot, "name", None)
        if given is not None and given != robot_spec and not is_urdf_path(robot_spec):
            self.fail("robot", f"the scene is for {robot_spec!r}, the robot given is {given!r}")
        if self.robot is None:
            try:
                self.robot = Robot.load(robot_spec)
            except RobotModelError as error:
                self.fail("robot", str(error))
        obstacles = self.named(fields["obstacles"], "obstacles", self.obstacle)
        surfaces = self.named(fields["surfaces"], "surfaces", self.surface)
        for index, surface in enumerate(surfaces.values()):
            if surface.obstacle is not None and surface.obstacle not in obstacles:
                self.fail(f"surfaces[{index}].obstacle", f"unknown obstacle {surface.obstacle!r}")
        spots = self.named(fields["spots"], "spots", self.spot)
        for index, spot in enumerate(spots.values()):
            for k, surface in enumerate(spot.surfaces):
                if surface not in surfaces:
                    self.fail(f"spots[{index}].surfaces[{k}]", f"unknown surface {surface!r}")
        start = self.mapping(fields["start"], "start", ("configuration", "contacts"))
        start_configuration = self.configuration(start["configuration"], "start.configuration")
        contacts = self.sequence(start["contacts"], "start.contacts")
        start_contacts = [self.contact(entry, f"start.contacts[{i}]", surfaces, spots)
                          for i, entry in enumerate(contacts)]
        used_spots = [contact.spot for contact in start_contacts]
        for index, spot in enumerate(used_spots):
            if spot in used_spots[:index]:
                self.fail(f"start.contacts[{index}].spot", f"spot {spot!r} is used twice")
        postures = self.sequence(fields["key_postures"], "key_postures")
        if len(postures) < 2:
            self.fail("key_postures", f"needs at least 2 postures, got {len(postures)}")
        key_postures = np.array([self.configuration(entry, f"key_postures[{i}]")
                                 for i, entry in enumerate(postures)])
        potential_slope = self.number(fields.get("potential_slope", DEFAULT_POTENTIAL_SLOPE),
                                      "potential_slope", positive=True)
        try:    # the planner's rough trajectory through them: bases apart, turns bounded
            RoughTrajectory(self.robot.model, key_postures, k=potential_slope)
        except ValueError as error:
            self.fail("key_postures", str(error))
        return Scene(name=name, robot=robot_spec, surfaces=surfaces, obstacles=obstacles,
                     spots=spots, start=start_contacts, start_configuration=start_configuration,
                     key_postures=key_postures, goal=self.goal(fields["goal"]),
                     potential_slope=potential_slope,
                     locked_joints=self.locked_joints(fields.get("locked_joints", [])),
                     source=self.source)

    # Elements.

    def locked_joints(self, value) -> tuple:
        names = [self.string(entry, f"locked_joints[{i}]")
                 for i, entry in enumerate(self.sequence(value, "locked_joints"))]
        for index, name in enumerate(names):
            if not self.robot.model.existJointName(name) or name == "universe":
                self.fail(f"locked_joints[{index}]", f"unknown joint {name!r}")
            if self.robot.model.joints[self.robot.model.getJointId(name)].nv == 0:
                self.fail(f"locked_joints[{index}]", f"joint {name!r} has no degree of freedom")
            if name in names[:index]:
                self.fail(f"locked_joints[{index}]", f"joint {name!r} is listed twice")
        return tuple(names)

    def named(self, value, path: str, build) -> dict:
        """A list of named elements as a dict by name (names unique)."""
        elements = {}
        for index, entry in enumerate(self.sequence(value, path)):
            element = build(entry, f"{path}[{index}]")
            if element.name in elements:
                self.fail(f"{path}[{index}].name", f"duplicate name {element.name!r}")
            elements[element.name] = element
        return elements

    def surface(self, entry, path: str) -> Surface:
        fields = self.mapping(entry, path, ("name", "frame", "polygon", "friction"), ("obstacle",))
        obstacle = fields.get("obstacle")
        return Surface(name=self.string(fields["name"], f"{path}.name"),
                       pose=self.pose(fields["frame"], f"{path}.frame"),
                       polygon=self.polygon(fields["polygon"], f"{path}.polygon"),
                       friction=self.number(fields["friction"], f"{path}.friction", positive=True),
                       obstacle=None if obstacle is None else self.string(obstacle,
                                                                          f"{path}.obstacle"))

    def obstacle(self, entry, path: str) -> Obstacle:
        fields = self.mapping(entry, path, ("name", "frame"), ("box", "mesh"))
        name = self.string(fields["name"], f"{path}.name")
        pose = self.pose(fields["frame"], f"{path}.frame")
        if ("box" in fields) == ("mesh" in fields):
            self.fail(path, "needs exactly one of the keys box and mesh")
        if "box" in fields:
            box = self.mapping(fields["box"], f"{path}.box", ("size",))
            size = self.vector(box["size"], f"{path}.box.size", 3, positive=True)
            return Obstacle(name=name, shape="box", pose=pose, size=size)
        mesh = self.mapping(fields["mesh"], f"{path}.mesh", ("file",), ("scale",))
        file = Path(self.string(mesh["file"], f"{path}.mesh.file")).expanduser()
        file = file if file.is_absolute() else self.directory / file
        if not file.is_file():
            self.fail(f"{path}.mesh.file", f"no such file {str(file)!r}")
        scale = (self.vector(mesh["scale"], f"{path}.mesh.scale", 3, positive=True)
                 if "scale" in mesh else np.ones(3))
        return Obstacle(name=name, shape="mesh", pose=pose, mesh=str(file.resolve()), scale=scale)

    def spot(self, entry, path: str) -> ContactSpot:
        fields = self.mapping(entry, path, ("name", "frame", "placement", "patch"), ("surfaces",))
        frame = self.string(fields["frame"], f"{path}.frame")
        if not self.robot.model.existFrame(frame):
            self.fail(f"{path}.frame", f"the robot has no frame {frame!r}")
        surfaces = self.sequence(fields.get("surfaces", []), f"{path}.surfaces")
        return ContactSpot(name=self.string(fields["name"], f"{path}.name"), frame=frame,
                           placement=self.pose(fields["placement"], f"{path}.placement"),
                           patch=self.polygon(fields["patch"], f"{path}.patch"),
                           surfaces=tuple(self.string(surface, f"{path}.surfaces[{i}]")
                                          for i, surface in enumerate(surfaces)))

    def contact(self, entry, path: str, surfaces: dict, spots: dict) -> ContactSpec:
        fields = self.mapping(entry, path, ("spot", "surface", "x", "y", "theta"))
        contact = ContactSpec(self.string(fields["spot"], f"{path}.spot"),
                              self.string(fields["surface"], f"{path}.surface"),
                              *(self.number(fields[key], f"{path}.{key}")
                                for key in ("x", "y", "theta")))
        problem = placement_problem(surfaces, spots, contact)
        if problem:
            self.fail(f"{path}{problem[0]}", problem[1])
        return contact

    def configuration(self, entry, path: str) -> np.ndarray:
        """{base: pose, joints: {name: rad}} as q (size nq); other joints at the robot's
        initial configuration (half_sitting for Talos)."""
        fields = self.mapping(entry, path, ("base",), ("joints",))
        model = self.robot.model
        q = self.robot.initial_configuration()
        if not self.robot.floating_base:
            self.fail(f"{path}.base", "the robot has no floating base")
        base = self.pose(fields["base"], f"{path}.base")
        q[:7] = pin.SE3ToXYZQUAT(base)
        joints = fields.get("joints", {})
        if not isinstance(joints, dict):
            self.fail(f"{path}.joints", "must be a mapping of joint names to positions (rad)")
        for joint, value in joints.items():
            joint_path = f"{path}.joints.{joint}"
            joint_id = model.getJointId(joint) if isinstance(joint, str) else model.njoints
            if joint_id not in self.robot.actuated_joint_ids or model.joints[joint_id].nq != 1:
                self.fail(joint_path, "not a 1-DoF joint of the robot")
            position = self.number(value, joint_path)
            index = model.joints[joint_id].idx_q
            lower, upper = model.lowerPositionLimit[index], model.upperPositionLimit[index]
            if joint_id in self.robot.limited_joint_ids and not lower <= position <= upper:
                self.fail(joint_path, f"{position:g} is outside the joint limits "
                                      f"[{lower:g}, {upper:g}]")
            q[index] = position
        return q

    def goal(self, entry) -> Goal:
        fields = self.mapping(entry, "goal", ("frame", "axis", "threshold"), ("sense",))
        frame = self.string(fields["frame"], "goal.frame")
        if not self.robot.model.existFrame(frame):
            self.fail("goal.frame", f"the robot has no frame {frame!r}")
        axis = fields["axis"]
        if axis not in ("x", "y", "z"):
            self.fail("goal.axis", f"must be x, y or z, got {axis!r}")
        sense = fields.get("sense", 1)
        if isinstance(sense, bool) or sense not in (1, -1):
            self.fail("goal.sense", f"must be +1 or -1, got {sense!r}")
        return Goal(frame, axis, self.number(fields["threshold"], "goal.threshold"), int(sense))

    # Values.

    def mapping(self, value, path: str, required: tuple, optional: tuple = ()) -> dict:
        if not isinstance(value, dict):
            self.fail(path, f"must be a mapping, got {type(value).__name__}")
        for key in required:
            if key not in value:
                self.fail(_join(path, key), "missing")
        for key in value:
            if key not in required and key not in optional:
                known = ", ".join((*required, *optional))
                self.fail(_join(path, str(key)), f"unknown key (known: {known})")
        return value

    def sequence(self, value, path: str) -> list:
        if not isinstance(value, list):
            self.fail(path, f"must be a list, got {type(value).__name__}")
        return value

    def string(self, value, path: str) -> str:
        if not isinstance(value, str) or not value:
            self.fail(path, f"must be a non-empty string, got {value!r}")
        return value

    def number(self, value, path: str, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(path, f"must be a number, got {value!r}")
        try:
            value = float(value)
        except OverflowError:       # an integer of hundreds of digits
            self.fail(path, "must be finite, got an integer too large for a float")
        if not math.isfinite(value):
            self.fail(path, f"must be finite, got {value!r}")
        if abs(value) > MAX_NUMBER:
            self.fail(path, f"must be at most {MAX_NUMBER:g} in magnitude, got {value!r}")
        if positive and value <= 0:
            self.fail(path, f"must be > 0, got {value!r}")
        return value

    def vector(self, value, path: str, size: int, positive: bool = False) -> np.ndarray:
        values = self.sequence(value, path)
        if len(values) != size:
            self.fail(path, f"must have {size} numbers, got {len(values)}")
        return np.array([self.number(v, f"{path}[{i}]", positive) for i, v in enumerate(values)])

    def pose(self, value, path: str) -> pin.SE3:
        """{position: [x, y, z] m, rpy: [roll, pitch, yaw] rad (default 0)}."""
        fields = self.mapping(value, path, ("position",), ("rpy",))
        rpy = self.vector(fields["rpy"], f"{path}.rpy", 3) if "rpy" in fields else np.zeros(3)
        return pin.SE3(pin.rpy.rpyToMatrix(rpy), self.vector(fields["position"],
                                                             f"{path}.position", 3))

    def polygon(self, value, path: str) -> np.ndarray:
        """(N, 2) vertices of a convex counter-clockwise polygon, N >= 3."""
        vertices = self.sequence(value, path)
        if len(vertices) < 3:
            self.fail(path, f"needs at least 3 vertices, got {len(vertices)}")
        polygon = np.array([self.vector(v, f"{path}[{i}]", 2) for i, v in enumerate(vertices)])
        problem = polygon_problem(polygon)
        if problem:
            self.fail(path, problem)
        return polygon


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def polygon_problem(polygon: np.ndarray) -> str:
    """Why (N, 2) vertices are not a strictly convex counter-clockwise polygon, or ""."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    following = np.roll(edges, -1, axis=0)
    turns = edges[:, 0] * following[:, 1] - edges[:, 1] * following[:, 0]
    area = 0.5 * float(np.sum(polygon[:, 0] * np.roll(polygon[:, 1], -1)
                              - np.roll(polygon[:, 0], -1) * polygon[:, 1]))
    scale = _CONVEXITY_EPSILON * max(1.0, float(np.max(np.abs(polygon))) ** 2)
    if area < -scale:
        return "vertices are clockwise (must be counter-clockwise)"
    if area <= scale or np.any(turns <= scale):
        return "not strictly convex (or repeated, collinear vertices)"
    winding = np.sum(np.arctan2(turns, np.sum(edges * following, axis=1))) / (2.0 * math.pi)
    if abs(winding - 1.0) > 1e-6:
        return "self-intersecting (winds around more than once)"
    return ""


def placement_problem(surfaces: dict, spots: dict, contact) -> tuple | None:
    """(field suffix, message) of what keeps `contact` (spot, surface, x, y, theta: a
    Contact or ContactSpec) from being a contact of a scene with these surfaces and spots
    (by name): an unknown spot or surface, a surface the spot may not touch, a number not
    finite, a point outside the surface's polygon (1 mm slack); None when nothing does."""
    if contact.spot not in spots:
        return ".spot", f"unknown spot {contact.spot!r}"
    if contact.surface not in surfaces:
        return ".surface", f"unknown surface {contact.surface!r}"
    allowed = spots[contact.spot].surfaces
    if allowed and contact.surface not in allowed:
        return ".surface", f"spot {contact.spot!r} may not touch surface {contact.surface!r}"
    for key in ("x", "y", "theta"):
        if not math.isfinite(getattr(contact, key)):
            return f".{key}", "not finite"
    if not _inside_convex(surfaces[contact.surface].polygon, np.array([contact.x, contact.y])):
        return "", (f"point ({contact.x:g}, {contact.y:g}) is outside the polygon of "
                    f"{contact.surface!r}")
    return None


def _inside_convex(polygon: np.ndarray, point: np.ndarray) -> bool:
    """Whether `point` lies in the closed convex counter-clockwise `polygon` (1 mm slack)."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    offsets = point - polygon
    lengths = np.linalg.norm(edges, axis=1)
    return bool(np.all((edges[:, 0] * offsets[:, 1] - edges[:, 1] * offsets[:, 0])
                       >= -1e-3 * lengths))
