"""A results page (Markdown) from benchmarks' `--json` files: their provenance (command, commit,
machine, when) and their figures, for docs/results/."""
from __future__ import annotations

import json
from pathlib import Path


class ResultsInputError(ValueError):
    """A JSON file that is not a benchmark's output: one line naming the file."""


def load_result(path: Path) -> dict:
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ResultsInputError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("provenance"), dict):
        raise ResultsInputError(f"{path}: no provenance (command, commit, machine): write it with a benchmark's "
                                "--json")
    return doc


def results_page(title: str, docs: list[tuple[str, dict]]) -> str:
    """Markdown: the title, then per JSON file its provenance and its figures."""
    out = [f"# {title}", ""]
    for name, doc in docs:
        p = doc["provenance"]
        m = p.get("machine", {})
        out += [f"## {name}", "",
                f"- command: `{p.get('command')}`",
                f"- commit: `{p.get('commit')}`",
                f"- machine: {m.get('cpu')}, {m.get('cores')} cores, {m.get('memory_gib')} GiB, kernel {m.get('kernel')}"
                f"; Python {p.get('python')}",
                f"- when: {p.get('utc')}", ""]
        body = {k: v for k, v in doc.items() if k != "provenance"}
        rows = body.pop("rows", None)
        if isinstance(rows, list) and rows and all(isinstance(r, dict) for r in rows):
            out += _table(rows) + [""]
        for key, value in body.items():
            out += [f"**{key}**", "", "```", json.dumps(value, indent=1, default=str)[:20000], "```", ""]
    return "\n".join(out).rstrip() + "\n"


def _table(rows: list[dict]) -> list[str]:
    keys: list[str] = []
    for r in rows:
        keys += [k for k, v in r.items() if k not in keys and not isinstance(v, (dict, list))]
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(k)) for k in keys) + " |")
    return lines


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)
