"""`stance bench`: benchmarks, one sub-benchmark per name (all of them when none is named).

- pik: one library IK step on Talos, PIKSolver (strategies none / clamping / progressive,
  and progressive on the QP hierarchy) against Pink's solve_ik on every available QP
  backend, same robot, stack and targets: feet > CoM > both hands > posture (`--stack
  hands`, the default), or pik_node's demo stack with the right hand only (`--stack demo`);
  the same steps timed interleaved (one step each in turn) and back to back (blocks).
- levels: cost of a step as priority levels are added, SVD and QP hierarchies side by side
  (Talos, 1 to 4 levels; Panda arm, 2 levels).
- groups: cost of a step with Talos' hips and shoulders limited as ball / swing joints
  (the shipped limit file's joint groups) against 1-DoF limits only, and of the QP
  hierarchy on the same problems (arms out: bounds binding every step); the mannequin's
  spherical joints on the thorn experiment, compiled clamping loop against the general one.
- node: pik_node's loop rate and latency over DDS (stance_tools.bench_node).
- plan: the contact planner on the chair scene, ordered sons on and off
  (stance_tools.bench_plan).
- interpolate: postures along the transitions of a plan (stance_tools.bench_interpolate).
- graph: CPU use per node of the whole graph, idle and executing a plan
  (stance_tools.bench_graph).

A sub-benchmark is registered in BENCHMARKS by its module and the names of two functions,
``add(parser)`` and ``run(args) -> int``; modules must import heavy dependencies (rclpy) in
their run function only.
"""

from __future__ import annotations

import os

# One BLAS thread before numpy loads (small SVDs slow down with more): as in the nodes.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import importlib  # noqa: E402
import json  # noqa: E402
import random  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import numpy as np  # noqa: E402

from .cli import positive  # noqa: E402

# name -> (module, add-arguments function, run function, help)
BENCHMARKS = {
    "pik": (__name__, "add_pik_arguments", "run_pik",
            "library step: PIKSolver (none/clamping/progressive, SVD and QP) vs Pink"),
    "levels": (__name__, "add_levels_arguments", "run_levels",
               "step cost per added priority level, SVD vs QP hierarchy (Talos, Panda)"),
    "groups": (__name__, "add_groups_arguments", "run_groups",
               "step cost with Talos' joint groups (hips, shoulders) vs 1-DoF limits only; "
               "the mannequin's spherical joints, compiled vs general clamping loop"),
    "support": (__name__, "add_levels_arguments", "run_support",
                "CoM kept inside the feet's support polygon (QP inequality rows) vs CoM "
                "held as an equality, Talos"),
    "node": ("stance_tools.bench_node", "add_node_arguments", "run_node",
             "pik_node over DDS: loop rate at 500 Hz, target-to-joint_states latency"),
    "interpolate": ("stance_tools.bench_interpolate", "add_interpolate_arguments",
                    "run_interpolate",
                    "interpolation between stances: whole-plan time, per transition"),
    "plan": ("stance_tools.bench_plan", "add_plan_arguments", "run_plan",
             "contact planner on the chair scene: nodes, posture generations, time; "
             "ordered sons on vs off"),
    "graph": ("stance_tools.bench_graph", "add_graph_arguments", "run_graph",
              "CPU per node of the whole graph (%% of one core), idle and executing a plan"),
}


def add_arguments(parser) -> None:
    benchmarks = parser.add_subparsers(dest="benchmark", metavar="BENCHMARK",
                                       help="default: every benchmark with its defaults")
    parsers = {}
    for name, (module_name, add_name, run_name, help_text) in BENCHMARKS.items():
        module = importlib.import_module(module_name)
        sub = benchmarks.add_parser(name, help=help_text)
        getattr(module, add_name)(sub)
        sub.set_defaults(run_benchmark=getattr(module, run_name))
        parsers[name] = sub
    parser.set_defaults(benchmark_parsers=parsers)


def run(args) -> int:
    if args.benchmark is not None:
        return args.run_benchmark(args)
    status = 0
    for sub in args.benchmark_parsers.values():
        defaults = sub.parse_args([])
        status = max(status, defaults.run_benchmark(defaults))
    return status


# ---------------------------------------------------------------------------------------
# pik: PIKSolver.step vs Pink solve_ik + integrate + configuration update
# ---------------------------------------------------------------------------------------

def mirrored_hands(right_offset) -> dict:
    """Hand target offsets (m, world): the right hand's, and the left hand's mirror image
    in the sagittal plane (y negated)."""
    x, y, z = right_offset
    return {"left_hand": (x, -y, z), "right_hand": (x, y, z)}


