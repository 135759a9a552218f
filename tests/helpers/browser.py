"""Headless Chromium for the browser tests (Playwright driving Debian's /usr/bin/chromium),
and the ``beadsight`` command whose pages they open."""

from __future__ import annotations

import os
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-quic",
    "--no-first-run",
    "--disable-component-update",
    "--disable-sync",
]
# screenshots for a person to look at (gitignored)
ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"


class Beadsight:
    """``python -m beadsight ARGS`` as a child process whose output lines (stdout and stderr)
    a thread collects; ``wait_line`` returns the first one matching a pattern."""

    def __init__(self, *args: str):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "beadsight", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.lines: queue.Queue = queue.Queue()  # None after the last line
        self.seen: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def wait_line(self, pattern: str, timeout_s: float) -> re.Match:
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"no line matching {pattern!r}; output so far: {self.seen}")
            line = self.lines.get(timeout=remaining)
            if line is None:
                raise AssertionError(f"beadsight exited; output: {self.seen}")
            self.seen.append(line)
            match = re.search(pattern, line)
            if match:
                return match

    def rest(self) -> list[str]:
        """Every line, once the process has ended and its output is read."""
        self.reader.join(10)
        while (line := self.lines.get_nowait()) is not None:
            self.seen.append(line)
        return self.seen
