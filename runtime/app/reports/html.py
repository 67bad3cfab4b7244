"""One self-contained HTML page for the latency report: tables, and the figures inline as base64
PNG (no network, no script), sized for a laptop screen at the robot."""
from __future__ import annotations

import base64

import jinja2

_TEMPLATE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{{ title }}</title>
<style>
body { font-family: -apple-system, "Segoe UI", "DejaVu Sans", Arial, sans-serif; margin: 0 auto; max-width: 1200px;
       padding: 16px; color: #222; background: #fff; }
h1 { font-size: 1.5em; margin: 0.2em 0; } h2 { font-size: 1.2em; margin-top: 1.4em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 8px 0; font-size: 0.95em; }
th, td { border: 1px solid #ccc; padding: 4px 8px; text-align: right; }
th { background: #f0f0f0; } td.name, th.name { text-align: left; }
.bad { color: #b03a2e; font-weight: bold; } .ok { color: #1e8449; }
.runs { display: grid; grid-template-columns: repeat({{ runs|length }}, 1fr); gap: 16px; }
img { max-width: 100%; height: auto; border: 1px solid #eee; }
.note { color: #555; font-size: 0.9em; } code { background: #f4f4f4; padding: 0 3px; }
</style></head><body>
<h1>{{ title }}</h1>
{% for r in runs %}
<p class="note"><b>{{ r.label }}</b>: <code>{{ r.report.run.file }}</code>, {{ r.report.run.ticks }} ticks
({{ "%.1f"|format(r.report.run.duration_s) }} s, period {{ fmt(r.report.run.period_ms) }} ms),{% if r.report.run.scenario %} scenario {{ r.report.run.scenario }},{% else %} no scenario (a run of <code>dct run</code>),{% endif %}
clock {{ r.report.run.clock or "?" }}, planner {{ r.report.run.planner or "?" }}.
{% if not r.report.run.recording_complete %}<span class="bad">Recording cut off ({{ r.report.run.recording_stopped_by }}): read up to its last complete chunk.</span>{% endif %}
{% if r.report.run.recorder and r.report.run.recorder.dropped_total %}<span class="bad">The recorder dropped {{ r.report.run.recorder.dropped_total }} records.</span>{% endif %}
</p>
{% endfor %}

<h2>Summary</h2>
<table>
<tr><th class="name">figure</th>{% for r in runs %}<th>{{ r.label }}</th>{% endfor %}</tr>
<tr><td class="name">whole tick p99 (ms)</td>{% for r in runs %}<td>{{ fmt(r.report.tick.p99_ms) }}</td>{% endfor %}</tr>
<tr><td class="name">whole tick p99 / period</td>{% for r in runs %}<td>{{ pct(r.report.run.tick_p99_share_of_period) }}</td>{% endfor %}</tr>
<tr><td class="name">whole tick max (ms)</td>{% for r in runs %}<td>{{ fmt(r.report.tick.max_ms) }}</td>{% endfor %}</tr>
<tr><td class="name">deadline misses (loop clock: the verdict)</td>{% for r in runs %}<td class="{{ 'bad' if r.report.deadline_misses.count else 'ok' }}">{{ r.report.deadline_misses.count }}</td>{% endfor %}</tr>
<tr><td class="name">deadline misses (wall clock, measured)</td>{% for r in runs %}<td class="{{ 'bad' if r.report.deadline_misses.wall_clock_count else 'ok' }}">{{ r.report.deadline_misses.wall_clock_count }}</td>{% endfor %}</tr>
<tr><td class="name">period jitter p99 / max (ms)</td>{% for r in runs %}<td>{{ fmt(r.report.jitter_ms.p99_ms) }} / {{ fmt(r.report.jitter_ms.max_ms) }}</td>{% endfor %}</tr>
<tr><td class="name">ticks skipped</td>{% for r in runs %}<td>{{ r.report.jitter_ms.ticks_skipped }}</td>{% endfor %}</tr>
<tr><td class="name">sensor-to-command p50 / p99 (ms)</td>{% for r in runs %}<td>{% if r.report.sensor_to_command_ms.recorded %}{{ fmt(r.report.sensor_to_command_ms.p50_ms) }} / {{ fmt(r.report.sensor_to_command_ms.p99_ms) }}{% else %}not recorded{% endif %}</td>{% endfor %}</tr>
</table>

<h2>Per stage (ms; stage times on the wall clock)</h2>
{% for r in runs %}
<table>
<tr><th class="name">{{ r.label }}</th><th>p50</th><th>p90</th><th>p99</th><th>p99.9</th><th>max</th><th>budget</th><th>overruns</th></tr>
{% for name, s in r.report.stages.items() %}
<tr><td class="name">{{ name }}</td><td>{{ fmt(s.p50_ms) }}</td><td>{{ fmt(s.p90_ms) }}</td><td>{{ fmt(s.p99_ms) }}</td><td>{{ fmt(s.p999_ms) }}</td>
<td class="{{ 'bad' if s.max_ms is not none and s.budget_ms is not none and s.max_ms > s.budget_ms else '' }}">{{ fmt(s.max_ms) }}</td><td>{{ fmt(s.budget_ms) }}</td>
<td class="{{ 'bad' if s.overruns else 'ok' }}">{{ s.overruns }}</td></tr>
{% endfor %}
{% set t = r.report.tick %}
<tr><td class="name"><b>whole tick</b></td><td>{{ fmt(t.p50_ms) }}</td><td>{{ fmt(t.p90_ms) }}</td><td>{{ fmt(t.p99_ms) }}</td><td>{{ fmt(t.p999_ms) }}</td><td>{{ fmt(t.max_ms) }}</td><td>{{ fmt(t.budget_ms) }}</td><td class="{{ 'bad' if t.overruns else 'ok' }}">{{ t.overruns }}</td></tr>
</table>
{% endfor %}
<p class="note">Whole-tick budget: the command deadline. Jitter: {{ runs[0].report.jitter_ms.note }}.</p>

<h2>Image capture to mask, CPU time per thread</h2>
{% for r in runs %}
{% set m = r.report.image_to_mask_ms %}
<p><b>{{ r.label }}</b>: image capture -> mask {% if m.recorded %}p50 {{ fmt(m.p50_ms) }}, p90 {{ fmt(m.p90_ms) }}, p99 {{ fmt(m.p99_ms) }}, max {{ fmt(m.max_ms) }} ms over {{ m.count }} answers ({{ m.what }}).{% else %}not recorded ({{ m.why }}).{% endif %}</p>
{% set th = r.report.threads %}
{% if th.recorded %}
<table>
<tr><th class="name">thread ({{ fmt(th.wall_s) }} s wall)</th><th>CPU (s)</th><th>share of wall</th></tr>
{% for name, t in th.by_name.items() %}
<tr><td class="name">{{ name }}{% if t.threads > 1 %} (&times;{{ t.threads }}){% endif %}</td><td>{{ fmt(t.cpu_s) }}</td><td>{{ pct(t.share_of_wall) }}</td></tr>
{% endfor %}
{% if th.process %}<tr><td class="name"><b>whole process</b></td><td>{{ fmt(th.process.cpu_s) }}</td><td>{{ pct(th.process.share_of_wall) }}</td></tr>{% endif %}
</table>
{% else %}
<p class="note">CPU time per thread: not recorded ({{ th.why }}).</p>
{% endif %}
{% endfor %}

<h2>Deadline misses</h2>
{% for r in runs %}
<p><b>{{ r.label }}</b>: {{ r.report.deadline_misses.count }} on the loop clock, {{ r.report.deadline_misses.wall_clock_count }} on the wall clock{% if r.report.deadline_misses.events %}; the first {{ r.report.deadline_misses.listed }}:{% else %}.{% endif %}</p>
{% if r.report.deadline_misses.events %}
<table>
<tr><th>tick</th><th>t (s since the first tick)</th><th class="name">clock</th><th>latency (ms)</th><th>wall latency (ms)</th><th class="name">ran long</th><th class="name">over budget</th><th class="name">ticks before (tick: ms, longest stage)</th></tr>
{% for e in r.report.deadline_misses.events %}
<tr><td>{{ e.tick }}</td><td>{{ fmt(e.t_since_start_s) }}</td><td class="name">{{ e.clock }}</td><td>{{ fmt(e.command_latency_ms) }}</td><td>{{ fmt(e.wall_command_latency_ms) }}</td>
<td class="name">{{ e.ran_long }} {{ fmt(e.ran_long_ms) }} ms (budget {{ fmt(e.ran_long_budget_ms) }})</td><td class="name">{{ e.stages_over_budget|join(", ") or "none" }}</td>
<td class="name">{% for b in e.before %}{{ b.tick }}: {{ fmt(b.tick_ms) }}, {{ b.longest_stage }}{% if not loop.last %}; {% endif %}{% endfor %}</td></tr>
{% endfor %}
</table>
{% endif %}
{% endfor %}

<h2>Figures</h2>
{% for i in range(runs[0].figures|length) %}
<p class="note">{{ runs[0].figures[i][0] }}</p>
<div class="runs">
{% for r in runs %}{% if i < r.figures|length %}<div>{% if runs|length > 1 %}<p class="note"><b>{{ r.label }}</b></p>{% endif %}<img alt="{{ r.figures[i][0] }} ({{ r.label }})" src="data:image/png;base64,{{ r.figures[i][1] }}"></div>{% endif %}{% endfor %}
</div>
{% endfor %}
<p class="note">Made by <code>dct report latency</code>. Sensor-to-command: {% if runs[0].report.sensor_to_command_ms.recorded %}{{ runs[0].report.sensor_to_command_ms.what }}{% else %}{{ runs[0].report.sensor_to_command_ms.why }}{% endif %}. CPU time per thread: {{ runs[0].report.threads.what if runs[0].report.threads.recorded else "not recorded" }}.</p>
</body></html>
"""


def _fmt(v) -> str:
    if v is None:
        return "-"
    return f"{v:.3f}" if abs(v) < 10 else f"{v:.1f}"


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def render_html(runs: list[tuple[str, dict, list[tuple[str, bytes]]]], title: str) -> str:
    """runs: (label, report dict, [(caption, PNG bytes)]) for each run, side by side."""
    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined)
    tpl = env.from_string(_TEMPLATE)
    return tpl.render(
        title=title, fmt=_fmt, pct=_pct,
        runs=[{"label": label, "report": report,
               "figures": [(cap, base64.b64encode(png).decode()) for cap, png in figs]}
              for label, report, figs in runs],
    )
