"""The tables of docs/evidence.md, regenerated from the evidence reports and run folders.

A table whose rows are generated carries a marker on the line right above its header; the
header and the separator stay as written, the rows below them are replaced:

    <!-- evidence-rows: groups report=by-source learner=td3bc -->
    <!-- evidence-rows: comparisons report=pooled learner=iql task=walker2d-m-r -->
    <!-- evidence-rows: across report=pooled learner=td3bc -->
    <!-- evidence-rows: scores report=design learner=iql -->
    <!-- evidence-rows: comparisons report=versus-rollouts learner=td3bc augmentation=hipode -->
    <!-- evidence-rows: runs folder=hopper-m-r-7c80ddd9 learner=td3bc -->
    <!-- evidence-rows: authenticity folder=hopper-m-r-7c80ddd9 learner=td3bc -->

`groups`, `comparisons`, `across` and `scores` (each arm's scores over tasks) read
`hipode report`'s report.json (pooled, by-source, by-stage-one-seed or design, against η = 0
or, named versus-rollouts…, against the plain model rollouts of the same stage-one seed, as
`bench/evidence.py report` writes them; `augmentation=` keeps one arm's
rows), and refuse a report that holds other runs than the pooled one (a design report: other
than the design's share of them); `runs` lists a sweep
folder's runs finished at the campaign's budget, and refuses when they are not the runs the
pooled report holds (a run finished after the report was written); `authenticity` puts the
source beside
each artifact of a sweep folder: the sweep's quality.json (rewards, real rewards at the same
states, terminal share) and each arm's `hipode verify` report under report/<learner>/verify/
(next-state error against the simulator, share within tolerance, novelty).
`python bench/evidence.py tables` rewrites the rows in place; with `--check` it changes nothing
and fails on any difference.
"""

from __future__ import annotations

import functools
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from evidence_design import design_runs

from hipode_pipeline.report import (
    difference_text,
    find_runs,
    interval_text,
    probability_text,
    replicates_text,
)

ReportReader = Callable[[Path], dict[str, Any]]  # a report.json's path -> its content
Budget = Callable[[str, str], int | None]  # (learner, task) -> the campaign's updates per run
MARKER = re.compile(r"<!-- evidence-rows: (?P<kind>[a-z]+)(?P<params>(?: [a-z]+=[^ ]+)*) -->")
SEPARATOR = re.compile(r"\|(\s*:?-+:?\s*\|)+")


class ReportKind(NamedTuple):
    path: str  # below bench/evidence/report/
    extra_keys: list[str]  # the columns its grouping adds after the task
    flags: str  # of `python bench/evidence.py report`, which writes it
    design: bool = False  # holds only the runs of the design (evidence_design), not every run


# report names as markers give them: each arm against η = 0, or (versus-rollouts…) against the
# plain model rollouts of the same stage-one seed (its dynamics ensemble)
REPORTS = {
    "pooled": ReportKind("report.json", [], ""),
    "by-source": ReportKind("by-source/report.json", ["source_sha256"], "--by-source"),
    "by-stage-one-seed": ReportKind(
        "by-stage-one-seed/report.json", ["source_sha256", "artifact_seed"], "--by-stage-one-seed"
    ),
    "design": ReportKind("design/report.json", [], "--design", design=True),
}
REPORTS |= {
    f"versus-rollouts{'' if name == 'pooled' else '-' + name}": kind._replace(
        path=f"versus-rollouts/{kind.path}", flags=f"--versus-rollouts {kind.flags}".strip()
    )
    for name, kind in REPORTS.items()
}
# the keys each kind of marker takes (required, optional)
KEYS = {
    "groups": ({"report", "learner"}, {"task", "augmentation"}),
    "comparisons": ({"report", "learner"}, {"task", "augmentation"}),
    "across": ({"report", "learner"}, {"augmentation"}),
    "scores": ({"report", "learner"}, {"augmentation"}),
    "runs": ({"folder", "learner"}, set()),
    "authenticity": ({"folder", "learner"}, set()),
}
TASK_ORDER = ["hopper-m-r", "walker2d-m-r", "halfcheetah-m-r"]
AUGMENTATION_ORDER = ["none", "hipode", "model-rollouts"]
ARM_ORDER = ["eta0", "hipode"]  # then the other arm folders by name


