"""`stance <command> --help` works for every command and every benchmark: argparse formats
help strings with %, so a bare % in one breaks the help of its whole command."""

import pytest
from stance_tools.bench import BENCHMARKS
from stance_tools.cli import SUBCOMMANDS
from stance_tools.cli import main as stance


@pytest.mark.parametrize("argv", [[name, "--help"] for name in SUBCOMMANDS]
                         + [["bench", name, "--help"] for name in BENCHMARKS])
def test_help_prints_usage_and_exits_zero(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        stance(argv)
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: stance {' '.join(argv[:-1])}")


def test_the_command_list_names_every_benchmark():
    _, listed = SUBCOMMANDS["bench"]
    assert listed.split(": ", 1)[1].split(", ") == list(BENCHMARKS)


@pytest.mark.parametrize("option, value", [
    ("--step", "nan"), ("--rate", "inf"), ("--rate", "1e7"), ("--timeout", "-1")])
def test_teleop_refuses_numbers_that_mean_nothing(option, value, capsys):
    """nan passed `> 0` (teleop sent NaN targets); inf or 1e7 Hz never ended."""
    with pytest.raises(SystemExit) as exit_info:
        stance(["teleop", "--task", "right_hand", option, value])
    assert exit_info.value.code == 2
    assert f"argument {option}: must be" in capsys.readouterr().err


def test_check_plan_refuses_a_nan_tolerance(capsys):
    """A NaN tolerance passed a plan with a 5 cm contact error."""
    with pytest.raises(SystemExit):
        stance(["check-plan", "plan.json", "--contact-tolerance", "nan"])
    assert "must be finite and > 0, got nan" in capsys.readouterr().err


def unreadable_bags(root):
    """Bags the readers cannot read: empty directory, empty file, text, bad metadata."""
    (root / "empty").mkdir()
    (root / "zero").mkdir()
    (root / "zero" / "a.mcap").write_bytes(b"")
    (root / "text.mcap").write_text("not a bag\n")
    (root / "metadata").mkdir()
    (root / "metadata" / "metadata.yaml").write_bytes(b"\xff\xfe not yaml")
    return {"empty": "no MCAP file in", "zero": "not a readable MCAP file",
            "text.mcap": "not a readable MCAP file", "metadata": "not rosbag2 metadata"}


@pytest.mark.parametrize("command", ["plot", "check-run"])
def test_unreadable_bags_are_named_not_tracebacks(tmp_path, command, capsys):
    """mcap's errors (a recorder killed before its summary, a file that is not MCAP) were
    caught nowhere: stance plot and check-run ended in tracebacks."""
    for name, message in unreadable_bags(tmp_path).items():
        assert stance([command, str(tmp_path / name)]) == 2
        error = capsys.readouterr().err
        assert f"stance {command}: " in error and message in error, error


def test_plot_refuses_a_joint_pattern_that_is_not_a_regex(tmp_path, capsys):
    (tmp_path / "bag").mkdir()
    assert stance(["plot", str(tmp_path / "bag"), "--joints", "("]) == 2
    assert "--joints '(': not a regular expression" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["record", "-o", "{tmp}/bag", "bad topic"], "'bad topic' is not a topic name"),
    (["record", "-o", "{tmp}/missing/deeper/bag", "/a"], "cannot create"),
    (["param", "set", "bad name", "strategy", "clamping"], "'bad name' is not a node name"),
    (["param", "set", "/pik_node", "strategy", "{a: 1}"], "'{a: 1}' is not a parameter value"),
])
def test_names_and_values_ros_cannot_take_are_refused_first(tmp_path, capsys, argv, message):
    """Each raised a traceback (rclpy's name check, a TypeError, FileNotFoundError) or
    recorded a topic that can never exist with exit 0."""
    (tmp_path / "missing").write_text("a file where a directory is needed\n")
    argv = [arg.replace("{tmp}", str(tmp_path)) for arg in argv]
    assert stance(argv) == 2
    assert message in capsys.readouterr().err
