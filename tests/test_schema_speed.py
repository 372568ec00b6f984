"""benchmarks/schema_speed.py: its payloads are accepted/refused as labelled, its line rule."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "schema_speed", ROOT / "benchmarks/schema_speed.py"
    )
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_line_rule_skips_blanks_comments_and_docstrings(tmp_path: Path) -> None:
    f = tmp_path / "s.py"
    f.write_text(
        '"""Module."""\nX = 1\n\n# --------- payload helpers\n\n\ndef f() -> int:\n'
        '    """Doc\n    on two lines."""\n    # a comment\n    return 1  # trailing\n'
    )
    assert _bench().count_lines(f) == (2, 11)  # "def f", "return 1"


def test_benchmark_runs_and_checks_each_payload(tmp_path: Path) -> None:
    out = tmp_path / "r.json"
    assert _bench().main(["--n", "60", "--repeats", "1", "--json", str(out)]) == 0
    res = json.loads(out.read_text())["installed"]
    assert 150 < res["validation_lines"] < res["file_lines"]
    for case in ("group", "channel", "command"):
        assert res[case] > 0 and res[f"{case}_invalid"] > 0


def test_a_payload_labelled_wrongly_is_caught() -> None:
    bench = _bench()
    from awaremw.gateway import schema

    parse, payloads, ok = bench.cases(schema)["group_invalid"]
    with pytest.raises(AssertionError, match="refused unexpectedly"):
        bench.rate(schema, parse, payloads, not ok, 10)
