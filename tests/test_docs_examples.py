"""The Python examples in the docs run as written and print what they say they print."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def python_blocks(page: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", page.read_text(encoding="utf-8"), flags=re.S)


def test_export_ply_example_runs_and_prints_its_comment(tmp_path, monkeypatch):
    (block,) = [b for b in python_blocks(DOCS / "depth-and-export.md") if "export_ply" in b]
    monkeypatch.chdir(tmp_path)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(block, "docs/depth-and-export.md", "exec"), {"__name__": "docs_example"})
    said = re.search(r"print\(summary\)\s+#\s*(.+)", block).group(1).strip()
    assert printed.getvalue().strip() == said
    assert (tmp_path / "mesh.ply").is_file()
