"""A command that needs an optional extra which is not installed says which one, in one line, exit 2.

The missing module is simulated (None in sys.modules makes `import` fail as if it were not
installed, and find_spec report it absent); nothing is uninstalled.
"""
from __future__ import annotations

import sys
from importlib.metadata import EntryPoint

import click
import pytest
from click.testing import CliRunner

from runtime.app import cli


def _dct(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    """`dct ARGS` through cli.main (its error handler included): (exit status, stderr); the command
    printed nothing on stdout (it stopped before any work)."""
    monkeypatch.setattr(sys, "argv", ["dct", *args])
    with pytest.raises(SystemExit) as info:
        cli.main()
    out, err = capsys.readouterr()
    assert out == "", out
    return info.value.code, err


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), err
    assert "internal error" not in err and "Traceback" not in err
    return lines[0]


def test_bench_planner_without_cvxpy_names_the_bench_extra_before_any_work(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "cvxpy", None)
    code, err = _dct(monkeypatch, capsys, "bench", "planner", "--repeats", "10")
    line = _one_line(err)
    assert code == 2
    assert "needs cvxpy, from the optional 'bench' extra" in line and "pip install -e '.[bench]'" in line


def test_a_missing_optional_module_deep_in_a_command_is_one_line_exit_2(monkeypatch, capsys, tmp_path):
    """`dct replay FOLDER` reads a rosbag2 folder with rosbags (the eval extra); no command-level
    check: the dct error handler finds the ModuleNotFoundError."""
    monkeypatch.setitem(sys.modules, "rosbags", None)
    monkeypatch.delitem(sys.modules, "rosbags.highlevel", raising=False)
    code, err = _dct(monkeypatch, capsys, "replay", str(tmp_path))
    line = _one_line(err)
    assert code == 2 and "rosbags (from the optional 'eval' extra) is not installed" in line
    assert "pip install -e '.[eval]'" in line


def test_campaign_on_ray_without_ray(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)
    code, err = _dct(monkeypatch, capsys, "bench", "paper", "--table", "1", "--ray", "local", "--seeds", "1")
    assert code == 2 and "--ray" in _one_line(err) and "'ray' extra" in err


def test_odom_eval_without_evo_names_the_eval_extra(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "evo", None)
    poses = tmp_path / "poses.txt"
    poses.write_text("")
    code, err = _dct(monkeypatch, capsys, "odom", "eval", "--scans", str(tmp_path), "--poses", str(poses),
                     "--json", str(tmp_path / "out.json"))
    assert code == 2 and "[eval]" in _one_line(err)


def test_any_other_missing_module_is_still_an_internal_error(monkeypatch, capsys):
    @click.command("broken-for-test")
    def broken() -> None:
        import importlib

        importlib.import_module("no_such_module_anywhere")

    monkeypatch.setitem(cli.dct.commands, "broken-for-test", broken)
    code, err = _dct(monkeypatch, capsys, "broken-for-test")
    assert code == 3 and "internal error: ModuleNotFoundError" in err


def test_a_command_group_that_needs_an_extra_to_load(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    ep = EntryPoint(name="cluster", value="ray.util.fake_group:group", group="dct.commands")
    monkeypatch.setattr(cli, "_command_entry_points", lambda: {"cluster": ep})
    result = CliRunner().invoke(cli.dct, ["cluster"])
    assert result.exit_code == 2
    assert "command group 'cluster' needs ray, from the optional 'ray' extra" in result.output
