"""`stance bench plan`: the contact planner on a scene (default the paper's chair escape):
nodes expanded, posture generations, stances, wall time, verification of the plan, posture
generator cost and success rate per call kind; then the same scene with ordered son
generation (Escande et al. 2.8) switched off, and the ratio of posture generations."""

from __future__ import annotations

import json

from .cli import positive

POSTURE_MEDIAN_TARGET = 0.030   # s per posture generation (issue target)


def add_plan_arguments(parser) -> None:
    parser.add_argument("--scene", default="chair_table", help="scene name or YAML path")
    parser.add_argument("--max-nodes", type=positive(int), default=2400, help="nodes expanded at most")
    parser.add_argument("--time-budget", type=positive(float), default=900.0, help="s per planning run")
    parser.add_argument("--unordered-budget", type=positive(float), default=300.0,
                        help="s for the run without ordered sons (compared per expanded "
                             "node); 0 skips it")
    parser.add_argument("--workers", type=positive(int), default=2,
                        help="processes generating a node's first sons together")
    parser.add_argument("--plan", default=None, help="write the ordered run's plan (JSON)")
    parser.add_argument("--json", default=None, help="write the figures (JSON)")


def _print_run(title, outcome, seconds):
    statistics = outcome.statistics
    print(f"{title}: {outcome.reason} ({outcome.message})")
    print(f"  nodes expanded {statistics.get('nodes_expanded', 0)}, posture generations "
          f"{statistics.get('posture_generations', 0)}, stances "
          f"{statistics.get('stances', 0)}, wall time {seconds:.1f} s")
    if statistics.get("transitions_checked"):
        print(f"  transitions interpolated before expansion {statistics['transitions_checked']}"
              f", rejected {statistics['transitions_rejected']}, "
              f"{statistics['transition_check_time']:.1f} s")
    for kind, figures in statistics.get("posture_calls", {}).items():
        rate = figures["successes"] / figures["calls"]
        print(f"  posture generator [{kind:6s}] calls {figures['calls']:6d}  success "
              f"{100 * rate:5.1f} %  median {1e3 * figures['median_s']:6.1f} ms  p99 "
              f"{1e3 * figures['p99_s']:7.1f} ms  median CPU "
              f"{1e3 * figures['median_cpu_s']:6.1f} ms")
    if "all" in statistics.get("posture_calls", {}):
        figures = statistics["posture_calls"]["all"]
        verdicts = [f"{what} {1e3 * figures[key]:.1f} ms "
                    f"{'PASS' if figures[key] <= POSTURE_MEDIAN_TARGET else 'FAIL'}"
                    for what, key in (("wall", "median_s"), ("CPU", "median_cpu_s"))]
        print(f"  posture generator median over all calls (target <= "
              f"{1e3 * POSTURE_MEDIAN_TARGET:.0f} ms): {', '.join(verdicts)}; wall time "
              f"counts the waits when the planner's processes outnumber the free cores")


def run_plan(args) -> int:
    import time

    from threadpoolctl import threadpool_limits

    from stance.planning.contacts import save_plan
    from stance.planning.verify import verify_plan

    from .plan import plan_scene

    figures = {"scene": args.scene}
    with threadpool_limits(1):
        began = time.perf_counter()
        outcome, scene, robot = plan_scene(args.scene, args.max_nodes, args.time_budget, True,
                                           workers=args.workers)
        seconds = time.perf_counter() - began
        _print_run("ordered sons (2.8)", outcome, seconds)
        figures["ordered"] = dict(outcome.statistics, reason=outcome.reason, wall_time=seconds)
        if outcome.success:
            report = verify_plan(outcome.plan, scene, robot)
            figures["verified"] = report.ok
            print(f"  independent verification: {'OK' if report.ok else 'FAILED'} "
                  f"{'; '.join(report.failures[:3])}")
            if args.plan:
                save_plan(outcome.plan, args.plan)
        budget = args.unordered_budget
        if budget > 0:
            began = time.perf_counter()
            unordered, _, _ = plan_scene(args.scene, args.max_nodes, budget, False,
                                         workers=args.workers)
            seconds = time.perf_counter() - began
            _print_run("every son generated", unordered, seconds)
            figures["unordered"] = dict(unordered.statistics, reason=unordered.reason,
                                        wall_time=seconds)
            ordered_stats, unordered_stats = outcome.statistics, unordered.statistics
            per_node = [stats["posture_generations"] / max(stats["nodes_expanded"], 1)
                        for stats in (ordered_stats, unordered_stats)]
            print(f"posture generations per expanded node: ordered {per_node[0]:.1f}, "
                  f"unordered {per_node[1]:.1f}: ratio {per_node[1] / per_node[0]:.2f}x "
                  f"(paper: 3-5x fewer with ordering)")
            if outcome.success and unordered.success:
                ratio = unordered_stats["posture_generations"] / \
                    ordered_stats["posture_generations"]
                print(f"posture generations to the goal: ratio {ratio:.2f}x")
                figures["ratio_to_goal"] = ratio
            figures["ratio_per_node"] = per_node[1] / per_node[0]
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(figures, stream, indent=1)
    return 0 if outcome.success else 1
