"""The one CLI error convention: `hil <command>: <message>`, `  what to do: <remedy>` on stderr, exit 2."""

import pytest

from hil.cli import main


def stderr_lines(capsys) -> list[str]:
    return capsys.readouterr().err.rstrip("\n").split("\n")


def test_bad_option_prints_message_and_remedy_and_exits_2(capsys):
    # rejected before any connection is attempted
    assert main(["tracker", "--url", "socket://127.0.0.1:9", "--shots", "-1"]) == 2
    first, second = stderr_lines(capsys)
    assert first == "hil tracker: --shots -1 is negative"
    assert second.startswith("  what to do: ") and len(second) > len("  what to do: ")


def test_sim_refuses_a_non_loopback_host_before_starting(capsys):
    assert main(["sim", "--host", "10.0.0.1"]) == 2
    first, second = stderr_lines(capsys)
    assert first.startswith("hil sim: --host 10.0.0.1") and "127.0.0.0/8" in second


def test_unknown_effect_names_the_known_ones(capsys):
    assert main(["sim", "--host", "127.0.0.9", "--effects", "gravity,thermal_expansion"]) == 2
    first, second = stderr_lines(capsys)
    assert first.startswith("hil sim: unknown effect(s) ['gravity']")
    assert "gravity_compliance" in first + second and "thermal_expansion" in first + second


def test_an_unknown_option_after_a_command_names_hil_once(capsys):

    with pytest.raises(SystemExit) as exit_info:
        main(["run", "grid_sampling", "--stepp", "3", "--cell", "c.toml", "--campaign", "c.sqlite"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2, err
    assert err.startswith("hil run grid_sampling: unrecognized arguments: --stepp 3"), err
    assert "see 'hil run grid_sampling --help'" in err  # the subcommand's own help, not the top level's


def test_an_unknown_option_of_a_sub_subcommand_points_at_its_own_help(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["campaign", "export", "c.sqlite", "-o", "x.csv"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "unrecognized arguments: -o x.csv" in err
    assert "see 'hil campaign export --help'" in err and "see 'hil --help'" not in err