# The stack: feet (12) > CoM xy (2) > both hands (12) > posture.
TALOS_LEVEL_STACK = """
- {name: left_foot, kind: pose, frame: left_sole_link, priority: 0, gain: 0.5}
- {name: right_foot, kind: pose, frame: right_sole_link, priority: 0, gain: 0.5}
- {name: com, kind: com, priority: 1, axes: [x, y], gain: 0.2}
- {name: left_hand, kind: pose, frame: gripper_left_base_link, priority: 2, gain: 0.1}
- {name: right_hand, kind: pose, frame: gripper_right_base_link, priority: 2, gain: 0.1}
- {name: posture, kind: posture, priority: 3, gain: 0.02}
"""
# Both hands 0.25 m forward, 0.2 m out and 0.2 m up from the start: reached, with the
# torso's pitch on its limit (the CoM level leans it back) and both wrists damped.
HANDS_FORWARD = mirrored_hands((0.25, -0.2, 0.2))
PIK_STACKS = ("hands", "demo")
STRATEGIES = ("progressive", "clamping", "none")
PINK_BACKENDS = ("quadprog", "daqp", "proxqp")
BACK_TO_BACK_BLOCK = 100   # steps a contender takes in a row in bench pik's back-to-back race
GRIPPER_JOINTS = ("gripper_left_joint", "gripper_right_joint")
GRIPPER_MARGIN = 0.01      # rad inside the grippers' upper limit (0) at the start
COST_PER_LEVEL = 10.0      # Pink has no priorities: cost 10^-priority * sqrt(weight)


def add_pik_arguments(parser) -> None:
    parser.add_argument("--steps", type=positive(int), default=2000, help="timed steps per contender")
    parser.add_argument("--warmup", type=int, default=200,
                        help="untimed steps first (numba and QP set-up excluded)")
    parser.add_argument("--stack", choices=PIK_STACKS, default="hands",
                        help="hands: feet > CoM xy > both hands > posture; demo: pik_node's "
                             "demo stack (right hand only)")
    parser.add_argument("--offset", type=float, nargs=3, default=HANDS_FORWARD["right_hand"],
                        metavar=("X", "Y", "Z"),
                        help="right-hand target offset (m, world); the left hand's is its "
                             "mirror image (y negated)")
    parser.add_argument("--dt", type=positive(float), default=0.002,
                        help="step period (s): velocity limits for both solvers")
    parser.add_argument("--backends", nargs="+", default=PINK_BACKENDS,
                        help="Pink QP backends (those not installed are skipped)")
    parser.add_argument("--block", type=positive(int), default=BACK_TO_BACK_BLOCK,
                        help="steps each contender takes in a row in the second, back-to-back "
                             "race (the first interleaves single steps)")
    parser.add_argument("--json", help="also write the figures to this JSON file")


@dataclass
class Record:
    """What one contender did over the timed run."""

    times_ns: list = field(default_factory=list)
    iterations: list = field(default_factory=list)
    max_limit_excess: float = 0.0
    failed_at: int | None = None
    failure: str = ""
    q: np.ndarray | None = None


class StanceContender:
    """PIKSolver.step with one limit strategy, on the SVD hierarchy or (qp) QPHierarchy,
    with the given limit models beyond the 1-DoF joints'."""

    def __init__(self, robot, strategy, specs, targets, start, dt, qp=False, name=None,
                 limit_models=()):
        from stance.pik import PIKSolver
        from stance.qp_hierarchy import QPHierarchy

        self.name = name or f"stance {strategy}{' qp' if qp else ''}"
        hierarchy = QPHierarchy.for_robot(robot, dt=dt) if qp else None
        self.solver = PIKSolver(robot, strategy=strategy, dt=dt, hierarchy=hierarchy,
                                limit_models=limit_models)
        self.solver.set_stack(specs, start)
        for spec in specs:
            self.solver.task(spec.name).target = targets[spec.name]

    def reset(self, q) -> None:
        """Each race starts as a fresh solver: no active set kept from an earlier race."""
        self.solver.forget_starts()

    def step(self, q):
        result = self.solver.step(q)
        return result.q, result.clamping_iterations


class SolverContender(StanceContender):
    """A PIKSolver already set up (stack, targets), stepped as a contender."""

    def __init__(self, name, solver):
        self.name, self.solver = name, solver


class PinkContender:
    """pink.solve_ik on one QP backend, then pin.integrate and Configuration.update."""

    def __init__(self, robot, backend, specs, targets, start, dt):
        import pink
        import pinocchio as pin

        self.name = f"pink {backend}"
        self.backend, self.dt = backend, dt
        self.solve_ik, self.integrate = pink.solve_ik, pin.integrate
        self.model = robot.model.copy()  # Pink attaches its limits to the model
        self.configuration = pink.Configuration(self.model, self.model.createData(), start)
        self.tasks = [pink_task(spec, targets[spec.name]) for spec in specs]

    def reset(self, q) -> None:
        self.configuration.update(q)

    def step(self, q):
        velocity = self.solve_ik(self.configuration, self.tasks, self.dt, solver=self.backend)
        q_next = self.integrate(self.model, self.configuration.q, velocity * self.dt)
        self.configuration.update(q_next)
        return q_next, 0


