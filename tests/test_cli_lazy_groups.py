"""A command group that cannot be imported shows up as unavailable with a one-line reason."""
from click.testing import CliRunner

from runtime.app import cli
class _BrokenEntryPoint:
    name = "broken"

    def load(self):
        raise ImportError("no module named 'missing_dependency'")


def test_an_unloadable_group_says_why_when_invoked(monkeypatch):
    monkeypatch.setattr(cli, "_command_entry_points", lambda: {"broken": _BrokenEntryPoint()})
    result = CliRunner().invoke(cli.dct, ["broken"])
    assert result.exit_code == 1
    assert "command group 'broken' cannot be loaded: no module named 'missing_dependency'" in result.output
