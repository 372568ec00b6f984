"""The ``awaremw`` command line: one entry point, one module per verb group.

Each verb module exposes ``register(subparsers)`` that adds its sub-command(s)
and sets ``func`` (a callable taking the parsed ``argparse.Namespace`` and
returning an exit code). Modules are imported lazily so that ``awaremw --help``
stays fast and a broken optional dependency does not break every verb.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

# Verb modules under awaremw.cli, in the order their verbs appear in --help.
VERB_MODULES: tuple[str, ...] = (
    "demo",
    "fleet",
    "gateway",
    "router",
    "client",
    "experiment",
    "bench",
    "keys",
    "view",
    "broker",
    "sniff",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="awaremw",
        description="AWARE data-centric WSN middleware, emulated over Eclipse Zenoh.",
        epilog="awaremw VERB --help: what a verb does, its options and examples.",
        # one line per verb: room for the longest summary beside the verb's name
        formatter_class=lambda prog: argparse.HelpFormatter(prog, max_help_position=16, width=80),
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    parser.add_argument("--version", action="version", version=f"awaremw {version()}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", title="verbs")
    for name in VERB_MODULES:
        try:
            mod = importlib.import_module(f"awaremw.cli.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"awaremw.cli.{name}":
                continue  # verb not built yet
            raise
        mod.register(sub)
    return parser


def version() -> str:
    """The installed distribution's version (the source tree's when not installed)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("awaremw")
    except PackageNotFoundError:
        return "unknown (not installed)"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    if getattr(args, "log_format", "human") == "json":
        from awaremw.runtime.logs import use_json_logs

        use_json_logs(f"awaremw {args.verb}", level)
    else:
        logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        code: int = args.func(args)
    except KeyboardInterrupt:
        return 130
    except Exception as e:
        # Zenoh refusing an endpoint (nothing listens, port taken, access denied) is
        # the user's setup, not our bug: one line without Rust source paths.
        from awaremw.cli.friendly import is_zenoh_error, zenoh_message, zenoh_unreachable

        if not is_zenoh_error(e):
            raise
        connect = list(getattr(args, "connect", None) or [])
        if connect:
            secrets_given = getattr(args, "secrets", None) is not None
            why = zenoh_unreachable(connect, e, secrets_given)
            print(f"awaremw {args.verb}: {why}", file=sys.stderr)
        else:
            print(f"awaremw {args.verb}: Zenoh: {zenoh_message(e)}", file=sys.stderr)
        return 1
    return code


if __name__ == "__main__":
    sys.exit(main())