def pink_task(spec, target):
    """The Pink task closest to a stance TaskSpec, with the spec's gain."""
    from pink.tasks import ComTask, FrameTask, PostureTask

    cost = COST_PER_LEVEL ** -spec.priority * np.sqrt(spec.weight)
    if spec.kind == "pose":
        task = FrameTask(spec.frame, position_cost=cost, orientation_cost=cost, gain=spec.gain)
    elif spec.kind == "com":
        task = ComTask([cost if axis in spec.selected_axes() else 0.0 for axis in "xyz"],
                       gain=spec.gain)
    elif spec.kind == "posture":
        task = PostureTask(cost, gain=spec.gain)
    else:
        raise ValueError(f"no Pink equivalent for task kind {spec.kind}")
    task.set_target(target)
    return task


def bench_start(robot) -> np.ndarray:
    """half_sitting with both grippers GRIPPER_MARGIN inside their upper limit."""
    q = robot.initial_configuration()
    for joint in GRIPPER_JOINTS:
        index = robot.model.joints[robot.joint_id(joint)].idx_q
        q[index] = robot.model.upperPositionLimit[index] - GRIPPER_MARGIN
    return q


def bench_targets(robot, specs, start, offsets) -> dict:
    """Targets held at the start, pose tasks named in `offsets` moved by their offset (m,
    world)."""
    from stance.pik import PIKSolver

    solver = PIKSolver(robot)
    solver.set_stack(specs, start)
    targets = {name: task.target for name, task in solver.tasks.items()}
    for name, offset in offsets.items():
        targets[name].translation += np.asarray(offset, dtype=float)
    return targets


def limit_excess(robot, q) -> float:
    values = q[robot.limited_q_index]
    return float(np.maximum(0.0, np.maximum(values - robot.upper, robot.lower - values)).max())


def race(contenders, robot, start, steps, states=None, block=1, seed=0) -> dict:
    """Every contender takes steps k..k+block-1 before any takes the next block, in an order
    drawn anew for each block (random.Random(seed): the same orders in every run) and never
    starting with the contender that ended the block before, so each contender follows
    every other about equally often. A step's time depends on how much of the caches its
    predecessor evicted: a fixed cyclic order (rotated per block) kept each contender's
    predecessor, Stance's progressive step always after a Pink step and Pink's quadprog
    step always after Stance's lightest one. block 1 (interleaved): each step runs after
    another contender's, its caches cold, as in a node whose loop does other work between
    steps; a larger block (back to back): caches warm, as in the posture generator's loop.
    Pink errors mark a contender failed: it takes no more turns. states: one configuration
    per step; every contender then takes step k from states[k] instead of from its own last
    configuration (open loop, the same inputs for all)."""
    records = {contender.name: Record() for contender in contenders}
    configurations = {contender.name: start for contender in contenders}
    for contender in contenders:
        contender.reset(start)
    orders, last = random.Random(seed), None
    for first in range(0, steps, block):
        running = [contender for contender in contenders
                   if records[contender.name].failed_at is None]
        order = orders.sample(running, len(running))
        while len(running) > 1 and order[0] is last:
            order = orders.sample(running, len(running))
        last = order[-1] if order else None
        for contender in order:
            for step in range(first, min(first + block, steps)):
                q = configurations[contender.name] if states is None else states[step]
                q = _timed_step(contender, records[contender.name], robot, step, q)
                if q is None:
                    break
                configurations[contender.name] = q
    return records


def _timed_step(contender, record, robot, step, q):
    """The contender's configuration after one timed step from q, recorded; None when the
    step fails (a Pink error, recorded as the contender's failure)."""
    from pink.exceptions import PinkError

    begin = time.perf_counter_ns()
    try:
        q, iterations = contender.step(q)
    except PinkError as error:
        record.failed_at, record.failure = step, f"{type(error).__name__}: {error}"
        return None
    record.times_ns.append(time.perf_counter_ns() - begin)
    record.iterations.append(iterations)
    record.max_limit_excess = max(record.max_limit_excess, limit_excess(robot, q))
    record.q = q
    return q


def figures(records, evaluator) -> dict:
    """Per contender: timing (us), clamping iterations, final task errors (stance's
    definitions, m or rad), worst limit excess (rad) and failure if any."""
    result = {}
    for name, record in records.items():
        result[name] = {
            **timing_us(record),
            "mean_clamping_iterations": (float(np.mean(record.iterations))
                                         if name.startswith("stance") and record.iterations
                                         else None),
            "final_task_errors": (evaluator.step(record.q).task_errors
                                  if record.q is not None else None),
            "max_limit_excess": record.max_limit_excess,
            "timed_steps": len(record.times_ns),
            "failed_at_step": record.failed_at,
            "failure": record.failure or None,
        }
    reference = result["stance progressive"]["median_us"]
    for name, entry in result.items():
        pink_median = entry["median_us"] if name.startswith("pink") else None
        entry["stance_over_pink_median"] = reference / pink_median if pink_median else None
    return result


