"""`dct vpp`: evaluate the VPP stage (movable-point partition, mask warps) against ground truth.

`dct vpp eval --scenario` runs in the simulator, which `runtime` must not import
(docs/architecture.md): the evaluation is found through the entry point group
"dct.vpp_scenario" (name "evaluate", in pyproject.toml: hil_sim.eval.vpp:evaluate_scenario) and
loaded only when asked for. Its contract: `evaluate_scenario(scenario: str, seed: int, oracle: SimOracleConfig,
progress: Callable[[float, float], None], camera_rate_hz: float) -> dict` (JSON-ready:
`point_precision`, `point_recall`, `iou_after_m`, `stage_ms`, ...); a scenario that cannot run
raises calibration.errors.ConfigFileError (exit 2).
"""
from __future__ import annotations

from pathlib import Path

import click

from calibration.cli_support import OneLineGroup
from runtime.common.cli_support import InputError, ProgressBar, checked_output, scenario_evaluator

SCENARIO_EVAL_GROUP = "dct.vpp_scenario"
SCENARIO_EVAL_NAME = "evaluate"


@click.group(name="vpp", cls=OneLineGroup)
def vpp_group() -> None:
    """VPP: the movable-point partition and its mask memory, evaluated against ground truth."""


def _fraction(ctx, param, value):
    if value is not None and not 0.0 < value <= 1.0:
        raise click.BadParameter(f"must be in (0, 1], got {value}")
    return value


def _fmt(v, spec: str = ".3f") -> str:
    return "n/a" if v is None else f"{v:{spec}}"


def summary_lines(report: dict) -> list[str]:
    """What `dct vpp eval` prints: the partition, the warped-mask IoU per method, the stage time."""
    o = report["oracle"]
    lines = [
        f"{report['scenario']} seed {report['seed']}, oracle precision {o['precision']:g} recall {o['recall']:g}: "
        f"point precision {_fmt(report['point_precision'])}, recall {_fmt(report['point_recall'])} "
        f"(in the camera's view {_fmt(report['point_recall_in_view'])}) over {report['frames']} scans",
    ]
    samples = report["iou_samples"]
    for method, per in report["iou_after_m"].items():
        cells = ", ".join(f"{d} m {_fmt(v)}" for d, v in per.items())
        lines.append(f"  warped-mask IoU, {method:<12} {cells}")
    lines.append("  samples per distance: " + ", ".join(f"{d} m {n}" for d, n in samples.items())
                 + "; left out: " + ", ".join(f"{k} {v}" for k, v in report["iou_left_out"].items()))
    s, c = report["stage_ms"], report["stage_cpu_ms"]
    lines.append(f"  VPP stage (this machine) p50 {_fmt(s['p50'], '.2f')} ms, p99 {_fmt(s['p99'], '.2f')} ms "
                 f"over {s['frames']} scans; CPU p50 {_fmt(c['p50'], '.2f')} ms, p99 {_fmt(c['p99'], '.2f')} ms")
    e = report["episode"]
    lines.append(f"  episode: {'success' if e['success'] else 'FAILED'} in {e['navigation_time_s']:.2f} s, "
                 f"{e['fixed_contacts']} fixed contacts" + (f" ({e['failure_reason']})" if e['failure_reason'] else ""))
    return lines


@vpp_group.command("eval")
@click.option("--scenario", required=True, metavar="NAME_OR_PATH", help="a scenario of the library, or a YAML file")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=0, show_default=True, help="scenario and oracle seed")
@click.option("--oracle", "preset", type=click.Choice(["perfect", "gpt5", "gemini25"]), default="perfect",
              show_default=True, help="the sim-oracle's quality: perfect, or the DCT paper's GPT-5 (precision 1.00, "
                                      "recall 0.82) or Gemini 2.5 (0.75, 0.95)")
@click.option("--oracle-precision", type=float, default=None, callback=_fraction,
              help="override the preset's object precision (0, 1]")
@click.option("--oracle-recall", type=float, default=None, callback=_fraction,
              help="override the preset's object recall (0, 1]")
@click.option("--camera-rate-hz", type=click.FloatRange(0.5, 30.0), default=10.0, show_default=True,
              help="camera frames per second (the masks are scored on every frame)")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="write the figures here (checked before the run, written atomically after it)")
@click.option("--force", is_flag=True, help="overwrite an existing --json file")
def eval_command(*, scenario: str, seed: int, preset: str, oracle_precision: float | None,
                 oracle_recall: float | None, camera_rate_hz: float, json_path: Path, force: bool) -> None:
    """The VPP stage of one closed-loop dct episode against the simulator's truth.

    Per scan: point partition precision and recall (movable vs fixed). Per mask the memory
    took in: its IoU with the true mask after 0.25, 0.5, 1.0 and 2.0 m of travel, warped by the
    plane-induced homography, the rotation-only homography and the scan reprojected into the
    capture image. The stage's time per scan (p50, p99). Definitions: hil_sim/eval/vpp.py.
    """
    from calibration.errors import ConfigFileError
    from calibration.outputs import atomic_write_json
    from models.vlm.sim_oracle import SimOracleConfig

    overrides = {k: v for k, v in (("precision", oracle_precision), ("recall", oracle_recall)) if v is not None}
    oracle = SimOracleConfig.from_preset(preset, seed=seed, **overrides)
    evaluate = scenario_evaluator(SCENARIO_EVAL_GROUP, SCENARIO_EVAL_NAME, "dct vpp eval")
    checked_output(json_path, "--json", [Path(scenario)] if Path(scenario).is_file() else [], force)
    bar = ProgressBar(scenario)
    try:
        report = evaluate(scenario, seed=seed, oracle=oracle, progress=bar, camera_rate_hz=camera_rate_hz)
    except ConfigFileError as exc:
        raise InputError(str(exc)) from None
    finally:
        bar.close()
    atomic_write_json(json_path, report)
    for line in summary_lines(report):
        click.echo(line)
    click.echo(f"-> {json_path}")


__all__ = ["SCENARIO_EVAL_GROUP", "SCENARIO_EVAL_NAME", "summary_lines", "vpp_group"]
