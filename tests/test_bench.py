"""`stance bench pik`, `levels`, `groups` and `support` run a few steps and report what
they promise: every contender's median, p99 and worst step, and the ratios they exist
for."""

import json

import pytest
from stance_tools.cli import main as stance


def test_bench_groups_reports_both_limit_sets_and_their_ratio(tmp_path, capsys):
    output = tmp_path / "groups.json"
    assert stance(["bench", "groups", "--steps", "30", "--warmup", "5",
                   "--json", str(output)]) == 0
    result = json.loads(output.read_text())
    assert set(result) >= {"hands forward", "arms out"}
    for scenario in ("hands forward", "arms out"):
        plain, grouped = result[scenario]["1-DoF limits"], result[scenario]["joint groups"]
        assert 0 < plain["median_us"] <= plain["p99_us"]
        assert 0 < grouped["median_us"] <= grouped["p99_us"]
        # four more limit models to ask at every clamping iteration cost something
        assert result[scenario]["ratio"] == grouped["median_us"] / plain["median_us"] > 1.0
        qp = result[scenario]["1-DoF limits qp"]
        assert 0 < qp["median_us"] <= qp["p99_us"] <= qp["max_us"]
        assert result[scenario]["qp_ratio"] == qp["median_us"] / plain["median_us"]
    loops = result["mannequin thorn"]
    compiled, general = loops["compiled loop"], loops["general loop"]
    assert 0 < compiled["median_us"] <= compiled["p99_us"]
    assert 0 < general["median_us"] <= general["p99_us"]
    assert loops["ratio"] == compiled["median_us"] / general["median_us"]
    # the same decisions either way, so the same clamping iterations
    assert compiled["mean_clamping_iterations"] == general["mean_clamping_iterations"]
    output = capsys.readouterr().out
    assert "arms out" in output and "spherical joints" in output


def test_bench_support_compares_the_polygon_with_the_held_com(tmp_path):
    output = tmp_path / "support.json"
    assert stance(["bench", "support", "--steps", "30", "--warmup", "300",
                   "--json", str(output)]) == 0
    result = json.loads(output.read_text())
    for scenario in ("hands forward", "reach far"):
        held, support = result[scenario]["com"], result[scenario]["support"]
        assert 0 < held["median_us"] <= held["p99_us"] <= held["max_us"]
        assert 0 < support["median_us"] <= support["p99_us"] <= support["max_us"]
        assert result[scenario]["ratio"] == support["median_us"] / held["median_us"]
        assert support["com_outside_m"] < 1e-3
    # reaching far, a CoM free inside the polygon lets the hands get closer than a held one
    far = result["reach far"]
    assert far["support"]["hand_error_m"] < far["com"]["hand_error_m"]


def test_bench_levels_compares_each_level_count_with_one_less(tmp_path):
    output = tmp_path / "levels.json"
    assert stance(["bench", "levels", "--steps", "20", "--warmup", "5",
                   "--json", str(output)]) == 0
    result = json.loads(output.read_text())
    talos, same_states = result["talos"], result["talos_same_states"]
    unlimited = result["talos_same_states_no_limits"]
    assert set(talos) == {f"{label} {count} levels" for label in ("svd", "qp")
                          for count in (1, 2, 3, 4)}
    assert set(same_states) == {f"svd {count} levels" for count in (1, 2, 3, 4)}
    assert set(unlimited) == {"svd-none 3 levels", "svd-none 4 levels"}
    assert unlimited["svd-none 4 levels"]["mean_clamping_iterations"] == 1.0
    for figures in (talos, same_states, unlimited):
        for name, entry in figures.items():
            label, count = name.split()[:2]
            previous = figures.get(f"{label} {int(count) - 1} levels")
            assert 0 < entry["median_us"] <= entry["p99_us"] <= entry["max_us"]
            assert entry["over_one_level_less"] == (
                None if previous is None else entry["median_us"] / previous["median_us"])
    # the replay feeds the four-level run its own configurations: the same solutions
    assert same_states["svd 4 levels"]["mean_clamping_iterations"] == \
        talos["svd 4 levels"]["mean_clamping_iterations"]


