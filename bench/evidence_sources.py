"""The evidence campaign's sources: which committed run folders this machine can add runs to.

The collection recipe rebuilds a source bit for bit only on the CPU that collected it
(docs/evidence.md, "Sources"), and a run folder holds the runs of one source, so a folder can be
extended only by a machine whose CPU its runs record. Each run's scores.json names its CPU
(`cpu`; since 2026-12-06 with family, model and stepping, before that often the brand alone).
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

SAME = "this CPU"
BRAND_ONLY = "same brand, generation not recorded"
OTHER = "another CPU"
Budget = Callable[[str, str], int | None]  # (learner, task) -> the campaign's updates per run


def cpu_match(recorded: str, this_cpu: str) -> str:
    """How a CPU recorded by a run compares with this machine's: the same (name, family, model
    and stepping), a brand-only record this machine's name starts with, or another CPU."""
    if recorded == this_cpu:
        return SAME
    if "(" not in recorded and this_cpu.split(" (")[0] == recorded:
        return BRAND_ONLY
    return OTHER


def read_sources(runs_root: Path, budget: Budget, this_cpu: str) -> list[dict[str, Any]]:
    """One entry per source folder (<task>-<sha8>) under `runs_root`: its task, source sha256,
    the CPUs its runs record, its finished runs at the campaign's budget per learner, and how
    the best-matching recorded CPU compares with this machine's."""
    entries = []
    folders = sorted(p for p in runs_root.glob("*") if p.is_dir()) if runs_root.is_dir() else []
    for folder in folders:
        cpus: Counter[str] = Counter()
        runs: Counter[str] = Counter()
        task, sha256 = None, None
        for path in sorted(folder.rglob("scores.json")):
            record = json.loads(path.read_text())
            task = record.get("task", task)
            sha256 = record.get("data_identity", {}).get("source_sha256") or sha256
            cpus[record.get("cpu") or "not recorded"] += 1
            if record.get("steps") == budget(record["learner"], record["task"]):
                runs[record["learner"]] += 1
        if task is None:
            continue  # a folder with no finished run says nothing about its machine
        matches = [cpu_match(cpu, this_cpu) for cpu in cpus]
        entries.append(
            {
                "folder": folder.name,
                "task": task,
                "source_sha256": sha256,
                "cpus": dict(cpus),
                "runs_at_budget": dict(sorted(runs.items())),
                "match": next((m for m in (SAME, BRAND_ONLY) if m in matches), OTHER),
            }
        )
    return entries


def markdown(entries: list[dict[str, Any]], this_cpu: str) -> str:
    """A table a person can read: each source folder and whether this machine can extend it."""
    lines = [
        f"This machine: {this_cpu}",
        "",
        "| folder | task | CPU its runs record (runs) | runs at budget | this machine |",
        "| --- | --- | --- | --- | --- |",
    ]
    for entry in entries:
        cpus = "; ".join(f"{cpu} ({n})" for cpu, n in entry["cpus"].items())
        runs = ", ".join(f"{learner} {n}" for learner, n in entry["runs_at_budget"].items())
        lines.append(
            f"| {entry['folder']} | {entry['task']} | {cpus} | {runs or '-'} | {entry['match']} |"
        )
    return "\n".join(lines) + "\n"


def extendable(entries: list[dict[str, Any]], task: str) -> str:
    """One line for a sweep of `task`: the folders this machine's CPU can extend, or why a
    missing local source will likely give a new folder."""
    mine = [e["folder"] for e in entries if e["task"] == task and e["match"] == SAME]
    maybe = [e["folder"] for e in entries if e["task"] == task and e["match"] == BRAND_ONLY]
    if mine:
        return f"{task}: this CPU built {', '.join(mine)}; a rebuilt source continues it"
    if maybe:
        return (
            f"{task}: no committed source names this CPU's generation; {', '.join(maybe)} "
            "recorded the brand only, so a rebuilt source may or may not match it"
        )
    return f"{task}: no committed source was built on this CPU; a collected source starts a folder"
