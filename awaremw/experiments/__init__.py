"""Experiments reproducing the paper's section V (``awaremw experiment NAME``).

Each experiment runs a shipped scenario, on the virtual clock or in real time
over Zenoh with the gateway and an MQTT subscriber, and writes figures and
``metrics.json`` into an output folder. See docs/experiments.md.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from awaremw.experiments.metrics import RunResult

Analyse = Callable[[RunResult, Path], dict[str, Any]]

# name -> (deployment, analysis module)
EXPERIMENTS: dict[str, tuple[str, str]] = {
    "romeo4r": ("romeo4r", "awaremw.experiments.romeo4r"),
    "fire": ("fire", "awaremw.experiments.fire"),
    "failover": ("failover", "awaremw.experiments.failover"),
    "large": ("large", "awaremw.experiments.large"),
    "city": ("city", "awaremw.experiments.city"),
}


def analysis(name: str) -> Analyse:
    import importlib

    _, module = EXPERIMENTS[name]
    fn: Analyse = importlib.import_module(module).analyse
    return fn


def write_metrics(out: Path, metrics: dict[str, Any]) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / "metrics.json"
    path.write_text(json.dumps(metrics, indent=2, sort_keys=False) + "\n", encoding="utf-8")
    return path
