"""Decode speed and size of the gateway's payload validation (awaremw/gateway/schema.py).

    python benchmarks/schema_speed.py [--n 20000] [--repeats 5] [--json OUT]
                                      [--schema-file PATH ...] [--lines-only]

Speed: realistic group-type, channel and command payloads, valid and invalid,
go through the public parse functions (``parse_group_type``, ``parse_channel``,
``parse_command``) exactly as the gateway's bridge calls them; each case is
parsed ``--n`` times (the invalid cases cycle through several distinct faults,
each one refused with its specific error), ``--repeats`` times; the figure is
the median payloads/s. Time is the process's CPU time (``time.process_time``),
not wall time: on a machine shared with other jobs, wall time mostly measures
their load.

Lines: the validation code of schema.py is counted by this rule: the lines
from the ``# ---... payload helpers`` section marker to the end of the file
that are not blank, not comments and not docstrings (docstrings found with
``ast``). What comes before the marker -- module docstring, imports, error
classes, ``Limits``, ``Definition``/``Command`` -- is the module's interface and
is the same whatever does the validation.

``--schema-file`` (repeatable) measures other versions of schema.py side by
side in one process (e.g. ``git show main:awaremw/gateway/schema.py >
/tmp/schema_before.py``), so that a before/after comparison shares the
machine's load; the default is the installed ``awaremw.gateway.schema``.
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import io
import json
import statistics
import sys
import time
import tokenize
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

MARKER = "payload helpers"


def j(obj: Any) -> bytes:
    return json.dumps(obj).encode()


GROUP_OK = [
    j(
        {
            "conditions": [
                {"attr": "temperature", "op": ">", "value": 45},
                {"attr": "rssi:100", "op": ">=", "value": -89.5},
            ],
            "hysteresis": 1.0,
        }
    )
]
GROUP_BAD = [
    j({"conditions": [{"attr": "temperature", "op": "=>", "value": 45}]}),  # bad_operator
    j({"conditions": [{"attr": "temperature", "op": ">", "value": "45"}]}),  # wrong_type
    j({"conditions": [{"attr": "temp", "op": ">", "value": 45}]}),  # unknown_attribute
    j({"conditions": [{"attr": "x", "op": ">"}]}),  # missing_field
    j({"conditions": [{"attr": "x", "op": ">", "value": 1}], "colour": "red"}),  # unknown_field
    j({"conditions": [{"attr": "x", "op": ">", "value": 1}], "hysteresis": -1}),  # bad_value
]
CHANNEL_OK = [
    j({"attr": "temperature", "group_type": 1, "group_id": "*", "period_s": 2.0, "agg": "avg"}),
    j({"attr": "rssi:100", "group_type": 2, "group_id": 513, "period_s": 5, "agg": "max"}),
]
CHANNEL_BAD = [
    j({"attr": "temperature", "group_type": 1, "period_s": 0.01, "agg": "avg"}),  # period
    j({"attr": "temperature", "group_type": 1, "period_s": 2, "agg": "median"}),  # agg
    j({"attr": "temperature", "group_type": 1, "group_id": 0, "period_s": 2}),  # group_id
    j({"attr": "temperature", "group_type": "any", "period_s": 2}),  # wrong_type
    j({"attr": "pressure", "period_s": 2}),  # unknown_attribute
    j({"attr": "temperature"}),  # missing_field
]
COMMAND_OK = [
    j({"target": {"group_type": 1, "group_id": 513}, "args": {"on": True, "rate_s": 5}}),
    j({"target": {"node": 7}, "args": {"colour": "red"}}),
    j({"target": "all"}),
]
COMMAND_BAD = [
    j({"target": {"robot": 3}}),  # unknown_target
    j({"target": {"node": 65534}}),  # unknown_target
    j({"target": "all", "args": {"a": {"b": 1}}}),  # wrong_type
    j({"target": "all", "args": {str(i): i for i in range(9)}}),  # bad_command
    j({"target": "all", "args": [1]}),  # wrong_type
    j({"target": "all", "extra": 1}),  # unknown_field
]


def cases(schema: ModuleType) -> dict[str, tuple[Callable[[bytes], object], list[bytes], bool]]:
    lim = schema.Limits()
    return {
        "group": (lambda p: schema.parse_group_type("1", p, lim), GROUP_OK, True),
        "group_invalid": (lambda p: schema.parse_group_type("1", p, lim), GROUP_BAD, False),
        "channel": (lambda p: schema.parse_channel("1", p, lim), CHANNEL_OK, True),
        "channel_invalid": (lambda p: schema.parse_channel("1", p, lim), CHANNEL_BAD, False),
        "command": (lambda p: schema.parse_command("led", p, lim, {1, 2}), COMMAND_OK, True),
        "command_invalid": (
            lambda p: schema.parse_command("led", p, lim, {1, 2}),
            COMMAND_BAD,
            False,
        ),
    }


def rate(
    schema: ModuleType, parse: Callable[[bytes], object], payloads: list[bytes], ok: bool, n: int
) -> float:
    """Payloads/s of one run; checks each payload is accepted / refused as the case says."""
    for p in payloads:  # correctness first: a fast wrong answer is no answer
        try:
            parse(p)
            accepted = True
        except schema.SchemaError:
            accepted = False
        if accepted != ok:
            raise AssertionError(f"{p!r} {'refused' if ok else 'accepted'} unexpectedly")
    batch = (payloads * (n // len(payloads) + 1))[:n]
    err = schema.SchemaError
    t0 = time.process_time()
    for p in batch:
        try:  # noqa: SIM105 -- contextlib.suppress would add its own cost to the timing
            parse(p)
        except err:
            pass
    return n / (time.process_time() - t0)


def count_lines(path: Path) -> tuple[int, int]:
    """(validation code lines by the rule in the module docstring, all lines of the file)."""
    text = path.read_text()
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith("# ---") and MARKER in ln)
    skip: set[int] = set()
    for node in ast.walk(ast.parse(text)):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr):
            c = body[0].value
            if isinstance(c, ast.Constant) and isinstance(c.value, str):
                skip.update(range(body[0].lineno - 1, (body[0].end_lineno or 0)))
    comment_only = {
        t.start[0] - 1
        for t in tokenize.generate_tokens(io.StringIO(text).readline)
        if t.type == tokenize.COMMENT and not lines[t.start[0] - 1][: t.start[1]].strip()
    }
    code = [
        i
        for i in range(start, len(lines))
        if lines[i].strip() and i not in skip and i not in comment_only
    ]
    return len(code), len(lines)


def load(path: str | None) -> tuple[str, ModuleType, Path]:
    if path is None:
        from awaremw.gateway import schema

        return "installed", schema, Path(schema.__file__)
    spec = importlib.util.spec_from_file_location(f"schema_{abs(hash(path))}", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return path, mod, Path(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20_000, help="parses per case and run")
    ap.add_argument("--repeats", type=int, default=5, help="runs per case (median reported)")
    ap.add_argument("--schema-file", action="append", default=None, help="other schema.py")
    ap.add_argument("--lines-only", action="store_true")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    args = ap.parse_args(argv)
    mods = [load(p) for p in (args.schema_file or [None])]
    out: dict[str, Any] = {}
    for label, _, path in mods:
        code, total = count_lines(path)
        out[label] = {"validation_lines": code, "file_lines": total}
        print(f"{label}: {total} lines, {code} lines of validation code")
    if not args.lines_only:
        runs: dict[str, dict[str, list[float]]] = {label: {} for label, *_ in mods}
        for _ in range(args.repeats):  # interleaved, so that load changes hit all alike
            for label, mod, _ in mods:
                for case, (parse, payloads, ok) in cases(mod).items():
                    r = rate(mod, parse, payloads, ok, args.n)
                    runs[label].setdefault(case, []).append(r)
        for label, per_case in runs.items():
            print(f"{label}: payloads/s, median of {args.repeats} x {args.n}")
            for case, rs in per_case.items():
                med = statistics.median(rs)
                out[label][case] = round(med)
                print(f"  {case:16} {med:10,.0f}   (runs: {', '.join(f'{r:,.0f}' for r in rs)})")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
