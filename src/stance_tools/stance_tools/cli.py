"""The `stance` command: one entry point, one module per subcommand.

Each subcommand module exposes ``add_arguments(parser)`` and ``run(args) -> int``; modules
are imported only when their subcommand runs, so `stance plot` never loads rclpy.
"""

import argparse
import math
import importlib
import sys

SUBCOMMANDS = {
    "record": ("stance_tools.record", "record topics to an MCAP bag (rosbag2 layout)"),
    "plot": ("stance_tools.plot", "write PNG plots from a recorded bag"),
    "teleop": ("stance_tools.teleop",
               "move a task's target from the keyboard or along a scripted path"),
    "demo": ("stance_tools.demo", "the whole graph on a scene (plan, execute, record, check, "
             "report); --scenario pik: the PIK demo"),
    "bench": ("stance_tools.bench",
              "benchmarks: pik, levels, groups, support, node, interpolate, plan, graph"),
    "reproduce": ("stance_tools.reproduce",
                  "reproduce the progressive clamping paper's experiments"),
    "plan": ("stance_tools.plan", "plan contact stances for a scene (best-first, no ROS)"),
    "check-plan": ("stance_tools.plan_tools",
                   "verify a contact plan's stances independently (exit 1 on failures)"),
    "plot-plan": ("stance_tools.plan_tools", "contact sheet (PNG) of a plan's stances"),
    "check-run": ("stance_tools.check_run",
                  "check an executed plan's bag: contacts, limits, C1, balance, stabilizer"),
    "graph": ("stance_tools.graph",
              "run the node graph: one process per node, crashed nodes restarted"),
    "compile": ("stance_tools.warm_cache",
                "fill numba's disk cache with pik_node's kernels (make setup runs it)"),
    "param": ("stance_tools.param",
              "set a running node's parameter (e.g. pik_node's strategy) without ros2"),
}


def positive(kind, most=None):
    """argparse type: a finite value of `kind` (int, float) above 0, and at most `most`
    when given (nan and inf are refused: nan passed every comparison)."""
    def parse(text):
        value = kind(text)
        if not math.isfinite(value) or value <= 0:
            raise argparse.ArgumentTypeError(f"must be finite and > 0, got {text}")
        if most is not None and value > most:
            raise argparse.ArgumentTypeError(f"must be at most {most:g}, got {text}")
        return value
    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="stance", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    chosen = (argv if argv is not None else sys.argv[1:])[:1]
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sub = commands.add_parser(name, help=help_text)
        if chosen == [name]:
            module = importlib.import_module(module_name)
            module.add_arguments(sub)
            sub.set_defaults(run=module.run)
    args = parser.parse_args(argv)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
