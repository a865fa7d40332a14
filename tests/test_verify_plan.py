"""Independent plan verification (stance.planning.verify) and `stance check-plan` /
`stance plot-plan`, on Talos standing in half_sitting on a floor."""

import json
import math
import os
from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest
from matplotlib.image import imread
from stance.planning import scene as scene_module
from stance.planning.contacts import Contact, Plan, Stance, save_plan
from stance.planning.scene import ContactSpot, Goal, Obstacle, Scene, Surface
from stance.planning.verify import PlanVerifier, robot_asset_paths, stance_transition, verify_plan
from stance.robot import Robot
from stance.stopping import Stopped
from stance_tools import cli

# Spot frames: z out of the sole (the sole frames' z points up into the foot).
OUT_OF_SOLE = pin.SE3(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
SOLE = np.array([[0.1, 0.05], [-0.1, 0.05], [-0.1, -0.05], [0.1, -0.05]])   # m
HEEL = np.array([[0.02, 0.03], [-0.02, 0.03], [-0.02, -0.03], [0.02, -0.03]])
HEEL_OFFSET = np.array([-0.07, 0.0, 0.0])   # heel spot centre in the left sole frame (m)


@pytest.fixture(scope="module")
def robot():
    return Robot.load("talos")


@pytest.fixture(scope="module")
def standing(robot):
    return robot.reference_configurations["half_sitting"].copy()


def make_scene(q, floor_obstacle="ground", extra_obstacles=()):
    floor = Surface("floor", pin.SE3.Identity(),
                    np.array([[-2.0, -2.0], [2.0, -2.0], [2.0, 2.0], [-2.0, 2.0]]), 0.7,
                    floor_obstacle)
    ground = Obstacle("ground", "box", pin.SE3(np.eye(3), np.array([0.0, 0.0, -0.05])),
                      np.array([4.0, 4.0, 0.1]))
    heel = pin.SE3(np.eye(3), HEEL_OFFSET) * OUT_OF_SOLE
    spots = {"left_foot": ContactSpot("left_foot", "left_sole_link", OUT_OF_SOLE, SOLE),
             "right_foot": ContactSpot("right_foot", "right_sole_link", OUT_OF_SOLE, SOLE),
             "left_heel": ContactSpot("left_heel", "left_sole_link", heel, HEEL)}
    obstacles = {o.name: o for o in (ground, *extra_obstacles)}
    return Scene("flat", "talos", {"floor": floor}, obstacles, spots, [], q, np.vstack([q, q]),
                 Goal("base_link", "x", 1.0))


def exact_contact(robot, q, scene, spot_name):
    """The floor contact realised by the spot at q (x, y and yaw of the spot's contact
    frame)."""
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, q)
    spot = scene.spots[spot_name]
    contact_frame = data.oMf[robot.frame_id(spot.frame)] * spot.placement * OUT_OF_SOLE.inverse()
    rotation = contact_frame.rotation
    return Contact(spot_name, "floor", float(contact_frame.translation[0]),
                   float(contact_frame.translation[1]),
                   math.atan2(rotation[1, 0], rotation[0, 0]))


@pytest.fixture(scope="module")
def good_plan(robot, standing):
    """Both feet; the heel added, removed (still touched), added again."""
    scene = make_scene(standing)
    left, right, heel = (exact_contact(robot, standing, scene, name)
                         for name in ("left_foot", "right_foot", "left_heel"))
    contact_sets = [(left, right), (left, right, heel), (left, right, heel.with_stability(False)),
                    (left, right, heel)]
    return Plan("flat", "talos", [Stance(c, standing.copy()) for c in contact_sets])


@pytest.fixture(scope="module")
def verifier(robot, standing):
    return PlanVerifier(make_scene(standing), robot)


def test_standing_plan_passes(verifier, good_plan):
    report = verifier.verify(good_plan)
    assert report.ok, report.failures
    first = report.stances[0]
    assert all(error.position < 1e-5 and max(error.normal, error.theta) < math.radians(0.2)
               for error in first.contact_errors)
    assert first.equilibrium and not first.collisions and not first.limit_violations
    assert first.com[2] > 0.8
    assert [s.transition for s in report.stances] == [
        "", "adds left_heel@floor", "removes left_heel@floor", "adds left_heel@floor"]


def test_verify_plan_builds_its_own_models(robot, standing, good_plan):
    assert verify_plan(good_plan, make_scene(standing), robot).ok