def timing_us(record) -> dict:
    """Median, 99th percentile and worst of a record's step times (us), None if it has
    none: the worst step is what a fixed-rate loop misses its period by."""
    times = np.array(record.times_ns) / 1e3
    if not len(times):
        return {"median_us": None, "p99_us": None, "max_us": None}
    return {"median_us": float(np.median(times)), "p99_us": float(np.percentile(times, 99)),
            "max_us": float(times.max())}


def start_note(robot, specs, targets, backends, dt) -> str:
    """Why the start is not half_sitting itself, with what Pink does from half_sitting."""
    from pink.exceptions import PinkError

    outcomes = []
    for backend in backends:
        contender = PinkContender(robot, backend, specs, targets,
                                  robot.initial_configuration(), dt)
        try:
            contender.step(robot.initial_configuration())
            outcomes.append(f"{backend} ok")
        except PinkError as error:
            outcomes.append(f"{backend} {type(error).__name__}")
    return (f"start: half_sitting with {' and '.join(GRIPPER_JOINTS)} moved {GRIPPER_MARGIN} "
            f"rad inside their upper limit 0. Pink's ConfigurationLimit assumes a start "
            f"strictly inside the limits and can raise NoSolutionFound from a joint exactly "
            f"on one (Pink #206, #163); one Pink step from half_sitting itself here: "
            f"{', '.join(outcomes)}.")


def print_table(result, errors_order=None) -> None:
    """One row per contender; errors_order None: the timing columns only."""
    extra = errors_order is not None
    task_columns = "".join(f"{name:>12}" for name in errors_order or ())
    print(f"{'contender':<24}{'median us':>10}{'p99 us':>10}{'max us':>10}"
          + (f"{'iters':>7}{'excess rad':>12}{task_columns}" if extra else "")
          + f"{'stance/pink':>13}")
    for name, entry in result.items():
        if entry["median_us"] is None:
            print(f"{name:<24} failed at timed step {entry['failed_at_step']}: "
                  f"{entry['failure']}")
            continue
        ratio = entry["stance_over_pink_median"]
        row = f"{name:<24}{entry['median_us']:>10.1f}{entry['p99_us']:>10.1f}" \
            f"{entry['max_us']:>10.1f}"
        if extra:
            iterations = entry["mean_clamping_iterations"]
            errors = entry["final_task_errors"]
            row += f"{'-' if iterations is None else f'{iterations:.2f}':>7}" \
                f"{entry['max_limit_excess']:>12.2e}" \
                + "".join(f"{errors[task]:>12.2e}" for task in errors_order)
        print(row + f"{'-' if ratio is None else f'{ratio:.2f}':>13}")
        if entry["failed_at_step"] is not None:
            print(f"{'':<24} failed at timed step {entry['failed_at_step']}: "
                  f"{entry['failure']}")


def run_pik(args) -> int:
    import qpsolvers
    from threadpoolctl import threadpool_limits

    from stance.pik import PIKSolver, default_stack_specs
    from stance.robot import Robot
    from stance.stack import parse_stack_yaml

    robot = Robot.from_example_robot_data("talos")
    specs = parse_stack_yaml(TALOS_LEVEL_STACK) if args.stack == "hands" else \
        default_stack_specs()
    start = bench_start(robot)
    right = tuple(float(value) for value in args.offset)
    offsets = {name: offset for name, offset in mirrored_hands(right).items()
               if any(spec.name == name for spec in specs)}
    targets = bench_targets(robot, specs, start, offsets)
    backends = [name for name in args.backends if name in qpsolvers.available_solvers]
    skipped = sorted(set(args.backends) - set(backends))
    evaluator = PIKSolver(robot)
    evaluator.set_stack(specs, start)
    for name, target in targets.items():
        evaluator.task(name).target = target

    with threadpool_limits(limits=1):
        contenders = [StanceContender(robot, strategy, specs, targets, start, args.dt)
                      for strategy in STRATEGIES]
        contenders.insert(1, StanceContender(robot, "progressive", specs, targets, start,
                                             args.dt, qp=True))
        contenders += [PinkContender(robot, backend, specs, targets, start, args.dt)
                       for backend in backends]
        note = start_note(robot, specs, targets, backends, args.dt)
        race(contenders, robot, start, args.warmup)
        # Both races take the same trajectory from the start.
        result = figures(race(contenders, robot, start, args.steps), evaluator)
        back_to_back = figures(race(contenders, robot, start, args.steps, block=args.block),
                               evaluator)

    print(f"stance bench pik: Talos (nv {robot.model.nv}), {args.stack} stack "
          f"({', '.join(f'{spec.name} {spec.priority}' for spec in specs)}), targets moved "
          f"from the start by {offsets} m, dt {args.dt} s, "
          f"{args.steps} timed steps after {args.warmup} warm-up, one BLAS thread")
    print("Pink costs 10^-priority per task, gains as in the stack, default limits"
          + (f"; backends not installed: {', '.join(skipped)}" if skipped else ""))
    print(note)
    print("Interleaved: every contender takes one step in turn (caches cold at each step, "
          "as in a node doing other work between steps)")
    print_table(result, [spec.name for spec in specs])
    print("iters: mean hierarchy solutions per step (clamping loop); excess: worst limit "
          "violation over the run; task errors at the final configuration (m, rad)")
    print(f"Back to back: every contender takes {args.block} steps in turn (caches warm, as "
          "in the posture generator's loop)")
    print_table(back_to_back)
    if args.json:
        with open(args.json, "w") as output:
            json.dump({"robot": "talos", "steps": args.steps, "warmup": args.warmup,
                       "dt": args.dt, "stack": args.stack, "hand_offsets": offsets,
                       "note": note, "contenders": result, "block": args.block,
                       "back_to_back": back_to_back}, output, indent=2)
    return 0


