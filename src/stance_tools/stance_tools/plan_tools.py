"""`stance check-plan PLAN.json` and `stance plot-plan PLAN.json -o SHEET.png`.

check-plan verifies every stance of a plan independently (stance.planning.verify) and prints
one row per stance; exit code 0 when all pass, 1 when some fail (failures listed on
stderr), 2 when the plan or the scene cannot be read.

plot-plan draws a contact sheet: one 3D panel per witness posture (every N-th stance, and
always the last) with the scene's obstacles (translucent boxes; mesh obstacles as their
bounding boxes), its surfaces (grey polygons), the robot as a stick figure (segments between
joint origins along the kinematic tree, plus each contact spot) and the contacts as patches
coloured by spot (hatched and pale while not in stability). All panels share one camera.
"""

from __future__ import annotations

import math
import sys
import textwrap
from pathlib import Path

import numpy as np

from .cli import positive

CHECK_COMMAND = "check-plan"
PLOT_COMMAND = "plot-plan"


def add_arguments(parser) -> None:
    """Both subcommands live here; the parser's prog ("stance check-plan") tells which."""
    if parser.prog.split()[-1] == CHECK_COMMAND:
        _add_check_arguments(parser)
    else:
        _add_plot_arguments(parser)


def run(args) -> int:
    return run_check(args) if args.command == CHECK_COMMAND else run_plot(args)


def _add_check_arguments(parser) -> None:
    parser.add_argument("plan", help="plan file (JSON, as written by the planner)")
    parser.add_argument("--scene", help="scene name or YAML path (default: the plan's scene)")
    parser.add_argument("--contact-tolerance", type=positive(float), default=0.001,
                        help="largest spot position error (m, default 0.001)")
    parser.add_argument("--angle-tolerance", type=positive(float), default=1.0,
                        help="largest spot angle error (deg, default 1)")


def _add_plot_arguments(parser) -> None:
    parser.add_argument("plan", help="plan file (JSON, as written by the planner)")
    parser.add_argument("-o", "--output", required=True, help="PNG file to write")
    parser.add_argument("--scene", help="scene name or YAML path (default: the plan's scene)")
    parser.add_argument("--every", type=positive(int), default=1,
                        help="draw every N-th stance (the last one always)")
    parser.add_argument("--columns", type=positive(int), default=4, help="panels per row")


def _load(args) -> tuple:
    """(plan, scene, robot) from the command line; raises OSError, ValueError."""
    from stance.planning.contacts import load_plan
    from stance.planning.scene import load_scene
    from stance.robot import Robot

    plan = load_plan(args.plan)
    scene = load_scene(args.scene or plan.scene)
    return plan, scene, Robot.load(scene.robot)


def _describe_contacts(contacts) -> str:
    return ", ".join(c.spot + ("" if c.in_stability else "*") for c in contacts) or "-"


def run_check(args) -> int:
    from stance.planning.verify import verify_plan

    try:
        plan, scene, robot = _load(args)
    except (OSError, ValueError, KeyError) as error:
        print(f"stance {CHECK_COMMAND}: {error}", file=sys.stderr)
        return 2
    report = verify_plan(plan, scene, robot, args.contact_tolerance,
                         math.radians(args.angle_tolerance))
    descriptions = [_describe_contacts(stance.contacts) for stance in plan.stances]
    width = max([len(text) + 2 for text in descriptions] + [34])
    print(f"{'stance':>6}  {'contacts (* = not in stability)':<{width}}{'pos mm':>7}"
          f"{'ang deg':>8}{'coll':>5}{'limits':>7}{'equil':>6}  change")
    for description, result in zip(descriptions, report.stances):
        errors = result.contact_errors
        position = max((e.position for e in errors), default=0.0) * 1000.0
        angle = math.degrees(max((max(e.normal, e.theta) for e in errors), default=0.0))
        status = "" if result.ok else "  FAIL"
        print(f"{result.index:>6}  {description:<{width}}{position:>7.2f}"
              f"{angle:>8.2f}{len(result.collisions):>5}{len(result.limit_violations):>7}"
              f"{'yes' if result.equilibrium else 'no':>6}  {result.transition or 'start'}"
              f"{status}")
    if report.ok:
        print(f"plan OK: {len(plan.stances)} stances")
        return 0
    print(f"plan FAILS: {len(report.failures)} failures", file=sys.stderr)
    for failure in report.failures:
        print(f"  {failure}", file=sys.stderr)
    return 1


