"""The design document ships with the code, and every citation of it resolves."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CITATION = re.compile(r"docs/design\.md §(\d+)")
OLD_NAME = "DESIGN" + ".md"  # the notes the design came from, not in the repository


def _tracked_text_files() -> list[Path]:
    out = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=False
    ).stdout.split()
    files = [ROOT / f for f in out] if out else list(ROOT.rglob("*.py"))
    me = Path(__file__).resolve()  # the checker's own examples are not citations
    kinds = (".py", ".md", ".yaml", ".toml")
    return [f for f in files if f.suffix in kinds and f.is_file() and f.resolve() != me]


def sections(text: str) -> set[int]:
    return {int(m) for m in re.findall(r"^## (\d+)\. ", text, flags=re.MULTILINE)}


def test_every_citation_of_the_design_document_resolves() -> None:
    have = sections((ROOT / "docs" / "design.md").read_text())
    cited: dict[int, list[str]] = {}
    for f in _tracked_text_files():
        text = f.read_text(errors="replace")
        assert OLD_NAME not in text, f"{f}: cites {OLD_NAME}, which is not in the repository"
        for n in CITATION.findall(text):
            cited.setdefault(int(n), []).append(str(f.relative_to(ROOT)))
    assert cited, "no citation found: the pattern is wrong"
    missing = {n: fs[:3] for n, fs in cited.items() if n not in have}
    assert not missing, f"citations of sections docs/design.md does not have: {missing}"


def test_the_check_sees_a_missing_section() -> None:
    assert sections("## 1. A\ntext\n## 3. C\n") == {1, 3}
    assert CITATION.findall("see docs/design.md §7 and docs/design.md §12") == ["7", "12"]
