"""Every shell example of README.md runs, as printed (ports filled in).

The ```sh blocks are read from README.md and run line by line with bash
(tests/docshell.py says how: a fresh directory, this venv first on PATH, a
private ``XDG_STATE_HOME``, free ports, long runs shortened), each block in a
shell of its own: the pieces-one-by-one recipe's client verbs find the account
of the gateway its own lines started. Skipped: the lines that
(re)install the venv or run the test suite and lint (the CI runs those).
"""

from __future__ import annotations

import re
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from docshell import BIN, ROOT, Shell, blocks

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

SKIP = ("pip install", "pytest", ".ci/run", "tests/containers", "ruff check", "mypy")


def sh_blocks() -> list[list[str]]:
    return [b.commands for b in blocks(ROOT / "README.md", ("sh",))]


@pytest.fixture
def shell(tmp_path: Path) -> Iterator[Shell]:
    s = Shell(tmp_path)
    try:
        yield s
    finally:
        s.close()


def test_readme_has_the_examples_this_test_runs() -> None:
    text = "\n".join(ln for b in sh_blocks() for ln in b)
    assert ". .venv/bin/activate" in text
    assert "awaremw fleet romeo4r --connect tcp/127.0.0.1:7447" in text
    assert re.search(r"^awaremw define group 1 .*$", text, re.M)
    assert "--mqtt" not in text  # the client verbs find the embedded broker's account


@pytest.mark.parametrize("index", range(len(sh_blocks())))
def test_readme_shell_block_runs(index: int, shell: Shell) -> None:
    block = sh_blocks()[index]
    ran = 0
    for raw in block:
        if any(s in raw for s in SKIP):
            continue
        if raw.startswith(". .venv/bin/activate"):
            # activating puts awaremw on PATH
            p = subprocess.run(
                ["bash", "-c", f". {BIN}/activate && command -v awaremw"],
                capture_output=True, text=True, timeout=30, check=False,
            )  # fmt: skip
            assert p.returncode == 0 and p.stdout.strip() == str(BIN / "awaremw"), p
            ran += 1
            continue
        shell.run(raw)
        ran += 1
    if not ran:
        pytest.skip("nothing runnable here (venv and test-suite lines)")
