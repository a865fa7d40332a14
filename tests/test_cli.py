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
