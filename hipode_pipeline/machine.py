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


def cpu_name(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU model from /proc/cpuinfo with its family, model and stepping, else whatever
    platform knows. Virtual machines may name only the brand ("AMD EPYC") for different
    generations, on which the numeric libraries can take different code paths and round
    differently; the three numbers tell those machines apart."""
    try:
        fields: dict[str, str] = {}
        for line in cpuinfo.read_text().splitlines():
            if not line.strip():
                break  # the first processor's block describes them all
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
    except OSError:
        fields = {}
    if "model name" not in fields:
        return platform.processor() or platform.machine()
    generation = [
        f"{label} {fields[key]}"
        for label, key in (("family", "cpu family"), ("model", "model"), ("stepping", "stepping"))
        if key in fields
    ]
    name = fields["model name"]
    return f"{name} ({', '.join(generation)})" if generation else name


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
