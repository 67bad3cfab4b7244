"""`dct report latency RUN.mcap`: the latency report of a recorded run (HTML and JSON) and its
trace (Chrome trace-event JSON, a PNG timeline); `dct report results`: a results page from
benchmarks' JSON."""
from __future__ import annotations

from pathlib import Path

import click


class InputError(click.ClickException):
    """Bad input (file, option): one line on stderr, exit status 2."""

    exit_code = 2


@click.group(name="report")
def report_group() -> None:
    """Reports from recorded runs (MCAP files of `dct hil run --record`)."""


@report_group.command("latency")
@click.argument("run", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--html", "html_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the report as one self-contained HTML page (figures inline).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the figures as JSON (stages, tick, jitter_ms, deadline_misses, sensor_to_command_ms, "
                   "image_to_mask_ms, threads).")
@click.option("--compare", "compare_path", type=click.Path(dir_okay=False, path_type=Path),
              help="A second recording to put beside RUN (before and after a change).")
@click.option("--trace", "trace_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write RUN as Chrome trace-event JSON (Perfetto, chrome://tracing): each stage of each tick, "
                   "the slack work, each 0x111 write, lidar frames, ICP registrations and VLM requests on tracks "
                   "of their own, flows from a lidar frame to the 0x111 that used it.")
@click.option("--trace-png", "trace_png_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Draw that trace as a PNG timeline (0.6 s from the first lidar -> ICP -> 0x111 flow).")
@click.option("--force", is_flag=True, help="Overwrite existing --html / --json / --trace / --trace-png files.")
def latency_command(*, run: Path, html_path: Path | None, json_path: Path | None, compare_path: Path | None,
                    trace_path: Path | None, trace_png_path: Path | None, force: bool) -> None:
    """Per-stage p50/p90/p99/p99.9/max against the budgets recorded with RUN, the whole tick, period
    jitter, deadline misses with their context, sensor-to-command latency. Prints a summary; exit
    status 2 on bad input (a file that is not a recording, an existing output without --force)."""
    from calibration.outputs import OutputPathError, atomic_write_json, atomic_write_text, check_output_path
    from runtime.app.reports.latency import ReportInputError, latency_report, load_ticks

    inputs = [run] + ([compare_path] if compare_path is not None else [])
    outputs = [(w, p) for w, p in (("--html", html_path), ("--json", json_path), ("--trace", trace_path),
                                   ("--trace-png", trace_png_path)) if p is not None]
    try:
        for what, p in outputs:
            check_output_path(p, what=what, inputs=inputs, overwrite=force)
        for i, (what, p) in enumerate(outputs):
            same = [w for w, q in outputs[i + 1:] if q.resolve() == p.resolve()]
            if same:
                raise InputError(f"{what} and {same[0]} are the same file {p}")
        data = [load_ticks(p) for p in inputs]
        trace = _trace(run) if trace_path is not None or trace_png_path is not None else None
    except (OutputPathError, ReportInputError) as exc:
        raise InputError(str(exc)) from exc
    reports = [latency_report(d) for d in data]
    labels = [p.name if len(inputs) == 1 or inputs[0].name != inputs[1].name else str(p) for p in inputs]
    if json_path is not None:
        payload = dict(reports[0])
        if compare_path is not None:
            payload["compare"] = reports[1]
        atomic_write_json(json_path, payload)
    if html_path is not None:
        from runtime.app.reports.html import render_html
        from runtime.app.reports.plots import all_figures

        title = "Latency report: " + " vs ".join(labels)
        page = render_html([(lab, rep, all_figures(d)) for lab, rep, d in zip(labels, reports, data)], title)
        atomic_write_text(html_path, page)
    for lab, rep in zip(labels, reports):
        click.echo(summary_text(lab, rep))
    if trace is not None:
        _write_trace(trace, run, trace_path, trace_png_path)


def _trace(run: Path):
    """RUN's trace and what it holds (ReportInputError for a malformed recording)."""
    from runtime.app.reports.trace import chrome_trace
    from runtime.app.reports.trace_data import load_trace_source

    return chrome_trace(load_trace_source(run))


def _write_trace(trace, run: Path, trace_path: Path | None, png_path: Path | None) -> None:
    """Write the trace (compact JSON) and its PNG, each atomically, and say what they hold."""
    import json

    from calibration.outputs import atomic_write_bytes, atomic_write_text
    from runtime.app.reports.trace import summary_lines

    events, summary = trace
    if trace_path is not None:
        atomic_write_text(trace_path, json.dumps(events, separators=(",", ":"), allow_nan=False))
        for line in summary_lines(summary, str(trace_path)):
            click.echo(line)
    if png_path is not None:
        from runtime.app.reports.trace_png import render_png

        atomic_write_bytes(png_path, render_png(events, title=f"{run.name}: tracks and flows"))
        click.echo(f"trace timeline {png_path}")


def summary_text(label: str, rep: dict) -> str:
    def f(v) -> str:
        return "-" if v is None else f"{v:.2f}"

    run = rep["run"]
    lines = [f"{label}: {run['ticks']} ticks, {run['duration_s']:.1f} s"
             + ("" if run["recording_complete"] else f" (cut off: {run['recording_stopped_by']})")]
    lines.append(f"  {'stage':10s} {'p50':>8s} {'p99':>8s} {'p99.9':>8s} {'max':>8s} {'budget':>8s} overruns")
    for name, s in list(rep["stages"].items()) + [("tick", rep["tick"])]:
        lines.append(f"  {name:10s} {f(s['p50_ms']):>8s} {f(s['p99_ms']):>8s} {f(s['p999_ms']):>8s} "
                     f"{f(s['max_ms']):>8s} {f(s['budget_ms']):>8s} {s['overruns']}")
    m = rep["deadline_misses"]
    s2c = rep["sensor_to_command_ms"]
    lines.append(f"  deadline misses: {m['count']} (loop clock), {m['wall_clock_count']} (wall clock); "
                 f"jitter p99 {f(rep['jitter_ms']['p99_ms'])} ms; sensor-to-command p99 "
                 + (f"{f(s2c['p99_ms'])} ms" if s2c["recorded"] else "not recorded"))
    i2m, th = rep.get("image_to_mask_ms", {}), rep.get("threads", {})
    lines.append("  image capture -> mask: " + (f"p50 {f(i2m['p50_ms'])} ms, max {f(i2m['max_ms'])} ms, "
                                                f"{i2m['count']} answers" if i2m.get("recorded") else "not recorded")
                 + "; CPU per thread: " + (", ".join(f"{n} {f(t['cpu_s'])} s" for n, t in th["by_name"].items())
                                           if th.get("recorded") else "not recorded"))
    return "\n".join(lines)


@report_group.command("results")
@click.argument("inputs", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", "out_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The Markdown page to write (e.g. docs/results/tick.md).")
@click.option("--title", default="Benchmark results", help="The page's title.")
@click.option("--force", is_flag=True, help="Overwrite an existing --out file.")
def results_command(*, inputs: tuple[Path, ...], out_path: Path, title: str, force: bool) -> None:
    """A Markdown page from benchmarks' --json files (`dct bench ... --json`): each one's command,
    commit, machine and date, then its figures. Exit status 2 on a file without provenance."""
    from calibration.outputs import OutputPathError, atomic_write_text, check_output_path
    from runtime.app.reports.results import ResultsInputError, load_result, results_page

    try:
        check_output_path(out_path, what="--out", inputs=list(inputs), overwrite=force)
        docs = [(p.name, load_result(p)) for p in inputs]
    except (OutputPathError, ResultsInputError) as exc:
        raise InputError(str(exc)) from None
    atomic_write_text(out_path, results_page(title, docs))
    click.echo(f"wrote {out_path}")
