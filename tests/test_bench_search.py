"""The scale benchmark's --search: doubling, the --max-motes bound, bisection.

The search logic is tested with a stand-in for one benchmark run whose
outcome is a known function of the mote count (the real runs are what the
benchmark measures, not what a test should time).
"""

from __future__ import annotations

import argparse
from typing import Any

import pytest

from awaremw.bench import scale


def _args(motes: int, max_motes: int) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    scale.add_arguments(p)
    return p.parse_args(["--motes", str(motes), "--max-motes", str(max_motes), "--search"])


@pytest.fixture
def capacity(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Runs pass up to ``capacity[0]`` motes."""
    cap = [0]

    async def fake_run_once(motes: int, duration: float, **_: Any) -> dict[str, Any]:
        ok = motes <= cap[0]
        return {
            "motes": motes,
            "timer_lag_p99_ms": 1.0 if ok else 99.0,
            "delivery_ratio": 1.0,
            "meets_target": ok,
        }

    monkeypatch.setattr(scale, "run_once", fake_run_once)
    return cap


def test_search_bisects_between_last_pass_and_first_failure(capacity: list[int]) -> None:
    capacity[0] = 5100
    out = scale.run(_args(2000, 16000))
    assert 5100 * 0.95 <= out["motes_max"] <= 5100
    assert out["search_bounded"] is False
    assert [t["motes"] for t in out["search"]][:3] == [2000, 4000, 8000]


def test_search_tries_the_bound_itself(capacity: list[int]) -> None:
    capacity[0] = 100000
    out = scale.run(_args(2000, 7000))
    assert [t["motes"] for t in out["search"]] == [2000, 4000, 7000]
    assert out["motes_max"] == 7000 and out["search_bounded"] is True


def test_search_reports_zero_when_the_start_fails(capacity: list[int]) -> None:
    capacity[0] = 100
    out = scale.run(_args(2000, 7000))
    assert out["motes_max"] == 0


def test_one_run_gets_the_medium_of_its_flags(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, Any] = {}

    async def fake_run_once(motes: int, **kwargs: Any) -> dict[str, Any]:
        seen.update(kwargs, motes=motes)
        return {"motes": motes}

    monkeypatch.setattr(scale, "run_once", fake_run_once)
    p = argparse.ArgumentParser()
    scale.add_arguments(p)
    scale.run(p.parse_args(["--motes", "30", "--mac", "aloha", "--collisions", "none"]))
    assert (seen["motes"], seen["mac"], seen["collisions"]) == (30, "aloha", "none")
