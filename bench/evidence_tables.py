"""The tables of docs/evidence.md, regenerated from the committed reports and run folders.

A table whose rows are generated carries a marker on the line above its header; the header
and the separator stay as written, the rows below them are replaced:

    <!-- evidence-rows: groups report=by-source learner=td3bc -->
    <!-- evidence-rows: comparisons report=pooled learner=iql task=walker2d-m-r -->
    <!-- evidence-rows: across report=pooled learner=td3bc -->
    <!-- evidence-rows: runs folder=hopper-m-r-7c80ddd9 learner=td3bc -->

`groups`, `comparisons` and `across` read `hipode report`'s report.json (pooled, by-source or
by-stage-one-seed, as `bench/evidence.py report` writes them); `runs` reads every run folder of a
sweep finished at the campaign's budget. `python bench/evidence.py tables` rewrites the rows in
place; with `--check` it changes nothing and fails naming each table that differs.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

MARKER = re.compile(r"<!-- evidence-rows: (?P<kind>[a-z]+)(?P<params>(?: [a-z]+=[^ ]+)*) -->")
REPORT_FILES = {
    "pooled": "report.json",
    "by-source": "by-source/report.json",
    "by-stage-one-seed": "by-stage-one-seed/report.json",
}
# the columns a report's grouping adds after the task
EXTRA_KEYS = {
    "pooled": [],
    "by-source": ["source_sha256"],
    "by-stage-one-seed": ["source_sha256", "artifact_seed"],
}
TASK_ORDER = ["hopper-m-r", "walker2d-m-r", "halfcheetah-m-r"]
AUGMENTATION_ORDER = ["none", "hipode", "model-rollouts"]
ARM_ORDER = ["eta0", "hipode"]  # then the other arm folders by name


class TableError(ValueError):
    """A marker or the data it names is wrong: the message names the file and line."""


def rank(order: list[str], value: Any) -> tuple[int, str]:
    """Known values in the order given, unknown ones after them by name."""
    text = str(value)
    return (order.index(text), "") if text in order else (len(order), text)


def interval(measure: dict[str, Any], key: str) -> str:
    low, high = measure[f"{key}_ci"]
    return f"{measure[key]:.1f} [{low:.1f}, {high:.1f}]"


def signed(value: float) -> str:
    return f"{value:+.1f}".replace("+-", "-")


def difference(measure: dict[str, Any]) -> str:
    low, high = measure["ci"]
    return f"{signed(measure['mean'])} [{signed(low)}, {signed(high)}]"


def probability(measure: dict[str, Any]) -> str:
    low, high = measure["ci"]
    return f"{measure['probability']:.2f} [{low:.2f}, {high:.2f}]"


def replicates(group: dict[str, Any]) -> str:
    """'10 (5 × 2)': runs, then training seeds × stage-one seeds."""
    text = f"{group['n_runs']} ({len(group['seeds'])}"
    if group["artifact_seeds"]:
        text += f" × {len(group['artifact_seeds'])}"
    return text + ")"


def row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def wanted(key: dict[str, Any], params: dict[str, str]) -> bool:
    return key["learner"] == params["learner"] and params.get("task", key["task"]) == key["task"]


def sort_key(key: dict[str, Any]) -> tuple:
    return (
        rank(TASK_ORDER, key["task"]),
        str(key.get("source_sha256") or ""),
        rank(AUGMENTATION_ORDER, key["augmentation"]),
        str(key.get("artifact_seed")),
    )


def extra_cells(key: dict[str, Any], report_name: str) -> list[str]:
    return [str(key.get(name))[:8] for name in EXTRA_KEYS[report_name]]


def group_rows(report: dict[str, Any], report_name: str, params: dict[str, str]) -> list[str]:
    """One row per group: runs, last-eval mean and IQM, last-3 mean, curve mean, with CIs."""
    groups = sorted((g for g in report["groups"] if wanted(g, params)), key=sort_key)
    return [
        row(
            [g["augmentation"], g["task"], *extra_cells(g, report_name), replicates(g)]
            + [
                interval(g["measures"]["last"], "mean"),
                interval(g["measures"]["last"], "iqm"),
                interval(g["measures"]["last_k_mean"], "mean"),
                interval(g["measures"]["curve_mean"], "mean"),
            ]
        )
        for g in groups
    ]


def comparison_rows(report: dict[str, Any], report_name: str, params: dict[str, str]) -> list[str]:
    """One row per arm − none comparison: pairs, paired differences and P(improvement)."""
    found = [c for c in report["comparisons"] if wanted(c["key"], params)]
    rows = []
    for comparison in sorted(found, key=lambda c: sort_key(c["key"])):
        key, measures = comparison["key"], comparison["measures"]
        last = measures["last"]
        rows.append(
            row(
                [key["augmentation"], key["task"], *extra_cells(key, report_name)]
                + [
                    str(last["paired_difference"]["pairs"]),
                    difference(last["paired_difference"]),
                    probability(last["probability_of_improvement"]),
                    difference(measures["last_k_mean"]["paired_difference"]),
                    difference(measures["curve_mean"]["paired_difference"]),
                ]
            )
        )
    return rows


def across_rows(report: dict[str, Any], report_name: str, params: dict[str, str]) -> list[str]:
    """One row per arm: the mean over tasks of each task's mean paired difference."""
    rows = []
    for entry in report["across_tasks"]:
        fields = dict(part.split("=", 1) for part in entry["arm"].split())
        if fields.get("learner") != params["learner"]:
            continue
        measures = entry["measures"]
        rows.append(
            row(
                [
                    fields["augmentation"],
                    ", ".join(entry["tasks"]),
                    str(measures["last"]["pairs"]),
                    difference(measures["last"]),
                    difference(measures["last_k_mean"]),
                    difference(measures["curve_mean"]),
                ]
            )
        )
    return rows


