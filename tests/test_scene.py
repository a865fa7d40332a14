"""Scene files: the shipped scenes load and their start configurations realise their start
contacts; malformed documents are rejected with the offending field's path."""

import copy
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from stance.planning.contacts import Contact
from stance.planning.scene import (SCENE_DIRECTORY, SceneError, load_scene, parse_scene,
                                   polygon_problem, scene_names)
from stance.robot import Robot

SHIPPED = ["chair_table", "flat_steps", "gap_wall", "platform_handrail"]
POSITION_TOLERANCE = 0.01               # m
ANGLE_TOLERANCE = math.radians(3.0)     # rad


@pytest.fixture(scope="module")
def robot():
    return Robot.load("talos")


@pytest.fixture(scope="module")
def scenes(robot):
    return {name: load_scene(name, robot) for name in SHIPPED}


@pytest.fixture
def document():
    """A valid document to mutate: the small flat_steps scene."""
    return yaml.safe_load((SCENE_DIRECTORY / "flat_steps.yaml").read_text())


def frame_position(robot, q, frame):
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, q)
    return data.oMf[robot.model.getFrameId(frame)].translation


def test_shipped_scenes_are_listed_and_load(scenes, robot):
    assert set(SHIPPED) <= set(scene_names())
    for name, scene in scenes.items():
        assert scene.name == name and scene.robot == "talos"
        assert scene.key_postures.ndim == 2 and scene.key_postures.shape[1] == robot.model.nq
        assert len(scene.key_postures) >= 2 and scene.start
        assert scene.source.endswith(f"{name}.yaml")


@pytest.mark.parametrize("name", SHIPPED)
def test_start_configuration_realises_the_start_contacts(scenes, robot, name):
    scene = scenes[name]
    q = scene.start_configuration
    assert np.isclose(np.linalg.norm(q[3:7]), 1.0)
    limited = q[robot.limited_q_index]
    assert np.all(limited >= robot.lower) and np.all(limited <= robot.upper)
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, q)
    for spec in scene.start:
        spot, surface = scene.spots[spec.spot], scene.surfaces[spec.surface]
        actual = data.oMf[robot.model.getFrameId(spot.frame)] * spot.placement
        target = Contact(spec.spot, spec.surface, spec.x, spec.y, spec.theta).spot_target(surface)
        error = pin.log6(target.inverse() * actual).vector
        assert np.linalg.norm(actual.translation - target.translation) < POSITION_TOLERANCE, spec
        assert np.linalg.norm(error[3:]) < ANGLE_TOLERANCE, spec


@pytest.mark.parametrize("name", SHIPPED)
def test_goal_is_reached_by_the_last_key_posture_only(scenes, robot, name):
    scene = scenes[name]
    goal = scene.goal
    assert not goal.reached(frame_position(robot, scene.start_configuration, goal.frame))
    assert goal.reached(frame_position(robot, scene.key_postures[-1], goal.frame))


@pytest.mark.parametrize("name", SHIPPED)
def test_start_and_key_postures_barely_penetrate_obstacles(scenes, robot, name):
    """Start: collision-free but for the bodies touching their contact surfaces' obstacles;
    key postures: at most 2 cm deep (the paper lets them collide a little)."""
    from stance.planning.collision import CollisionModel

    scene = scenes[name]
    collision = CollisionModel(robot, scene)
    ignored = collision.ignored_pairs_for_contacts(scene.start)
    assert collision.penetrations(scene.start_configuration, ignored, 0.002) == []
    for q in scene.key_postures[1:]:
        assert collision.penetrations(q, frozenset(), 0.02) == []


def test_chair_start_sits_on_the_seat_with_feet_on_the_floor(scenes):
    scene = scenes["chair_table"]
    assert {(c.spot, c.surface) for c in scene.start} == {
        ("left_sole", "floor"), ("right_sole", "floor"),
        ("left_thigh", "seat"), ("right_thigh", "seat")}
    assert scene.surfaces["seat"].pose.translation[2] == pytest.approx(0.45)
    assert {"seat", "table", "floor"} <= set(scene.surfaces)
    for surface in scene.surfaces.values():
        assert surface.obstacle in scene.obstacles


def test_load_by_path_and_from_yaml_text(robot, scenes):
    path = SCENE_DIRECTORY / "flat_steps.yaml"
    by_path = load_scene(str(path), robot)
    by_text = parse_scene(yaml.safe_load(path.read_text()), "<goal>", robot)
    for scene in (by_path, by_text):
        np.testing.assert_array_equal(scene.start_configuration,
                                      scenes["flat_steps"].start_configuration)
        assert scene.goal == scenes["flat_steps"].goal
    with pytest.raises(SceneError, match="unknown scene 'no_such_scene'"):
        load_scene("no_such_scene", robot)


def test_unspecified_joints_take_half_sitting(robot, scenes):
    q = scenes["chair_table"].start_configuration
    half_sitting = robot.reference_configurations["half_sitting"]
    arm = robot.model.joints[robot.joint_id("arm_left_4_joint")].idx_q
    knee = robot.model.joints[robot.joint_id("leg_left_4_joint")].idx_q
    assert q[arm] == half_sitting[arm] and q[knee] != pytest.approx(half_sitting[knee])


