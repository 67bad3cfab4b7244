"""The `dct` command line.

Convention for the group modules (`*/cli.py`): import heavy libraries (MuJoCo, torch)
inside the commands, not at module level, so that `dct --help` stays fast.

Each package contributes its command group through the `dct.commands` entry point
(pyproject.toml). A group is imported only when it is invoked, so `dct can decode` on
the robot never imports MuJoCo, and this module never imports hil_sim directly.
"""
from __future__ import annotations

import os
import sys
from importlib.metadata import EntryPoint, entry_points

import click

from calibration.cli_support import LazyGroup
from calibration.extras import missing_extra, missing_extra_message


def _command_entry_points() -> dict:
    eps = {ep.name: ep for ep in entry_points(group="dct.commands")}
    for name, value in _RUNTIME_COMMANDS.items():  # runtime's own, loaded as lazily as the groups
        eps.setdefault(name, EntryPoint(name=name, value=value, group="dct.commands"))
    return eps


#: Commands of this package itself: `dct run` (the controller process, runtime.app.run_process) and
#: `dct config` (runtime.app.config_cli).
_RUNTIME_COMMANDS = {"run": "runtime.app.run_cli:run_command", "config": "runtime.app.config_cli:config_group"}


class _DctGroup(LazyGroup):
    """The `dct` group: each package's command group is imported when it is invoked."""

    unavailable_what = "command group"

    def lazy_commands(self) -> dict:
        return _command_entry_points()


@click.group(cls=_DctGroup, context_settings={"help_option_names": ["-h", "--help"]})
def dct() -> None:
    """DCT contact-tolerant navigation controller: CAN tools, HIL simulation, calibration, models."""


def main() -> None:
    # Offscreen rendering for the simulator's camera: there is no display on a robot computer
    # or a CI machine. Set before any group imports MuJoCo; an explicit setting wins.
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    try:
        rv = dct.main(standalone_mode=False)
    except click.UsageError as exc:
        path = exc.ctx.command_path if exc.ctx is not None else "dct"
        click.echo(f"Error: {path}: {_one_line(exc.format_message())} (see {path} --help)", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        click.echo(f"Error: {_one_line(exc.format_message())}", err=True)
        sys.exit(exc.exit_code)
    except (click.exceptions.Abort, KeyboardInterrupt):  # click turns Ctrl-C into Abort
        click.echo("Aborted!", err=True)
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - the last line of defence: one line, never a traceback
        if os.environ.get("DCT_DEBUG"):
            raise
        module = missing_extra(exc)  # an optional dependency the command needs (calibration.extras)
        if module is not None:
            click.echo(f"Error: {missing_extra_message(module)}", err=True)
            sys.exit(2)
        click.echo(f"Error: internal error: {type(exc).__name__}: {_one_line(str(exc))} "
                   "(set DCT_DEBUG=1 for the traceback)", err=True)
        sys.exit(3)
    sys.exit(rv if isinstance(rv, int) else 0)


def _one_line(text: str, limit: int = 1000) -> str:
    """Every CLI error is one line: fold newlines, cap the length."""
    folded = " ".join(str(text).split())
    return folded if len(folded) <= limit else folded[: limit - 3] + "..."

if __name__ == "__main__":
    main()
