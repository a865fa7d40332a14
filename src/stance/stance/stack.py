"""Task stack descriptions: what a user writes (YAML, messages) before tasks are built.

A stack is a list of task specs; each spec names a task kind, a robot frame where the kind
needs one, a strict priority level (0 = highest), a weight inside its level, an axis
selection and a gain. `validate_stack` rejects anything malformed with one clear message.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace

import yaml

from .yaml_file import load_yaml

KINDS = ("pose", "position", "orientation", "com", "posture", "support")
FRAME_KINDS = ("pose", "position", "orientation")
AXES = ("x", "y", "z", "rx", "ry", "rz")
KIND_AXES = {
    "pose": AXES,
    "position": AXES[:3],
    "orientation": AXES[3:],
    "com": AXES[:3],
    "posture": (),
    "support": (),
}
MAX_PRIORITY = 31
# A task's rows are scaled by sqrt(weight): past 1e6 between two tasks of a level, a
# priority-0 contact slid while its level reported `met`, and a tiny weight on a level of
# its own stalls it against the damping
MIN_WEIGHT, MAX_WEIGHT = 1e-6, 1e6
MAX_TASKS = 64    # a stack's tasks: 1000 one-axis tasks took pik_node from 500 Hz to 40 Hz
NAME_PATTERN = re.compile(r"[A-Za-z][A-Za-z0-9_]*")   # the whole name (fullmatch)
MAX_NAME_LENGTH = 64   # characters: a name also names topics (pik_node's task targets)


def short_repr(value, limit: int = MAX_NAME_LENGTH) -> str:
    """repr(value) for a message, cut after `limit` characters (its length then said): a
    sender's megabyte of name must not come back in every status."""
    text = repr(value)
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... ({len(value) if isinstance(value, str) else len(text)} characters)"


class StackError(ValueError):
    """A task stack or a task spec is malformed; the message names the offending field."""


@dataclass(frozen=True)
class TaskSpec:
    """One task of a stack.

    name: unique, [A-Za-z][A-Za-z0-9_]*, at most MAX_NAME_LENGTH characters; kind: one of
    KINDS; frame: robot frame for frame kinds; priority: 0 (highest) .. MAX_PRIORITY; weight
    > 0 within the level; axes: subset of the kind's axes (world-aligned), empty = all; gain
    in (0, 1]: fraction of the error corrected per IK step.
    """

    name: str
    kind: str
    frame: str = ""
    priority: int = 0
    weight: float = 1.0
    axes: tuple = field(default_factory=tuple)
    gain: float = 0.1
    enabled: bool = True

    def selected_axes(self) -> tuple:
        return self.axes or KIND_AXES[self.kind]