def test_bench_pik_runs_the_issue_stack_against_pink(tmp_path):
    """By default the stack is feet > CoM > both hands > posture, both hands moved (the
    left one mirrored), and every Pink contender solves the same problem; the back-to-back
    race takes the interleaved race's steps in blocks."""
    output = tmp_path / "pik.json"
    assert stance(["bench", "pik", "--steps", "20", "--warmup", "5", "--backends", "daqp",
                   "--block", "7", "--json", str(output)]) == 0
    result = json.loads(output.read_text())
    assert result["stack"] == "hands"
    right = result["hand_offsets"]["right_hand"]
    assert result["hand_offsets"]["left_hand"] == [right[0], -right[1], right[2]]
    contenders = result["contenders"]
    assert {"stance progressive", "stance progressive qp", "pink daqp"} <= set(contenders)
    pink = contenders["pink daqp"]
    assert pink["failed_at_step"] is None
    assert 0 < pink["median_us"] <= pink["p99_us"] <= pink["max_us"]
    progressive = contenders["stance progressive"]
    assert pink["stance_over_pink_median"] == pytest.approx(
        progressive["median_us"] / pink["median_us"])
    assert set(progressive["final_task_errors"]) == {
        "left_foot", "right_foot", "com", "left_hand", "right_hand", "posture"}
    assert result["block"] == 7
    for name, entry in result["back_to_back"].items():
        assert entry["timed_steps"] == 20 and entry["failed_at_step"] is None
        assert entry["final_task_errors"] == contenders[name]["final_task_errors"], name


def test_bench_pik_demo_stack_moves_the_right_hand_only(tmp_path):
    output = tmp_path / "pik.json"
    assert stance(["bench", "pik", "--stack", "demo", "--steps", "5", "--warmup", "2",
                   "--backends", "daqp", "--json", str(output)]) == 0
    result = json.loads(output.read_text())
    assert set(result["hand_offsets"]) == {"right_hand"}
    assert "left_hand" not in result["contenders"]["stance progressive"]["final_task_errors"]


@pytest.mark.parametrize("block", ["0", "-3", "two"])
def test_bench_pik_refuses_a_block_below_one_step(block, capsys):
    with pytest.raises(SystemExit) as exit_info:
        stance(["bench", "pik", "--block", block])
    assert exit_info.value.code == 2
    assert "argument --block" in capsys.readouterr().err


class _LoggedContender:
    """A contender that only writes its name to a shared log when it steps."""

    def __init__(self, name, log):
        self.name, self.log = name, log

    def reset(self, q) -> None:
        """Nothing to reset."""

    def step(self, q):
        self.log.append(self.name)
        return q, 0


@pytest.mark.parametrize("block", [1, 3])
def test_race_spreads_each_contenders_predecessor_over_the_others(block):
    # a step's time depends on the caches its predecessor evicted: no contender may
    # always step after the same one (a rotated cyclic order did, most of the time)
    from types import SimpleNamespace

    import numpy as np
    from stance_tools.bench import race

    robot = SimpleNamespace(limited_q_index=[0], lower=np.array([-1.0]),
                            upper=np.array([1.0]))
    names = ["a", "b", "c", "d"]
    log = []
    records = race([_LoggedContender(name, log) for name in names], robot, np.zeros(1),
                   600 * block, block=block)
    assert all(len(records[name].times_ns) == 600 * block for name in names)
    switches = [(before, after) for before, after in zip(log, log[1:]) if before != after]
    assert len(switches) == len(log) // block - 1   # never the same contender twice in a row
    for name in names:
        predecessors = [before for before, after in switches if after == name]
        shares = [predecessors.count(other) / len(predecessors) for other in names
                  if other != name]
        assert min(shares) > 0.25 and max(shares) < 0.45, (name, shares)
    replay = []
    race([_LoggedContender(name, replay) for name in names], robot, np.zeros(1),
         600 * block, block=block)
    assert replay == log        # the same orders in every run
