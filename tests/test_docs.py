"""Every shell and Python block of docs/*.md runs, as printed (ports filled in).

A document's blocks run in order in one shell (tests/docshell.py: a fresh
directory, this venv first on PATH, a private ``XDG_STATE_HOME``, free ports,
long runs shortened). What a block starts in the background runs until the
document's next ``##`` section: a later block of the same section may use it,
as a reader would, and a new section starts from nothing. Blocks fenced
``text`` (API outlines, usage synopses) and unlabeled ones (transcripts) are
not programs and are not run.

The skip-list names each block that cannot run here, and why.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from docshell import ROOT, Block, Shell, blocks

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

DOCS = sorted((ROOT / "docs").glob("*.md"))

# (document, a piece of the block's first command) -> why it cannot run here.
SKIP: dict[tuple[str, str], str] = {
    ("containers.md", ""): "needs podman-compose or Docker and the images that "
    "tests/containers/run.sh builds; .ci/run runs that stack",
    ("dashboard.md", ""): "a usage synopsis ([optional] parts); tests/test_web.py runs "
    "demo --web and view against a real broker and browser",
    ("runtime.md", ".venv/bin/pip install"): "installs the compiled build into the test "
    "venv (it would replace the editable install); .ci/run builds and tests it apart",
    ("figures.md", "python3 -m venv .venv-fast"): "builds a second venv and compiles the "
    "package (minutes); .ci/run builds and tests the compiled build",
    ("security.md", "awaremw router --secrets secrets/ --listen tcp/0.0.0.0"): "a deployment "
    "across hosts (ROUTER, BROKER, PW placeholders); docs/running.md runs the same on one "
    "machine",
    ("security.md", "mqtts://operator:PW@broker.lan"): "a TLS broker named broker.lan with "
    "DIR's certificates; tests/test_mqtt_tls.py runs these against Mosquitto",
    ("hosts.md", "awaremw keys init secrets/"): "three hosts (HOST_A, HOST_B, HOST_C "
    "placeholders); tests/test_netns.py runs these lines on three network namespaces",
}

# Arguments of Python blocks that read sys.argv: (document, first line) -> argv.
ARGV: dict[tuple[str, str], list[str]] = {
    ("security.md", "import sys"): ["secrets", "app", "tcp/127.0.0.1:7447"],
}
# What a Python block must print: (document, first line) -> pieces of its stdout.
EXPECT: dict[tuple[str, str], tuple[str, ...]] = {
    # The Zenoh HBN example prints the definitions it has just put (issue 33).
    ("gateway.md", "import json, time"): (
        "aware/hbn/def/group/1 {", "aware/hbn/def/channel/1 {", "'op': '>', 'value': 45",
    ),
}
NEEDS_TSHARK = "tshark "


def why_skipped(block: Block) -> str | None:
    text = "\n".join(block.commands)
    for (doc, piece), why in SKIP.items():
        if doc == block.path.name and piece in text:
            return why
    return None


@pytest.fixture
def shell(tmp_path: Path) -> Iterator[Shell]:
    s = Shell(tmp_path)
    try:
        yield s
    finally:
        s.close()


def test_every_skip_names_a_block_that_exists() -> None:
    for doc, first in EXPECT:
        assert any(b.text.startswith(first) for b in blocks(ROOT / "docs" / doc)), (doc, first)
    for doc, piece in SKIP:
        path = ROOT / "docs" / doc
        assert path.exists(), doc
        assert any(piece in b.text for b in blocks(path)), (doc, piece)


def _tshark() -> bool:
    return shutil.which("tshark") is not None


@pytest.mark.timeout(900)
@pytest.mark.parametrize("doc", [d for d in DOCS if blocks(d)], ids=lambda d: d.name)
def test_doc_blocks_run(doc: Path, shell: Shell) -> None:
    ran = skipped = 0
    section = None
    for block in blocks(doc):
        if block.section != section:
            shell.close()  # a new section starts from nothing
            section = block.section
        if why_skipped(block) is not None:
            skipped += 1
            continue
        if block.lang == "python":
            argv = next((a for (d, first), a in ARGV.items()
                         if d == doc.name and block.text.startswith(first)), [])  # fmt: skip
            out = shell.python(block, argv)
            for (d, first), pieces in EXPECT.items():
                if d == doc.name and block.text.startswith(first):
                    for piece in pieces:
                        assert piece in out, (doc.name, piece, out[-2000:])
            ran += 1
            continue
        for raw in block.commands:
            if raw.startswith(NEEDS_TSHARK) and not _tshark():
                if os.environ.get("AWAREMW_REQUIRE_TSHARK") == "1":
                    pytest.fail("tshark not installed")
                continue
            if "awaremw broker --mosquitto" in raw and not (
                shutil.which("mosquitto") or os.access("/usr/sbin/mosquitto", os.X_OK)
            ):
                if os.environ.get("AWAREMW_REQUIRE_MOSQUITTO") == "1":
                    pytest.fail("mosquitto not installed")
                pytest.skip("mosquitto not installed")
            shell.run(raw)
        ran += 1
    if not ran:
        pytest.skip(f"every block of {doc.name} is on the skip-list")