def test_mesh_obstacle_path_is_relative_to_the_scene_file(tmp_path, document, robot):
    facets = [((0, 0, 0), (1, 0, 0), (0, 1, 0)), ((0, 0, 0), (0, 0, 1), (1, 0, 0)),
              ((0, 0, 0), (0, 1, 0), (0, 0, 1)), ((1, 0, 0), (0, 0, 1), (0, 1, 0))]
    lines = ["solid t"] + [line for facet in facets for line in (
        "facet normal 0 0 0", "outer loop", *(f"vertex {x} {y} {z}" for x, y, z in facet),
        "endloop", "endfacet")] + ["endsolid t"]
    (tmp_path / "rock.stl").write_text("\n".join(lines))
    document["obstacles"].append({"name": "rock", "mesh": {"file": "rock.stl", "scale": [2, 2, 2]},
                                  "frame": {"position": [1.0, 0.0, 0.0]}})
    path = tmp_path / "rock_scene.yaml"
    path.write_text(yaml.safe_dump(document))
    rock = load_scene(str(path), robot).obstacles["rock"]
    assert rock.shape == "mesh" and rock.mesh == str(tmp_path / "rock.stl")
    np.testing.assert_array_equal(rock.scale, [2.0, 2.0, 2.0])


def _set(path: str, value):
    """A mutation setting document[path] (keys and list indices separated by dots)."""
    def mutate(document):
        *parents, last = path.split(".")
        node = document
        for key in parents:
            node = node[int(key)] if isinstance(node, list) else node[key]
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value
    return mutate


def _delete(path: str):
    def mutate(document):
        *parents, last = path.split(".")
        node = document
        for key in parents:
            node = node[int(key)] if isinstance(node, list) else node[key]
        del node[last]
    return mutate


def _add_surface_copy(document):
    document["surfaces"].append(copy.deepcopy(document["surfaces"][0]))


def _add_obstacle_mesh(document):
    document["obstacles"][0]["mesh"] = {"file": "missing.stl"}


def _missing_mesh(document):
    obstacle = document["obstacles"][0]
    del obstacle["box"]
    obstacle["mesh"] = {"file": "/nonexistent/missing.stl"}


def _repeat_start_spot(document):
    document["start"]["contacts"][1]["spot"] = "left_sole"


def _restrict_spot_surfaces(document):
    document["surfaces"].append({**copy.deepcopy(document["surfaces"][0]), "name": "ice"})
    document["spots"][0]["surfaces"] = ["ice"]


