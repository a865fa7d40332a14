"""`stance plan SCENE -o plan.json`: plan contact stances for a scene with the library's
best-first planner (no ROS), print progress, write the plan (JSON) and exit 0 on success.
The same planner runs behind contact_planner_node's PlanContacts action."""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import sys  # noqa: E402
import time  # noqa: E402


def add_arguments(parser) -> None:
    parser.add_argument("scene", help="shipped scene name (e.g. chair_table) or YAML path")
    parser.add_argument("-o", "--output", default="plan.json", help="plan file (JSON)")
    parser.add_argument("--max-nodes", type=int, default=2400, help="nodes expanded at most")
    parser.add_argument("--time-budget", type=float, default=900.0, help="seconds at most")
    parser.add_argument("--unordered", action="store_true",
                        help="generate every son of every pair (no section 2.8 ordering)")
    parser.add_argument("--workers", type=int, default=2,
                        help="processes generating a node's first sons together")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def plan_scene(scene_spec: str, max_nodes: int, time_budget: float, ordered: bool,
               progress=None, workers: int = 1):
    """(PlanOutcome, scene, robot) for a shipped scene name or a scene file."""
    from stance.planning.planner import PlanRequest, plan_contacts
    from stance.planning.scene import load_scene
    from stance.robot import Robot

    scene = load_scene(scene_spec)
    robot = Robot.load(scene.robot)
    request = PlanRequest(scene=scene, max_nodes=max_nodes, time_budget=time_budget,
                          ordered_sons=ordered, workers=workers)
    return plan_contacts(robot, request, progress=progress), scene, robot


def run(args) -> int:
    from threadpoolctl import threadpool_limits

    from stance.planning.contacts import save_plan
    from stance.planning.scene import SceneError

    last = [0.0]

    def report(progress):
        if args.quiet or time.monotonic() - last[0] < 2.0:
            return
        last[0] = time.monotonic()
        print(f"  {progress.elapsed:7.1f} s  nodes {progress.nodes_expanded:5d}  posture "
              f"generations {progress.posture_generations:6d}  best f_T "
              f"{progress.best_potential:9.3f}", flush=True)

    with threadpool_limits(1):
        try:
            outcome, _, _ = plan_scene(args.scene, args.max_nodes, args.time_budget,
                                       not args.unordered, report, args.workers)
        except SceneError as error:
            print(f"stance plan: bad scene: {error}", file=sys.stderr)
            return 2
        except ValueError as error:     # PlanRequest's budgets and settings
            print(f"stance plan: {error}", file=sys.stderr)
            return 2
    statistics = outcome.statistics
    print(f"{outcome.reason}: {outcome.message} ({statistics.get('nodes_expanded', 0)} nodes,"
          f" {statistics.get('posture_generations', 0)} posture generations, "
          f"{statistics.get('planning_time', 0.0):.1f} s)")
    if not outcome.success:
        return 1
    save_plan(outcome.plan, args.output)
    print(f"wrote {args.output}: {len(outcome.plan.stances)} stances")
    return 0