# --- plot-plan -------------------------------------------------------------------------------

_BOX_FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))


def _box_faces(pose, size) -> list:
    """Six (4, 3) world faces of a box of full extents `size` centred at `pose`."""
    corners = np.array([[sx, sy, sz] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5)
                        for sz in (-0.5, 0.5)]) * np.asarray(size, dtype=float)
    world = corners @ pose.rotation.T + pose.translation
    return [world[list(face)] for face in _BOX_FACES]


def _obstacle_faces(obstacle) -> list:
    import pinocchio as pin

    if obstacle.shape == "box":
        return _box_faces(obstacle.pose, obstacle.size)
    import coal

    mesh = coal.MeshLoader().load(obstacle.mesh, np.asarray(obstacle.scale, dtype=float))
    mesh.computeLocalAABB()
    box = mesh.aabb_local
    centre = pin.SE3(np.eye(3), np.asarray(box.center()))
    return _box_faces(obstacle.pose * centre,
                      [box.width(), box.depth(), box.height()])


def _clip(polygon, lower, upper) -> np.ndarray:
    """A convex 3D polygon (N, 3) clipped to the box [lower, upper] (Sutherland-Hodgman on
    the six axis planes), so the 3D axes never draw outside their limits."""
    for axis in range(3):
        for bound, sign in ((lower[axis], 1.0), (upper[axis], -1.0)):
            if len(polygon) == 0:
                return polygon
            inside = sign * (polygon[:, axis] - bound) >= 0.0
            kept = []
            for i in range(len(polygon)):
                a, b = polygon[i], polygon[(i + 1) % len(polygon)]
                if inside[i]:
                    kept.append(a)
                if inside[i] != inside[(i + 1) % len(polygon)]:
                    s = (bound - a[axis]) / (b[axis] - a[axis])
                    kept.append(a + s * (b - a))
            polygon = np.array(kept).reshape(-1, 3)
    return polygon


def _skeleton(robot, data, spot_frames) -> list:
    """Stick-figure segments ((3,), (3,)) at the posture in `data` (after forward
    kinematics): joint to parent joint origins, and each spot frame's parent joint to the
    spot."""
    model = robot.model
    segments = [(data.oMi[model.parents[j]].translation, data.oMi[j].translation)
                for j in range(2 if robot.floating_base else 1, model.njoints)]
    for frame, placement in spot_frames:
        frame_id = robot.frame_id(frame)
        spot = data.oMf[frame_id] * placement
        segments.append((data.oMi[model.frames[frame_id].parentJoint].translation,
                         spot.translation))
    return segments


