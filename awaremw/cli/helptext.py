"""The shape of every verb's ``--help``: one summary line, a short description,
examples; plain text (no markup from docstrings).

``add_verb`` is how a verb module adds its sub-command, so that ``awaremw
--help`` lists each verb on one line and ``awaremw VERB --help`` ends with
examples a user can copy. ``add_wall_timeout`` is the one wall-clock limit of
the verbs that have no emulated clock (``watch``, ``view``, ``sniff``):
``--timeout S``; ``--duration`` always means emulated seconds, and the old
spelling on those verbs still works with a note on stderr. ``add_zenoh_mode``
is the ``--zenoh-mode`` of the verbs that run motes (``fleet``, ``gateway``).
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from typing import Any

# `awaremw --help` lists a verb on one line: its summary fits beside the name.
MAX_SUMMARY = 62


def add_verb(
    sub: argparse._SubParsersAction[argparse.ArgumentParser],
    name: str,
    summary: str,
    description: str,
    examples: Sequence[str] = (),
    **kw: Any,
) -> argparse.ArgumentParser:
    """A sub-command with a one-line ``summary``, a plain ``description`` and
    ``examples`` (shell lines; a trailing ``# ...`` explains one)."""
    if len(summary) > MAX_SUMMARY:
        raise ValueError(f"summary of {name!r} is longer than {MAX_SUMMARY} characters")
    epilog = "examples:\n" + "\n".join(f"  {e}" for e in examples) if examples else None
    parser: argparse.ArgumentParser = sub.add_parser(
        name,
        help=summary,
        description=description.strip(),
        epilog=epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        **kw,
    )
    return parser


class _DeprecatedDuration(argparse.Action):
    """``--duration`` on a wall-clock verb: taken as ``--timeout``, with a note."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        print(
            f"{parser.prog}: {option_string} is deprecated here (it meant wall seconds); "
            "use --timeout S (--duration means emulated seconds on the verbs that run motes)",
            file=sys.stderr,
        )
        setattr(namespace, self.dest, values)


def add_wall_timeout(p: argparse.ArgumentParser, what: str) -> None:
    """``--timeout S``: ``what`` ends after S wall-clock seconds (default: never)."""
    p.add_argument(
        "--timeout",
        type=float,
        default=None,
        metavar="S",
        help=f"{what} after S wall-clock seconds (default: until Ctrl-C)",
    )
    p.add_argument(
        "--duration",
        dest="timeout",
        type=float,
        action=_DeprecatedDuration,
        help=argparse.SUPPRESS,
    )


def add_log_format(p: argparse.ArgumentParser) -> None:
    """``--log-format human|json`` on a long-running verb (docs/monitoring.md)."""
    p.add_argument(
        "--log-format",
        choices=("human", "json"),
        default="human",
        help="json: every line one JSON object (time, level, component, message and the "
        "event's fields), for a log collector (default human)",
    )


def add_metrics_option(p: argparse.ArgumentParser) -> None:
    """``--metrics HOST:PORT``: /metrics, /healthz and /readyz (docs/monitoring.md)."""
    p.add_argument(
        "--metrics",
        default=None,
        metavar="HOST:PORT",
        help="serve /metrics (Prometheus), /healthz and /readyz there (docs/monitoring.md); "
        "beyond loopback only with a password in $AWAREMW_METRICS_PASSWORD",
    )


def add_zenoh_mode(p: argparse.ArgumentParser) -> None:
    """``--zenoh-mode peer|client``: how the process's Zenoh session joins the router."""
    p.add_argument(
        "--zenoh-mode",
        choices=("peer", "client"),
        default="peer",
        help="Zenoh mode: peer (default; links directly to the peers the router names) "
        "or client (everything through the --connect router, e.g. across networks)",
    )


_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")  # :class:`~a.b.C` -> a.b.C (then its last part)


def plain_summary(doc: str) -> str:
    """The first paragraph of a docstring as plain text (no reStructuredText)."""
    first = doc.strip().split("\n\n", 1)[0]
    first = _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1], first)
    first = first.replace("``", "").replace("::", ":")
    return "\n".join(line.strip() for line in first.splitlines())
