"""Click building blocks shared by the `dct` command groups: one-line errors, the lazy group,
output path checks.

They live in calibration, the lowest package, so that the command line of every package (and
`dct` itself, runtime.app.cli) can use them.

* `OneLineError`: an error printed as one line ("Error: <message>"), newlines folded.
* `OneLineCommand`, `OneLineGroup`: usage errors (bad option, missing argument, unknown
  sub-command) as one such line, exit status 2.
* `LazyGroup`: a group whose sub-commands also come from an entry point group, each imported
  only when it is used; one that cannot be imported is listed as unavailable and says why when
  invoked, rather than breaking the whole command line.
* `checked_output`: `calibration.outputs.check_output_path` as a one-line error.
"""
from __future__ import annotations

from importlib.metadata import entry_points
from pathlib import Path

import click

from calibration.outputs import OutputPathError, check_output_path


class OneLineError(click.ClickException):
    """A command-line error printed as one line ("Error: <message>"); newlines are folded."""

    def format_message(self) -> str:
        return " ".join(str(self.message).split())


def _usage_error(ctx: click.Context, exc: click.UsageError) -> OneLineError:
    err = OneLineError(f"{ctx.command_path}: {exc.format_message()} (see --help)")
    err.exit_code = exc.exit_code
    return err


class OneLineCommand(click.Command):
    """A click command whose usage errors (bad option, missing argument) are one line, exit 2."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        try:
            return super().parse_args(ctx, args)
        except click.UsageError as exc:
            raise _usage_error(ctx, exc) from None


class OneLineGroup(click.Group):
    """A click group whose usage errors (unknown sub-command, ...) and its commands' are one line."""

    command_class = OneLineCommand

    def resolve_command(self, ctx: click.Context, args: list[str]):
        try:
            return super().resolve_command(ctx, args)
        except click.UsageError as exc:
            raise _usage_error(ctx, exc) from None


class LazyGroup(click.Group):
    """Its own sub-commands plus those of the entry point group `entry_point_group`, each
    imported on first use (so that `dct can decode` on the robot never imports MuJoCo)."""

    #: The entry point group the lazily loaded sub-commands come from.
    entry_point_group = ""
    #: What an unavailable sub-command is called in its error: "<what> '<name>' cannot be loaded".
    unavailable_what = "command"

    def lazy_commands(self) -> dict:
        """{name: entry point} of the sub-commands loaded on first use."""
        return {ep.name: ep for ep in entry_points(group=self.entry_point_group)}

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(self.lazy_commands()))

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        cmd = super().get_command(ctx, name)
        if cmd is not None:
            return cmd
        ep = self.lazy_commands().get(name)
        if ep is None:
            return None
        try:
            return ep.load()
        except ImportError as exc:
            return self._unavailable(name, exc)

    def _unavailable(self, name: str, exc: ImportError) -> click.Command:
        """A stand-in listed with the reason; invoked, it fails with one line (exit 2 naming the extra
        when an optional dependency is missing, calibration.extras)."""
        from calibration.extras import MissingExtraError, missing_extra, missing_extra_message

        what, why, module = self.unavailable_what, str(exc), missing_extra(exc)

        @click.command(name=name, help=f"(unavailable: {why})")
        def unavailable() -> None:
            if module is not None:
                raise MissingExtraError(missing_extra_message(module, f"{what} '{name}'"))
            raise OneLineError(f"{what} '{name}' cannot be loaded: {why}")

        return unavailable


def checked_output(path: Path, what: str, inputs=(), overwrite: bool = True) -> Path:
    """check_output_path as a one-line CLI error."""
    try:
        return check_output_path(path, what=what, inputs=[p for p in inputs if p is not None], overwrite=overwrite)
    except OutputPathError as exc:
        raise OneLineError(str(exc)) from None


__all__ = ["LazyGroup", "OneLineCommand", "OneLineError", "OneLineGroup", "checked_output"]
