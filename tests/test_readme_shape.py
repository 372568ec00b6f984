"""The README is a front door: short, every doc listed once, links that resolve,
no history, and the first command where .ci/run finds it."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text(encoding="utf-8")


def test_at_most_200_lines() -> None:
    assert len(README.splitlines()) <= 200


def test_the_doc_table_lists_every_doc_once() -> None:
    table = README.split("## Documentation", 1)[1].split("\n## ", 1)[0]
    listed = re.findall(r"^\| (docs/[\w.-]+\.md) \|", table, re.M)
    assert len(listed) == len(set(listed)), sorted(d for d in listed if listed.count(d) > 1)
    on_disk = {f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")}
    assert set(listed) == on_disk, (set(listed) ^ on_disk)


def test_links_and_images_resolve() -> None:
    for target in re.findall(r"\]\(([^)#]+)\)", README):
        if "://" not in target:
            assert (ROOT / target).exists(), target
    for doc in re.findall(r"\bdocs/[\w-]+\.md\b", README):
        assert (ROOT / doc).exists(), doc


def test_no_history_in_the_front_door() -> None:
    for pattern in (r"\bissue \d+", r"before the tuning", r"\bround of speed-ups"):
        assert not re.search(pattern, README, re.I), pattern


def test_the_first_command_is_where_ci_finds_it() -> None:
    script = (ROOT / ".ci/run").read_text(encoding="utf-8")
    awk = re.search(r"first=\$\(awk '([^']+)' README\.md\)", script)
    assert awk, "the awk line of .ci/run changed"
    first = subprocess.run(["awk", awk.group(1), str(ROOT / "README.md")],
                           capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
    assert first.endswith(".venv/bin/awaremw demo"), first