def validate_spec(spec: TaskSpec, frame_exists=None) -> None:
    """Raise StackError if `spec` is malformed; `frame_exists(name)` checks robot frames."""
    where = f"task {short_repr(spec.name)}"
    if not isinstance(spec.name, str) or not NAME_PATTERN.fullmatch(spec.name):
        raise StackError(f"task name {short_repr(spec.name)} must match {NAME_PATTERN.pattern}")
    if len(spec.name) > MAX_NAME_LENGTH:
        raise StackError(f"task name {spec.name[:16]!r}... has {len(spec.name)} characters, "
                         f"more than {MAX_NAME_LENGTH}")
    if spec.kind not in KINDS:
        raise StackError(f"{where}: unknown kind {short_repr(spec.kind)} "
                         f"(expected one of {', '.join(KINDS)})")
    if not isinstance(spec.frame, str):
        raise StackError(f"{where}: frame must be a string (got {short_repr(spec.frame)})")
    if spec.kind in FRAME_KINDS:
        if not spec.frame:
            raise StackError(f"{where}: kind {spec.kind} needs a frame")
        if frame_exists is not None and not frame_exists(spec.frame):
            raise StackError(f"{where}: unknown frame {short_repr(spec.frame)}")
    elif spec.frame:
        raise StackError(f"{where}: kind {spec.kind} takes no frame (got {short_repr(spec.frame)})")
    if isinstance(spec.priority, bool) or not isinstance(spec.priority, int) \
            or not 0 <= spec.priority <= MAX_PRIORITY:
        raise StackError(f"{where}: priority {spec.priority!r} out of range 0..{MAX_PRIORITY}")
    if not _finite_number(spec.weight) or not MIN_WEIGHT <= spec.weight <= MAX_WEIGHT:
        raise StackError(f"{where}: weight must be a number in [{MIN_WEIGHT:g}, "
                         f"{MAX_WEIGHT:g}] (got {spec.weight!r})")
    if not _finite_number(spec.gain) or not 0 < spec.gain <= 1:
        raise StackError(f"{where}: gain must be in (0, 1] (got {spec.gain!r})")
    allowed = KIND_AXES[spec.kind]
    for axis in spec.axes:
        if axis not in allowed:
            raise StackError(f"{where}: axis {short_repr(axis)} not valid for kind {spec.kind} "
                             f"(allowed: {', '.join(allowed) or 'none'})")
    if len(set(spec.axes)) != len(spec.axes):
        raise StackError(f"{where}: repeated axis in {list(spec.axes)}")
    if not isinstance(spec.enabled, bool):
        raise StackError(f"{where}: enabled must be true or false (got {spec.enabled!r})")


def validate_stack(specs, frame_exists=None) -> list:
    """Validate every spec and the stack as a whole; returns the specs as a list."""
    specs = list(specs)
    if not specs:
        raise StackError("the stack is empty")
    if len(specs) > MAX_TASKS:
        raise StackError(f"the stack has {len(specs)} tasks, more than {MAX_TASKS}")
    seen = set()
    for spec in specs:
        if not isinstance(spec, TaskSpec):
            raise StackError(f"stack entries must be TaskSpec, got {type(spec).__name__}")
        validate_spec(spec, frame_exists)
        if spec.name in seen:
            raise StackError(f"duplicate task name {short_repr(spec.name)}")
        seen.add(spec.name)
    return specs


def spec_from_dict(entry: dict) -> TaskSpec:
    """Build a TaskSpec from a YAML mapping; unknown keys are errors."""
    if not isinstance(entry, dict):
        raise StackError(f"each task must be a mapping, got {short_repr(entry)}")
    known = {"name", "kind", "frame", "priority", "weight", "axes", "gain", "enabled"}
    unknown = set(entry) - known
    if unknown:
        raise StackError(f"task {short_repr(entry.get('name', '?'))}: unknown keys "
                         f"{short_repr(sorted(unknown))}")
    if "name" not in entry or "kind" not in entry:
        raise StackError(f"task {entry!r} needs at least a name and a kind")
    axes = entry.get("axes", ())
    if not isinstance(axes, (list, tuple)):
        axes = (axes,)
    spec = TaskSpec(name=entry["name"], kind=entry["kind"])
    return replace(spec, frame=entry.get("frame", ""), priority=entry.get("priority", 0),
                   weight=entry.get("weight", 1.0), axes=tuple(axes),
                   gain=entry.get("gain", spec.gain), enabled=entry.get("enabled", True))


def parse_stack_yaml(text: str, frame_exists=None) -> list:
    """Parse a stack written as YAML: either a list of tasks or a mapping with key `tasks`."""
    try:
        document = load_yaml(text)
    except yaml.YAMLError as error:
        raise StackError(f"stack is not valid YAML: {error}") from error
    if isinstance(document, dict) and "tasks" in document:
        document = document["tasks"]
    if not isinstance(document, list):
        raise StackError("a stack is a YAML list of tasks (or a mapping with a 'tasks' list)")
    return validate_stack([spec_from_dict(entry) for entry in document], frame_exists)


def _finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
