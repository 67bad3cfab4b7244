"""`dct report results`: a docs/results page from benchmarks' JSON, stamped with its provenance."""
from __future__ import annotations

import json
import subprocess
import sys

from runtime.common.provenance import provenance, with_provenance


def _dct(*args):
    return subprocess.run([sys.executable, "-m", "runtime.app.cli", *args], capture_output=True, text=True,
                          timeout=120)


def test_provenance_names_the_command_the_commit_and_the_machine():
    p = provenance(["bench", "tick", "--json", "x.json"])
    assert p["command"] == "dct bench tick --json x.json"
    assert p["commit"] is None or len(p["commit"].split("-")[0]) == 12  # a checkout: its commit
    assert p["machine"]["cores"] >= 1 and p["machine"]["cpu"]
    assert p["utc"].endswith("Z")


def test_a_page_from_a_benchmarks_json_has_its_stamp_and_its_rows(tmp_path):
    doc = with_provenance({"rows": [{"case": "case1", "success": 1.0, "time_s": 4.5512}], "warnings": []})
    src = tmp_path / "t1.json"
    src.write_text(json.dumps(doc))
    out = tmp_path / "t1.md"
    r = _dct("report", "results", str(src), "--out", str(out), "--title", "Table I")
    assert r.returncode == 0, r.stderr
    page = out.read_text()
    assert page.startswith("# Table I")
    assert f"`{doc['provenance']['command']}`" in page and doc["provenance"]["machine"]["cpu"] in page
    assert "| case | success | time_s |" in page and "| case1 | 1 | 4.551 |" in page
    r = _dct("report", "results", str(src), "--out", str(out))
    assert r.returncode == 2 and "exists" in r.stderr  # never overwritten without --force


def test_a_json_without_provenance_is_refused_in_one_line(tmp_path):
    src = tmp_path / "plain.json"
    src.write_text(json.dumps({"rows": []}))
    r = _dct("report", "results", str(src), "--out", str(tmp_path / "x.md"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "provenance" in r.stderr
    assert not (tmp_path / "x.md").exists()