# ---------------------------------------------------------------------------------------
# levels: step cost as priority levels are added, SVD vs QP hierarchy
# ---------------------------------------------------------------------------------------

PANDA_STACK = """
- {name: hand, kind: pose, frame: panda_hand, priority: 0, gain: 0.1}
- {name: posture, kind: posture, priority: 1, gain: 0.02}
"""
HIERARCHIES = {"svd": False, "qp": True}   # contender label -> PIKSolver on QPHierarchy


def add_levels_arguments(parser) -> None:
    parser.add_argument("--steps", type=positive(int), default=2000, help="timed steps per contender")
    parser.add_argument("--warmup", type=int, default=200, help="untimed steps first")
    parser.add_argument("--dt", type=positive(float), default=0.002,
                        help="step period (s): velocity limits, bounds of the QP hierarchy")
    parser.add_argument("--json", help="also write the figures to this JSON file")


def level_contenders(robot, stack_yaml, start, offsets, dt, level_counts,
                     strategy="progressive", hierarchies=HIERARCHIES) -> list:
    """Contenders "<hierarchy> <n> levels" on the stack's first n priority levels, for
    each hierarchy and n in level_counts, with a limit strategy (progressive clamping; any
    other is named "<hierarchy>-<strategy> <n> levels")."""
    from stance.stack import parse_stack_yaml

    specs = parse_stack_yaml(stack_yaml)
    targets = bench_targets(robot, specs, start, offsets)
    suffix = "" if strategy == "progressive" else f"-{strategy}"
    return [StanceContender(robot, strategy, [spec for spec in specs
                                              if spec.priority < count],
                            targets, start, dt, qp=qp, name=f"{label}{suffix} {count} levels")
            for count in level_counts for label, qp in hierarchies.items()]


def level_figures(records, contenders, steps) -> dict:
    """Per contender: timing (us), mean clamping iterations, worst limit excess (rad), the
    median ratio of n levels over n - 1 levels of the same hierarchy, and for the QP
    hierarchy its counters per step over all `steps` (warm-up included): levels whose
    bounds crossed solved from their hot start, the polish's solves, levels ProxSuite
    solved, its cold starts, its solutions the polish could not certify, exact solves out
    of iterations."""
    result = {}
    for contender in contenders:
        record = records[contender.name]
        label, count = contender.name.split()[:2]
        previous = result.get(f"{label} {int(count) - 1} levels")
        hierarchy = contender.solver.hierarchy
        entry = {**timing_us(record),
                 "mean_clamping_iterations": float(np.mean(record.iterations)),
                 "max_limit_excess": record.max_limit_excess,
                 **{f"{counter}_per_step": (getattr(hierarchy, counter) / steps
                                            if hasattr(hierarchy, counter) else None)
                    for counter in ("hot_starts", "polish_solves", "qp_solves",
                                    "cold_starts", "unpolished", "unconverged")}}
        entry["over_one_level_less"] = (entry["median_us"] / previous["median_us"]
                                        if previous else None)
        result[contender.name] = entry
    return result


def print_level_table(title, result) -> None:
    print(title)
    counters = ("hot_starts_per_step", "polish_solves_per_step", "qp_solves_per_step",
                "cold_starts_per_step", "unpolished_per_step", "unconverged_per_step")
    print(f"{'contender':<16}{'median us':>10}{'p99 us':>10}{'max us':>10}{'iters':>7}"
          f"{'excess rad':>12}{'x previous':>12}{'hot':>7}{'polish':>7}{'QPs':>7}{'cold':>7}"
          f"{'unpol':>7}{'uncon':>7}")
    for name, entry in result.items():
        ratio = entry["over_one_level_less"]
        print(f"{name:<16}{entry['median_us']:>10.1f}{entry['p99_us']:>10.1f}"
              f"{entry['max_us']:>10.1f}{entry['mean_clamping_iterations']:>7.2f}"
              f"{entry['max_limit_excess']:>12.2e}"
              f"{'-' if ratio is None else f'{ratio:.2f}':>12}"
              + "".join(f"{'-' if entry[key] is None else f'{entry[key]:.2f}':>7}"
                        for key in counters))


