"""Benchmark of `hipode export --minari`: write and load time and size of source ⊕ synthetic as
a Minari dataset, by writer and storage backend.

Synthetic rows become one-step Minari episodes, so the cost is per row. Arms, in interleaved
rounds on the same Hopper-shaped random data (the cost depends on shapes only):
  direct-hdf5   the export's writer: Minari's HDF5 layout written with h5py, one group per row
  minari-hdf5   Minari's own create_dataset_from_buffers, HDF5 backend
  minari-arrow  the same, arrow backend (pyarrow), without the is_synthetic info (Minari's arrow
                reader fails on it); its writer rescans the dataset per episode, so it runs
                only at the smallest size
"Load" is minari.load_dataset (metadata) and "iterate" reads every episode through Minari.

    python bench/minari_export.py [--sizes 100000 1000000] [--rounds 2] [--arrow-rows 1000]

Writes bench/results/minari_export.json and .md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from machine import cpu_name, load_average

from hipode_pipeline.data.minari_write import write_minari_dataset
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.merge import MergedData
from hipode_pipeline.minari_export import one_step_episode, source_episodes, write_merged_minari
from hipode_pipeline.paths import use_datasets_root
from hipode_pipeline.versions import package_versions

RESULTS = Path(__file__).resolve().parent / "results"
COMMANDS = ["python bench/minari_export.py " + " ".join(sys.argv[1:])]
OBS_DIM, ACT_DIM, SOURCE_ROWS, EPISODE = 11, 3, 10_000, 1000


def random_transitions(n: int, seed: int, episode: int | None) -> Transitions:
    """Hopper-shaped rows; with `episode`, chained episodes of that length (a source)."""
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n + 1, OBS_DIM)).astype(np.float32)
    ends = np.zeros(n, bool)
    if episode:
        ends[episode - 1 :: episode] = True
    return Transitions(
        observations=obs[:-1],
        actions=rng.uniform(-1, 1, (n, ACT_DIM)).astype(np.float32),
        rewards=rng.normal(size=n).astype(np.float32),
        next_observations=obs[1:] if episode else rng.normal(size=(n, OBS_DIM)).astype(np.float32),
        terminals=np.zeros(n, bool),
        timeouts=ends,
    )


def merged(rows: int) -> MergedData:
    source = {
        "id": "bench-source",
        "env_id": "Hopper-v5",
        "ref_min_score": -20.272305,
        "ref_max_score": 3234.3,
        "sha256": "",
        "n": SOURCE_ROWS,
    }
    return MergedData(
        random_transitions(SOURCE_ROWS, 0, EPISODE),
        random_transitions(rows, 1, None),
        source,
        {"checksum": "bench"},
        None,
    )


def write_direct(data: MergedData, root: Path, dataset_id: str) -> None:
    write_merged_minari(data, dataset_id, root, show_progress=False)


def write_with_minari(data: MergedData, root: Path, dataset_id: str, backend: str) -> None:
    """Every episode through Minari's writer: the source's, then one per synthetic row."""
    syn = data.synthetic
    episodes = source_episodes(data.real) + [one_step_episode(syn, i) for i in range(len(syn))]
    for e in episodes:
        if backend == "arrow":
            # arrow checks dtypes against the env's spaces (float64 states), and Minari
            # 0.5.4's arrow reader fails on a per-step bool info
            e["observations"] = e["observations"].astype(np.float64)
            del e["infos"]
    write_minari_dataset(
        dataset_id,
        episodes,
        env_id="Hopper-v5",
        root=root,
        staging=root / ".staging",
        ref_min_score=-20.272305,
        ref_max_score=3234.3,
        algorithm_name="bench",
        description="bench",
        extra_metadata={},
        data_format=backend,
    )


def measure(arm: str, rows: int, work: Path, iterate: bool = True) -> dict:
    import minari

    root = work / arm
    shutil.rmtree(root, ignore_errors=True)
    dataset_id = "bench/hopper/export-v0"
    data = merged(rows)
    load_before = load_average()
    use_datasets_root(root)
    started = time.perf_counter()
    if arm == "direct-hdf5":
        write_direct(data, root, dataset_id)
    else:
        write_with_minari(data, root, dataset_id, arm.split("-")[1])
    write_s = time.perf_counter() - started
    size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    started = time.perf_counter()
    dataset = minari.load_dataset(dataset_id)
    load_s = time.perf_counter() - started
    started = time.perf_counter()
    if iterate:
        steps = sum(len(e.rewards) for e in dataset.iterate_episodes())
        assert steps == SOURCE_ROWS + rows, steps
    else:
        assert dataset.total_steps == SOURCE_ROWS + rows, dataset.total_steps
    iterate_s = round(time.perf_counter() - started, 2) if iterate else None
    shutil.rmtree(root, ignore_errors=True)
    return {
        "arm": arm,
        "synthetic_rows": rows,
        "write_s": round(write_s, 2),
        "rows_per_s": round(rows / write_s),
        "bytes_per_row": round(size / (SOURCE_ROWS + rows)),
        "size_mb": round(size / 1e6, 1),
        "load_s": round(load_s, 3),
        "iterate_s": iterate_s,
        "load_average_before": load_before,
        "load_average_after": load_average(),
    }


def markdown(record: dict) -> str:
    lines = [
        "# Minari export: write and load cost by writer and backend",
        "",
        f"Commands: {', '.join(f'`{c}`' for c in record['commands'])} "
        f"(last {record['measured_utc']}), {record['cpu']}, "
        f"code {record['code']}; load average (1/5/15 min) in each row. Source: {SOURCE_ROWS} "
        f"rows in episodes of {EPISODE}; synthetic rows are one-step episodes; Hopper shapes, "
        "random values. Minari "
        f"{record['versions'].get('minari')}, h5py {record['versions'].get('h5py')}.",
        "",
        "| arm | synthetic rows | write s | synthetic rows/s | MB | bytes/row (all rows) | "
        "load_dataset s | iterate all s | load before → after |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in record["rows"]:
        la = f"{r['load_average_before']} → {r['load_average_after']}"
        lines.append(
            f"| {r['arm']} | {r['synthetic_rows']:,} | {r['write_s']} | "
            f"{r['rows_per_s']:,} | {r['size_mb']} | {r['bytes_per_row']:,} | "
            f"{r['load_s']} | {'—' if r['iterate_s'] is None else r['iterate_s']} | {la} |"
        )
    lines += [
        "",
        "Ratios per size (minari-hdf5 / direct-hdf5, means over rounds): "
        + "; ".join(record["ratios"])
        or "none",
        "",
    ]
    return "\n".join(lines)


def save(rows: list[dict]) -> str:
    """Write the results so far (a long run leaves what it measured if stopped)."""
    print(json.dumps(rows[-1]), flush=True)
    ratios = []
    for size in sorted({r["synthetic_rows"] for r in rows}):
        by = {
            a: [r for r in rows if r["arm"] == a and r["synthetic_rows"] == size]
            for a in ("direct-hdf5", "minari-hdf5")
        }
        if all(by.values()):
            mean = {
                a: {k: np.mean([r[k] for r in v]) for k in ("write_s", "size_mb", "iterate_s")}
                for a, v in by.items()
            }
            ratio = {
                k: mean["minari-hdf5"][k] / mean["direct-hdf5"][k]
                for k in ("write_s", "size_mb", "iterate_s")
            }
            ratios.append(
                f"{size:,} rows: write ×{ratio['write_s']:.2f}, size ×{ratio['size_mb']:.2f}, "
                f"iterate ×{ratio['iterate_s']:.2f}"
            )
    code = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=RESULTS.parent
    ).stdout.strip()
    record = {
        "commands": COMMANDS,
        "measured_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "cpu": cpu_name(),
        "code": code,
        "versions": package_versions(),
        "rows": rows,
        "ratios": ratios,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "minari_export.json").write_text(json.dumps(record, indent=2) + "\n")
    text = markdown(record)
    (RESULTS / "minari_export.md").write_text(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument(
        "--minari-max-rows",
        type=int,
        default=100_000,
        help="run Minari's HDF5 writer only up to this size (it is slow, large)",
    )
    parser.add_argument("--arrow-rows", type=int, default=1000)
    parser.add_argument(
        "--iterate-max-rows",
        type=int,
        default=100_000,
        help="read every episode back only up to this size",
    )
    parser.add_argument(
        "--append", action="store_true", help="add to bench/results/minari_export.json's rows"
    )
    args = parser.parse_args()
    rows = []
    if args.append:
        previous = json.loads((RESULTS / "minari_export.json").read_text())
        rows = previous["rows"]
        COMMANDS[:0] = previous.get("commands", [previous.get("command")])
    with tempfile.TemporaryDirectory(prefix="minari-export-") as tmp:
        work = Path(tmp)
        if args.arrow_rows:
            for arm in ("direct-hdf5", "minari-hdf5", "minari-arrow"):
                rows.append(measure(arm, args.arrow_rows, work))
                save(rows)
        for size in args.sizes:
            arms = ["direct-hdf5"] + (["minari-hdf5"] if size <= args.minari_max_rows else [])
            for _ in range(args.rounds if len(arms) > 1 else 1):
                for arm in arms:
                    rows.append(measure(arm, size, work, size <= args.iterate_max_rows))
                    save(rows)
    print(save(rows))


if __name__ == "__main__":
    main()
