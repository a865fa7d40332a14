"""Reproductions of the experiments of Raunhardt and Boulic, "Progressive Clamping" (ROS-free).

- chain: planar kinematic chain with three conflicting positional tasks (Figs. 9-10).
- thorn: humanoid reaching behind its back with hand and toes on one foot (Figs. 11-12).

Each experiment runs several joint limit strategies from the same start through one runner
(`run_strategy`) and returns `Trajectory` records; figures and tables are written by
`write_table` and the experiment's own plotting function.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class Trajectory:
    """One IK run: configurations and per-step reports (step k goes from q[k] to q[k + 1]).

    q: (steps + 1, nq) configurations. damping: (steps, limited DoFs) h of each step, one
    column per name of damped_dofs (the solver's limited DoFs).
    task_errors: task name -> (steps,) error norms at q[k] (m or rad).
    total_error: (steps,) sum of the task error norms counted by the experiment.
    """

    strategy: str
    q: np.ndarray
    damping: np.ndarray
    damped_dofs: list
    task_errors: dict
    total_error: np.ndarray

    def first_step_below(self, threshold: float):
        """Index of the first step whose total error is below threshold, None if never."""
        below = np.flatnonzero(self.total_error < threshold)
        return int(below[0]) if len(below) else None


def run_strategy(solver, q_start, steps: int, counted_tasks, stop_below: float | None = None
                 ) -> Trajectory:
    """Step `solver` from q_start `steps` times (fewer if the total error of the tasks named in
    counted_tasks drops below stop_below)."""
    configurations = [np.array(q_start, dtype=float)]
    damping, errors = [], {name: [] for name in solver.tasks}
    total = []
    q = configurations[0]
    for _ in range(steps):
        result = solver.step(q)
        for name, value in result.task_errors.items():
            errors[name].append(value)
        total.append(sum(result.task_errors[name] for name in counted_tasks))
        damping.append(result.damping)
        q = result.q
        configurations.append(q)
        if stop_below is not None and total[-1] < stop_below:
            break
    return Trajectory(strategy=solver.strategy_name, q=np.array(configurations),
                      damping=np.array(damping), damped_dofs=list(solver.limited_dof_names),
                      task_errors={name: np.array(values) for name, values in errors.items()},
                      total_error=np.array(total))


def write_table(outdir: Path, name: str, title: str, rows: list) -> tuple:
    """Write rows (a list of flat dicts, same keys) as NAME.md and NAME.json in outdir;
    returns both paths."""
    outdir.mkdir(parents=True, exist_ok=True)
    columns = list(rows[0])
    lines = [f"# {title}", "", "| " + " | ".join(columns) + " |",
             "|" + "---|" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(_cell(row[column]) for column in columns) + " |")
    markdown = outdir / f"{name}.md"
    markdown.write_text("\n".join(lines) + "\n")
    data = outdir / f"{name}.json"
    data.write_text(json.dumps(rows, indent=2) + "\n")
    return markdown, data


def _cell(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_cell(item) for item in value) or "-"
    return "-" if value is None else str(value)


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (imported only when plotting)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(figure, path: Path) -> Path:
    """Write figure as a PNG and release it."""
    figure.savefig(path, dpi=110)
    pyplot().close(figure)
    return path
