"""`dct models`: train and check the distance net. torch is imported inside the commands."""
from __future__ import annotations

import json
from pathlib import Path

import click

# Accuracy targets of the shipped distance net (issue: distance net).
DISTANCE_TARGETS = {
    "max_abs_error_m": 5e-3,
    "p99_abs_error_m": 1e-3,
    "max_overestimate_m": 1e-5,
    "inside_max_abs_error_m": 2e-2,
    "inside_sign_errors": 0,
    "max_dual_norm": 1.0 + 1e-5,
}


def _load_robot(robot_path: str | None):
    from calibration.errors import ConfigFileError
    from calibration.robot_description import load_robot_description

    try:
        return load_robot_description(robot_path)
    except ConfigFileError as exc:
        raise click.ClickException(str(exc)) from exc


def check_targets(stats: dict) -> list[str]:
    """Names and values of the figures that miss DISTANCE_TARGETS (empty: all met)."""
    return [f"{k} = {stats[k]:.6g} > {limit:.6g}" for k, limit in DISTANCE_TARGETS.items() if stats[k] > limit]


@click.group(name="models")
def models_group() -> None:
    """Model artifacts: the distance net (train, check)."""


@models_group.command("train-distance")
@click.option("--output", "output", type=click.Path(dir_okay=False), default=None,
              help="Artifact path [default: models/artifacts/<robot>_distance_net.pt in the package].")
@click.option("--robot", "robot_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Robot description YAML [default: the shipped LIMO description].")
@click.option("--steps", type=click.IntRange(min=1), default=None, help="Optimizer steps.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True,
              help="torch threads for training (1 is as fast for this small net and robust on a shared 2-core CPU).")
@click.option("--time-limit-s", type=click.FloatRange(min=1.0), default=480.0, show_default=True,
              help="Stop training after this long; the learning rate anneals by time or steps (the export and check follow, about 10 s).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None,
              help="Write the artifact metadata (training info, error statistics) here.")
def train_distance(output: str | None, robot_path: str | None, steps: int | None, seed: int, threads: int,
                   time_limit_s: float, json_path: str | None) -> None:
    """Train the distance net on exact dual solutions and export it as frozen TorchScript."""
    from dataclasses import replace

    from models.distance_net import SHIPPED_ARTIFACT, shipped_artifact_path
    from models.distance_training import TrainingConfig, train_and_export
    from models.errors import DistanceNetError

    robot = _load_robot(robot_path)
    config = TrainingConfig(seed=seed, threads=threads, time_limit_s=time_limit_s)
    if steps is not None:
        config = replace(config, steps=steps)
    if output is None:
        output = str(shipped_artifact_path().with_name(SHIPPED_ARTIFACT.replace("limo", robot.name)))
    try:
        meta = train_and_export(robot, Path(output), config, log=lambda s: click.echo(s, err=True))
    except DistanceNetError as exc:
        raise click.ClickException(str(exc)) from exc
    stats = meta["error_statistics"]
    click.echo(f"saved {output} ({Path(output).stat().st_size} bytes) after {meta['training']['steps_done']} steps "
               f"in {meta['training']['train_time_s']} s")
    click.echo(json.dumps(stats, indent=1))
    if json_path:
        Path(json_path).write_text(json.dumps(meta, indent=1))
    missed = check_targets(stats)
    if missed:
        click.echo("WARNING: accuracy targets missed: " + "; ".join(missed), err=True)


@models_group.command("check-distance")
@click.option("--model", "model_path", type=click.Path(dir_okay=False), default=None,
              help="Artifact [default: the shipped LIMO distance net].")
@click.option("--robot", "robot_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Robot description YAML [default: the shipped LIMO description].")
@click.option("--n-points", type=click.IntRange(min=100_000), default=100_000, show_default=True,
              help="Held-out points outside (and as many inside).")
@click.option("--seed", type=int, default=20240531, show_default=True, help="Seed of the held-out points.")
@click.option("--timing/--no-timing", default=True, show_default=True,
              help="Also time the net (1 thread) against one OSQP solve per point.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None, help="Write the figures here.")
def check_distance(model_path: str | None, robot_path: str | None, n_points: int, seed: int, timing: bool,
                   json_path: str | None) -> None:
    """Evaluate the distance net on held-out points against the exact distance (float64)."""
    from models.distance_check import benchmark_inference, evaluate_mu_function
    from models.distance_net import DistanceNet
    from models.errors import DistanceNetError

    robot = _load_robot(robot_path)
    try:
        net = DistanceNet.load(model_path, robot)
    except DistanceNetError as exc:
        raise click.ClickException(str(exc)) from exc
    stats = evaluate_mu_function(net.mu, net.G, net.g, n_points=n_points, seed=seed)
    missed = check_targets(stats)
    report = dict(stats, model=str(net.path), targets=DISTANCE_TARGETS, targets_met=not missed,
                  model_version=net.metadata.get("version"))
    if timing:
        report["timing"] = benchmark_inference(net)
    text = json.dumps(report, indent=1)
    click.echo(text)
    if json_path:
        Path(json_path).write_text(text)
    if missed:
        raise click.ClickException("accuracy targets missed: " + "; ".join(missed))
