"""Structured logs: ``--log-format json`` (docs/monitoring.md).

With :func:`use_json_logs` every line the process writes is one JSON object with
``time`` (ISO 8601, UTC), ``level``, ``component`` and ``message``, and the
event's fields as keys:

* log records (the ``logging`` module) by :class:`JsonFormatter`: the logger's
  name is the component, ``extra={...}`` fields become keys, an exception its
  ``exception`` text;
* the verb's own lines (``print``) by :class:`JsonLines`, a stream in place of
  ``sys.stdout`` / ``sys.stderr``: the verb is the component, ``key=value``
  tokens of the line become keys (the fleet's progress line: ``t``, ``motes``,
  ``tx``, ...).

Worker processes inherit the choice through ``$AWAREMW_LOG_FORMAT``.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import sys
import time
from typing import Any, TextIO

ENV = "AWAREMW_LOG_FORMAT"  # "json": worker processes log as their parent does
FORMATS = ("human", "json")
_FIELD = re.compile(r"(?<![\w.])([a-z_][a-z0-9_]*)=(\S+)")
# A LogRecord's own attributes: anything else on a record came with ``extra``.
_STANDARD = frozenset(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {
    "message",
    "asctime",
    "taskName",
}


def _iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"


def _value(text: str) -> Any:
    """A token's value: a number when it reads as one (``12``, ``0.5``, ``1.2ms``
    stays text), else the text."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def line_fields(message: str) -> dict[str, Any]:
    """The ``key=value`` tokens of a line (``t=12.0 motes=25`` -> t, motes)."""
    return {k: _value(v.rstrip(",;")) for k, v in _FIELD.findall(message)}


def record(level: str, component: str, message: str, fields: dict[str, Any]) -> str:
    """One JSON log line (the four keys first; a field never overrides them)."""
    doc: dict[str, Any] = {
        "time": _iso(time.time()),
        "level": level,
        "component": component,
        "message": message,
    }
    for k, v in fields.items():
        doc.setdefault(k, v)
    return json.dumps(doc, ensure_ascii=False, default=str)


class JsonFormatter(logging.Formatter):
    """A log record as one JSON line."""

    def format(self, rec: logging.LogRecord) -> str:
        fields = {k: v for k, v in vars(rec).items() if k not in _STANDARD}
        if rec.exc_info:
            fields["exception"] = self.formatException(rec.exc_info)
        return record(rec.levelname.lower(), rec.name, rec.getMessage(), fields)


class JsonLines(io.TextIOBase):
    """A text stream that writes each line given to it as one JSON log line on
    ``target`` (a partial line waits for its end, bounded: :data:`MAX_LINE`)."""

    MAX_LINE = 65_536

    def __init__(self, target: TextIO, component: str, level: str) -> None:
        self.target, self.component, self.level = target, component, level
        self._partial = ""

    def writable(self) -> bool:
        return True

    def isatty(self) -> bool:
        return False  # no live view, no colours: lines

    def write(self, s: str) -> int:
        text = self._partial + s
        *lines, self._partial = text.split("\n")
        if len(self._partial) > self.MAX_LINE:
            lines.append(self._partial)
            self._partial = ""
        for line in lines:
            if line.strip():
                self.target.write(self._json(line) + "\n")
        return len(s)

    def flush(self) -> None:
        self.target.flush()

    def close_partial(self) -> None:
        if self._partial.strip():
            self.target.write(self._json(self._partial) + "\n")
        self._partial = ""
        self.flush()

    def _json(self, line: str) -> str:
        return record(self.level, self.component, line, line_fields(line))


def use_json_logs(component: str, level: int) -> None:
    """Every line of this process from now on as JSON (see the module docstring)."""
    out, err = sys.stdout, sys.stderr
    handler = logging.StreamHandler(err)
    handler.setFormatter(JsonFormatter())
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level)
    sys.stdout = JsonLines(out, component, "info")
    sys.stderr = JsonLines(err, component, "warning")
    os.environ[ENV] = "json"