def run_plot(args) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pinocchio as pin
    from matplotlib.patches import Patch
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection
    from stance.planning.equilibrium import contact_vertices

    try:
        plan, scene, robot = _load(args)
    except (OSError, ValueError, KeyError) as error:
        print(f"stance {PLOT_COMMAND}: {error}", file=sys.stderr)
        return 2
    if not plan.stances:
        print(f"stance {PLOT_COMMAND}: the plan has no stance", file=sys.stderr)
        return 1
    problem = _undrawable(plan, scene, robot)
    if problem:
        print(f"stance {PLOT_COMMAND}: {args.plan}: {problem} (stance {CHECK_COMMAND} tells "
              "all that is wrong)", file=sys.stderr)
        return 2
    indices = list(range(0, len(plan.stances), max(1, args.every)))
    if indices[-1] != len(plan.stances) - 1:
        indices.append(len(plan.stances) - 1)

    data = robot.model.createData()
    spot_frames = [(spot.frame, spot.placement) for spot in scene.spots.values()]
    skeletons = []
    for index in indices:
        pin.framesForwardKinematics(robot.model, data, plan.stances[index].q)
        skeletons.append(_skeleton(robot, data, spot_frames))
    # One camera: the robot's reach over all drawn stances, plus a margin, equal scales.
    points = np.array([p for skeleton in skeletons for segment in skeleton for p in segment])
    margin = 0.3
    lower, upper = points.min(axis=0) - margin, points.max(axis=0) + margin

    scene_faces = [(_clip(face, lower, upper), "tab:brown")
                   for obstacle in scene.obstacles.values() for face in _obstacle_faces(obstacle)]
    for surface in scene.surfaces.values():
        polygon = np.c_[surface.polygon, np.zeros(len(surface.polygon))]
        world = polygon @ surface.pose.rotation.T + surface.pose.translation
        scene_faces.append((_clip(world, lower, upper), "silver"))
    scene_faces = [(face, colour) for face, colour in scene_faces if len(face) >= 3]
    colours = {name: plt.cm.tab10(i % 10) for i, name in enumerate(scene.spots)}

    columns = max(1, min(args.columns, len(indices)))
    rows = math.ceil(len(indices) / columns)
    figure = plt.figure(figsize=(3.6 * columns, 4.4 * rows + 0.8))
    for panel, (index, skeleton) in enumerate(zip(indices, skeletons)):
        stance = plan.stances[index]
        axes = figure.add_subplot(rows, columns, panel + 1, projection="3d",
                                  computed_zorder=False)   # scene, then contacts, then robot
        axes.add_collection3d(Poly3DCollection(
            [face for face, _ in scene_faces], facecolors=[c for _, c in scene_faces],
            edgecolors="dimgray", linewidths=0.3, alpha=0.18))
        for contact in stance.contacts:
            vertices, _, _ = contact_vertices(contact, scene)
            axes.add_collection3d(Poly3DCollection(
                [vertices], facecolors=[colours[contact.spot]], edgecolors="black",
                alpha=0.9 if contact.in_stability else 0.35, linewidths=0.8,
                hatch=None if contact.in_stability else "////"))
        axes.add_collection3d(Line3DCollection(skeleton, colors="black", linewidths=1.4))
        axes.set_xlim(lower[0], upper[0])
        axes.set_ylim(lower[1], upper[1])
        axes.set_zlim(lower[2], upper[2])
        axes.set_box_aspect(upper - lower, zoom=1.15)
        axes.view_init(elev=18, azim=-60)
        axes.locator_params(nbins=4)
        axes.tick_params(labelsize=6, pad=0)
        axes.set_title(textwrap.fill(f"stance {index}: {_describe_contacts(stance.contacts)}", 48),
                       fontsize=9)
    handles = [Patch(color=colour, label=name)
               for name, colour in colours.items()]
    figure.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=9,
                  title="contact spots (* / hatched: not in stability)", title_fontsize=9)
    figure.suptitle(f"plan on scene {scene.name}: {len(plan.stances)} stances", fontsize=11,
                    y=1.0 - 0.1 / figure.get_figheight(), va="top")  # in the top margin
    figure.subplots_adjust(left=0.01, right=0.99, bottom=0.8 / figure.get_figheight(),
                           top=1.0 - 0.5 / figure.get_figheight(), wspace=0.05, hspace=0.1)
    output = Path(args.output)
    if not output.suffix:           # what matplotlib writes: the name the user sees
        output = output.with_suffix(".png")
    try:
        if output.is_dir():
            raise IsADirectoryError(f"{output} is a directory")
        figure.savefig(output, dpi=110)
    except (OSError, ValueError) as error:   # ValueError: a format matplotlib cannot write
        print(f"stance {PLOT_COMMAND}: cannot write {output}: {error}", file=sys.stderr)
        return 2
    finally:
        plt.close(figure)
    print(output)
    return 0


def _undrawable(plan, scene, robot) -> str:
    """What keeps a stance of the plan from being drawn (a witness that is not nq finite
    values, a contact naming a spot or surface the scene lacks), or ''."""
    from stance.planning.scene import placement_problem

    for index, stance in enumerate(plan.stances):
        q = np.asarray(stance.q)
        if q.shape != (robot.model.nq,) or not np.isfinite(q).all():
            return f"stances[{index}].q: not {robot.model.nq} finite values"
        for k, contact in enumerate(stance.contacts):
            problem = placement_problem(scene.surfaces, scene.spots, contact)
            if problem and problem[0] in (".spot", ".surface"):
                return f"stances[{index}].contacts[{k}]{problem[0]}: {problem[1]}"
    return ""
