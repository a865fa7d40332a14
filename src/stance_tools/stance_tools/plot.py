"""`stance plot BAG`: PNG figures of a recorded run, read without ROS (see stance_tools.bag).

- joints.png: each joint position of /joint_states over time against its URDF limits (taken from
  the latched /robot_description); raw radians or meters, nothing normalized.
- damping.png: progressive clamping h per joint from /pik/status (stance_msgs/SolverStatus).
- errors.png: per-level residuals and per-task errors from /pik/status, log scale.

Time is in seconds from the first message of the bag (log time). A figure whose topic is missing
is reported as an error (exit code 1); the others are still written.

`plot_pipeline` draws the figures of an executed contact plan from a stance_tools.check_run
report (stance demo --scenario SCENE): contacts.png, stabilizer.png, joints.png, com.png, and
damping.png and errors.png when the bag has /pik/status; time there is in seconds from the
execution start (header stamps).
"""

import math
import re
import sys
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after selecting the non-interactive backend)
import numpy as np  # noqa: E402

from stance_tools.bag import read_messages, start_time_ns  # noqa: E402

JOINT_STATES = "/joint_states"
ROBOT_DESCRIPTION = "/robot_description"
SOLVER_STATUS = "/pik/status"
LOG_FLOOR = 1e-16  # errors are drawn no lower than this on log axes (exact zeros)
SERIES_GAP = 0.25  # s without a sample that breaks a curve (the task left the stack)


def joint_limits(urdf):
    """{joint name: (lower, upper)} of the revolute and prismatic joints of a URDF string;
    ValueError when it is not XML or a limit is not a number."""
    limits = {}
    try:
        joints = ET.fromstring(urdf).findall("joint")   # direct children: not transmissions
    except ET.ParseError as error:
        raise ValueError(f"{ROBOT_DESCRIPTION} is not a URDF: {error}") from None
    for joint in joints:
        limit = joint.find("limit")
        if joint.get("type") in ("revolute", "prismatic") and limit is not None:
            try:
                limits[joint.get("name")] = (float(limit.get("lower", 0.0)),
                                             float(limit.get("upper", 0.0)))
            except ValueError as error:
                raise ValueError(f"{ROBOT_DESCRIPTION}: joint {joint.get('name')!r}: "
                                 f"{error}") from None
    return limits


class Series:
    """Named scalar time series sampled at irregular times (times in s)."""

    def __init__(self):
        self._times = defaultdict(list)
        self._values = defaultdict(list)

    def add(self, name, time, value):
        self._times[name].append(time)
        self._values[name].append(value)

    def extend(self, name, times, values):
        self._times[name].extend(times)
        self._values[name].extend(values)

    def names(self):
        return list(self._times)

    def arrays(self, name):
        """(times in s, values) as numpy arrays."""
        return np.asarray(self._times[name]), np.asarray(self._values[name], dtype=float)

    def __bool__(self):
        return bool(self._times)


class Run:
    """What the figures need from a bag, read in one pass. Times in s from origin_ns (log
    time, ns; default: the bag's first message); with `since` (s), only the messages logged
    from then on are read (a latched description before it is not)."""

    def __init__(self, bag, origin_ns=None, since=None,
                 topics=(JOINT_STATES, ROBOT_DESCRIPTION, SOLVER_STATUS)):
        self.positions = Series()  # joint name -> position (rad or m)
        self.damping = Series()  # joint name -> h in [0, 1]
        self.clamped = Series()  # joint name -> 1.0 where clamped
        self.residuals = Series()  # level label -> residual norm
        self.task_errors = Series()  # task label -> error norm
        self.urdf = None
        self.has_joint_states = self.has_status = False
        origin = (start_time_ns(bag) or 0) if origin_ns is None else origin_ns
        first = None if since is None else origin + round(since * 1e9)
        for topic, log_time, msg in read_messages(bag, topics, start_time_ns=first):
            t = (log_time - origin) * 1e-9
            if topic == ROBOT_DESCRIPTION:
                self.urdf = msg.data
            elif topic == JOINT_STATES:
                self.has_joint_states = True
                for name, position in zip(msg.name, msg.position):
                    self.positions.add(name, t, position)
            else:
                self._add_status(t, msg)

    def _add_status(self, t, status):
        self.has_status = True
        for name, h, clamped in zip(status.joint_names, status.damping, status.clamped):
            self.damping.add(name, t, h)
            self.clamped.add(name, t, float(clamped))
        for level in status.levels:
            self.residuals.add(f"P{level.priority}: {', '.join(level.tasks)}", t,
                               level.residual_norm)
        for task in status.tasks:
            self.task_errors.add(f"{task.name} (P{task.priority})", t, task.error_norm)


