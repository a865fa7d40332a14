"""`stance bench interpolate`: interpolation between the stances of a plan (Escande et al.
2008, 3.3): total wall time for the whole plan (median over repeats), per-transition
figures (moving spots, posture generations, iterations, time, failures), the ratio to the
paper's 90 s for the chair plan at n = 20, and the durations of the sinusoidal and
time-optimal timings when every transition succeeded."""

from __future__ import annotations

import json

from .cli import positive

PAPER_SECONDS = 90.0   # the paper's whole chair plan, n = 20 (3.3)


def add_interpolate_arguments(parser) -> None:
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--plan", default=None, help="plan file (JSON, `stance plan -o`)")
    source.add_argument("--scene", default="flat_steps",
                        help="scene to plan first when no --plan is given")
    parser.add_argument("-n", "--steps", type=positive(int), default=20, help="steps per transition")
    parser.add_argument("--lift", type=float, default=0.05,
                        help="m: straight lines leaving and entering contacts")
    parser.add_argument("--repeats", type=positive(int), default=3, help="timed runs (median)")
    parser.add_argument("--json", default=None, help="write the figures (JSON)")


def _run_once(planner, stances):
    """(seconds, per-transition figures, (interior samples, statistics) of the transitions
    that succeeded)."""
    import time

    from stance.execution.interpolation import InterpolationError

    figures, results = [], []
    began = time.perf_counter()
    for index, (first, second) in enumerate(zip(stances[:-1], stances[1:])):
        started = time.perf_counter()
        try:
            results.append(planner.transition(index, first, second))
            figures.append(dict(results[-1][1], ok=True))
        except InterpolationError as error:
            figures.append({"ok": False, "error": str(error), "sample": error.sample,
                            "seconds": time.perf_counter() - started})
    return time.perf_counter() - began, figures, results


def run_interpolate(args) -> int:
    import numpy as np
    from threadpoolctl import threadpool_limits

    from stance.execution.interpolation import TransitionPlanner, assemble
    from stance.execution.timing import ACCELERATION_LIMIT, sinusoidal_trajectory, \
        time_optimal_trajectory
    from stance.planning.collision import CollisionModel
    from stance.planning.contacts import load_plan
    from stance.planning.scene import load_scene
    from stance.robot import Robot

    with threadpool_limits(1):
        if args.plan:
            plan = load_plan(args.plan)
            robot = Robot.load(plan.robot)
            scene = load_scene(plan.scene, robot)
        else:
            from .plan import plan_scene
            outcome, scene, robot = plan_scene(args.scene, 2400, 900.0, True)
            if not outcome.success:
                print(f"planning {args.scene} failed: {outcome.reason} ({outcome.message})")
                return 1
            plan = outcome.plan
        planner = TransitionPlanner(robot, scene, CollisionModel(robot, scene),
                                    steps=args.steps, lift=args.lift)
        runs = [_run_once(planner, plan.stances) for _ in range(max(args.repeats, 1))]
    totals = [seconds for seconds, _, _ in runs]
    _, figures, results = runs[-1]
    total = float(np.median(totals))
    failed = [i for i, f in enumerate(figures) if not f["ok"]]
    print(f"plan {plan.scene}: {len(plan.stances)} stances, {len(figures)} transitions, "
          f"n = {args.steps}, lift {args.lift} m")
    for index, entry in enumerate(figures):
        if entry["ok"]:
            detour = "" if entry["detour_from"] is None else \
                f"  detour from sample {entry['detour_from']:g}"
            if entry["subdivided"]:
                detour += f"  {entry['subdivided']} steps halved"
            print(f"  {index:3d} -> {index + 1:3d}  moving {','.join(entry['moving']) or '-':28s}"
                  f" generations {entry['generations']:3d}  iterations "
                  f"{entry['iterations']:4d}  {1e3 * entry['seconds']:7.1f} ms{detour}")
        else:
            print(f"  {index:3d} -> {index + 1:3d}  FAILED after {1e3 * entry['seconds']:.1f} "
                  f"ms: {entry['error']}")
    seconds = [entry["seconds"] for entry in figures]
    print(f"whole plan: median {total:.2f} s over {len(totals)} runs (min {min(totals):.2f}, "
          f"max {max(totals):.2f}); per transition median {1e3 * np.median(seconds):.1f} ms, "
          f"max {1e3 * max(seconds):.1f} ms; {len(failed)} failed transitions "
          f"{failed if failed else ''}; "
          f"{sum(entry.get('detour_from') is not None for entry in figures)} detours, "
          f"{sum(entry.get('subdivided', 0) for entry in figures)} steps halved")
    print(f"first (cold) run {totals[0]:.2f} s: the static equilibrium regions of the "
          f"support sets are computed then and cached for the later runs")
    result = {"scene": plan.scene, "steps": args.steps, "lift": args.lift,
              "stances": len(plan.stances), "total_seconds": total, "runs": totals,
              "failed": failed, "transitions": figures}
    if plan.scene == "chair_table" and args.steps == 20:
        result["ratio_to_paper"] = total / PAPER_SECONDS
        incomplete = f" (INCOMPLETE: {len(failed)} transitions stopped at their failing " \
            f"sample)" if failed else ""
        print(f"chair plan: {total:.2f} s vs the paper's {PAPER_SECONDS:.0f} s: "
              f"{PAPER_SECONDS / total:.1f}x faster (target <= 10 s){incomplete}")
    if not failed:
        path = assemble(plan.stances, args.steps, results)
        durations = {
            "sinusoidal_s": sinusoidal_trajectory(robot, path.q, path.event_samples).duration,
            "sinusoidal_bounded_s": sinusoidal_trajectory(
                robot, path.q, path.event_samples, acceleration_limit=ACCELERATION_LIMIT
            ).duration,
            "time_optimal_s": time_optimal_trajectory(robot, path.q,
                                                      path.event_samples).duration}
        print(f"timing at half the velocity limits: sinusoidal (paper, speed only) "
              f"{durations['sinusoidal_s']:.1f} s; with |joint acceleration| <= "
              f"{ACCELERATION_LIMIT} rad/s^2: sinusoidal {durations['sinusoidal_bounded_s']:.1f}"
              f" s, time-optimal {durations['time_optimal_s']:.1f} s")
        result.update(durations)
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(result, stream, indent=1)
    return 0 if not failed else 1