MALFORMED = [
    (_delete("name"), "name", "missing"),
    (_set("robot", "ur5"), "robot", "the scene is for 'ur5', the robot given is 'talos'"),
    (_set("colour", "red"), "colour", "unknown key"),
    (_set("surfaces", {"floor": 1}), "surfaces", "must be a list"),
    (_set("surfaces.0.polygon", [[0, 0], [0, 1], [1, 1], [1, 0]]), "surfaces[0].polygon",
     "clockwise"),
    (_set("surfaces.0.polygon", [[0, 0], [2, 0], [1, 0.2], [1, 1]]), "surfaces[0].polygon",
     "convex"),
    (_set("surfaces.0.polygon", [[0, 0], [1, 0]]), "surfaces[0].polygon", "at least 3"),
    (_set("surfaces.0.polygon", [[0, 0], [1, 0], [1]]), "surfaces[0].polygon[2]",
     "2 numbers"),
    (_set("surfaces.0.friction", 0.0), "surfaces[0].friction", "> 0"),
    (_set("surfaces.0.friction", float("nan")), "surfaces[0].friction", "finite"),
    (_set("surfaces.0.friction", "high"), "surfaces[0].friction", "number"),
    (_set("surfaces.0.obstacle", "wall"), "surfaces[0].obstacle", "unknown obstacle"),
    (_set("surfaces.0.frame.rpy", [0, 0]), "surfaces[0].frame.rpy", "3 numbers"),
    (_set("surfaces.0.frame.position", [0, float("inf"), 0]), "surfaces[0].frame.position[1]",
     "finite"),
    (_add_surface_copy, "surfaces[1].name", "duplicate"),
    (_set("obstacles.0.box.size", [1, 1, 0]), "obstacles[0].box.size[2]", "> 0"),
    (_set("obstacles.0.box.height", 1), "obstacles[0].box.height", "unknown key"),
    (_add_obstacle_mesh, "obstacles[0]", "exactly one"),
    (_missing_mesh, "obstacles[0].mesh.file", "no such file"),
    (_set("spots.1.frame", "tail_link"), "spots[1].frame", "no frame"),
    (_set("spots.0.surfaces", ["lava"]), "spots[0].surfaces[0]", "unknown surface"),
    (_set("spots.0.patch", [[0, 0], [0.1, 0.1], [0.2, 0.2]]), "spots[0].patch", "convex"),
    (_delete("spots.0.placement"), "spots[0].placement", "missing"),
    (_set("start.contacts.0.spot", "nose"), "start.contacts[0].spot", "unknown spot"),
    (_set("start.contacts.1.surface", "roof"), "start.contacts[1].surface", "unknown surface"),
    (_set("start.contacts.0.x", 5.0), "start.contacts[0]", "outside the polygon"),
    (_set("start.contacts.0.theta", True), "start.contacts[0].theta", "number"),
    (_repeat_start_spot, "start.contacts[1].spot", "used twice"),
    (_restrict_spot_surfaces, "start.contacts[0].surface", "may not touch"),
    (_set("start.configuration.joints", {"wing_joint": 0.1}),
     "start.configuration.joints.wing_joint", "not a 1-DoF joint"),
    (_set("start.configuration.joints", {"leg_left_4_joint": 3.0}),
     "start.configuration.joints.leg_left_4_joint", "outside the joint limits"),
    (_delete("start.configuration.base"), "start.configuration.base", "missing"),
    (_set("key_postures", [{"base": {"position": [0, 0, 1]}}]), "key_postures", "at least 2"),
    (_set("key_postures.1.base.position", [0, 0, float("nan")]),
     "key_postures[1].base.position[2]", "finite"),
    (_set("key_postures.1.base.position", [0.0, 0.0, 1.0193]), "key_postures", "coincide"),
    (_set("key_postures.1.base.rpy", [0.0, 0.0, 3.1]), "key_postures", "turns more than"),
    (_set("surfaces.0.friction", 10 ** 400), "surfaces[0].friction", "too large for a float"),
    (_set("surfaces.0.frame.position", [0, 1e160, 0]), "surfaces[0].frame.position[1]",
     "at most 1e+06 in magnitude"),
    (_set("goal.axis", "w"), "goal.axis", "x, y or z"),
    (_set("goal.frame", "tail_link"), "goal.frame", "no frame"),
    (_set("goal.sense", 0), "goal.sense", "+1 or -1"),
    (_delete("goal.threshold"), "goal.threshold", "missing"),
    (_set("locked_joints", "gripper_left_joint"), "locked_joints", "must be a list"),
    (_set("locked_joints", ["wing_joint"]), "locked_joints[0]", "unknown joint"),
    (_set("locked_joints", ["gripper_left_joint", "gripper_left_joint"]), "locked_joints[1]",
     "listed twice"),
]


@pytest.mark.parametrize("mutate, path, reason", MALFORMED,
                         ids=[f"{path}-{reason}" for _, path, reason in MALFORMED])
def test_malformed_documents_name_the_field(document, robot, mutate, path, reason):
    parse_scene(copy.deepcopy(document), "<test>", robot)     # valid before the mutation
    mutate(document)
    with pytest.raises(SceneError) as error:
        parse_scene(document, "<test>", robot)
    message = str(error.value)
    assert message.startswith(f"{path}: "), message
    assert reason in message, message


def test_unknown_robot_and_non_mapping_documents_are_rejected(document):
    document["robot"] = "no_such_robot"
    with pytest.raises(SceneError, match=r"^robot: "):
        parse_scene(document, "<test>")
    with pytest.raises(SceneError, match=r"^document: must be a mapping"):
        parse_scene(["name"], "<test>")


def test_a_file_that_is_not_text_is_a_scene_error(tmp_path):
    binary = tmp_path / "scene.yaml"
    binary.write_bytes(b"\xf0\x00\xff robot: talos")
    with pytest.raises(SceneError, match="not a YAML text file"):
        load_scene(str(binary))


@pytest.mark.parametrize("polygon, problem", [
    ([[0, 0], [1, 0], [0, 1]], ""),
    ([[0, 0], [1, 0], [1, 1], [0, 1]], ""),
    ([[0, 0], [0, 1], [1, 1], [1, 0]], "clockwise"),
    ([[0, 0], [1, 0], [2, 0], [1, 1]], "convex"),
    ([[0, 0], [1, 0], [1, 0], [0, 1]], "convex"),
    ([[0, 0], [1, 0], [0.2, 0.2], [0, 1]], "convex"),
    # A pentagram: every turn is to the left, but it winds twice.
    ([[math.cos(a), math.sin(a)] for a in np.arange(5) * 4 * math.pi / 5], "self-intersecting"),
])
def test_polygon_problem(polygon, problem):
    found = polygon_problem(np.array(polygon, dtype=float))
    assert (problem in found) if problem else found == ""


def test_the_documented_example_is_a_valid_scene(robot):
    text = (Path(__file__).resolve().parents[1] / "docs" / "scenes.md").read_text()
    example = text.split("```yaml\n", 1)[1].split("```", 1)[0]
    scene = parse_scene(yaml.safe_load(example), "docs/scenes.md", robot)
    assert scene.name == "step_forward" and len(scene.key_postures) == 2
    torso = robot.model.joints[robot.joint_id("torso_2_joint")].idx_q
    assert scene.key_postures[1, torso] == pytest.approx(0.1)