def grid(count):
    """(rows, columns) of a near-square grid with at least count cells."""
    columns = max(1, math.ceil(math.sqrt(count)))
    return math.ceil(count / columns), columns


def plot_joints(run, path, pattern=None, moving_only=False):
    """Joint positions against URDF limits, one small subplot per joint."""
    limits = joint_limits(run.urdf) if run.urdf else {}
    names = [n for n in run.positions.names() if not pattern or re.search(pattern, n)]
    if moving_only:
        names = [n for n in names if np.ptp(run.positions.arrays(n)[1]) > 1e-9]
    if not names:
        raise LookupError("no joint to plot (check --joints / --moving)")
    rows, columns = grid(len(names))
    height = 2.0 * rows + 0.6
    # A fixed layout: constrained layout costs seconds on a 32-joint grid.
    fig, axes = plt.subplots(rows, columns, figsize=(2.8 * columns, height), sharex=True,
                             squeeze=False)
    fig.subplots_adjust(hspace=0.45, wspace=0.3, top=1.0 - 0.75 / height)
    for index, (ax, name) in enumerate(zip(axes.flat, names)):
        times, values = run.positions.arrays(name)
        ax.plot(times, values, lw=1.0, color="tab:blue")
        if name in limits:
            lower, upper = limits[name]
            ax.axhspan(lower, upper, color="tab:green", alpha=0.12, lw=0)
            for bound in (lower, upper):
                ax.axhline(bound, color="tab:red", ls="--", lw=0.9)
            outside = (values < lower) | (values > upper)
            if outside.any():
                ax.plot(times[outside], values[outside], ".", ms=2, color="tab:red")
        ax.set_title(name if name in limits else f"{name} (no limit)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        if index + columns >= len(names):  # lowest subplot of its column
            ax.tick_params(labelbottom=True)
            ax.set_xlabel("time (s)", fontsize=8)
    for ax in axes.flat[len(names):]:
        ax.set_visible(False)
    note = "" if limits else " - no /robot_description: limits not shown"
    fig.suptitle(f"Joint positions (rad, prismatic m); red dashed: URDF limits, red dots: "
                 f"outside{note}", fontsize=10)
    save(fig, path)


MOST_DAMPED = 8        # joints drawn as curves; the heat map shows them all
ENVELOPE_WINDOW = 0.05  # s: h is non-zero only while a joint heads toward its limit, so
                        # raw samples flicker; curves show the maximum over this window


def plot_damping(run, path, time_label="time (s)"):
    """h(t) of the most damped joints (window maximum), and a time x joint heat map of h
    (maximum per time bin) for all joints."""
    names = run.damping.names()
    damped = {n: run.damping.arrays(n)[1].mean() for n in names
              if run.damping.arrays(n)[1].max() > 0.0}
    active = sorted(damped, key=damped.get, reverse=True)[:MOST_DAMPED]
    fig, (top, bottom) = plt.subplots(
        2, 1, figsize=(11, 4 + 0.18 * len(names)), height_ratios=[1.0, 0.4 + 0.04 * len(names)],
        layout="constrained")
    for name in active:
        times, h = run.damping.arrays(name)
        (line,) = top.plot(times, window_maximum(times, h, ENVELOPE_WINDOW), lw=1.2,
                           label=name)
        clamped = run.clamped.arrays(name)[1] > 0
        if clamped.any():
            top.plot(times[clamped], np.full(clamped.sum(), 1.02), "|", ms=4,
                     color=line.get_color())
    if active:
        top.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        top.set_title(f"Progressive clamping h of the {len(active)} most damped joints "
                      f"(maximum over {1000 * ENVELOPE_WINDOW:.0f} ms; | at top: clamped)",
                      fontsize=10)
    else:
        top.text(0.5, 0.5, "no joint was ever damped: h = 0 throughout", ha="center",
                 va="center", transform=top.transAxes, fontsize=12)
        top.set_title("Progressive clamping h", fontsize=10)
    top.set_ylim(-0.05, 1.05)
    top.set_ylabel("h")
    top.grid(alpha=0.3)

    bottom.set_xlabel(time_label)
    bottom.set_title("h per joint", fontsize=10)
    if names:
        (start, end), h = heat_map(run.damping, names)
        image = bottom.imshow(h, cmap="magma_r", vmin=0.0, vmax=1.0, aspect="auto",
                              interpolation="nearest", extent=(start, end, len(names), 0))
        bottom.set_yticks(np.arange(len(names)) + 0.5, names, fontsize=6)
        fig.colorbar(image, ax=bottom, label="h", pad=0.01)
        top.set_xlim(bottom.get_xlim())
    else:
        bottom.text(0.5, 0.5, "the solver status lists no limited joint", ha="center",
                    va="center", transform=bottom.transAxes)
    save(fig, path)


def window_maximum(times, values, window):
    """Maximum of values over the trailing `window` seconds at each sample (times sorted):
    a sparse table, table[j] = max of the 2^k samples up to j, and each sample's window is
    the union of two such spans."""
    start = np.searchsorted(times, times - window)
    level = np.log2(np.arange(len(times)) - start + 1).astype(int)  # floor: 2^k <= width
    table = np.asarray(values, dtype=float).copy()
    result = np.empty(len(table))
    for k in range(int(level.max(initial=0)) + 1):
        if k:
            half = 2 ** (k - 1)
            table[half:] = np.maximum(table[half:], table[:-half])
        at = np.flatnonzero(level == k)
        result[at] = np.maximum(table[at], table[start[at] + 2 ** k - 1])
    return result


HEAT_MAP_COLUMNS = 2000  # time bins of the h heat map at most (each shows its maximum)


def heat_map(series, names):
    """((start, end) of the bins in s, h[joint, bin]): the maximum of each joint's h per time
    bin from the first sample to the last, at most HEAT_MAP_COLUMNS bins; NaN where a joint
    has no sample."""
    arrays = [series.arrays(name) for name in names]
    start = min(times[0] for times, _ in arrays)
    end = max(times[-1] for times, _ in arrays)
    columns = max(1, min(HEAT_MAP_COLUMNS, max(len(times) for times, _ in arrays)))
    width = (end - start) / columns or 1.0
    values = np.full((len(names), columns), np.nan)
    for row, (times, h) in enumerate(arrays):
        index = np.minimum(((times - start) / width).astype(int), columns - 1)
        np.fmax.at(values[row], index, h)
    return (start, start + columns * width), values


LEGEND_ENTRIES = 12  # curves per panel beyond which levels are merged per priority and
#                     tasks per name (a contact plan changes the stack at every stance)


def plot_errors(run, path, time_label="time (s)"):
    """Per-level residual norms and per-task error norms over time, log scale."""
    fig, axes = plt.subplots(2, 1, figsize=(11, 7.5), sharex=True, layout="constrained")
    panels = ((axes[0], run.residuals, lambda label: label.split(":")[0],
               "Residual norm per priority level", "priority"),
              (axes[1], run.task_errors, lambda label: label.rsplit(" (P", 1)[0],
               "Error norm per task", "task name"))
    for ax, series, key, title, merged_by in panels:
        if len(series.names()) > LEGEND_ENTRIES:
            series = merged(series, key)
            title += f" (one curve per {merged_by} across stack changes)"
        for label in series.names():
            times, values = with_gaps(*series.arrays(label))
            ax.plot(times, np.maximum(values, LOG_FLOOR), lw=1.0, label=label)
        ax.set_yscale("log")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3, which="both")
        if series:
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[0].set_ylabel("residual (task units)")
    axes[1].set_ylabel("error (m or rad)")
    axes[1].set_xlabel(time_label)
    save(fig, path)


