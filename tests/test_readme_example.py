"""The README's Python example runs as written (the front door cannot drift from the API)."""

from __future__ import annotations

import re
import runpy
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def python_blocks(text: str) -> list[str]:
    """The ```python fenced blocks of a Markdown text, in order."""
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.DOTALL | re.MULTILINE)


def test_readme_has_one_python_example():
    blocks = python_blocks(README.read_text(encoding="utf-8"))
    assert len(blocks) == 1, f"expected one ```python block in README.md, found {len(blocks)}"
    assert "Pipeline(" in blocks[0] and ".process(" in blocks[0]


def test_readme_example_runs(tmp_path, capsys):
    (block,) = python_blocks(README.read_text(encoding="utf-8"))
    script = tmp_path / "readme_example.py"
    script.write_text(block, encoding="utf-8")
    namespace = runpy.run_path(str(script), run_name="__main__")
    result = namespace["result"]
    assert result.sh.shape == (16,)
    assert abs(float(result.dominant_direction_world @ result.dominant_direction_world) - 1) < 1e-6
    assert 0.0 <= result.confidence.value <= 1.0
    assert "degrees off, confidence" in capsys.readouterr().out