def run_rows(runs: Path, params: dict[str, str], steps: int) -> list[str]:
    """One row per arm folder: each finished run's last eval / last 3 / curve mean, and speed."""
    from hipode_pipeline.run_folder import scores_if_finished
    from hipode_pipeline.sweep.worker import recorded_seeds, run_folder

    folder, learner = runs / params["folder"], params["learner"]
    task = params["folder"].rsplit("-", 1)[0]  # <task>-<sha8>
    if not (folder / task).is_dir():
        raise TableError(f"folder={params['folder']}: expected {folder / task} to exist")
    rows = []
    arms = sorted(p.name for p in (folder / task).iterdir() if p.is_dir())
    for arm in sorted(arms, key=lambda name: rank(ARM_ORDER, name)):
        cells, speeds = [], []
        for seed in recorded_seeds(folder, task, arm, learner):
            scores = scores_if_finished(run_folder(folder, task, arm, learner, seed), steps)
            if scores is None:
                continue
            curve = [e["score_mean"] for e in scores["evaluations"] if e["step"] <= steps]
            last3 = sum(curve[-3:]) / len(curve[-3:])
            cells.append(f"{seed}: {curve[-1]:.1f} / {last3:.1f} / {sum(curve) / len(curve):.1f}")
            speeds.append(f"{scores['updates_per_second']:.0f}")
        if cells:
            rows.append(row([arm, "; ".join(cells), ", ".join(speeds)]))
    return rows


KINDS: dict[str, Callable[..., list[str]]] = {
    "groups": group_rows,
    "comparisons": comparison_rows,
    "across": across_rows,
}


def table_rows(
    kind: str, params: dict[str, str], reports: Path, runs: Path, steps: dict[str, int]
) -> list[str]:
    """The rows a marker asks for (TableError on a marker that names nothing)."""
    if "learner" not in params:
        raise TableError("expected learner=<name>")
    if kind == "runs":
        if "folder" not in params or params["learner"] not in steps:
            raise TableError(f"runs: expected folder=<task>-<sha8> and learner in {sorted(steps)}")
        return run_rows(runs, params, steps[params["learner"]])
    if kind not in KINDS:
        raise TableError(f"expected a kind in {sorted([*KINDS, 'runs'])}, found {kind!r}")
    name = params.get("report", "")
    if name not in REPORT_FILES:
        raise TableError(f"report: expected one of {sorted(REPORT_FILES)}, found {name!r}")
    path = reports / REPORT_FILES[name]
    if not path.is_file():
        raise TableError(f"report={name}: {path} is missing; run `bench/evidence.py report`")
    rows = KINDS[kind](json.loads(path.read_text()), name, params)
    if not rows:
        raise TableError(f"{path}: no rows for {params}")
    return rows


def regenerate(
    text: str, doc: Path, reports: Path, runs: Path, steps: dict[str, int]
) -> tuple[str, list[str]]:
    """The document with every marked table's rows regenerated, and the markers whose rows
    changed (as 'doc:line marker')."""
    lines = text.split("\n")
    changed = []
    index = 0
    while index < len(lines):
        match = MARKER.fullmatch(lines[index].strip())
        if not match:
            if lines[index].strip().startswith("<!-- evidence-rows:"):
                raise TableError(f"{doc}:{index + 1}: malformed marker {lines[index].strip()!r}")
            index += 1
            continue
        where = f"{doc}:{index + 1}"
        header = index + 1
        if header + 1 >= len(lines) or not lines[header + 1].startswith("|"):
            raise TableError(f"{where}: expected a table header and separator below the marker")
        params = dict(part.split("=", 1) for part in match["params"].split())
        try:
            rows = table_rows(match["kind"], params, reports, runs, steps)
        except TableError as error:
            raise TableError(f"{where}: {error}") from None
        start = end = header + 2
        while end < len(lines) and lines[end].startswith("|"):
            end += 1
        if lines[start:end] != rows:
            changed.append(f"{where} {lines[index].strip()}")
            lines[start:end] = rows
        index = start + len(rows)
    return "\n".join(lines), changed