def merged(series, key):
    """A Series with one curve per key(label) of series: its curves' samples, time-sorted."""
    gathered = Series()
    for label in series.names():
        gathered.extend(key(label), *series.arrays(label))
    result = Series()
    for label in gathered.names():
        times, values = gathered.arrays(label)
        order = np.argsort(times, kind="stable")
        result.extend(label, times[order], values[order])
    return result


def with_gaps(times, values, gap=SERIES_GAP):
    """(times, values) with a NaN inserted wherever no sample came for more than gap s, so
    that a line is broken there (a task or level absent from the stack meanwhile)."""
    breaks = np.flatnonzero(np.diff(times) > gap) + 1
    return (np.insert(times.astype(float), breaks, np.nan),
            np.insert(values.astype(float), breaks, np.nan))


def save(fig, path):
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def add_arguments(parser):
    parser.add_argument("bag", help="bag directory or .mcap file")
    parser.add_argument("-o", "--output", metavar="OUTDIR",
                        help="directory for the PNGs (default: the bag directory)")
    parser.add_argument("--joints", metavar="REGEX", help="only joints whose name matches")
    parser.add_argument("--moving", action="store_true", help="only joints that move")


def run(args):
    bag = Path(args.bag)
    if not bag.exists():
        print(f"stance plot: {bag} does not exist", file=sys.stderr)
        return 2
    if args.joints is not None:
        try:
            re.compile(args.joints)
        except re.error as error:
            print(f"stance plot: --joints {args.joints!r}: not a regular expression "
                  f"({error})", file=sys.stderr)
            return 2
    output = Path(args.output) if args.output else (bag if bag.is_dir() else bag.parent)
    try:
        output.mkdir(parents=True, exist_ok=True)
        data = Run(bag)
    except (OSError, ValueError) as error:     # bag.BagError: a bag that cannot be read
        print(f"stance plot: {error}", file=sys.stderr)
        return 2
    if data.has_joint_states and data.urdf is None:
        print(f"warning: no {ROBOT_DESCRIPTION} in {bag}: joint limits not shown",
              file=sys.stderr)
    figures = [
        ("joints.png", data.has_joint_states, JOINT_STATES,
         lambda p: plot_joints(data, p, args.joints, args.moving)),
        ("damping.png", data.has_status, SOLVER_STATUS, lambda p: plot_damping(data, p)),
        ("errors.png", data.has_status, SOLVER_STATUS, lambda p: plot_errors(data, p)),
    ]
    failed = False
    for name, available, topic, draw in figures:
        path = output / name
        if not available:
            print(f"stance plot: cannot write {name}: no {topic} messages in {bag}",
                  file=sys.stderr)
            failed = True
            continue
        try:
            draw(path)
        except (LookupError, OSError, ValueError) as error:
            print(f"stance plot: cannot write {name}: {error}", file=sys.stderr)
            failed = True
            continue
        print(path)
    return 1 if failed else 0


