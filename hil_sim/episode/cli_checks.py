"""What the `dct hil` and `dct bench` commands check before an episode runs.

InputError is their one-line error for bad input (exit status 2; 1 means: the episode failed);
check_scenario_and_output checks a scenario and a --json output before a long real-time run.
"""
from __future__ import annotations

from pathlib import Path

import click


class InputError(click.ClickException):
    """Bad input (file, option): one line on stderr, exit status 2 (1 means: the episode failed)."""

    exit_code = 2


def check_scenario_and_output(scenario: str, seed: int, json_path: Path | None, force: bool,
                              duration_s: float | None = None) -> None:
    """Before a long real-time run: the scenario loads (a generated one from its seed; a --duration
    only for a patrol) and the --json output may be written (an existing file only with --force);
    else one line, exit 2."""
    from calibration.errors import ConfigFileError
    from calibration.outputs import OutputPathError, check_output_path
    from hil_sim.episode.patrol import PatrolError, with_duration
    from hil_sim.world.scenario import load_scenario

    try:
        with_duration(load_scenario(scenario, seed=seed), duration_s)
        if json_path is not None:
            check_output_path(json_path, what="--json", overwrite=force)
    except (ConfigFileError, OutputPathError, PatrolError) as exc:
        raise InputError(str(exc)) from exc


__all__ = ["InputError", "check_scenario_and_output"]
