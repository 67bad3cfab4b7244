"""`dct models`: train and check the distance net. torch is imported inside the commands.

Every input error is one line on stderr and exit 1 (click.ClickException); output paths are
checked before the work (calibration.outputs.check_output_path) and written atomically after it.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

# Accuracy targets of a distance net, on the held-out check of
# models.distance_check.evaluate_mu_function (100 000 points up to 3 m outside, as many inside):
# `train-distance` does not write a net that misses one (unless --force), `check-distance` exits 1.
DISTANCE_TARGETS = {
    "max_abs_error_m": 5e-3,
    "p99_abs_error_m": 1e-3,
    "max_overestimate_m": 1e-5,
    "outside_sign_errors": 0,
    "inside_max_abs_error_m": 2e-2,
    "inside_sign_errors": 0,
    "max_dual_norm": 1.0 + 1e-5,
}


def _one_line(message: str) -> str:
    """A possibly multi-line message (a file's validation errors) as one line."""
    return "; ".join(line.strip() for line in str(message).splitlines() if line.strip())


def _fail(exc: BaseException) -> click.ClickException:
    return click.ClickException(_one_line(str(exc)) or type(exc).__name__)


def _load_robot(robot_path: str | None):
    from calibration.robot_description import load_robot_description

    try:
        return load_robot_description(robot_path)
    except (ValueError, OSError) as exc:  # ConfigFileError, and a file that is not UTF-8 text
        where = f"robot description {robot_path}: " if isinstance(exc, UnicodeDecodeError) else ""
        raise click.ClickException(where + _one_line(str(exc))) from exc


def _checked_output(path: str | None, what: str, inputs: list[str | None], allow_shipped: bool = False,
                    shipped_flag: str | None = None) -> Path | None:
    """check_output_path as a one-line CLI error; None stays None (no such output).

    shipped_flag: the option that allows a path inside the package, named in the refusal.
    """
    from calibration.outputs import OutputPathError, check_output_path, is_shipped_artifact

    if path is None:
        return None
    try:
        return check_output_path(path, what=what, inputs=[p for p in inputs if p], allow_shipped=allow_shipped)
    except OutputPathError as exc:
        hint = f" (or pass {shipped_flag} to replace it)" if shipped_flag and is_shipped_artifact(path) else ""
        raise click.ClickException(_one_line(str(exc)) + hint) from exc


def _write_json(path: Path | None, obj: Any) -> None:
    from calibration.outputs import atomic_write_json

    if path is not None:
        atomic_write_json(path, obj)


def check_targets(stats: dict) -> list[str]:
    """Names and values of the figures that miss DISTANCE_TARGETS (empty: all met)."""
    return [f"{k} = {stats[k]:.6g} > {limit:.6g}" for k, limit in DISTANCE_TARGETS.items() if stats[k] > limit]


@click.group(name="models")
def models_group() -> None:
    """Model artifacts: the distance net (train, check, upgrade)."""


@models_group.command("train-distance")
@click.option("--output", "output", type=click.Path(), required=True,
              help="Artifact path (required). Inside the installed package (the shipped net) only with "
                   "--replace-shipped. Checked before training, written atomically after it.")
@click.option("--replace-shipped", is_flag=True, default=False,
              help="Allow --output inside the installed package, e.g. models/artifacts/limo_distance_net.pt.")
@click.option("--force", is_flag=True, default=False,
              help="Write the net even when it misses the accuracy targets (DISTANCE_TARGETS).")
@click.option("--robot", "robot_path", type=click.Path(), default=None,
              help="Robot description YAML [default: the shipped LIMO description].")
@click.option("--steps", type=click.IntRange(min=1), default=None, help="Optimizer steps [default: 150000].")
@click.option("--dataset-size", type=click.IntRange(min=1_000), default=None,
              help="Training points [default: 1000000]; small values for quick trial runs.")
@click.option("--eval-points", type=click.IntRange(min=1_000), default=100_000, show_default=True,
              help="Held-out points of the accuracy check (outside, and as many inside).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True,
              help="torch threads for training (1 is as fast for this small net and robust on a shared 2-core CPU).")
@click.option("--time-limit-s", type=click.FloatRange(min=1.0), default=480.0, show_default=True,
              help="Stop training after this long; the learning rate anneals by time or steps "
                   "(the export and check follow, about 10 s).")
@click.option("--json", "json_path", type=click.Path(), default=None,
              help="Write the artifact metadata (training info, error statistics, integrity record) here.")
def train_distance(*, output: str, replace_shipped: bool, force: bool, robot_path: str | None, steps: int | None,
                   dataset_size: int | None, eval_points: int, seed: int, threads: int, time_limit_s: float,
                   json_path: str | None) -> None:
    """Train the distance net on exact dual solutions and export it as frozen TorchScript.

    The net is written only when it meets the accuracy targets on the held-out check
    (max_abs_error_m <= 5 mm, p99 <= 1 mm, overestimate <= 1e-5 m, no sign errors, inside max
    error <= 2 cm, dual norm <= 1 + 1e-5); else the figures are printed and the exit status is 1
    (--force writes it anyway).
    """
    from dataclasses import replace

    from models.distance_net import DistanceNet, save_artifact
    from models.distance_training import TrainingConfig, train_and_evaluate
    from models.errors import DistanceNetError

    robot = _load_robot(robot_path)
    out = _checked_output(output, "model output", [robot_path], allow_shipped=replace_shipped,
                          shipped_flag="--replace-shipped")
    json_out = _checked_output(json_path, "JSON output", [robot_path, output])
    config = TrainingConfig(seed=seed, threads=threads, time_limit_s=time_limit_s)
    if steps is not None:
        config = replace(config, steps=steps)
    if dataset_size is not None:
        config = replace(config, dataset_size=dataset_size)
    try:
        model, meta = train_and_evaluate(robot, config, eval_points=eval_points, log=lambda s: click.echo(s, err=True))
    except DistanceNetError as exc:
        raise _fail(exc) from exc
    stats = meta["error_statistics"]
    click.echo(json.dumps(stats, indent=1))
    missed = check_targets(stats)
    if missed and not force:
        raise click.ClickException(f"accuracy targets missed, {out} not written (--force writes it anyway): "
                                   + "; ".join(missed))
    try:
        save_artifact(model, out, meta)
        saved = DistanceNet.load(out, robot).metadata
    except DistanceNetError as exc:
        raise _fail(exc) from exc
    _write_json(json_out, saved)
    click.echo(f"saved {out} ({out.stat().st_size} bytes) after {meta['training']['steps_done']} steps "
               f"in {meta['training']['train_time_s']} s")
    if missed:
        click.echo("WARNING: accuracy targets missed (written because of --force): " + "; ".join(missed), err=True)


@models_group.command("check-distance")
@click.option("--model", "model_path", type=click.Path(), default=None,
              help="Artifact [default: the shipped LIMO distance net].")
@click.option("--robot", "robot_path", type=click.Path(), default=None,
              help="Robot description YAML [default: the shipped LIMO description].")
@click.option("--n-points", type=click.IntRange(min=100_000), default=100_000, show_default=True,
              help="Held-out points outside (and as many inside).")
@click.option("--seed", type=int, default=20240531, show_default=True, help="Seed of the held-out points.")
@click.option("--timing/--no-timing", default=True, show_default=True,
              help="Also time the net (1 thread) against one OSQP solve per point.")
@click.option("--json", "json_path", type=click.Path(), default=None,
              help="Write the figures here (also when targets are missed: the report says targets_met).")
def check_distance(*, model_path: str | None, robot_path: str | None, n_points: int, seed: int, timing: bool,
                   json_path: str | None) -> None:
    """Evaluate the distance net on held-out points against the exact distance (float64).

    Exit 1 when a figure misses the accuracy targets.
    """
    from models.distance_check import benchmark_inference, evaluate_mu_function
    from models.distance_net import DistanceNet
    from models.errors import DistanceNetError

    robot = _load_robot(robot_path)
    json_out = _checked_output(json_path, "JSON output", [model_path, robot_path])
    try:
        net = DistanceNet.load(model_path, robot)
    except DistanceNetError as exc:
        raise _fail(exc) from exc
    stats = evaluate_mu_function(net.mu, net.G, net.g, n_points=n_points, seed=seed)
    missed = check_targets(stats)
    report = dict(stats, model=str(net.path), targets=DISTANCE_TARGETS, targets_met=not missed,
                  model_version=net.metadata.get("version"))
    if timing:
        report["timing"] = benchmark_inference(net)
    click.echo(json.dumps(report, indent=1))
    _write_json(json_out, report)
    if missed:
        raise click.ClickException("accuracy targets missed: " + "; ".join(missed))


@models_group.command("upgrade-distance")
@click.argument("model_path", type=click.Path())
@click.option("--output", "output", type=click.Path(), required=True,
              help="Upgraded artifact path (inside the installed package only with --replace-shipped).")
@click.option("--replace-shipped", is_flag=True, default=False,
              help="Allow --output inside the installed package, e.g. the shipped LIMO net.")
@click.option("--robot", "robot_path", type=click.Path(), default=None,
              help="Robot description YAML [default: the shipped LIMO description].")
def upgrade_distance(*, model_path: str, output: str, replace_shipped: bool, robot_path: str | None) -> None:
    """Re-save an older-format distance net (same weights) with the integrity record of the
    current format, after re-checking its held-out figures against the stored ones."""
    from models.distance_net import upgrade_artifact
    from models.errors import DistanceNetError

    robot = _load_robot(robot_path)
    out = _checked_output(output, "model output", [model_path, robot_path], allow_shipped=replace_shipped,
                          shipped_flag="--replace-shipped")
    try:
        meta = upgrade_artifact(model_path, out, robot)
    except DistanceNetError as exc:
        raise _fail(exc) from exc
    integrity, bound = meta["integrity"], meta["integrity"]["error_bound"]
    click.echo(f"saved {out}: version {meta['version']}, weights sha256 {integrity['weights_sha256']}, "
               f"{integrity['probe']['n_points']} probe points, error bound {bound['outside_m']:.3g} m "
               f"outside / {bound['inside_m']:.3g} m inside")
