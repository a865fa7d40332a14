"""`stance compile`: fill numba's disk cache with the kernels pik_node's first step needs.

Compiling the library's kernels for one robot's limit models takes over a minute on a 2-core
machine; a node that finds them cached starts in about a second. `make setup` runs this
once per source version (the cache is keyed on the library's sources,
stance.numba_cache), so neither the first `ros2 run pik_node` nor the demo's start-up
timeout pays for the compilation. With the cache filled, the command takes about a second.
"""

import time

from stance import PIKSolver, Robot
from stance.pik import HIERARCHIES, demo_stack_file
from stance.stack import parse_stack_yaml
from stance.swing import load_limit_file

# Hz: pik_node's default rate. The kernels compiled depend on dt being set (velocity limits
# on), not on its value.
NODE_RATE = 500.0


def add_arguments(parser) -> None:
    parser.add_argument("--robot", action="append", choices=("talos", "mannequin"),
                        help="robot whose demo stack and limit file to compile for "
                             "(repeatable; default: talos)")
    parser.add_argument("--hierarchy", action="append", choices=HIERARCHIES,
                        help="prioritized solver to compile for (repeatable; default: svd, "
                             "pik_node's default)")


def warm(robot_name: str, hierarchy: str) -> float:
    """Take pik_node's warm-up step (default parameters, the robot's demo stack and limit
    file) and return its duration (s): the compilation, or the cache's loading."""
    start = time.perf_counter()
    robot = Robot.load(robot_name)
    limit_models = load_limit_file(robot.limit_file, robot) if robot.limit_file else ()
    solver = PIKSolver(robot, dt=1.0 / NODE_RATE, hierarchy=hierarchy,
                       limit_models=limit_models)
    q = robot.initial_configuration()
    specs = parse_stack_yaml(demo_stack_file(robot_name).read_text(), robot.model.existFrame)
    solver.set_stack(specs, q)
    solver.warm_up(q)
    return time.perf_counter() - start


def run(args) -> int:
    for robot_name in args.robot or ["talos"]:
        for hierarchy in args.hierarchy or ["svd"]:
            seconds = warm(robot_name, hierarchy)
            print(f"pik_node kernels ready: {robot_name}, {hierarchy} hierarchy ({seconds:.1f} s)")
    return 0
