"""Lines of a child process's stdout, read on a thread, awaited with a timeout."""

from __future__ import annotations

import queue
import re
import subprocess
import threading
import time


class Lines:
    """A child's output lines; :meth:`wait_for` a pattern, with a timeout."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.q: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        assert proc.stdout is not None
        out = proc.stdout
        threading.Thread(target=lambda: [self.q.put(ln) for ln in out], daemon=True).start()

    def wait_for(self, pattern: str, timeout: float) -> re.Match[str]:
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self.q.get(timeout=left)
            except queue.Empty:
                break
            self.seen.append(line)
            if m := re.search(pattern, line):
                return m
        raise AssertionError(
            f"no line matching {pattern!r} in {timeout} s; got:\n" + "".join(self.seen)
        )