class TableError(ValueError):
    """A marker, or the data it names, is wrong; regenerate() prefixes the doc's file:line."""


def rank(order: list[str], value: Any) -> tuple[int, str]:
    """Known values in the order given, unknown ones after them by name."""
    text = str(value)
    return (order.index(text), "") if text in order else (len(order), text)


def row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def wanted(key: dict[str, Any], params: dict[str, str]) -> bool:
    return key["learner"] == params["learner"] and all(
        name not in params or key.get(name) == params[name] for name in ("task", "augmentation")
    )


def sort_key(key: dict[str, Any]) -> tuple:
    return (
        rank(TASK_ORDER, key["task"]),
        str(key.get("source_sha256") or ""),
        rank(AUGMENTATION_ORDER, key["augmentation"]),
        str(key.get("artifact_seed")),
    )


def extra_cells(key: dict[str, Any], report_name: str) -> list[str]:
    return [str(key.get(name))[:8] for name in REPORTS[report_name].extra_keys]


def group_rows(report: dict[str, Any], report_name: str, params: dict[str, str]) -> list[str]:
    """One row per group: runs, last-eval mean and IQM, last-k mean, curve mean, with CIs."""
    groups = sorted((g for g in report["groups"] if wanted(g, params)), key=sort_key)
    return [
        row(
            [g["augmentation"], g["task"], *extra_cells(g, report_name), replicates_text(g)]
            + [
                interval_text(g["measures"]["last"], "mean"),
                interval_text(g["measures"]["last"], "iqm"),
                interval_text(g["measures"]["last_k_mean"], "mean"),
                interval_text(g["measures"]["curve_mean"], "mean"),
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
        paired = measures["last"]["paired_difference"]
        rows.append(
            row(
                [key["augmentation"], key["task"], *extra_cells(key, report_name)]
                + [
                    "0" if paired is None else str(paired["pairs"]),
                    difference_text(paired),
                    probability_text(measures["last"]["probability_of_improvement"]),
                    difference_text(measures["last_k_mean"]["paired_difference"]),
                    difference_text(measures["curve_mean"]["paired_difference"]),
                ]
            )
        )
    return rows


def across_rows(report: dict[str, Any], report_name: str, params: dict[str, str]) -> list[str]:
    """One row per arm: the mean over tasks of each task's mean paired difference (and, at the
    last evaluation, of each task's P(improvement))."""
    rows = []
    for entry in report["across_tasks"]:
        fields = entry.get("key") or dict(part.split("=", 1) for part in entry["arm"].split())
        if not wanted({"task": None, **fields}, params):
            continue
        measures = entry["measures"]
        last = measures.get("last")
        rows.append(
            row(
                [
                    fields["augmentation"],
                    ", ".join(entry["tasks"]),
                    "0" if last is None else str(last["pairs"]),
                    difference_text(last),
                    probability_text(last and last.get("probability_of_improvement")),
                    difference_text(measures.get("last_k_mean")),
                    difference_text(measures.get("curve_mean")),
                ]
            )
        )
    return rows


def score_rows(report: dict[str, Any], report_name: str, params: dict[str, str]) -> list[str]:
    """One row per arm: its runs' scores aggregated over tasks (IQM and mean, tasks weighing
    the same)."""
    if "scores_across_tasks" not in report:
        raise TableError("no scores across tasks: an older report; run its report command again")
    found = [e for e in report["scores_across_tasks"] if wanted({"task": None, **e["key"]}, params)]
    rows = []
    for entry in sorted(found, key=lambda e: rank(AUGMENTATION_ORDER, e["key"]["augmentation"])):
        measures = entry["measures"]
        rows.append(
            row(
                [
                    entry["key"]["augmentation"],
                    ", ".join(entry["tasks"]),
                    str(entry["n_runs"]),
                    str(entry["sources"]),
                    interval_text(measures["last"], "iqm"),
                    interval_text(measures["last"], "mean"),
                    interval_text(measures["last_k_mean"], "iqm"),
                    interval_text(measures["curve_mean"], "iqm"),
                ]
            )
        )
    return rows


def run_rows(
    runs: Path, pooled: Path, read: ReportReader, params: dict[str, str], budget: Budget
) -> list[str]:
    """One row per arm folder: each finished run's last eval / last k / curve mean, and speed.
    `runs` is the runs folder as the reports name it (relative to the working directory)."""
    from hipode_pipeline.run_folder import scores_if_finished
    from hipode_pipeline.sweep.report import curve_mean, window_score
    from hipode_pipeline.sweep.worker import recorded_seeds, run_folder

    folder, learner = runs / params["folder"], params["learner"]
    task, _ = folder_parts(params["folder"])
    if not (folder / task).is_dir():
        raise TableError(f"folder={params['folder']}: expected {folder / task} to exist")
    steps = budget(learner, task)
    if steps is None:
        raise TableError(f"learner: expected one the campaign has a budget for, found {learner!r}")
    # the run folders the pooled report holds, as it names them (relative to the checkout)
    in_report = report_runs(read(pooled))
    rows, unreported = [], []
    arms = [p.name for p in (folder / task).iterdir() if p.is_dir()]
    for arm in sorted(arms, key=lambda name: rank(ARM_ORDER, name)):
        cells, speeds = [], []
        for seed in recorded_seeds(folder, task, arm, learner):
            run_dir = run_folder(folder, task, arm, learner, seed)
            scores = scores_if_finished(run_dir, steps)
            if scores is None:
                continue
            if run_dir.as_posix() not in in_report:
                unreported.append(run_dir.as_posix())
            curve = [
                [e["step"], e["score_mean"]] for e in scores["evaluations"] if e["step"] <= steps
            ]
            record = {"curve": curve}
            last, window, mean = curve[-1][1], window_score(record), curve_mean(record)
            cells.append(f"{seed}: {last:.1f} / {window:.1f} / {mean:.1f}")
            speeds.append(f"{scores['updates_per_second']:.0f}")
        if cells:
            rows.append(row([arm, "; ".join(cells), ", ".join(speeds)]))
    if unreported:
        raise TableError(
            f"runs finished after {pooled} was written: "
            f"{', '.join(unreported)}; run `python bench/evidence.py report` (and --by-source, "
            "--by-stage-one-seed, and each with --versus-rollouts) first"
        )
    return rows


FOLDER = re.compile(r"(?P<task>.+)-(?P<sha8>[0-9a-f]{8})")


def folder_parts(name: str) -> tuple[str, str]:
    """A sweep folder's task and the first 8 hex of its source's sha256: <task>-<sha8>."""
    match = FOLDER.fullmatch(name)
    if match is None:
        raise TableError(f"folder={name}: expected <task>-<first 8 hex of the source's sha256>")
    return match["task"], match["sha8"]


def verify_report(folder: Path, arm: dict[str, Any], source: dict[str, Any]) -> dict[str, Any]:
    """The one `hipode verify` report in a sweep's verify/<arm>/, checked to be of the arm's
    artifact built from the folder's source."""
    found = sorted((folder / arm["name"]).glob("*.verify.json"))
    if len(found) != 1:
        raise TableError(
            f"{folder / arm['name']}: expected one *.verify.json, found {len(found)}; run "
            f"`hipode verify {arm['artifact']} --no-baseline --sample 2000 "
            f"--out-dir {folder / arm['name']}`"
        )
    report = read_report(found[0])
    for field, expected in (("artifact", arm["artifact"]), ("source_sha256", source["sha256"])):
        if report.get(field) != expected:
            raise TableError(
                f"{found[0]}: field {field}: expected {expected!r} (the arm's), found "
                f"{report.get(field)!r}; verify the arm's own artifact again"
            )
    return report


def authenticity_rows(runs: Path, read: ReportReader, params: dict[str, str]) -> list[str]:
    """The source, then one row per artifact of the folder's arms: its reward beside the real
    reward at the same states, terminal share, next-state error against the simulator (median on
    rows with exact ground truth, source stds), share within tolerance and novelty (median)."""
    task, sha8 = folder_parts(params["folder"])
    results = runs / params["folder"] / "report" / params["learner"]
    quality = read(results / "quality.json")
    rewrite = f"rewrite it on a machine that holds source {sha8} with `{quality['command']}" + (
        "`" if "--report-only" in quality["command"] else " --report-only`"
    )
    source = quality.get("sources", {}).get(task)
    if source is None:
        raise TableError(f"{results / 'quality.json'}: no field sources.{task}; {rewrite}")
    if not source["sha256"].startswith(sha8):
        raise TableError(
            f"{results / 'quality.json'}: field sources.{task}.sha256: expected {sha8}…, "
            f"found {source['sha256'][:8]}…"
        )
    rows = [row(["source", "", f"{source['reward_mean']:.3f}", terminal_text(source)] + [""] * 3)]
    arms = [a for a in quality["arms"][task] if a["learner"] == params["learner"]]
    trained = {
        r["arm"] for r in quality["runs"] if (r["task"], r["learner"]) == (task, params["learner"])
    }
    for arm in sorted(arms, key=lambda a: rank(ARM_ORDER, a["name"])):
        if arm["data"] == "source":
            continue
        synthetic, seed = arm["synthetic"], arm.get("stage_one_seed")
        if synthetic is None and arm["name"] not in trained:
            continue  # planned by a wider sweep, never built nor trained: nothing to describe
        if synthetic is None or seed is None:
            missing = "synthetic" if synthetic is None else "stage_one_seed"
            raise TableError(
                f"{results / 'quality.json'}: arm {arm['name']} has no {missing}; {rewrite}"
            )
        checked = verify_report(results / "verify", arm, source)["hipode"]
        rows.append(
            row(
                [
                    (arm.get("augment") or {}).get("method", "hipode"),
                    str(seed),
                    f"{synthetic['reward_mean']:.3f} "
                    f"({synthetic['source_reward_mean_same_states']:.3f})",
                    terminal_text(synthetic),
                    f"{checked['next_state_error_median_exact_rows']:.4f}",
                    f"{100 * checked['within_tolerance']:.2f} %",
                    f"{checked['novelty_median']:.3f}",
                ]
            )
        )
    return rows


def terminal_text(stats: dict[str, Any]) -> str:
    return f"{100 * stats['terminal_fraction']:.2f} %"


def read_report(path: Path) -> dict[str, Any]:
    writer = {
        "report.json": "python bench/evidence.py report",
        "quality.json": "python bench/evidence.py sweep <task> [--learner L] --report-only",
    }.get(path.name, "hipode verify")
    if not path.is_file():
        raise TableError(f"{path} is missing; `{writer}` writes it")
    try:
        return json.loads(path.read_text())
    except ValueError as error:
        raise TableError(f"{path}: expected JSON from `{writer}`, : {error}") from None


KINDS: dict[str, Callable[..., list[str]]] = {
    "groups": group_rows,
    "comparisons": comparison_rows,
    "across": across_rows,
    "scores": score_rows,
}


def report_runs(report: dict[str, Any]) -> set[str]:
    return {run for group in report["groups"] for run in group["runs"]}


@functools.cache
def design_of(runs: frozenset[str], budget: Budget) -> set[str]:
    """Of these run folders, the ones the design reports aggregate."""
    chosen = design_runs(find_runs(sorted(Path(run) for run in runs)), budget)
    return {str(run.path) for run in chosen}


def same_runs(
    report: dict[str, Any], where: Path, name: str, pooled: dict[str, Any], budget: Budget
) -> None:
    """Every report groups the same committed runs (a design report: the design's share of
    them): one written before the last report round would show other numbers than the pooled
    tables beside it."""
    expected = report_runs(pooled)
    if REPORTS[name].design:
        expected = design_of(frozenset(expected), budget)
    if report_runs(report) != expected:
        picked = "the design picks from the" if REPORTS[name].design else "the"
        raise TableError(
            f"{where} holds other runs than {picked} pooled report; run `python "
            f"bench/evidence.py report {REPORTS[name].flags}` again"
        )


def table_rows(
    kind: str,
    params: dict[str, str],
    reports: Path,
    runs: Path,
    budget: Budget,
    read: ReportReader = read_report,
) -> list[str]:
    """The rows a marker asks for (TableError on a marker that names nothing or no rows)."""
    if kind not in KEYS:
        raise TableError(f"expected a kind in {sorted(KEYS)}, found {kind!r}")
    required, optional = KEYS[kind]
    if not required <= set(params) <= required | optional:
        raise TableError(
            f"{kind}: expected keys {sorted(required)} (optional: {sorted(optional)}), "
            f"found {sorted(params)}"
        )
    name = params.get("report", "pooled")
    if name not in REPORTS:
        raise TableError(f"report: expected one of {sorted(REPORTS)}, found {name!r}")
    where, pooled = reports / REPORTS[name].path, reports / REPORTS["pooled"].path
    try:
        if kind == "runs":
            rows = run_rows(runs, pooled, read, params, budget)
        elif kind == "authenticity":
            rows = authenticity_rows(runs, read, params)
        else:
            report = read(where)
            same_runs(report, where, name, read(pooled), budget)
            rows = KINDS[kind](report, name, params)
    except (KeyError, TypeError, IndexError, ZeroDivisionError) as error:
        read_from = {"runs": runs, "authenticity": runs / params.get("folder", "")}
        raise TableError(f"{read_from.get(kind, where)}: unexpected content ({error!r})") from None
    if not rows:
        raise TableError(f"no rows for {kind} {params}")
    return rows


def regenerate(
    text: str, doc: Path, reports: Path, runs: Path, budget: Budget
) -> tuple[str, list[tuple[str, list[str], list[str]]]]:
    """The document with every marked table's rows regenerated, and for each table that
    changed: 'doc:line marker', its old rows and its new rows."""
    lines = text.split("\n")
    changed = []
    read = functools.cache(read_report)  # each report once, however many tables quote it
    index = 0
    while index < len(lines):
        match = MARKER.fullmatch(lines[index].strip())
        if not match:
            if lines[index].strip().startswith("<!-- evidence-rows:"):
                raise TableError(f"{doc}:{index + 1}: malformed marker {lines[index].strip()!r}")
            index += 1
            continue
        where = f"{doc}:{index + 1}"
        header, separator = index + 1, index + 2
        if (
            separator >= len(lines)
            or not lines[header].startswith("|")
            or not SEPARATOR.fullmatch(lines[separator].strip())
        ):
            raise TableError(
                f"{where}: expected a table header and a |---| separator on the two lines "
                "right below the marker"
            )
        params = dict(part.split("=", 1) for part in match["params"].split())
        try:
            rows = table_rows(match["kind"], params, reports, runs, budget, read)
        except TableError as error:
            raise TableError(f"{where}: {error}") from None
        start = end = separator + 1
        while end < len(lines) and lines[end].startswith("|"):
            end += 1
        if lines[start:end] != rows:
            changed.append((f"{where} {lines[index].strip()}", lines[start:end], rows))
            lines[start:end] = rows
        index = start + len(rows)
    return "\n".join(lines), changed