# --- figures of an executed contact plan (stance demo --scenario SCENE) ----------------------

def plot_pipeline(bag, report, scene_spec, output):
    """contacts.png, stabilizer.png, joints.png (moving joints) and com.png of a run checked
    by stance_tools.check_run (report: its Report), and damping.png and errors.png from
    pik_node's status when the bag has it; returns the paths written."""
    from stance.planning.scene import load_scene

    output = Path(output)
    scene = load_scene(scene_spec)
    paths = [output / name for name in ("contacts.png", "stabilizer.png", "joints.png",
                                        "com.png")]
    plot_contacts(report, scene, paths[0])
    plot_stabilizer(report, paths[1])
    plot_execution_joints(report, paths[2])
    plot_com(report, scene, paths[3])
    status = Run(bag, origin_ns=round(report.run.stamps[0] * 1e9), since=-JOINTS_BEFORE,
                 topics=[SOLVER_STATUS])
    if status.has_status:
        paths += [output / "damping.png", output / "errors.png"]
        plot_damping(status, paths[-2], "time from execution start (s)")
        plot_errors(status, paths[-1], "time from execution start (s)")
    return paths


JOINTS_BEFORE = 0.5  # s of joint states drawn before the execution starts


def plot_execution_joints(report, path):
    """plot_joints of the moving joints from JOINTS_BEFORE s before the execution start
    (pik_node's jump to the first witness) to the end, time from the execution start."""
    run = report.run
    shown = run.times >= run.stamps[0] - JOINTS_BEFORE
    positions = Series()
    for j, name in enumerate(run.joint_names):
        positions.extend(name, run.times[shown] - run.stamps[0], run.joints[shown, j])
    plot_joints(SimpleNamespace(positions=positions, urdf=report.robot.urdf), path,
                moving_only=True)


