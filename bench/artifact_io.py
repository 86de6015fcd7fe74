"""Artifact write and read rates at N = 10^4 ... 10^6 transitions (Hopper-sized rows).

Writes seeded random transitions with `write_artifact` (atomic, checksummed) and reads them
back with `read_artifact` (schema, dtype, shape, finiteness and checksum verified), a few
repeats each, and records the median wall time per size in bench/results/artifact_io.md/.json.

    python bench/artifact_io.py [--sizes 10000 100000 1000000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from hipode_pipeline.artifact import read_artifact, write_artifact
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.files import write_json_atomic, write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"
OBS_DIM, ACT_DIM = 11, 3  # Hopper-v5


def random_artifact_rows(n: int, seed: int = 0) -> tuple[Transitions, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    transitions = Transitions(
        observations=rng.standard_normal((n, OBS_DIM), dtype=np.float32),
        actions=rng.uniform(-1, 1, (n, ACT_DIM)).astype(np.float32),
        rewards=rng.standard_normal(n, dtype=np.float32),
        next_observations=rng.standard_normal((n, OBS_DIM), dtype=np.float32),
        terminals=rng.random(n) < 0.01,
        timeouts=np.zeros(n, dtype=bool),
    )
    diagnostics = {
        "dynamics_error": rng.random(n, dtype=np.float32),
        "value": rng.standard_normal(n, dtype=np.float32),
        "source_index": rng.integers(0, n, n, dtype=np.int64),
    }
    return transitions, diagnostics


def measure(n: int, repeats: int, folder: Path) -> dict:
    transitions, diagnostics = random_artifact_rows(n)
    path = folder / f"artifact-{n}.hdf5"
    writes, reads = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        write_artifact(path, transitions, diagnostics, {"bench": "artifact_io"}, force=True)
        writes.append(time.perf_counter() - started)
        started = time.perf_counter()
        artifact = read_artifact(path)
        reads.append(time.perf_counter() - started)
        assert len(artifact) == n
    write_s, read_s = statistics.median(writes), statistics.median(reads)
    return {
        "n": n,
        "file_mb": round(path.stat().st_size / 1e6, 2),
        "write_s": round(write_s, 4),
        "read_s": round(read_s, 4),
        "write_rows_per_s": round(n / write_s),
        "read_rows_per_s": round(n / read_s),
        "repeats": repeats,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as folder:
        rows = [measure(n, args.repeats, Path(folder)) for n in args.sizes]
    command = "python bench/artifact_io.py " + " ".join(sys.argv[1:])
    result = {
        "command": command.strip(),
        "measured_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.processor() or ''}",
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "rows": rows,
    }
    lines = [
        "# Artifact write and read rates",
        "",
        f"Command: `{result['command']}` ({result['measured_utc']}); machine "
        f"{result['machine'].strip(', ')}; load average (1/5/15 min) before "
        f"{' '.join(f'{x:.2f}' for x in load_before)}, after "
        f"{' '.join(f'{x:.2f}' for x in result['load_average_after'])} (2 shared cores).",
        "",
        "Hopper-sized rows (11-dim states, 3-dim actions, 3 diagnostics); write = "
        "`write_artifact` (checksum, temp file, rename); read = `read_artifact` (every check "
        f"and the checksum). Median of {args.repeats} repeats.",
        "",
        "| N | file (MB) | write (s) | read (s) | write rows/s | read rows/s |",
        "|---|---|---|---|---|---|",
        *(
            f"| {r['n']:,} | {r['file_mb']} | {r['write_s']} | {r['read_s']} | "
            f"{r['write_rows_per_s']:,} | {r['read_rows_per_s']:,} |"
            for r in rows
        ),
        "",
    ]
    write_text_atomic(RESULTS / "artifact_io.md", "\n".join(lines))
    write_json_atomic(RESULTS / "artifact_io.json", result)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
