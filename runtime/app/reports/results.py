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
    """Markdown: the title, then per JSON file its provenance and its figures: tables for a list
    of rows and for a mapping of mappings of numbers, a list for the other numbers and words;
    what does not fit (per-episode lists, the whole config) is named, it is in the JSON."""
    out = [f"# {title}", ""]
    for name, doc in docs:
        p = doc["provenance"]
        m = p.get("machine") or {}
        out += [f"## {name}", "",
                f"- command: `{p.get('command')}`",
                f"- commit: `{p.get('commit')}`",
                f"- machine: {m.get('cpu')}, {m.get('cores')} cores, {m.get('memory_gib')} GiB, kernel {m.get('kernel')}"
                f"; Python {p.get('python')}",
                f"- when: {p.get('utc')}", ""]
        out += _figures({k: v for k, v in doc.items() if k != "provenance"})
    return "\n".join(out).rstrip() + "\n"


def _figures(body: dict) -> list[str]:
    out, scalars, left = [], [], []
    for key, value in body.items():
        if _is_rows(value):
            out += [f"**{key}**", ""] + _table(value) + [""]
        elif isinstance(value, dict) and value and all(_is_scalars(v) for v in value.values()):
            out += [f"**{key}**", ""] + _table([{"": k, **v} for k, v in value.items()]) + [""]
        elif _is_scalar(value) or _is_scalars(value) or (isinstance(value, list) and len(value) <= 8
                                                         and all(_is_scalar(v) for v in value)):
            scalars.append(f"- {key}: {_cell(value) if _is_scalar(value) else json.dumps(value)}")
        else:
            left.append(key)
    if scalars:
        out += scalars + [""]
    if left:
        out += [f"In the JSON only: {', '.join(left)}.", ""]
    return out


def _is_scalar(v) -> bool:
    return v is None or isinstance(v, (bool, int, float, str))


def _is_scalars(v) -> bool:
    return isinstance(v, dict) and bool(v) and all(_is_scalar(x) for x in v.values())


def _is_rows(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(r, dict) for r in v) and len(v) <= 200


def _table(rows: list[dict]) -> list[str]:
    keys: list[str] = []
    for r in rows:
        keys += [k for k, v in r.items() if k not in keys and _is_scalar(v)]
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(k)) for k in keys) + " |")
    return lines


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v).replace("|", "\\|").replace("\n", " ")
