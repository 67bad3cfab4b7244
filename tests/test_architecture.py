"""The import rule of docs/architecture.md, checked with import-linter's contracts in pyproject.toml."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _lint(config: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
         "sys.exit(lint_imports_command())", "--no-cache", "--no-logo", "--config", str(config)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )


def test_every_import_follows_the_layers():
    r = _lint(ROOT / "pyproject.toml")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


def test_a_layer_reversed_is_reported_broken(tmp_path):
    """The check can fail: the same tree against a rule it breaks (runtime below calibration)."""
    config = tmp_path / "reversed.toml"
    config.write_text(
        '[tool.importlinter]\nroot_packages = ["runtime", "calibration"]\n\n'
        '[[tool.importlinter.contracts]]\nid = "reversed"\nname = "reversed"\ntype = "layers"\n'
        'layers = ["calibration", "runtime"]\n'
    )
    r = _lint(config)
    assert r.returncode != 0
    assert "BROKEN" in r.stdout