def test_a_verification_stops_when_asked_before_a_stance(robot, standing, good_plan):
    """should_stop is asked before each stance: the first True abandons the plan."""
    asked = []
    with pytest.raises(Stopped, match="verification stopped at stance 2"):
        verify_plan(good_plan, make_scene(standing), robot,
                    should_stop=lambda: asked.append(True) or len(asked) > 2)
    assert len(asked) == 3


def test_foot_five_millimetres_off_is_reported(verifier, good_plan):
    left, right = good_plan.stances[0].contacts
    moved = Plan("flat", "talos", [Stance((replace(left, x=left.x + 0.005), right),
                                          good_plan.stances[0].q)])
    report = verifier.verify(moved)
    assert not report.ok
    assert report.stances[0].contact_errors[0].position == pytest.approx(0.005, abs=1e-5)
    assert report.stances[0].contact_errors[1].position < 1e-5
    assert report.failures == ["stance 0: left_foot@floor: spot 5.0 mm from its target"]


def test_contacts_off_their_surface_are_reported(robot, verifier, good_plan):
    """The whole stance (feet and witness) moved 5 m along x, past the floor's edge at 2 m:
    every spot is on its target and in equilibrium on the floor's plane, but off the floor.
    It used to pass."""
    stance = good_plan.stances[0]
    q = stance.q.copy()
    q[0] += 5.0
    moved = Plan("flat", "talos", [Stance(tuple(replace(c, x=c.x + 5.0) for c in
                                                stance.contacts), q)])
    report = verifier.verify(moved)
    assert [f for f in report.failures if "outside the polygon of 'floor'" in f] == [
        f"stance 0: {c.spot}@floor: point ({c.x + 5.0:g}, {c.y:g}) is outside the polygon of "
        "'floor'" for c in stance.contacts]


def test_a_witness_not_finite_is_reported_and_leaves_the_verifier_intact(verifier,
                                                                         good_plan):
    """A NaN in a witness is reported before any kinematics: it used to raise in the LP
    and leave the verifier's collision data NaN (every later plan collided)."""
    stance = good_plan.stances[0]
    q = stance.q.copy()
    q[7] = math.nan
    report = verifier.verify(Plan("flat", "talos", [Stance(stance.contacts, q)]))
    assert report.failures == ["stance 0: configuration not finite"]
    assert verifier.verify(good_plan).ok


def test_turned_foot_is_reported(verifier, good_plan):
    left, right = good_plan.stances[0].contacts
    turned = Plan("flat", "talos", [Stance((left, replace(right, theta=right.theta + 0.05)),
                                           good_plan.stances[0].q)])
    report = verifier.verify(turned)
    assert report.stances[0].contact_errors[1].theta == pytest.approx(0.05, abs=1e-6)
    assert len(report.failures) == 1 and "right_foot@floor: spot turned" in report.failures[0]


def test_joint_beyond_its_limit_is_reported(robot, verifier, good_plan):
    q = good_plan.stances[0].q.copy()
    elbow = robot.limited_joint_names.index("arm_left_4_joint")
    q[robot.limited_q_index[elbow]] = robot.upper[elbow] + 0.05
    report = verifier.verify(Plan("flat", "talos", [Stance(good_plan.stances[0].contacts, q)]))
    assert report.stances[0].limit_violations == {"arm_left_4_joint": pytest.approx(0.05)}
    assert "stance 0: joint arm_left_4_joint 0.0500 beyond its limit" in report.failures


def test_com_pushed_outside_the_feet_is_reported(verifier, good_plan):
    q = good_plan.stances[0].q.copy()
    q[0] += 0.3   # the base (and the CoM) 30 cm forward of the feet's contacts
    report = verifier.verify(Plan("flat", "talos", [Stance(good_plan.stances[0].contacts, q)]))
    assert not report.stances[0].equilibrium
    assert any("no static equilibrium" in failure for failure in report.failures)


def test_com_outside_a_single_foot_is_the_only_failure(verifier, good_plan):
    left, right = good_plan.stances[0].contacts
    one_foot = Plan("flat", "talos", [good_plan.stances[0],
                                      Stance((left, right.with_stability(False)),
                                             good_plan.stances[0].q)])
    report = verifier.verify(one_foot)
    assert report.stances[0].ok
    assert report.stances[1].transition == "removes right_foot@floor"
    assert len(report.failures) == 1 and "no static equilibrium" in report.failures[0]


