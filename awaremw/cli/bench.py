"""``awaremw bench NAME [--json] [benchmark arguments]``: run a registered benchmark.

Names come from :data:`awaremw.bench.BENCHMARKS`; each module adds its own
arguments (``awaremw bench NAME --help``) and returns one dict, printed as one
JSON object with ``--json`` or as ``key: value`` lines otherwise.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
from typing import Any

from awaremw.cli.friendly import refuse
from awaremw.cli.helptext import add_verb, plain_summary


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from awaremw.bench import BENCHMARKS

    p = add_verb(
        subparsers,
        "bench",
        "run a benchmark (figures as text or JSON)",
        "Benchmarks: " + ", ".join(BENCHMARKS) + ".\n\n"
        "Run a benchmark and print its figures: key: value lines, or one JSON object\n"
        "with --json. awaremw bench NAME --help lists a benchmark's own options.",
        [
            "awaremw bench virtual --motes 1000 --duration 60 --json",
            "awaremw bench scale --motes 2000 --processes 2 --json",
            "awaremw bench mac --help",
        ],
        add_help=False,  # "bench NAME --help" is the benchmark's own help
    )
    p.add_argument("-h", "--help", action="store_true", help="this help, or NAME's")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("name", nargs="?", metavar="NAME", help=", ".join(BENCHMARKS))
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    p.set_defaults(func=run, _bench_parser=p)


def run(args: argparse.Namespace) -> int:
    from awaremw.bench import BENCHMARKS

    outer: argparse.ArgumentParser = args._bench_parser
    if args.name is None:
        outer.print_help()
        return 0 if args.help else 2
    if args.name not in BENCHMARKS:
        return refuse(
            "awaremw bench", f"unknown benchmark {args.name!r}; known: {', '.join(BENCHMARKS)}"
        )
    modname = BENCHMARKS[args.name]
    try:
        mod = importlib.import_module(modname)
    except ModuleNotFoundError as e:
        if e.name is not None and modname.startswith(e.name):
            return refuse(
                "awaremw bench",
                f"benchmark {args.name!r} is registered but its module {modname} is not available",
            )
        raise
    for attr in ("add_arguments", "run"):
        if not callable(getattr(mod, attr, None)):
            return refuse("awaremw bench", f"{modname} has no {attr}()")
    inner = argparse.ArgumentParser(
        prog=f"awaremw bench {args.name}",
        description=plain_summary(mod.__doc__ or "") or None,
        epilog=f"examples:\n  awaremw bench {args.name} --json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    inner.add_argument("--json", action="store_true", help="print one JSON object")
    mod.add_arguments(inner)
    rest = list(args.rest)
    if args.help:
        rest.append("--help")
    ns = inner.parse_args(rest)
    as_json = bool(ns.json or args.json)
    try:
        result: dict[str, Any] = mod.run(ns)
    except ValueError as e:
        # The benchmarks refuse what they cannot run (a size beyond the address
        # space, a duration too short for its workload) with a ValueError: one line.
        if getattr(args, "verbose", False):
            raise
        return refuse(f"awaremw bench {args.name}", e)
    if as_json:
        print(json.dumps(result, default=_jsonable))
    else:
        width = max((len(k) for k in result), default=0)
        for k, v in result.items():
            print(f"{k:<{width}}  {v}")
    return 0


def _jsonable(v: object) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return str(v)