def visited(contender, start, steps) -> list:
    """The configurations a contender steps from over `steps` steps from start."""
    states, q = [], start
    for _ in range(steps):
        states.append(q)
        q, _ = contender.step(q)
    return states


def run_levels(args) -> int:
    from threadpoolctl import threadpool_limits

    from stance.robot import Robot

    talos = Robot.from_example_robot_data("talos")
    panda = Robot.from_example_robot_data("panda")
    talos_start, panda_start = bench_start(talos), panda.initial_configuration("default")
    hand_offsets = HANDS_FORWARD
    with threadpool_limits(limits=1):
        talos_contenders = level_contenders(talos, TALOS_LEVEL_STACK, talos_start,
                                            hand_offsets, args.dt, (1, 2, 3, 4))
        panda_contenders = level_contenders(panda, PANDA_STACK, panda_start,
                                            {"hand": (0.2, 0.2, -0.2)}, args.dt, (2,))
        results = {}
        for robot, start, contenders, key in (
                (talos, talos_start, talos_contenders, "talos"),
                (panda, panda_start, panda_contenders, "panda")):
            race(contenders, robot, start, args.warmup)
            records = race(contenders, robot, start, args.steps)
            results[key] = level_figures(records, contenders, args.warmup + args.steps)
        # the same configurations for every level count: those the timed four-level run
        # stepped from
        svd = [contender for contender in talos_contenders if contender.name.startswith("svd")]
        states = visited(svd[-1], talos_start, args.steps)
        results["talos_same_states"] = level_figures(
            race(svd, talos, talos_start, args.steps, states=states), svd, args.steps)
        # the same configurations with no limit strategy: the levels' own cost, without the
        # clamping loop's re-evaluations (paper IV.C)
        unlimited = level_contenders(talos, TALOS_LEVEL_STACK, talos_start, hand_offsets,
                                     args.dt, (3, 4), strategy="none",
                                     hierarchies={"svd": False})
        results["talos_same_states_no_limits"] = level_figures(
            race(unlimited, talos, talos_start, args.steps, states=states), unlimited,
            args.steps)

    print(f"stance bench levels: progressive clamping, dt {args.dt} s (velocity bounds), "
          f"{args.steps} timed steps after {args.warmup} warm-up, one BLAS thread; svd = "
          f"DampedHierarchy, qp = QPHierarchy (ProxSuite)")
    print_level_table(f"Talos (nv {talos.model.nv}): feet (12) > CoM xy (2) > both hands (12)"
                      f" > posture, hands moved {hand_offsets} m", results["talos"])
    print_level_table("Talos, each level count stepping from the configurations of the svd "
                      "4-level run (open loop): what a level costs on the same inputs",
                      results["talos_same_states"])
    print_level_table("Talos, the same configurations with no limit strategy: each level's "
                      "own cost, without the clamping loop's re-evaluations (paper IV.C)",
                      results["talos_same_states_no_limits"])
    print_level_table(f"Panda (nv {panda.model.nv}, fixed base): hand pose > posture, hand "
                      f"moved (0.2, 0.2, -0.2) m", results["panda"])
    print("x previous: median over the same hierarchy's median with one level less; iters: "
          "mean hierarchy solutions per step; excess: worst limit violation over the run; "
          "hot, polish, QPs, cold, unpol, uncon: per step (warm-up included), levels whose "
          "bounds crossed solved from their previous active set, the polish's solves (one "
          "per level where that set holds), levels ProxSuite solved, its cold "
          "starts, its solutions the polish could not certify, exact solves out of "
          "iterations (feasible, not shown optimal)")
    if args.json:
        with open(args.json, "w") as output:
            json.dump({"steps": args.steps, "warmup": args.warmup, "dt": args.dt,
                       "hand_offsets": hand_offsets, **results}, output, indent=2)
    return 0


# ---------------------------------------------------------------------------------------
# groups: Talos' joint groups (limit file) against 1-DoF limits only
# ---------------------------------------------------------------------------------------

def add_groups_arguments(parser) -> None:
    add_levels_arguments(parser)


GROUP_SCENARIOS = {   # hand offsets (m, world): the groups far from their cones; the
    #                   shoulders in theirs (the arms spread), altered every step
    "hands forward": HANDS_FORWARD,
    "arms out": mirrored_hands((0.1, -0.6, 0.3)),
}