def test_collisions_and_the_contact_allowance(robot, standing, good_plan):
    sunk = good_plan.stances[0].q.copy()
    sunk[2] -= 0.005   # soles 5 mm into the ground
    plan = Plan("flat", "talos", [Stance(good_plan.stances[0].contacts, sunk)])
    allowed = PlanVerifier(make_scene(standing), robot).verify(plan).stances[0]
    assert not allowed.collisions   # feet may touch the obstacle under their surface
    assert all(error.position == pytest.approx(0.005, abs=1e-4)
               for error in allowed.contact_errors)
    strict = PlanVerifier(make_scene(standing, floor_obstacle=None), robot).verify(plan)
    pairs = {(a, b) for a, b, _ in strict.stances[0].collisions}
    assert pairs == {("leg_left_6_link_0", "obstacle:ground"),
                     ("leg_right_6_link_0", "obstacle:ground")}
    # A bar through the pelvis (an obstacle wholly inside a hollow mesh would not count).
    pole = Obstacle("pole", "box", pin.SE3(np.eye(3), np.array([0.0, 0.0, 1.0])),
                    np.array([1.0, 0.05, 0.05]))
    skewered = PlanVerifier(make_scene(standing, extra_obstacles=[pole]), robot)
    report = skewered.verify(Plan("flat", "talos", [good_plan.stances[0]]))
    assert {b for _, b, _ in report.stances[0].collisions} == {"obstacle:pole"}
    assert any("obstacle:pole" in failure for failure in report.failures)


def test_mesh_obstacle_collides(robot, standing, good_plan):
    package_dirs, _ = robot_asset_paths("talos")
    pelvis = os.path.join(package_dirs[1], "talos_data", "meshes", "torso", "base_link.STL")
    shell = Obstacle("shell", "mesh", pin.SE3(np.eye(3), np.array([0.1, 0.0, 1.0])), mesh=pelvis)
    report = PlanVerifier(make_scene(standing, extra_obstacles=[shell]), robot).verify(
        Plan("flat", "talos", [good_plan.stances[0]]))
    assert "obstacle:shell" in {b for _, b, _ in report.stances[0].collisions}


def test_transition_rule():
    a, b, c = (Contact(name, "floor", 0.1 * i, 0.0, 0.0) for i, name in enumerate("abc"))
    assert stance_transition((a, b), (a, b, c)) == (True, "adds c@floor")
    assert stance_transition((a, b, c), (a, c)) == (True, "removes b@floor")
    assert stance_transition((a, b), (a, b.with_stability(False))) == (
        True, "removes b@floor")
    # a contact being broken (geometric only) may vanish as another is added
    assert stance_transition((a, b.with_stability(False)), (a, c)) == (True, "adds c@floor")
    assert stance_transition((a, b), (b, a)) == (False, "no change of the supporting contacts")
    ok, text = stance_transition((a, b), (a, c))   # b moved to c's place: two changes
    assert not ok and text == "adds c@floor, removes b@floor"
    ok, _ = stance_transition((a, b), (a, replace(b, x=b.x + 1e-6)))
    assert not ok   # a contact that slides is not the same contact
    ok, _ = stance_transition((a, b), (a.with_stability(False), b.with_stability(False)))
    assert not ok


def test_duplicate_spot_and_unknown_names_are_reported(verifier, good_plan):
    left, right = good_plan.stances[0].contacts
    q = good_plan.stances[0].q
    twice = verifier.verify(Plan("flat", "talos", [Stance((left, replace(right, spot="left_foot")),
                                                          q)]))
    assert any("spot 'left_foot' in 2 contacts" in failure for failure in twice.failures)
    unknown = verifier.verify(Plan("flat", "talos", [Stance((replace(left, surface="moon"),), q)]))
    assert unknown.failures == ["stance 0: left_foot@moon: unknown surface 'moon'"]


def test_a_spot_on_a_frame_the_robot_lacks_is_reported(robot, standing, good_plan):
    scene = make_scene(standing)
    scene.spots["left_foot"] = replace(scene.spots["left_foot"], frame="no_such_link")
    report = PlanVerifier(scene, robot).verify(replace(good_plan, stances=good_plan.stances[:1]))
    assert report.failures == ["stance 0: spot 'left_foot': unknown frame 'no_such_link'"]


