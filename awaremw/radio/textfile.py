"""Reading the radio's data files (noise traces, links files): bounded, UTF-8,
and every failure one error of the caller's kind that names the file."""

from __future__ import annotations

from pathlib import Path


def read_bounded(path: Path, max_bytes: int, error: type[ValueError], what: str) -> str:
    """The text of ``path``; ``error`` (naming the file) if it is larger than
    ``max_bytes``, unreadable or not UTF-8. ``what``: "a trace", "a links file"."""
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise error(f"{path}: {size} bytes; {what} may have {max_bytes}")
        return path.read_text(encoding="utf-8")
    except OSError as e:
        raise error(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise error(f"{path}: not UTF-8 text: {e}") from None
