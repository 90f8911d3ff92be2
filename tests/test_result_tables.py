"""The committed result tables are what the committed run records give: ``examples/maintainer/update_readme_tables.py``
rebuilds Table 1 and the trusted-selection table from ``docs/results/runs`` and leaves the README,
``docs/results/README.md`` and the tables' JSON as they are."""

import json
import runpy
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "examples" / "maintainer" / "update_readme_tables.py"


def test_the_committed_tables_are_rebuilt_unchanged_from_the_run_records(tmp_path, monkeypatch):
    docs = {"README.md": tmp_path / "README.md", "docs/results/README.md": tmp_path / "results_README.md"}
    for name, copy in docs.items():
        shutil.copy(REPO / name, copy)
    tables = tmp_path / "tables"
    monkeypatch.chdir(REPO)  # the records' folder, as the script's default names it
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "update_readme_tables.py",
            f"out={tables}",
            f"trusted_json={tables / 'trusted.json'}",
            f"table1_json={tables / 'json' / 'table1.json'}",
            f"files=[{','.join(map(str, docs.values()))}]",
        ],
    )
    runpy.run_path(str(SCRIPT), run_name="__main__")
    for name, copy in docs.items():
        assert copy.read_text() == (REPO / name).read_text(), f"{name}: run examples/maintainer/update_readme_tables.py"
    assert "<!-- table 1 -->" in docs["README.md"].read_text()
    assert "<!-- trusted-selection table -->" in docs["docs/results/README.md"].read_text()
    made = {"table1.json": tables / "json" / "table1.json", "trusted_selection.json": tables / "trusted.json"}
    for committed, path in made.items():
        assert json.loads(path.read_text()) == json.loads((REPO / "docs" / "results" / committed).read_text())
