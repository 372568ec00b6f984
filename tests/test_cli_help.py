"""Every verb's --help is plain text with examples; ``awaremw --help`` fits one
screen, one line per verb; ``--version``; the commands motes accept are listed
and any other name is refused before anything is sent."""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import subprocess
import sys
from collections.abc import Iterator

import pytest

from awaremw.bench import BENCHMARKS
from awaremw.cli import build_parser, main
from awaremw.nodes.kinds import COMMANDS

# reStructuredText a terminal would print raw: literals, roles, literal-block markers.
MARKUP = re.compile(r"``|`[^`\s][^`]*`|:(class|mod|data|func|meth|attr|ref):|::(\s|$)")


def verbs(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*path, name), sub
                yield from verbs(sub, (*path, name))


ALL = sorted(path for path, _ in verbs(build_parser()))


def help_of(argv: list[str]) -> str:
    out = io.StringIO()
    code: object = None
    with contextlib.redirect_stdout(out):
        try:
            code = main([*argv, "--help"])  # `bench` prints its help itself
        except SystemExit as e:
            code = e.code
    assert code in (0, None), (argv, code)
    return out.getvalue()


def test_every_verb_and_sub_verb_is_walked() -> None:
    names = {p[0] for p in ALL}
    assert {"demo", "fleet", "gateway", "router", "define", "command", "watch"} <= names
    assert ("define", "group") in ALL and ("keys", "init") in ALL and ("fleet-ctl", "add") in ALL


@pytest.mark.parametrize("path", ALL + [("bench", n) for n in BENCHMARKS], ids=" ".join)
def test_help_is_plain_text(path: tuple[str, ...]) -> None:
    text = help_of(list(path))
    assert not MARKUP.search(text), f"markup in `awaremw {' '.join(path)} --help`:\n{text}"
    assert text.startswith("usage: awaremw ")


@pytest.mark.parametrize("path", [p for p in ALL if len(p) == 1] + [("bench", "virtual")])
def test_every_verb_has_a_description_and_examples(path: tuple[str, ...]) -> None:
    text = help_of(list(path))
    examples = text.split("\nexamples:\n", 1)
    assert len(examples) == 2, f"no examples in `awaremw {' '.join(path)} --help`"
    assert all(ln.startswith("  awaremw ") or ln.startswith("  tshark ")
               for ln in examples[1].strip("\n").splitlines()), examples[1]  # fmt: skip
    head = examples[0].split("\n\n")
    assert len(head) >= 3 and head[1].strip(), "no description between usage and options"


def test_top_level_help_fits_one_screen_one_line_per_verb() -> None:
    text = help_of([])
    lines = text.splitlines()
    assert len(lines) <= 30 and max(map(len, lines)) <= 80, text
    top = sorted({p[0] for p in ALL})
    for verb in top:
        [line] = [ln for ln in lines if re.match(rf"^    {re.escape(verb)}\s", ln)]
        assert len(line.split(None, 1)[1]) > 10  # the summary is on the verb's own line
    # no summary spills onto a second line
    body = text.split("\nverbs:\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert len(body) == 1 + len(top), body


def test_version() -> None:
    from importlib.metadata import version

    p = subprocess.run([sys.executable, "-m", "awaremw", "--version"],
                       capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert p.returncode == 0 and p.stdout.strip() == f"awaremw {version('awaremw')}"


def test_command_help_lists_the_commands_motes_accept() -> None:
    text = help_of(["command"])
    for name in COMMANDS:
        assert re.search(rf"^  {name}\s+\S", text, re.M), name


def test_unknown_command_refused_with_the_list_before_connecting(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Port 9 (discard): nothing listens; the refusal comes before any connection.
    assert main(["command", "reboot", "--mqtt", "mqtt://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "unknown command 'reboot'" in err
    assert f"motes accept: {', '.join(sorted(COMMANDS))}" in err


def test_wall_clock_verbs_take_timeout_and_the_old_spelling_with_a_note(
    capsys: pytest.CaptureFixture[str],
) -> None:
    for verb in ("watch", "sniff", "view"):
        assert "--timeout S" in help_of([verb])
    parser = build_parser()
    ns = parser.parse_args(["watch", "--duration", "5"])
    assert ns.timeout == 5.0
    assert "--duration is deprecated here" in capsys.readouterr().err
    ns = parser.parse_args(["sniff", "--timeout", "2"])
    assert ns.timeout == 2.0