def run_groups(args) -> int:
    from threadpoolctl import threadpool_limits

    from stance.robot import Robot
    from stance.stack import parse_stack_yaml
    from stance.swing import load_limit_file

    talos = Robot.from_example_robot_data("talos")
    start = bench_start(talos)
    specs = parse_stack_yaml(TALOS_LEVEL_STACK)
    groups = load_limit_file("talos", talos)
    results = {}
    print(f"stance bench groups: Talos, feet > CoM xy > both hands > posture, progressive "
          f"clamping, dt {args.dt} s, {args.steps} timed steps after {args.warmup} warm-up, "
          f"the contenders interleaved, one BLAS thread; groups: "
          f"{', '.join(model.name for model in groups)}")
    print(f"{'scenario':<15}{'limits':<19}{'median us':>10}{'p99 us':>10}{'max us':>10}"
          f"{'iters':>7}{'x 1-DoF':>9}")
    for scenario, offsets in GROUP_SCENARIOS.items():
        targets = bench_targets(talos, specs, start, offsets)
        with threadpool_limits(limits=1):
            contenders = [StanceContender(talos, "progressive", specs, targets, start,
                                          args.dt, qp=qp, name=name, limit_models=models)
                          for name, models, qp in (("1-DoF limits", (), False),
                                                   ("joint groups", groups, False),
                                                   ("1-DoF limits qp", (), True))]
            race(contenders, talos, start, args.warmup)
            records = race(contenders, talos, start, args.steps)
        result = {contender.name: {**timing_us(records[contender.name]),
                                   "mean_clamping_iterations":
                                       float(np.mean(records[contender.name].iterations))}
                  for contender in contenders}
        plain = result["1-DoF limits"]["median_us"]
        result["ratio"] = result["joint groups"]["median_us"] / plain
        result["qp_ratio"] = result["1-DoF limits qp"]["median_us"] / plain
        results[scenario] = {"hand_offsets": offsets, **result}
        for name, ratio in (("1-DoF limits", None), ("joint groups", result["ratio"]),
                            ("1-DoF limits qp", result["qp_ratio"])):
            entry = result[name]
            print(f"{scenario:<15}{name:<19}{entry['median_us']:>10.1f}{entry['p99_us']:>10.1f}"
                  f"{entry['max_us']:>10.1f}{entry['mean_clamping_iterations']:>7.2f}"
                  f"{'-' if ratio is None else f'{ratio:.2f}':>9}")
    print("hand offsets (m, world): " + "; ".join(
        f"{scenario} {offsets}" for scenario, offsets in GROUP_SCENARIOS.items())
        + "; qp: the same 1-DoF limits on the QP hierarchy (joint and velocity bounds)")
    results["mannequin thorn"] = spherical_joint_loops(args)
    if args.json:
        with open(args.json, "w") as output:
            json.dump({"steps": args.steps, "warmup": args.warmup, "dt": args.dt, **results},
                      output, indent=2)
    return 0


def spherical_joint_loops(args) -> dict:
    """The mannequin's step on the thorn experiment (stance reproduce thorn: its stack,
    targets and start), its eleven spherical joints deciding in the compiled clamping loop
    against the general loop, interleaved; printed and returned as timing per loop."""
    from threadpoolctl import threadpool_limits

    from stance.experiments.thorn import HUMANOIDS, thorn_solver

    humanoid = HUMANOIDS["mannequin"]
    mannequin = humanoid.load()
    start = mannequin.initial_configuration(humanoid.start)
    with threadpool_limits(limits=1):
        contenders = [SolverContender(name, thorn_solver(humanoid, mannequin, "progressive",
                                                         start, compiled_loop=compiled))
                      for name, compiled in (("compiled loop", True),
                                             ("general loop", False))]
        race(contenders, mannequin, start, args.warmup)
        records = race(contenders, mannequin, start, args.steps)
    result = {name: {**timing_us(record),
                     "mean_clamping_iterations": float(np.mean(record.iterations))}
              for name, record in records.items()}
    ratio = result["compiled loop"]["median_us"] / result["general loop"]["median_us"]
    print(f"mannequin (nv {mannequin.model.nv}), thorn experiment (Figs. 11-12), its "
          f"{len(humanoid.limit_models(mannequin))} spherical joints limited, progressive "
          f"clamping, the two loops interleaved:")
    print(f"{'loop':<15}{'median us':>10}{'p99 us':>10}{'iters':>7}{'x general':>11}")
    for name, entry in result.items():
        print(f"{name:<15}{entry['median_us']:>10.1f}{entry['p99_us']:>10.1f}"
              f"{entry['mean_clamping_iterations']:>7.2f}"
              f"{f'{ratio:.2f}' if name == 'compiled loop' else '-':>11}")
    return {**result, "ratio": ratio}


# ---------------------------------------------------------------------------------------
# support: the CoM inside the feet's support polygon (inequality rows) vs held in place
# ---------------------------------------------------------------------------------------

SOLE_HALF_SIZE = (0.10, 0.05)   # m: Talos' sole patch (data/scenes), about each sole frame
SUPPORT_SCENARIOS = {   # (hand offsets (m, world), polygon shift (m, world x)): the CoM
    "hands forward": (HANDS_FORWARD, 0.0),                   # stays inside;
    "reach far": (mirrored_hands((0.7, -0.2, -0.3)), 0.0),   # it would leave;
    "polygon ahead": (HANDS_FORWARD, 3.0),   # a polygon out of reach: the CoM heads for it
}                                            # until the body is stretched on its bounds


