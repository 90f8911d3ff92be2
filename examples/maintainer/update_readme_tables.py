"""Maintainers: rebuild the committed result tables from the run records and rewrite them in the docs.

    python examples/maintainer/update_readme_tables.py                 # from the repository's root
    python examples/maintainer/update_readme_tables.py files=[README.md]

Runs ``examples/paper/summarize_results.py`` on the committed run records (``docs/results/runs``)
for the protocol's world-model variant and the trusted-selection table's four MetaWorld tasks, which
writes ``docs/results/table1.json`` (with its bar plots beside it) and
``docs/results/trusted_selection.json``, then rewrites the generated tables between their
``<!-- table 1 -->`` / ``<!-- trusted-selection table -->`` markers in each of ``files``. Each
region's first paragraph (its caption, written by hand) is kept; a file holds the markers of the
tables it shows. Run it after adding a run record
(``python examples/paper/summarize_results.py out=<the run's out> save_records=docs/results/runs``).
"""

from __future__ import annotations

import runpy
import sys
from dataclasses import dataclass, field
from pathlib import Path

from torchrl_dalir.config import parse_config
from torchrl_dalir.pipeline.records import DEFAULT_VARIANT
from torchrl_dalir.utils import atomic_write

SUMMARIZE = Path(__file__).resolve().parents[1] / "paper" / "summarize_results.py"
TABLES = {"table 1": "table1.md", "trusted-selection table": "trusted_selection.md"}  # marker -> file under out


@dataclass
class Config:
    out: str = "outputs/tables"  # the summary's working folder
    records: list[str] = field(default_factory=lambda: ["docs/results/runs"])
    variant: str = DEFAULT_VARIANT
    tasks: list[str] = field(default_factory=lambda: ["disassemble", "shelf-place", "stick-pull", "pick-place-wall"])
    trusted_json: str = "docs/results/trusted_selection.json"
    table1_json: str = "docs/results/table1.json"
    files: list[str] = field(default_factory=lambda: ["README.md", "docs/results/README.md"])


def main(argv: list[str]) -> None:
    cfg = parse_config(Config, argv)
    summarize = runpy.run_path(str(SUMMARIZE))
    summarize["main"](
        [
            f"out={cfg.out}",
            f"records=[{','.join(cfg.records)}]",
            f"variant={cfg.variant}",
            f"tasks=[{','.join(cfg.tasks)}]",
            f"trusted_json={cfg.trusted_json}",
            f"table1_json={cfg.table1_json}",
        ]
    )
    for name in cfg.files:
        path = Path(name)
        text = path.read_text(encoding="utf-8")
        for marker, table in TABLES.items():
            if f"<!-- {marker} -->" in text:
                text = summarize["replace_region"](text, marker, (Path(cfg.out) / table).read_text(encoding="utf-8"))
                print(f"{path}: the {marker} rewritten")
        atomic_write(path, text)


if __name__ == "__main__":
    main(sys.argv[1:])
