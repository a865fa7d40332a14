"""`stance bench graph` with short phases: every node of the default graph gets finite,
non-negative CPU figures idle and executing, and no node process outlives the command.
(Timing, the < 1 core target, belongs to the benchmark, not to this test.)"""

import json
import math
import types

from stance_tools.processes import group_exists

NODES = ("pik_node", "contact_planner_node", "trajectory_node", "stabilizer_gate_node")
PHASES = ("idle", "executing")
STATISTICS = ("median", "p99", "mean")


def test_bench_graph_reports_every_node_in_both_phases_and_stops_them(processes, tmp_path):
    figures_path = tmp_path / "graph.json"
    bench = processes.start("stance", "bench", "graph", "--seconds", "3", "--settle", "1",
                            "--log-dir", str(tmp_path / "logs"), "--json", str(figures_path),
                            name="bench")
    assert bench.wait(timeout=400) == 0, bench.log_path.read_text()[-3000:]
    output = bench.log_path.read_text()
    figures = json.loads(figures_path.read_text())

    assert set(figures["node_pids"]) == set(NODES)
    assert set(figures["phases"]) == set(PHASES)
    for phase in PHASES:
        entry = figures["phases"][phase]
        assert entry["windows"] == 3, (phase, entry)
        for name in NODES + ("total",):
            values = entry["total"] if name == "total" else entry["nodes"][name]
            for statistic in STATISTICS:
                value = values[statistic]
                assert math.isfinite(value) and value >= 0.0, (phase, name, statistic, value)
        for name in NODES:
            assert any(line.startswith(name) and line.split()[1] == phase
                       for line in output.splitlines()), (name, phase)
    assert figures["phases"]["executing"]["execution"].startswith("executing:")
    assert "target: graph total mean < 100 % of one core" in output
    assert len(figures["load_average"]["start"]) == len(figures["load_average"]["end"]) == 3

    for name, pid in figures["node_pids"].items():  # each node ran in its own process group
        assert not group_exists(types.SimpleNamespace(pid=pid)), f"{name} still running"