def support_solver(robot, start, targets, dt, balance, shift=0.0):
    """PIKSolver on the QP hierarchy, the issue's stack with its CoM level as `balance`:
    "com" (CoM xy held, an equality) or "support" (CoM xy inside the soles' hull, moved
    `shift` m along world x)."""
    import pinocchio as pin

    from stance.pik import PIKSolver
    from stance.stack import TaskSpec, parse_stack_yaml
    from stance.tasks import frame_rectangle_corners

    specs = [TaskSpec("balance", "support", priority=1, gain=0.2) if spec.kind == "com"
             and balance == "support" else spec for spec in parse_stack_yaml(TALOS_LEVEL_STACK)]
    solver = PIKSolver(robot, strategy="progressive", dt=dt, hierarchy="qp")
    solver.set_stack(specs, start)
    for spec in specs:
        if spec.kind == "support":
            pin.framesForwardKinematics(robot.model, robot.data, start)
            solver.task(spec.name).set_target(frame_rectangle_corners(
                robot, ("left_sole_link", "right_sole_link"), SOLE_HALF_SIZE) + [shift, 0.0])
        else:
            solver.task(spec.name).target = targets[spec.name]
    return solver


def run_support(args) -> int:
    from threadpoolctl import threadpool_limits

    from stance.robot import Robot
    from stance.stack import parse_stack_yaml

    talos = Robot.from_example_robot_data("talos")
    start = bench_start(talos)
    specs = parse_stack_yaml(TALOS_LEVEL_STACK)
    results = {}
    print(f"stance bench support: Talos, QP hierarchy, feet > balance > both hands > posture,"
          f" progressive clamping, dt {args.dt} s, {args.steps} timed steps after "
          f"{args.warmup} warm-up, interleaved, one BLAS thread; balance: com = CoM xy held "
          f"(equality), support = CoM xy inside the soles' hull (inequality rows)")
    print(f"{'scenario':<15}{'balance':<9}{'median us':>10}{'p99 us':>10}{'max us':>10}"
          f"{'iters':>7}{'polish':>8}{'QPs':>6}{'x com':>7}{'hands m':>9}{'outside m':>11}")
    for scenario, (offsets, shift) in SUPPORT_SCENARIOS.items():
        targets = bench_targets(talos, specs, start, offsets)
        with threadpool_limits(limits=1):
            contenders = [SolverContender(balance, support_solver(talos, start, targets,
                                                                  args.dt, balance, shift))
                          for balance in ("com", "support")]
            race(contenders, talos, start, args.warmup)
            counted = {contender.name: (contender.solver.hierarchy.polish_solves,
                                        contender.solver.hierarchy.qp_solves)
                       for contender in contenders}
            records = race(contenders, talos, start, args.steps)
        result = {}
        for contender in contenders:
            record, hierarchy = records[contender.name], contender.solver.hierarchy
            polished, solved = counted[contender.name]
            final = contender.solver.step(record.q)
            support = support_solver(talos, start, targets, args.dt, "support", shift)
            support.compute_kinematics(record.q)
            result[contender.name] = {
                **timing_us(record), "mean_clamping_iterations": float(np.mean(
                    record.iterations)),
                "polish_solves_per_step": (hierarchy.polish_solves - polished) / args.steps,
                "qp_solves_per_step": (hierarchy.qp_solves - solved) / args.steps,
                "hand_error_m": float(np.hypot(final.task_errors["left_hand"],
                                               final.task_errors["right_hand"])),
                "com_outside_m": support.task("balance").distance_outside(talos)}
        result["ratio"] = result["support"]["median_us"] / result["com"]["median_us"]
        results[scenario] = {"hand_offsets": offsets, "polygon_shift_m": shift, **result}
        for name in ("com", "support"):
            entry = result[name]
            ratio = f"{result['ratio']:.2f}" if name == "support" else "-"
            print(f"{scenario:<15}{name:<9}{entry['median_us']:>10.1f}"
                  f"{entry['p99_us']:>10.1f}{entry['max_us']:>10.1f}"
                  f"{entry['mean_clamping_iterations']:>7.2f}"
                  f"{entry['polish_solves_per_step']:>8.2f}{entry['qp_solves_per_step']:>6.2f}"
                  f"{ratio:>7}{entry['hand_error_m']:>9.3f}{entry['com_outside_m']:>11.1e}")
    print("hand offsets (m, world), polygon shift (m, x): " + "; ".join(
        f"{scenario} {offsets}, {shift}" for scenario, (offsets, shift)
        in SUPPORT_SCENARIOS.items())
        + "; polish, QPs: per timed step, the polish's solves and the levels ProxSuite solved;"
        " hands m: both hands' final position and orientation error; outside m: the final"
        " CoM's distance outside the soles' hull (shifted)")
    if args.json:
        with open(args.json, "w") as output:
            json.dump({"steps": args.steps, "warmup": args.warmup, "dt": args.dt, **results},
                      output, indent=2)
    return 0
