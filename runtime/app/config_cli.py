"""`dct config`: the controller configuration as the controller will use it."""
from __future__ import annotations

import json
from pathlib import Path

import click

from runtime.config import presets


class _InputError(click.ClickException):
    exit_code = 2


@click.group("config", context_settings={"help_option_names": ["-h", "--help"]})
def config_group() -> None:
    """The controller configuration: the shipped defaults with your overlay."""


@config_group.command("show")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Your config file: an overlay on the shipped defaults (set only what you change).")
@click.option("--planner", type=click.Choice(list(presets.PRESETS)), default=None,
              help="A preset in place of the config's planner and partition, as `dct hil run --planner` does.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON: {field: {value, source}}.")
def show_command(*, config_path, planner, as_json) -> None:
    """Print every setting with where it came from: your file, the shipped defaults, a preset, or a
    built-in default. Exit 2 on a file that does not load (one line naming the field)."""
    from calibration.errors import ConfigFileError
    from runtime.config.loading import config_sources, format_sources

    if config_path is not None and not config_path.is_file():
        raise _InputError(f"--config: {config_path}: no such file")
    try:
        config, rows = config_sources(config_path)
    except ConfigFileError as exc:
        raise _InputError(str(exc)) from None
    if planner is not None:
        config = config.with_planner_mode(planner)
        changed = {"planner.mode": config.planner.mode, "planner.algorithm": config.planner.algorithm,
                   "partition": config.partition}
        rows = [(f, changed.get(f, v), f"--planner {planner}" if f in changed else s) for f, v, s in rows]
    if as_json:
        click.echo(json.dumps({f: {"value": v, "source": s} for f, v, s in rows}, indent=1))
    else:
        click.echo(format_sources(rows))