def _stance_lines(ax, stamps, origin, labels=False):
    """Grey vertical lines where each stance is reached (s from origin), numbered on top."""
    for k, stamp in enumerate(stamps):
        ax.axvline(stamp - origin, color="0.6", lw=0.6, zorder=0)
    if labels:
        step = max(1, len(stamps) // 15)
        top = ax.secondary_xaxis("top")
        top.set_xticks([s - origin for s in stamps[::step]],
                       [str(k) for k in range(0, len(stamps), step)], fontsize=7)
        top.set_xlabel("stance reached", fontsize=8)


ERROR_FLOOR = 1e-3  # mm: contact errors drawn no lower (log axis)


def plot_contacts(report, scene, path):
    """Per spot, when it holds which contact (bars, labelled by surface and stances), and
    each held spot's distance to its contact target (mm) against the tolerance."""
    from stance_tools.check_run import CONTACT_TOLERANCE, held_intervals

    run = report.run
    origin, end = run.stamps[0], run.times[-1]
    spots = list(scene.spots)
    colours = {spot: plt.cm.tab10(i % 10) for i, spot in enumerate(spots)}
    fig, (bars, errors) = plt.subplots(
        2, 1, figsize=(12, 2.2 + 0.45 * len(spots) + 3.2), sharex=True,
        height_ratios=[0.6 + 0.45 * len(spots), 3.2], layout="constrained")
    for contact, first, last, start, stop in held_intervals(run.stances, run.stamps):
        stop = min(stop, end)
        row = spots.index(contact.spot)
        bars.barh(row, stop - start, left=start - origin, height=0.6,
                  color=colours[contact.spot], alpha=0.8, edgecolor="black", lw=0.5)
        bars.text((start + stop) / 2 - origin, row, f"{first}-{last}", ha="center",
                  va="center", fontsize=6)
        inside = (run.times >= start) & (run.times <= stop)
        target = contact.spot_target(scene.surfaces[contact.surface]).translation
        error = 1e3 * np.linalg.norm(report.positions[contact.spot][inside] - target, axis=1)
        errors.plot(run.times[inside] - origin, np.maximum(error, ERROR_FLOOR), lw=0.9,
                    color=colours[contact.spot])
    bars.set_yticks(range(len(spots)), spots, fontsize=8)
    bars.set_ylim(len(spots) - 0.5, -0.5)
    bars.set_title("Contacts held per spot (bar text: first-last stance of the contact); grey: "
                   "stance reached", fontsize=10)
    _stance_lines(bars, run.stamps, origin, labels=True)
    errors.axhline(1e3 * CONTACT_TOLERANCE, color="tab:red", ls="--", lw=1.0,
                   label=f"tolerance {1e3 * CONTACT_TOLERANCE:g} mm")
    for spot in spots:
        errors.plot([], [], color=colours[spot], label=spot)
    errors.legend(fontsize=8, loc="upper right")
    errors.set_yscale("log")
    errors.set_ylim(ERROR_FLOOR, 5e3 * CONTACT_TOLERANCE)
    errors.set_ylabel("held spot to target (mm, log)")
    errors.set_xlabel("time from execution start (s)")
    errors.grid(alpha=0.3)
    _stance_lines(errors, run.stamps, origin)
    save(fig, path)


def plot_stabilizer(report, path):
    """/stabilizer/state: commanded state and blend over time, stance boundaries."""
    run = report.run
    times, enabled, blend = run.stabilizer
    origin = run.stamps[0]
    check = next(c for c in report.checks if c.name == "stabilizer")
    fig, ax = plt.subplots(figsize=(12, 3.6), layout="constrained")
    ax.step(times - origin, enabled.astype(float), where="post", lw=1.6, color="tab:blue",
            label="enabled (commanded)")
    ax.plot(times - origin, blend, lw=1.0, ls="--", color="tab:orange",
            label="blend (0 off, 1 on)")
    _stance_lines(ax, run.stamps, origin, labels=True)
    switches = len(check.rows)
    ax.set_title(f"Stabilizer state: {switches} switch(es) "
                 f"{'(as scheduled)' if check.passed else '(NOT as scheduled)'}", fontsize=10)
    ax.set_ylim(-0.1, 1.15)
    ax.set_yticks([0, 1], ["off", "on"])
    ax.set_xlabel("time from execution start (s)")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    save(fig, path)


def plot_com(report, scene, path):
    """CoM path in the world xy over the contact patches and each stance's support polygon,
    and the CoM's distance inside the current support polygon over time (m)."""
    from matplotlib.patches import Patch
    from stance.planning.equilibrium import contact_vertices, support_polygon
    from stance_tools.check_run import support_at

    run, com = report.run, report.com
    origin = run.stamps[0]
    executing = run.times >= origin
    colours = {spot: plt.cm.tab10(i % 10) for i, spot in enumerate(scene.spots)}
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(11, 10), height_ratios=[2.2, 1.0],
                                      layout="constrained")
    drawn = set()
    for stance in run.stances:
        for contact in stance.contacts:
            if contact in drawn:
                continue
            drawn.add(contact)
            vertices = contact_vertices(contact, scene)[0]
            top.fill(vertices[:, 0], vertices[:, 1], facecolor=(*colours[contact.spot][:3], 0.08),
                     edgecolor=colours[contact.spot], lw=1.0)
    samples = np.flatnonzero(executing)
    inside = np.full(len(samples), np.nan)
    polygons = {}   # transition k -> (A, b) of its support polygon, None if non-coplanar
    for n, i in enumerate(samples):
        k, support = support_at(run.stances, run.stamps, run.times[i])
        if k not in polygons:
            try:
                polygons[k] = support_polygon(support, scene)[1:]
            except ValueError:   # non-coplanar support: no polygon
                polygons[k] = None
        if polygons[k] is not None:
            a, b = polygons[k]
            inside[n] = np.min(b - a @ com[i, :2])
    path_points = top.scatter(com[executing, 0], com[executing, 1],
                              c=run.times[executing] - origin, s=2, cmap="viridis")
    fig.colorbar(path_points, ax=top, label="time from execution start (s)")
    top.set_aspect("equal")
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m)")
    top.grid(alpha=0.3)
    top.legend(handles=[Patch(facecolor=(*c[:3], 0.08), edgecolor=c, label=s)
                        for s, c in colours.items()], fontsize=8, loc="upper left")
    top.set_title("CoM (world xy, coloured by time) over the contact patches of all stances",
                  fontsize=10)
    bottom.plot(run.times[samples] - origin, 100.0 * inside, lw=1.2, color="tab:blue")
    bottom.axhline(0.0, color="tab:red", ls="--", lw=1.0)
    _stance_lines(bottom, run.stamps, origin)
    bottom.set_ylabel("CoM inside support polygon (cm)")
    bottom.set_xlabel("time from execution start (s)")
    bottom.set_title("Distance of the CoM inside the current support polygon (< 0: outside; "
                     "gaps: non-coplanar support)", fontsize=10)
    bottom.grid(alpha=0.3)
    save(fig, path)
