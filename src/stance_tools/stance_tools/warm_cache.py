"""`stance compile`: fill numba's disk cache with the kernels pik_node's first step needs.

Compiling the library's kernels for one robot's limit models takes over a minute on a 2-core
machine (each other set of limit models or hierarchy 10-25 s more); a node that finds them
cached starts in about a second. `make setup` runs this once per source version (the cache
is keyed on the library's sources, stance.numba_cache) for every configuration Talos ships,
so neither the first `pik_node` nor the demo's start-up timeout pays for the compilation.
With the cache filled, the command takes about a second per configuration.
"""

import time
from pathlib import Path

from stance import PIKSolver, Robot
from stance.pik import HIERARCHIES, demo_stack_file
from stance.stack import parse_stack_yaml
from stance.swing import SHIPPED_LIMIT_FILES, load_limit_file

# Hz: pik_node's default rate. The kernels compiled depend on dt being set (velocity limits
# on), not on its value.
NODE_RATE = 500.0
ROBOTS_OWN_LIMITS = ""   # limits_file value of pik_node's default: the robot's own file


def add_arguments(parser) -> None:
    parser.add_argument("--robot", action="append", choices=("talos", "mannequin"),
                        help="robot whose demo stack to compile for (repeatable; default: "
                             "talos)")
    parser.add_argument("--hierarchy", action="append", choices=HIERARCHIES,
                        help="prioritized solver to compile for (repeatable; default: "
                             f"{' and '.join(HIERARCHIES)})")
    parser.add_argument("--limits-file", action="append", metavar="FILE",
                        help="limit file to compile for, as pik_node's limits_file: a YAML "
                             "path or a shipped name, \"\" for the robot's own (repeatable; "
                             "default: the robot's own and the one shipped under its name)")


def shipped_limit_files(robot_name: str) -> list:
    """limits_file values of the robot's shipped configurations: its own limits (""), and
    the limit file shipped under its name when that is not its own (Talos': its hips and
    shoulders as joint groups)."""
    shipped = SHIPPED_LIMIT_FILES / f"{robot_name}_limits.yaml"
    own = Robot.load(robot_name).limit_file
    separate = shipped.is_file() and (own is None or shipped.resolve() != Path(own).resolve())
    return [ROBOTS_OWN_LIMITS, robot_name] if separate else [ROBOTS_OWN_LIMITS]


def warm(robot_name: str, hierarchy: str, limits_file: str = ROBOTS_OWN_LIMITS) -> float:
    """Take pik_node's warm-up step (default parameters but the hierarchy and limit file,
    the robot's demo stack) and return its duration (s): the compilation, or the cache's
    loading."""
    start = time.perf_counter()
    robot = Robot.load(robot_name)
    limit_file = limits_file or robot.limit_file   # a path or a shipped name
    limit_models = load_limit_file(limit_file, robot) if limit_file else ()
    solver = PIKSolver(robot, dt=1.0 / NODE_RATE, hierarchy=hierarchy,
                       limit_models=limit_models)
    q = robot.initial_configuration()
    specs = parse_stack_yaml(demo_stack_file(robot_name).read_text(), robot.model.existFrame)
    solver.set_stack(specs, q)
    solver.warm_up(q)
    return time.perf_counter() - start


def configurations(robots=None, limits_files=None, hierarchies=None) -> list:
    """(robot, limits_file, hierarchy) triples to compile for: the options' values, each
    defaulting as the command's help says."""
    return [(robot_name, limits_file, hierarchy)
            for robot_name in robots or ["talos"]
            for limits_file in limits_files or shipped_limit_files(robot_name)
            for hierarchy in hierarchies or HIERARCHIES]


def run(args) -> int:
    for robot_name, limits_file, hierarchy in configurations(args.robot, args.limits_file,
                                                             args.hierarchy):
        seconds = warm(robot_name, hierarchy, limits_file)
        limits = f"limit file {limits_file}" if limits_file else "its own limits"
        print(f"pik_node kernels ready: {robot_name}, {limits}, {hierarchy} hierarchy "
              f"({seconds:.1f} s)")
    return 0
