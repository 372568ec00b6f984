"""benchmarks/run_all.py: docs/figures.md's table is its rows and the README's short
table its brief rows, both made from benchmarks/results.json; the median run is one
whole run; a --quick session has the structure the lead's full session has."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _run_all() -> ModuleType:
    spec = importlib.util.spec_from_file_location("run_all", ROOT / "benchmarks/run_all.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["run_all"] = mod  # dataclasses resolve their module by name
    spec.loader.exec_module(mod)
    return mod


def _table_rows(text: str) -> list[list[str]]:
    """Cells of the table rows (header and rule left out) of a markdown table."""
    rows = []
    for line in text.splitlines():
        if not line.startswith("| ") or line.startswith(("| benchmark |", "|---")):
            continue
        rows.append([c.strip() for c in line.strip().strip("|").split(" | ")])
    return rows


def _table_in(path: str) -> str:
    ra = _run_all()
    text = (ROOT / path).read_text(encoding="utf-8")
    assert text.count(ra.BEGIN) == 1 and text.count(ra.END) == 1
    return text.split(ra.BEGIN, 1)[1].split(ra.END, 1)[0]


def test_figures_rows_are_exactly_run_all_rows() -> None:
    """Every row of docs/figures.md's table is made by run_all, with its command,
    in its order; no row that the script does not make."""
    ra = _run_all()
    rows = _table_rows(_table_in("docs/figures.md"))
    assert [(r[0], r[1]) for r in rows] == [(row.label, f"`{row.command}`") for row in ra.ROWS]
    # Each row names a command a user can type.
    assert all(row.command.startswith("awaremw ") for row in ra.ROWS)
    assert len({row.key for row in ra.ROWS}) == len(ra.ROWS)


def test_readme_short_table_is_the_brief_rows_linking_to_figures() -> None:
    ra = _run_all()
    assert set(ra.BRIEF) <= {row.key for row in ra.ROWS}
    text = _table_in("README.md")
    rows = _table_rows(text)
    assert [r[0] for r in rows] == [row.label for row in ra.ROWS if row.key in ra.BRIEF]
    assert "[docs/figures.md](docs/figures.md)" in text


def test_both_tables_are_what_run_all_makes_of_the_results_file() -> None:
    """`run_all.py --write-docs` wrote them from benchmarks/results.json, unedited."""
    ra = _run_all()
    report = json.loads((ROOT / "benchmarks/results.json").read_text(encoding="utf-8"))
    assert _table_in("docs/figures.md") == "\n" + ra.markdown(report)
    assert _table_in("README.md") == "\n" + ra.brief_markdown(report)


def test_markdown_from_a_report_has_every_row_and_the_machine() -> None:
    ra = _run_all()
    run = {"timer_lag_p99_ms": 2.0, "timer_lag_p50_ms": 0.6, "motes": 2000, "processes": 2}
    pk = {"eclipse-zenoh": "1.0"}
    machine = {"cores": 2, "cpu_model": "X", "python": "3.11.7", "packages": pk}
    row = {"command": ra.ROWS[0].command, "runs": [run, run, run], "median": run,
           "headline_values": [2.0, 2.0, 2.0], "errors": []}  # fmt: skip
    report: dict[str, Any] = {"repeat": 3, "machine": machine, "rows": {"scale-hello": row}}
    md = ra.markdown(report)
    rows = _table_rows(md)
    assert [r[0] for r in rows] == [row.label for row in ra.ROWS]
    assert "p99 **2 ms**" in rows[0][2] and "median of 3 by `timer_lag_p99_ms`" in rows[0][2]
    assert all(r[2].startswith("no figure (not run)") for r in rows[1:])
    assert "2 cores (X)" in md and "eclipse-zenoh 1.0" in md


def test_median_run_is_one_whole_run() -> None:
    ra = _run_all()
    runs = [{"p99": 9.0, "n": 1}, {"p99": 2.0, "n": 2}, {"p99": 5.0, "n": 3}]
    i, values = ra.median_run(runs, "p99")
    assert runs[i] == {"p99": 5.0, "n": 3} and values == [9.0, 2.0, 5.0]
    # Even counts take the lower middle; a run without the figure sorts last.
    i, _ = ra.median_run([{"p99": 4.0}, {"p99": None}, {"p99": 1.0}, {"p99": 3.0}], "p99")
    assert i == 3


@pytest.mark.zenoh
@pytest.mark.timeout(900)  # about 2 minutes on a quiet machine, 5 under load
def test_quick_session_writes_every_row_with_its_median_run(tmp_path: Path) -> None:
    ra = _run_all()
    out = tmp_path / "results.json"
    argv = [sys.executable, str(ROOT / "benchmarks/run_all.py"), "--quick", "--out", str(out)]
    # CI builds the compiled build once, before the tests; the session reuses it.
    if os.environ.get("AWAREMW_COMPILED_SITE"):
        argv += ["--compiled", os.environ["AWAREMW_COMPILED_SITE"]]
    p = subprocess.run(argv, capture_output=True, text=True, timeout=600, check=False,
                       cwd=tmp_path)  # fmt: skip
    assert p.returncode == 0, p.stderr[-3000:]
    report = json.loads(out.read_text())
    assert report["quick"] is True and report["repeat"] == 1
    m = report["machine"]
    assert m["cores"] >= 1 and m["python"] and m["cpu_model"]
    assert m["packages"]["eclipse-zenoh"] and m["packages"]["msgpack"]
    assert set(report["rows"]) == {row.key for row in ra.ROWS}
    for row in ra.ROWS:
        e = report["rows"][row.key]
        assert e["errors"] == [] and len(e["runs"]) == 1, (row.key, e["errors"])
        assert e["median"] == e["runs"][0] and row.headline in e["median"]
        assert e["command"] == "awaremw " + " ".join(row.quick)
    assert report["rows"]["bridge"]["median"]["bridge_samples"] == 100
    large = report["rows"]["experiment-large"]["median"]
    assert {"wall_s", "duration_s", "motes_scored", "records_delivered",
            "distinct_group_ids"} <= set(large)  # fmt: skip
    # Progress: one line per run on stderr; the table on stdout, one row each.
    assert p.stderr.count(" run 1/1: awaremw ") == len(ra.ROWS)
    assert len(_table_rows(p.stdout)) == len(ra.ROWS)
    # --markdown regenerates the same table from the file.
    md = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks/run_all.py"), "--markdown", "--results", str(out)],
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout  # fmt: skip
    assert md == p.stdout
