"""What a sweep or benchmark records about the machine it ran on: CPU model and load.

The machines here are shared, so every figure is recorded beside the load it was taken under.
"""

from __future__ import annotations

import os
import platform
import statistics
import threading
from datetime import UTC, datetime
from pathlib import Path


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo, else whatever platform knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def utc_now() -> str:
    """The current time in UTC to the second, ISO 8601, as every record of the package writes it."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def load_average() -> str:
    """The 1, 5 and 15-minute load averages as text."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


class LoadSampler:
    """The 1-minute load average every `every` seconds while the `with` block runs."""

    def __init__(self, every: float = 5.0):
        self.every, self.samples = every, [os.getloadavg()[0]]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.every):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self) -> LoadSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def stats(self) -> dict[str, float]:
        return {
            "min": min(self.samples),
            "mean": statistics.fmean(self.samples),
            "max": max(self.samples),
            "samples": len(self.samples),
        }