@pytest.fixture
def plan_files(tmp_path, monkeypatch, standing, good_plan):
    """A good and a bad plan file; the scene loader returns the test scene."""
    scene = make_scene(standing)
    monkeypatch.setattr(scene_module, "load_scene", lambda spec: scene, raising=False)
    good, bad = tmp_path / "good.json", tmp_path / "bad.json"
    save_plan(good_plan, str(good))
    q = good_plan.stances[1].q.copy()
    q[0] += 0.3
    broken = Plan("flat", "talos", [good_plan.stances[0], Stance(good_plan.stances[1].contacts, q)])
    save_plan(broken, str(bad))
    return good, bad


def test_check_plan_exit_codes(plan_files, capsys):
    good, bad = plan_files
    assert cli.main(["check-plan", str(good)]) == 0
    output = capsys.readouterr()
    assert "plan OK: 4 stances" in output.out
    assert len(output.out.splitlines()) == 1 + 4 + 1   # header, one row per stance, verdict
    assert cli.main(["check-plan", str(bad), "--scene", "flat"]) == 1
    output = capsys.readouterr()
    assert "FAIL" in output.out.splitlines()[2] and "FAIL" not in output.out.splitlines()[1]
    assert "stance 1: no static equilibrium" in output.err
    assert cli.main(["check-plan", str(good.parent / "missing.json")]) == 2


def edited_plan_file(source, target, edit):
    """A copy of a plan file with edit(document) applied."""
    document = json.loads(source.read_text())
    edit(document)
    target.write_text(json.dumps(document))
    return target


MALFORMED_PLANS = [   # edit, what check-plan and plot-plan say; None: plot-plan's own check
    (lambda d: d["stances"][1]["contacts"][0].update(in_stability="false"),
     "stances[1].contacts[0].in_stability: expected true or false"),    # read as true
    (lambda d: d["stances"][1].update(contacts=5), "stances[1]: expected a mapping with a "
                                                   "contacts list"),   # a TypeError
    (lambda d: d["stances"][0]["contacts"][0].pop("x"), "stances[0].contacts[0].x: missing"),
    (lambda d: d.update(scene=5), "scene: expected a string"),
    (lambda d: d["stances"][1]["contacts"][0].update(spot="nosuch_spot"), None),
    (lambda d: d["stances"][1].update(q=d["stances"][1]["q"][:10]), None),
]


@pytest.mark.parametrize("edit, message", MALFORMED_PLANS)
def test_malformed_plan_files_are_named_by_both_commands(plan_files, tmp_path, capsys, edit,
                                                         message):
    good, _ = plan_files
    path = edited_plan_file(good, tmp_path / "edited.json", edit)
    if message is not None:      # the file is not a plan: neither command goes on
        for command, extra in (("check-plan", []),
                               ("plot-plan", ["-o", str(tmp_path / "sheet.png")])):
            assert cli.main([command, str(path), *extra]) == 2
            assert f"stance {command}: {path}: {message}" in capsys.readouterr().err
        return
    assert cli.main(["check-plan", str(path)]) == 1    # a plan, failing verification
    capsys.readouterr()
    assert cli.main(["plot-plan", str(path), "-o", str(tmp_path / "sheet.png")]) == 2
    assert "stance check-plan tells all that is wrong" in capsys.readouterr().err
    assert not (tmp_path / "sheet.png").exists()


def test_plot_plan_names_an_output_it_cannot_write(plan_files, tmp_path, capsys):
    good, _ = plan_files
    (tmp_path / "folder.png").mkdir()
    for output, reason in ((tmp_path / "sheet.txt", "Format 'txt' is not supported"),
                           (tmp_path / "missing" / "sheet.png", "No such file"),
                           (tmp_path / "folder.png", "is a directory")):
        assert cli.main(["plot-plan", str(good), "-o", str(output)]) == 2
        error = capsys.readouterr().err
        assert f"cannot write {output}" in error and reason in error, error
    # without a suffix matplotlib writes a PNG named with one: the name printed is that one
    assert cli.main(["plot-plan", str(good), "-o", str(tmp_path / "sheet")]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "sheet.png")
    assert (tmp_path / "sheet.png").is_file()


def test_plot_plan_writes_a_contact_sheet(plan_files, tmp_path, capsys):
    good, _ = plan_files
    sheet = tmp_path / "sheet.png"
    assert cli.main(["plot-plan", str(good), "-o", str(sheet), "--every", "2"]) == 0
    assert capsys.readouterr().out.strip() == str(sheet)
    image = imread(sheet)
    assert image.shape[0] > 300 and image.shape[1] > 900
    assert np.var(image[..., :3]) > 1e-3
