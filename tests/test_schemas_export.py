"""The checked-in JSON Schema and the README's catalogue are generated from the code."""
from __future__ import annotations

import subprocess
import sys

from schemas.__main__ import rendered, stale, DEFAULT_DIR
from schemas.catalogue import markdown
from tests.conftest import REPO


def test_checked_in_json_schema_is_current():
    assert stale(DEFAULT_DIR) == [], "run `python -m schemas export` and commit schemas/json/"


def test_export_writes_every_message(tmp_path):
    result = subprocess.run([sys.executable, "-m", "schemas", "export", str(tmp_path)], capture_output=True, text=True)
    assert result.returncode == 0
    assert sorted(p.name for p in tmp_path.glob("*.json")) == sorted(rendered())
    (tmp_path / "Odometry.json").write_text("{}")
    check = subprocess.run([sys.executable, "-m", "schemas", "check", str(tmp_path)], capture_output=True, text=True)
    assert check.returncode == 1 and "Odometry.json" in check.stderr


def test_readme_carries_the_catalogue():
    assert markdown() in (REPO / "README.md").read_text(), "README catalogue is stale: `python -m schemas catalogue`"
