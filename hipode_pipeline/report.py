"""`hipode report`: runs aggregated across seeds, the way the field reports them.

Per group of runs (default: same task, learner and data), three per-run measures: the last
evaluation's score, the mean of the last k evaluations, and the curve mean (over all
evaluations, a learning-speed measure). Across the group's seeds: the interquartile mean (IQM)
and the mean, each with a stratified bootstrap 95 % confidence interval (rliable; with one task
per group the bootstrap resamples seeds; a group spanning several source datasets resamples
each source's runs within it, the sources being strata throughout). Against a baseline arm
(`--compare data=source`): the probability of improvement P(X > Y) over runs on the same
source (and stage-one seed, against a baseline whose runs have one), with its bootstrap CI
(rliable's where the runs share one such stratum), and the paired difference of the per-seed
measure, over the seeds both arms ran, with a bootstrap CI.
Learning curves: the mean score over seeds per evaluation step, with a bootstrap 95 % CI of
that mean.

A run is one replicate: (source dataset, stage-one seed of its artifact, training seed). Arms
whose artifacts were built with several stage-one seeds pool them (group by `augmentation`:
none, hipode or model-rollouts, instead of by artifact); their paired differences pair each run
with the baseline's run of the same source and training seed, and the bootstrap resamples
training seeds and stage-one seeds independently (crossed), so the interval covers both sources
of variance. A group holds runs of one budget (`steps`). With `task` among the keys,
comparisons are also aggregated over tasks: the mean over tasks of each task's mean paired
difference and of each task's P(improvement), bootstrapped within each task (stratified); and
each arm's scores are aggregated over tasks as rliable does (IQM and mean of every run on every
task, each task weighing the same). One run, or one pair, has no spread to
resample: such a statistic is reported without an interval, and so is a group statistic, a
P(improvement) or a paired difference where any source holds a single run or pair, and a mean
over tasks where any task lacks one.

Run folders are read only (`scores.json`, a finished run's record); scores are D4RL-normalized
on whatever data the runs used (here: Gymnasium v5 datasets built locally, scored with D4RL's
reference returns).
"""

from __future__ import annotations

import csv
import io
import json
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from hipode_pipeline.errors import DataFormatError, MissingExtraError, SettingError
from hipode_pipeline.files import save_figure_atomic, write_text_atomic

MEASURES = ("last", "last_k_mean", "curve_mean")
MEASURE_TEXT = {
    "last": "last evaluation",
    "last_k_mean": "mean of the last {k} evaluations",
    "curve_mean": "mean over all evaluations",
}
DEFAULT_BY = ("task", "learner", "data")
# what the runs summary says of a run whose scores.json predates the field
NOT_RECORDED = "not recorded"
# a bootstrap over one value returns that value as both bounds: no interval at all
MIN_FOR_INTERVAL = 2
NO_INTERVAL = "no interval"
LONG_COMMAND = 200  # characters of a command report.md shows
OUTPUTS = (
    "report.json",
    "report.md",
    "report.csv",
    "report.tex",
    "curves.png",
    "differences.png",
)


@dataclass(frozen=True)
class Run:
    """One finished run as its scores.json tells it."""

    path: Path
    keys: dict[str, Any]  # task, learner, data, eta, mixing, seed, artifact_seed, ...
    steps: list[int]  # evaluation steps
    scores: list[float]  # D4RL-normalized score mean at each evaluation
    # where, when and under what load its last session finished; None where not recorded
    cpu: str | None = None
    finished_utc: datetime | None = None
    load_1min: float | None = None

    @property
    def seed(self) -> int:
        return int(self.keys["seed"])

    @property
    def artifact_seed(self) -> Any:
        """The stage-one seed of the run's artifact; None for a run on the source alone."""
        return self.keys["artifact_seed"]

    @property
    def replicate(self) -> tuple[Any, Any, int]:
        """What tells the runs of one arm apart: source, stage-one seed, training seed."""
        return (self.keys.get("source_sha256"), self.artifact_seed, self.seed)

    def measure(self, name: str, k: int) -> float:
        values = np.asarray(self.scores, dtype=np.float64)
        if name == "last":
            return float(values[-1])
        if name == "last_k_mean":
            return float(values[-k:].mean())
        return float(values.mean())


@dataclass
class Group:
    key: dict[str, Any]
    runs: list[Run] = field(default_factory=list)

    @property
    def label(self) -> str:
        return key_label(self.key.items())


def key_label(pairs: Any) -> str:
    """A group key as the tables name it: 'task=hopper-m-r learner=td3bc …'."""
    return " ".join(f"{k}={_shown(v)}" for k, v in pairs)


def without_task(items: list[Any], key_of: Any) -> dict[tuple, list[Any]]:
    """`items` by their key without the task, in first-seen order: what a mean over tasks
    aggregates."""
    merged: dict[tuple, list[Any]] = {}
    for item in items:
        key = tuple((name, value) for name, value in key_of(item).items() if name != "task")
        merged.setdefault(key, []).append(item)
    return merged


def _shown(value: Any) -> str:
    """A group key's value as tables print it; None (e.g. no stage-one seed) as '-'."""
    return "-" if value is None else str(value)


def find_runs(paths: Sequence[Path]) -> list[Run]:
    """Every run folder (a folder with scores.json) at or below `paths`, in path order."""
    folders: list[Path] = []
    for path in paths:
        path = Path(path)
        if not path.exists():
            raise DataFormatError(path, "(path)", "a run folder or a folder holding run folders")
        if (path / "scores.json").is_file():
            folders.append(path)
        else:
            folders += sorted(p.parent for p in path.rglob("scores.json"))
    if not folders:
        raise DataFormatError(
            paths[0], "scores.json", "at least one finished run (a folder with scores.json)"
        )
    return [read_run(folder) for folder in dict.fromkeys(folders)]


def read_run(folder: Path) -> Run:
    path = folder / "scores.json"
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise DataFormatError(
            path, "(file)", "a JSON object (a finished run's scores)", error
        ) from None
    if not isinstance(data, dict):
        raise DataFormatError(path, "(file)", "a JSON object", type(data).__name__)
    evaluations = data.get("evaluations")
    if not isinstance(evaluations, list) or not evaluations:
        raise DataFormatError(path, "evaluations", "a non-empty list of evaluations")
    steps, scores = [], []
    for index, evaluation in enumerate(evaluations):
        score = evaluation.get("score_mean") if isinstance(evaluation, dict) else None
        step = evaluation.get("step") if isinstance(evaluation, dict) else None
        if not isinstance(score, int | float) or isinstance(score, bool) or not np.isfinite(score):
            raise DataFormatError(
                path, f"evaluations[{index}].score_mean", "a finite normalized score", score
            )
        if not isinstance(step, int) or isinstance(step, bool):
            raise DataFormatError(path, f"evaluations[{index}].step", "an integer", step)
        steps.append(step)
        scores.append(float(score))
    if not isinstance(data.get("seed"), int):
        raise DataFormatError(
            path, "seed", "an integer (the run's training seed)", data.get("seed")
        )
    identity = data.get("data_identity") if isinstance(data.get("data_identity"), dict) else {}
    keys = {
        **{k: v for k, v in identity.items() if isinstance(v, str | int | float | bool)},
        **{k: v for k, v in data.items() if isinstance(v, str | int | float | bool)},
    }
    keys["augmentation"] = augmentation(keys.get("data"), identity)
    # a run on the source alone has no stage-one seed: None, so it can still be grouped by it
    keys["artifact_seed"] = None if keys.get("data") == "source" else keys.get("artifact_seed")
    return Run(folder, keys, steps, scores, *finish_record(path, data))


def finish_record(
    path: Path, data: dict[str, Any]
) -> tuple[str | None, datetime | None, float | None]:
    """The CPU, the finish time (UTC) and the 1-minute load average that scores.json records of
    the run's last session; each None where it records none (runs written before it did)."""
    cpu, finished, load = data.get("cpu"), data.get("finished_utc"), data.get("load_average")
    if cpu is not None and not isinstance(cpu, str):
        raise DataFormatError(path, "cpu", "the CPU's name (text)", cpu)
    finished_utc = None
    if finished is not None:
        try:
            finished_utc = datetime.fromisoformat(finished)
        except (TypeError, ValueError):
            finished_utc = None
        # a time without its offset cannot be placed among the others
        if finished_utc is None or finished_utc.tzinfo is None:
            raise DataFormatError(
                path, "finished_utc", "an ISO 8601 time with its UTC offset", finished
            )
    load_1min = load[0] if isinstance(load, list) and load else None
    if load is not None and (
        not isinstance(load_1min, int | float)
        or isinstance(load_1min, bool)
        or not np.isfinite(load_1min)
        or load_1min < 0
    ):
        raise DataFormatError(
            path, "load_average", "the 1, 5 and 15-minute load averages (numbers)", load
        )
    return (
        # platform may know no CPU name at all: an empty one says nothing
        None if cpu is None else (cpu.strip() or None),
        None if finished_utc is None else finished_utc.astimezone(UTC),
        None if load_1min is None else float(load_1min),
    )


def runs_summary(runs: Sequence[Run]) -> dict[str, Any]:
    """On which CPUs, when and under what load the runs were trained, as they record it: runs
    of other CPUs can round differently, and a loaded machine trains slower."""
    finished = sorted(run.finished_utc for run in runs if run.finished_utc is not None)
    loads = [run.load_1min for run in runs if run.load_1min is not None]
    return {
        "n_runs": len(runs),
        "cpus": dict(Counter(run.cpu or NOT_RECORDED for run in runs).most_common()),
        "finished_utc": {
            "earliest": finished[0].isoformat() if finished else None,
            "latest": finished[-1].isoformat() if finished else None,
            "not_recorded": len(runs) - len(finished),
        },
        "load_average_1min": {
            "min": min(loads) if loads else None,
            "max": max(loads) if loads else None,
            "not_recorded": len(runs) - len(loads),
        },
    }


def augmentation(data: Any, identity: dict[str, Any]) -> str:
    """Where a run's synthetic rows came from: none (the source alone), else the artifact's
    method (hipode, model-rollouts); artifacts written before methods were recorded are HIPODE's,
    and an artifact with no hyper-parameters at all is unknown."""
    if data == "source":
        return "none"
    hyper = identity.get("artifact_hyper_parameters")
    if not isinstance(hyper, dict):
        return "unknown"
    return str(hyper.get("method", "hipode"))


def parse_by(text: str) -> tuple[str, ...]:
    keys = tuple(k.strip() for k in text.split(",") if k.strip())
    if not keys or "seed" in keys:
        raise SettingError(
            f"--by {text!r}: expected run keys to group by (not seed), e.g. task,data"
        )
    return keys


def parse_compare(text: str | None) -> tuple[str, Any] | None:
    """'data=source' -> ('data', 'source'): the baseline arm each other arm is compared with."""
    if text is None:
        return None
    key, sep, value = text.partition("=")
    if not sep or not key.strip() or not value.strip():
        raise SettingError(f"--compare {text!r}: expected KEY=VALUE, e.g. data=source")
    return key.strip(), value.strip()


def group_runs(runs: list[Run], by: tuple[str, ...]) -> list[Group]:
    groups: dict[tuple, Group] = {}
    for run in runs:
        missing = [k for k in by if k not in run.keys]
        if missing:
            raise DataFormatError(
                run.path / "scores.json", missing[0], f"a value for --by key '{missing[0]}'"
            )
        key = {k: run.keys[k] for k in by}
        group = groups.setdefault(tuple(key.values()), Group(key))
        if run.replicate in {r.replicate for r in group.runs}:
            raise DataFormatError(
                run.path,
                "seed",
                f"one run per seed (per source and stage-one seed) in group {group.label} "
                f"(another folder has seed {run.seed}, stage-one seed {run.artifact_seed}); "
                "group by more keys (--by) or pass fewer folders",
            )
        group.runs.append(run)
    for group in groups.values():
        group.runs.sort(key=lambda r: (r.seed, str(r.artifact_seed), str(r.replicate[0])))
        # runs of different budgets are different experiments: pooling them would blur both
        first, *rest = group.runs
        other = next((r for r in rest if r.keys.get("steps") != first.keys.get("steps")), None)
        if other is not None:
            raise DataFormatError(
                other.path / "scores.json",
                "steps",
                f"{first.keys.get('steps')} updates, the budget of {first.path} in group "
                f"{group.label} (one budget per group): group by steps too (--by) or pass "
                "fewer folders",
                other.keys.get("steps"),
            )
    return list(groups.values())


def _rliable():
    """rliable's metrics (IQM, probability of improvement), or a clear error without the extra."""
    try:
        from rliable import metrics
    except ImportError:
        raise MissingExtraError(
            "hipode report needs rliable: install the optional extra: pip install -e '.[report]'"
        ) from None
    return metrics


def rliable_resamples(sizes: Sequence[int], reps: int, seed: int) -> list[np.ndarray]:
    """The run indices of rliable's stratified bootstrap (get_interval_estimates, one task),
    `reps` x n per array of n runs, drawn as it draws them: one `np.random.choice` per array
    and resample from numpy's global stream. That stream is seeded per call and the caller's
    given back, so an interval depends on its own scores, reps and seed only. The statistics are
    then computed on all resamples at once instead of one Python call per resample."""
    caller_state = np.random.get_state()
    np.random.seed(seed)
    try:
        if len(set(sizes)) == 1:
            # one bound: the same draws, in the same order, as one call (choice is randint here)
            drawn = np.random.randint(0, sizes[0], size=(reps, sum(sizes)))
            return np.split(drawn, np.cumsum(sizes)[:-1], axis=1)
        picks = [np.empty((reps, n), dtype=np.int64) for n in sizes]
        for rep in range(reps):
            for picked, n in zip(picks, sizes, strict=True):
                picked[rep] = np.random.choice(n, n, replace=True)
        return picks
    finally:
        np.random.set_state(caller_state)


def bounds95(samples: np.ndarray) -> list[float]:
    """`percentile_interval` of one statistic's bootstrap `samples`, as [low, high]."""
    return [float(bound) for bound in percentile_interval(np.reshape(samples, (-1, 1)))[:, 0]]


def percentile_interval(samples: np.ndarray) -> np.ndarray:
    """2 x k: each column's 2.5th and 97.5th percentile of `samples` (reps x k), the percentile
    method rliable asks arch for."""
    return np.array([np.percentile(column, [2.5, 97.5]) for column in samples.T]).T


def iqm_and_mean(resampled: np.ndarray) -> np.ndarray:
    """reps x 2: each resample's (row's) IQM (rliable's 25 % trimmed mean) and mean."""
    from scipy.stats import trim_mean

    return np.stack([trim_mean(resampled, 0.25, axis=1), resampled.mean(axis=1)], axis=1)


def wins(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(..., n, m): 1 where x beats y, one half for a tie (the U statistic's counting)."""
    above, tied = x[..., :, None] > y[..., None, :], x[..., :, None] == y[..., None, :]
    return above + 0.5 * tied


def within_strata(strata: Sequence[Any], reps: int, rng: np.random.Generator) -> np.ndarray:
    """`reps` resamples of the indices 0..n-1, each drawing every stratum's members from that
    stratum only (reps x n); one stratum is a plain bootstrap of the n indices."""
    labels = list(strata)
    picks = np.empty((reps, len(labels)), dtype=np.int64)
    for stratum in dict.fromkeys(labels):
        members = np.array([i for i, label in enumerate(labels) if label == stratum])
        picks[:, members] = members[rng.integers(len(members), size=(reps, len(members)))]
    return picks


def has_spread(strata: Sequence[Any]) -> bool:
    """Whether a bootstrap within these strata (each run's source) can move: every stratum
    holds at least two runs, else a lone run enters every resample unchanged."""
    return bool(strata) and min(Counter(strata).values()) >= MIN_FOR_INTERVAL


def interval_estimates(
    values: np.ndarray, reps: int, seed: int, strata: Sequence[Any] | None = None
) -> dict[str, Any]:
    """IQM and mean of per-run `values` with bootstrap 95 % CIs: rliable's resamples over the
    runs of one source; where `strata` (each run's source) name several, our own percentile
    bootstrap that resamples each source's runs within it. No interval where a source holds a
    single run."""
    metrics = _rliable()
    scores = np.asarray(values, dtype=np.float64).reshape(-1, 1)
    strata = [None] * len(scores) if strata is None else list(strata)
    if len(strata) != len(scores):
        raise ValueError(f"expected one stratum per value, found {len(strata)} for {len(scores)}")

    def aggregates(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x), metrics.aggregate_mean(x)])

    point, interval = aggregates(scores), None
    if has_spread(strata):
        if len(set(strata)) == 1:
            (picks,) = rliable_resamples([len(scores)], reps, seed)
        else:
            picks = within_strata(strata, reps, np.random.default_rng(seed))
        interval = percentile_interval(iqm_and_mean(scores[:, 0][picks]))
    return {
        "iqm": float(point[0]),
        "iqm_ci": None if interval is None else [float(interval[0, 0]), float(interval[1, 0])],
        "mean": float(point[1]),
        "mean_ci": None if interval is None else [float(interval[0, 1]), float(interval[1, 1])],
        "std": float(scores.std(ddof=1)) if len(scores) > 1 else None,
        "n": int(len(scores)),
    }


def improvement(x: np.ndarray, y: np.ndarray, reps: int, seed: int) -> dict[str, Any]:
    """P(X > Y) over the two arms' seeds with its bootstrap CI (rliable); no CI where an arm
    has a single run."""
    metrics = _rliable()
    pair = (np.reshape(x, (-1, 1)), np.reshape(y, (-1, 1)))
    if min(len(pair[0]), len(pair[1])) < MIN_FOR_INTERVAL:
        point = metrics.probability_of_improvement(*pair)
        return {"probability": float(point), "ci": None, "_samples": None}
    point = metrics.probability_of_improvement(*pair)
    picks_x, picks_y = rliable_resamples([len(x), len(y)], reps, seed)
    samples = wins(np.ravel(x)[picks_x], np.ravel(y)[picks_y]).mean(axis=(1, 2))
    # the resamples stay for the mean over tasks; not written
    return {"probability": float(point), "ci": bounds95(samples), "_samples": samples}


def improvement_within_sources(
    mine: list[Run], theirs: list[Run], name: str, k: int, reps: int, seed: int
) -> dict[str, Any] | None:
    """P(a run of the arm scores above a run of the baseline on the same source), ties counting
    one half: over every (arm run, baseline run) couple that shares a source, so runs on
    different datasets are never compared; where the baseline's runs have stage-one seeds (plain
    model rollouts), couples share the stage-one seed too, as the paired differences do. One
    shared stratum: rliable's, as `improvement`. Several: each arm's runs resampled within each
    stratum; no interval where a stratum has a single run on either side. None where the arms
    share no stratum."""
    by_artifact = any(run.artifact_seed is not None for run in theirs)
    strata: dict[Any, tuple[list[float], list[float]]] = {}
    for runs, side in ((mine, 0), (theirs, 1)):
        for run in runs:
            source, artifact_seed, _ = run.replicate
            stratum = (source, artifact_seed) if by_artifact else (source, None)
            strata.setdefault(stratum, ([], []))[side].append(run.measure(name, k))
    kept = [stratum for stratum, (x, y) in strata.items() if x and y]
    if not kept:
        return None
    sources = len({source for source, _ in kept})
    shared = [tuple(np.array(values) for values in strata[stratum]) for stratum in kept]
    if len(shared) == 1:
        return {**improvement(*shared[0], reps, seed), "sources": sources}
    couples = sum(len(x) * len(y) for x, y in shared)
    per_stratum = [wins(x, y) for x, y in shared]
    point = sum(w.sum() for w in per_stratum) / couples
    if min(min(len(x), len(y)) for x, y in shared) < MIN_FOR_INTERVAL:
        return {"probability": float(point), "ci": None, "sources": sources, "_samples": None}
    rng = np.random.default_rng(seed)
    total = np.zeros(reps)
    for w in per_stratum:
        rows = rng.integers(w.shape[0], size=(reps, w.shape[0]))
        columns = rng.integers(w.shape[1], size=(reps, w.shape[1]))
        total += w[rows[:, :, None], columns[:, None, :]].sum(axis=(1, 2))
    samples = total / couples
    return {
        "probability": float(point),
        "ci": bounds95(samples),
        "sources": sources,
        "_samples": samples,
    }


def paired_cells(mine: list[Run], theirs: list[Run], name: str, k: int) -> dict[tuple, float]:
    """arm - baseline per replicate of the arm: each run minus the baseline's run of the same
    source and training seed (and the same stage-one seed where the baseline has them too)."""
    base = {r.replicate: r.measure(name, k) for r in theirs}
    cells = {}
    for run in mine:
        source, artifact_seed, seed = run.replicate
        for key in ((source, artifact_seed, seed), (source, None, seed)):
            if key in base:
                cells[run.replicate] = run.measure(name, k) - base[key]
                break
    return cells


def crossed_bootstrap(cells: dict[tuple, float], reps: int, seed: int) -> np.ndarray:
    """`reps` bootstrap means of `cells` ((source, stage-one seed, training seed) -> value):
    within each source, training seeds and stage-one seeds are resampled independently and the
    cells of the resampled grid averaged; sources are strata, kept as they are."""
    rng = np.random.default_rng(seed)
    total, count = np.zeros(reps), np.zeros(reps)
    for source in sorted({key[0] for key in cells}, key=str):
        keys = [key for key in cells if key[0] == source]
        artifact_seeds = sorted({key[1] for key in keys}, key=str)
        seeds = sorted({key[2] for key in keys})
        grid = np.full((len(artifact_seeds), len(seeds)), np.nan)
        for key in keys:
            grid[artifact_seeds.index(key[1]), seeds.index(key[2])] = cells[key]
        rows = rng.integers(len(artifact_seeds), size=(reps, len(artifact_seeds)))
        columns = rng.integers(len(seeds), size=(reps, len(seeds)))
        picked = grid[rows[:, :, None], columns[:, None, :]]  # reps x stage-one x training
        total += np.nansum(picked, axis=(1, 2))
        count += np.sum(~np.isnan(picked), axis=(1, 2))
    # a resample can miss every filled cell of an incomplete grid; it then says nothing
    return total[count > 0] / count[count > 0]


def paired_difference(cells: dict[tuple, float], reps: int, seed: int) -> dict[str, Any] | None:
    """Mean over the paired replicates of arm - baseline, with a crossed bootstrap 95 % CI
    (none where a source holds a single pair: the strata are kept, so that pair would enter
    every resample unchanged and the interval would leave out its source's spread)."""
    if not cells:
        return None
    diffs = np.array(list(cells.values()))
    resamplable = has_spread([key[0] for key in cells])
    means = crossed_bootstrap(cells, reps, seed) if resamplable else None
    return {
        "mean": float(diffs.mean()),
        "ci": None if means is None else bounds95(means),
        "seeds": sorted({key[2] for key in cells}),
        "artifact_seeds": sorted({key[1] for key in cells if key[1] is not None}),
        "pairs": len(cells),
        "sem": float(diffs.std(ddof=1) / np.sqrt(len(diffs))) if len(diffs) > 1 else None,
        "_means": means,  # the bootstrap means, for the aggregate over tasks; not written
    }


def aggregate_over_tasks(
    comparisons: list[dict[str, Any]], by: tuple[str, ...], seed: int = 0
) -> list[dict]:
    """Per arm key without the task: the mean over tasks of each task's mean paired difference,
    with a 95 % CI from the tasks' bootstraps combined resample by resample (stratified by task);
    no CI where a task has none."""
    if "task" not in by:
        return []
    rows = []
    for key, entries in without_task(comparisons, lambda entry: entry["key"]).items():
        row: dict[str, Any] = {
            "arm": key_label(key),
            "key": dict(key),
            "tasks": [entry["key"]["task"] for entry in entries],
            "measures": {},
        }
        for name in MEASURES:
            diffs = [entry["measures"][name]["paired_difference"] for entry in entries]
            if any(d is None for d in diffs):
                continue
            chances = [entry["measures"][name]["probability_of_improvement"] for entry in entries]
            row["measures"][name] = {
                **mean_over_tasks(diffs, "mean", "_means", seed),
                "pairs": int(sum(d["pairs"] for d in diffs)),
                # rliable's P(improvement) over several tasks: the mean of the tasks' own
                "probability_of_improvement": None
                if any(p is None for p in chances)
                else mean_over_tasks(chances, "probability", "_samples", seed),
            }
        if row["measures"]:  # an arm with no pair on some task has no mean over the tasks
            rows.append(row)
    return rows


def weighted_iqm(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Interquartile mean of each row of `values` (... x n), run i weighing `weights[i]` (they
    sum to 1): the mean over the middle half of the weight, a run straddling a quartile counting
    in part. With equal weights and n a multiple of 4 it is rliable's IQM."""
    order = np.argsort(values, axis=-1)
    ordered, weight = np.take_along_axis(values, order, axis=-1), weights[order]
    upper = np.cumsum(weight, axis=-1)
    share = np.clip(np.minimum(upper, 0.75) - np.maximum(upper - weight, 0.25), 0.0, None)
    return (ordered * share).sum(axis=-1) / 0.5


def scores_over_tasks(
    groups: list[Group], by: tuple[str, ...], k: int, reps: int, seed: int
) -> list[dict[str, Any]]:
    """Per arm key without the task, rliable's aggregate over tasks of the runs' scores: the IQM
    and the mean of every run of the arm on every task, each task weighing the same (a run 1 /
    (tasks x its task's runs)), with 95 % CIs from a bootstrap that resamples each source's runs
    within it (sources as strata, so tasks too); no CI where a source holds a single run."""
    if "task" not in by:
        return []
    rows = []
    for key, members in without_task(groups, lambda group: group.key).items():
        if len(members) < 2:
            continue  # one task: its group's own row says it
        runs = [run for group in members for run in group.runs]
        weights = np.concatenate(
            [np.full(len(g.runs), 1.0 / (len(members) * len(g.runs))) for g in members]
        )
        # a run without a recorded source must still be resampled within its own task
        strata = [(g.key["task"], run.replicate[0]) for g in members for run in g.runs]
        picks = (
            within_strata(strata, reps, np.random.default_rng(seed)) if has_spread(strata) else None
        )
        row: dict[str, Any] = {
            "arm": key_label(key),
            "key": dict(key),
            "tasks": [group.key["task"] for group in members],
            "steps": sorted({run.keys.get("steps") for run in runs}, key=str),
            "n_runs": len(runs),
            "sources": len(set(strata)),
            "measures": {},
        }
        for name in MEASURES:
            values = np.array([run.measure(name, k) for run in runs])
            measure: dict[str, Any] = {
                "iqm": float(weighted_iqm(values, weights)),
                "mean": float(values @ weights),
                "iqm_ci": None,
                "mean_ci": None,
            }
            if picks is not None:
                resampled = values[picks]
                measure["iqm_ci"] = bounds95(weighted_iqm(resampled, weights))
                measure["mean_ci"] = bounds95(resampled @ weights)
            row["measures"][name] = measure
        rows.append(row)
    return rows


def mean_over_tasks(
    per_task: list[dict[str, Any]], point: str, samples: str, seed: int = 0
) -> dict[str, Any]:
    """The mean over tasks of each task's `point` statistic, with a 95 % CI from the tasks'
    bootstrap `samples` averaged resample by resample (stratified by task); no CI where a task
    has none."""
    ci = None
    if all(task[samples] is not None for task in per_task):
        # a crossed bootstrap may keep fewer resamples than asked (one missed every cell)
        size = min(len(task[samples]) for task in per_task)
        # each task's bootstrap drew from the same seed: tasks of one size drew the same indices,
        # so each task's resamples are shuffled apart to make the strata independent
        shuffled = [
            np.random.default_rng([seed, index]).permutation(task[samples])[:size]
            for index, task in enumerate(per_task)
        ]
        ci = bounds95(np.mean(shuffled, axis=0))
    return {point: float(np.mean([task[point] for task in per_task])), "ci": ci}


def baseline_of(group: Group, baselines: list[Group], keys: list[str]) -> Group | None:
    """The baseline group with the same `keys` as `group`; failing that, the one that matches
    where it has a value: the source alone has no stage-one seed, so grouping the arms by
    artifact_seed pairs each of them with the one baseline."""
    for exact in (True, False):
        for base in baselines:
            if all(
                base.key[k] == group.key[k] or (not exact and base.key[k] is None) for k in keys
            ):
                return base
    return None


def says_something(entry: dict[str, Any]) -> bool:
    """Whether a comparison holds any P(improvement) or paired difference."""
    return any(value is not None for m in entry["measures"].values() for value in m.values())


def _without_samples(entries: list[dict[str, Any]]) -> None:
    for entry in entries:
        for measure in entry["measures"].values():
            if measure.get("paired_difference"):
                measure["paired_difference"].pop("_means", None)
            if measure.get("probability_of_improvement"):
                measure["probability_of_improvement"].pop("_samples", None)


def build_report(
    runs: list[Run],
    *,
    by: tuple[str, ...] = DEFAULT_BY,
    compare: tuple[str, Any] | None = None,
    k: int = 3,
    reps: int = 5000,
    seed: int = 0,
) -> dict[str, Any]:
    """Everything the report files hold, as one JSON-ready dict."""
    if k < 1 or reps < 100:
        raise SettingError(f"expected --last-k >= 1 and --reps >= 100, found {k} and {reps}")
    groups = group_runs(runs, by)
    if compare is not None and compare[0] not in by:
        raise SettingError(f"--compare {compare[0]}=…: expected one of the --by keys {list(by)}")
    rows = []
    for group in groups:
        row: dict[str, Any] = {
            **group.key,
            "seeds": sorted({r.seed for r in group.runs}),
            "artifact_seeds": sorted(
                {r.artifact_seed for r in group.runs if r.artifact_seed is not None}, key=str
            ),
            "sources": len({r.replicate[0] for r in group.runs}),
            "n_runs": len(group.runs),
            "measures": {},
        }
        sources = [r.replicate[0] for r in group.runs]
        for name in MEASURES:
            values = np.array([r.measure(name, k) for r in group.runs])
            row["measures"][name] = interval_estimates(values, reps, seed, sources)
        row["curve"] = mean_curve(group.runs, reps, seed)
        row["runs"] = [str(r.path) for r in group.runs]
        rows.append(row)
    comparisons = []
    if compare is not None:
        key, value = compare
        baselines = [g for g in groups if str(g.key[key]) == value]
        if not baselines:
            raise SettingError(f"--compare {key}={value}: no group has {key} = {value!r}")
        for group in groups:
            if str(group.key[key]) == value:
                continue
            base = baseline_of(group, baselines, [k2 for k2 in by if k2 != key])
            if base is None:
                continue
            entry: dict[str, Any] = {
                "arm": group.label,
                "baseline": base.label,
                "key": group.key,
                "measures": {},
            }
            for name in MEASURES:
                cells = paired_cells(group.runs, base.runs, name, k)
                entry["measures"][name] = {
                    "probability_of_improvement": improvement_within_sources(
                        group.runs, base.runs, name, k, reps, seed
                    ),
                    "paired_difference": paired_difference(cells, reps, seed),
                }
            comparisons.append(entry)
    across_tasks = aggregate_over_tasks(comparisons, by, seed)
    scores_across_tasks = scores_over_tasks(groups, by, k, reps, seed)
    # an arm that shares no source (or stage-one seed) with its baseline says nothing; left out
    # after the mean over tasks, which must not average over fewer tasks because of it
    comparisons = [entry for entry in comparisons if says_something(entry)]
    _without_samples(comparisons)
    return {
        "by": list(by),
        "compare": None if compare is None else f"{compare[0]}={compare[1]}",
        "last_k": k,
        "bootstrap": {"reps": reps, "seed": seed, "confidence": 0.95},
        "runs": runs_summary(runs),
        "definitions": {
            **{name: text.format(k=k) for name, text in MEASURE_TEXT.items()},
            "run": "one replicate: (source dataset, stage-one seed of the artifact, training "
            "seed); an arm pooling several stage-one seeds has one run per pair of seeds",
            "iqm": "interquartile mean over runs (rliable aggregate_iqm)",
            "ci": "bootstrap 95 % CI over runs: rliable's get_interval_estimates (its resamples "
            "and percentile intervals, computed at once) for runs of "
            "one source; for several, a percentile bootstrap resampling each source's runs "
            "within it",
            "probability_of_improvement": "P(a run of the arm scores above a run of the "
            "baseline on the same source, and of the same stage-one seed where the baseline's "
            "runs have one), ties counting one half; one such stratum: rliable's, with its "
            "bootstrap CI; several: runs resampled within each",
            "paired_difference": "mean over the arm's runs of run - the baseline's run of the "
            "same source and training seed; 95 % CI from a crossed bootstrap (training seeds "
            "and stage-one seeds resampled independently, sources as strata)",
            "across_tasks": "mean over tasks of each task's mean paired difference, and of "
            "each task's P(improvement) (rliable's aggregate over tasks); 95 % CIs from the "
            "tasks' bootstraps averaged resample by resample (stratified by task)",
            "scores_across_tasks": "per arm, the IQM and the mean of its runs' scores on every "
            "task, each task weighing the same (rliable's aggregate over tasks where every task "
            "has as many runs and their total is a multiple of 4; otherwise a run straddling a "
            "quartile counts in part); 95 % CIs resampling each source's runs within it",
            "scores": "D4RL-normalized returns on the runs' data (locally built Gymnasium v5 "
            "datasets scored with D4RL's reference returns, unless the runs say otherwise)",
        },
        "groups": rows,
        "comparisons": comparisons,
        "across_tasks": across_tasks,
        "scores_across_tasks": scores_across_tasks,
    }


def mean_curve(runs: list[Run], reps: int, seed: int) -> dict[str, Any]:
    """Mean score over seeds at each step every run evaluated, with a bootstrap 95 % CI (runs
    resampled within their source); no band (None) where a source holds a single run."""
    steps = sorted(set.intersection(*(set(r.steps) for r in runs)))
    by_step = [dict(zip(r.steps, r.scores, strict=True)) for r in runs]
    matrix = np.array([[scores[s] for s in steps] for scores in by_step])
    sources = [r.replicate[0] for r in runs]
    curve: dict[str, Any] = {
        "steps": steps,
        "mean": matrix.mean(axis=0).round(4).tolist(),
        "ci_low": None,
        "ci_high": None,
    }
    if has_spread(sources):
        means = matrix[within_strata(sources, reps, np.random.default_rng(seed))].mean(axis=1)
        curve["ci_low"] = np.quantile(means, 0.025, axis=0).round(4).tolist()
        curve["ci_high"] = np.quantile(means, 0.975, axis=0).round(4).tolist()
    return curve


def interval_text(m: dict[str, Any], name: str) -> str:
    """A group measure's statistic with its interval: '35.9 [28.7, 42.4]'; '45.5 (no interval)'
    from one run."""
    if m[f"{name}_ci"] is None:
        return f"{m[name]:.1f} ({NO_INTERVAL})"
    low, high = m[f"{name}_ci"]
    return f"{m[name]:.1f} [{low:.1f}, {high:.1f}]"


def difference_text(d: dict[str, Any] | None) -> str:
    """A (paired or across-task) mean difference with its interval: '-16.2 [-22.9, -9.1]';
    '+2.7 (no interval)' from one pair; '-' where there is none (no pairs)."""
    if d is None:
        return "-"
    if d["ci"] is None:
        return f"{d['mean']:+.1f} ({NO_INTERVAL})"
    return f"{d['mean']:+.1f} [{d['ci'][0]:+.1f}, {d['ci'][1]:+.1f}]"


def probability_text(p: dict[str, Any] | None) -> str:
    """P(improvement) with its interval: '0.02 [0.00, 0.12]'; '1.00 (no interval)' where an arm
    has one run (on some source); '-' where the arms share no source."""
    if p is None:
        return "-"
    if p["ci"] is None:
        return f"{p['probability']:.2f} ({NO_INTERVAL})"
    return f"{p['probability']:.2f} [{p['ci'][0]:.2f}, {p['ci'][1]:.2f}]"


def score_columns(report: dict[str, Any]) -> list[str]:
    """Per measure, the IQM and the mean columns of a table of scores."""
    columns = []
    for name in MEASURES:
        text = report["definitions"][name]
        columns += [f"{text}: IQM [95% CI]", f"{text}: mean [95% CI]"]
    return columns


def score_cells(measures: dict[str, Any]) -> list[str]:
    """Per measure, the IQM and the mean with their intervals."""
    return [interval_text(measures[name], stat) for name in MEASURES for stat in ("iqm", "mean")]


def table_rows(report: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The human table: per group, IQM and mean [95 % CI] of each measure, over n seeds."""
    by = report["by"]
    columns = [*by, "runs (training × stage-one seeds)", *score_columns(report)]
    rows = [
        [_shown(group[k]) for k in by] + [replicates_text(group)] + score_cells(group["measures"])
        for group in report["groups"]
    ]
    return columns, rows


def comparison_rows(report: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    columns = ["arm", "baseline"]
    for name in MEASURES:
        text = report["definitions"][name]
        columns += [f"{text}: P(improvement) [95% CI]", f"{text}: paired diff [95% CI]"]
    rows = []
    for entry in report["comparisons"]:
        row = [entry["arm"], entry["baseline"]]
        for name in MEASURES:
            m = entry["measures"][name]
            row.append(probability_text(m["probability_of_improvement"]))
            d = m["paired_difference"]
            row.append(difference_text(d) + ("" if d is None else f" ({d['pairs']} pairs)"))
        rows.append(row)
    return columns, rows


def scores_across_task_rows(report: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """Each arm's scores aggregated over tasks: IQM and mean [95 % CI] of each measure."""
    columns = ["arm", "tasks", "runs", "sources", *score_columns(report)]
    rows = [
        [entry["arm"], ", ".join(entry["tasks"]), str(entry["n_runs"]), str(entry["sources"])]
        + score_cells(entry["measures"])
        for entry in report.get("scores_across_tasks", [])
    ]
    return columns, rows


def across_task_rows(report: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The aggregate over tasks of each arm's paired difference."""
    columns = ["arm", "tasks"]
    for name in MEASURES:
        text = report["definitions"][name]
        columns += [f"{text}: mean diff [95% CI]", f"{text}: P(improvement) [95% CI]"]
    rows = []
    for entry in report.get("across_tasks", []):
        row = [entry["arm"], ", ".join(entry["tasks"])]
        for name in MEASURES:
            measure = entry["measures"].get(name)
            row.append(difference_text(measure))
            # reports written before the mean over tasks carried P(improvement) lack it
            row.append(probability_text(measure and measure.get("probability_of_improvement")))
        rows.append(row)
    return columns, rows


def replicates_text(group: dict[str, Any]) -> str:
    """How many runs a group holds and what they vary: training seeds, stage-one seeds and
    sources; "of" marks a grid the runs do not fill (its product would overstate them)."""
    grid = [len(group["seeds"])]
    if group["artifact_seeds"]:
        grid.append(len(group["artifact_seeds"]))
    sources = group["sources"]
    text = " × ".join(map(str, grid)) + (f" × {sources} sources" if sources > 1 else "")
    filled = int(np.prod(grid)) * sources == group["n_runs"]
    return f"{group['n_runs']} ({'' if filled else 'of '}{text})"


def runs_text(count: int) -> str:
    return f"{count} run{'' if count == 1 else 's'}"


def provenance_lines(report: dict[str, Any]) -> list[str]:
    """report.md's header: when, by which command and on which code the report was written
    (where the command added that), and on which CPUs, when and under what load the runs were
    trained."""
    lines = []
    written = report.get("written")
    if written:
        versions = written["versions"]
        commit = versions.get("git_commit")
        code = f"commit {commit[:12]}" if commit else "unknown commit (not a git checkout)"
        code += " with local edits" if versions.get("git_modified") else ""
        command = written["command"]
        if len(command) > LONG_COMMAND:  # a list of run folders; report.json keeps it whole
            command = command[:LONG_COMMAND].rsplit(" ", 1)[0] + " … (whole in report.json)"
        lines.append(
            f"- Written {written['utc']} (UTC) by `{command}`; code: {code} "
            f"(hipode-pipeline {versions.get('hipode_pipeline')})."
        )
    summary = report.get("runs")
    if summary:
        cpus = ", ".join(f"{cpu} ({runs_text(n)})" for cpu, n in summary["cpus"].items())
        lines.append(f"- {runs_text(summary['n_runs'])}, trained on CPUs: {cpus}.")
        finished, load = summary["finished_utc"], summary["load_average_1min"]
        lines.append(
            recorded_line(
                f"Finished between {finished['earliest']} and {finished['latest']} (UTC)"
                if finished["earliest"]
                else None,
                "Finish times not recorded",
                finished["not_recorded"],
                "without a finish time",
            )
        )
        lines.append(
            recorded_line(
                f"1-minute load average at their finish: {load['min']:.2f} to {load['max']:.2f}"
                if load["min"] is not None
                else None,
                "Load average at their finish not recorded",
                load["not_recorded"],
                "without one",
            )
        )
    return [*lines, ""] if lines else []


def recorded_line(text: str | None, none_text: str, missing: int, without: str) -> str:
    """A header line of what the runs recorded, naming how many lack it; `none_text` where
    none does."""
    if text is None:
        return f"- {none_text}."
    return f"- {text}" + (f"; {runs_text(missing)} {without}" if missing else "") + "."


def markdown(report: dict[str, Any]) -> str:
    columns, rows = table_rows(report)
    lines = [
        "# Scores across seeds",
        "",
        *provenance_lines(report),
        f"Grouped by {', '.join(report['by'])}. Scores: {report['definitions']['scores']}. "
        f"Intervals: {report['definitions']['ci']} ({report['bootstrap']['reps']} resamples, "
        f"seed {report['bootstrap']['seed']}); they are over seeds, not evaluation episodes. "
        f"A run: {report['definitions']['run']}.",
        "",
        _md_table(columns, rows),
    ]
    definitions = report["definitions"]
    sections = (
        (
            "comparisons",
            comparison_rows,
            f"Against {report['compare']} (paired difference: {definitions['paired_difference']}):",
        ),
        (
            "scores_across_tasks",
            scores_across_task_rows,
            f"Scores across tasks ({definitions['scores_across_tasks']}):",
        ),
        ("across_tasks", across_task_rows, f"Across tasks ({definitions['across_tasks']}):"),
    )
    for key, section_rows, title in sections:
        if report.get(key):
            columns, rows = section_rows(report)
            lines += ["", title, "", _md_table(columns, rows)]
    return "\n".join(lines) + "\n"


def _md_table(columns: list[str], rows: list[list[str]]) -> str:
    return "\n".join(
        ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        + ["| " + " | ".join(row) + " |" for row in rows]
    )


def csv_text(report: dict[str, Any]) -> str:
    out = io.StringIO()
    writer = csv.writer(out)
    by = report["by"]
    writer.writerow(
        [*by, "measure", "n", "iqm", "iqm_low", "iqm_high", "mean", "mean_low", "mean_high"]
    )
    for group in report["groups"]:
        for name in MEASURES:
            m = group["measures"][name]
            writer.writerow(
                [group[k] for k in by]
                + [name, m["n"], m["iqm"], *(m["iqm_ci"] or ["", ""])]
                + [m["mean"], *(m["mean_ci"] or ["", ""])]
            )
    return out.getvalue()


def latex(report: dict[str, Any]) -> str:
    """A booktabs table of the IQM [95 % CI] of each measure per group."""
    by = report["by"]
    header = [*by, *(report["definitions"][m] for m in MEASURES)]
    lines = [
        "\\begin{tabular}{" + "l" * len(by) + "r" * len(MEASURES) + "}",
        "\\toprule",
        " & ".join(_tex(h) for h in header) + " \\\\",
        "\\midrule",
    ]
    for group in report["groups"]:
        cells = [_tex(_shown(group[k])) for k in by]
        for name in MEASURES:
            m = group["measures"][name]
            cells.append(_tex(interval_text(m, "iqm")))
        lines.append(" & ".join(cells) + " \\\\")
    lines += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(lines) + "\n"


def _tex(text: str) -> str:
    for char in "\\&%$#_{}":
        text = text.replace(char, "\\" + char if char != "\\" else "\\textbackslash{}")
    return text


PANEL_KEYS = ("task", "learner")  # scores of different tasks share no scale; learners apart


def curve_panels(report: dict[str, Any]) -> dict[str, list[tuple[str, dict[str, Any]]]]:
    """The groups' curves per panel: one panel per task and per learner where the report groups
    by several of them, each curve named by its other keys (its arm)."""
    split = [
        k for k in PANEL_KEYS if k in report["by"] and len({g[k] for g in report["groups"]}) > 1
    ]
    keys = [k for k in report["by"] if k not in split]
    panels: dict[str, list[tuple[str, dict[str, Any]]]] = {}
    for group in report["groups"]:
        arm = " ".join(_shown(group[k]) for k in keys)
        title = " · ".join(_shown(group[k]) for k in split)
        panels.setdefault(title, []).append((arm, group))
    return panels


def update_count(value: float, _position: int | None = None) -> str:
    """An axis tick of updates, short enough not to crowd: 200000 -> 200k, 1000000 -> 1M."""
    for size, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= size:
            return f"{value / size:g}{suffix}"
    return f"{value:g}"


def plot_curves(report: dict[str, Any], path: Path) -> None:
    """Mean learning curve per group with its bootstrap 95 % CI band, as PNG; a panel per task
    and learner (curve_panels), an arm in the same colour in every panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    panels = curve_panels(report)
    columns = min(3, len(panels))
    rows = -(-len(panels) // columns)
    figure, axes = plt.subplots(
        rows, columns, figsize=(4.8 * columns, 3.9 * rows), dpi=120, squeeze=False
    )
    colors: dict[str, str] = {}
    for axis, (title, curves) in zip(axes.flat, panels.items(), strict=False):
        for arm, group in curves:
            color = colors.setdefault(arm, f"C{len(colors) % 10}")
            curve = group["curve"]
            banded = curve["ci_low"] is not None
            label = f"{arm} ({group['n_runs']} runs{'' if banded else ', no band'})"
            axis.plot(curve["steps"], curve["mean"], color=color, label=label)
            if banded:
                axis.fill_between(
                    curve["steps"], curve["ci_low"], curve["ci_high"], color=color, alpha=0.2
                )
        axis.set_title(title, fontsize=10)
        axis.xaxis.set_major_locator(MaxNLocator(5))
        axis.xaxis.set_major_formatter(FuncFormatter(update_count))
        axis.set_xlabel("updates")
        axis.set_ylabel("D4RL-normalized score")
        axis.legend(fontsize=7)
    for axis in list(axes.flat)[len(panels) :]:
        axis.set_visible(False)
    figure.suptitle("mean over runs; band: bootstrap 95% CI of the mean over runs", fontsize=10)
    figure.tight_layout()
    save_figure_atomic(figure, path)


@dataclass(frozen=True)
class DifferencePoint:
    """One interval of the differences plot: an arm's paired difference on one task, or its
    mean over tasks, for one measure."""

    label: str
    measure: str
    mean: float
    low: float
    high: float
    pairs: int
    across_tasks: bool
    has_interval: bool


def across_key(entry: dict[str, Any]) -> dict[str, str]:
    """An across-task row's keys; reports written before rows carried them spell them in
    'arm' ('learner=td3bc augmentation=hipode')."""
    if "key" in entry:
        return entry["key"]
    return dict(part.split("=", 1) for part in entry["arm"].split())


def label_text(value: Any) -> str:
    """A key's value in a plot label: a sha256 by its first 8 hex, like the docs' tables."""
    text = _shown(value)
    return text[:8] if len(text) == 64 and all(c in "0123456789abcdef" for c in text) else text


def difference_points(report: dict[str, Any]) -> list[DifferencePoint]:
    """Every paired difference of the report: the per-task ones, then each arm's mean over
    tasks where it spans several, labelled by their keys in the report's order
    ('hopper-m-r · td3bc · hipode', 'mean of 3 tasks · td3bc · hipode')."""
    entries = [
        (e["key"], {n: m["paired_difference"] for n, m in e["measures"].items()}, False)
        for e in report["comparisons"]
    ]
    for entry in report.get("across_tasks", []):
        if len(entry["tasks"]) < 2:
            continue  # over one task it repeats that task's row
        key = {"task": f"mean of {len(entry['tasks'])} tasks", **across_key(entry)}
        entries.append(({k: key[k] for k in report["by"] if k in key}, entry["measures"], True))
    points = []
    for key, differences, across in entries:
        label = " · ".join(label_text(v) for v in key.values())
        for name in MEASURES:
            d = differences.get(name)
            if d:
                low, high = d["ci"] or (d["mean"], d["mean"])
                points.append(
                    DifferencePoint(
                        label, name, d["mean"], low, high, d["pairs"], across, d["ci"] is not None
                    )
                )
    return points


def plot_differences(report: dict[str, Any], path: Path) -> None:
    """Paired difference (arm − baseline) with its 95 % CI, a row per arm and task and one per
    arm over tasks, a panel per measure, a line at zero: the comparisons at a glance, as PNG.
    A difference without an interval (where a source holds a single pair, or a mean over tasks
    where a task has no interval) is a hollow marker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = difference_points(report)
    labels = list(dict.fromkeys(p.label for p in points))
    names = [n for n in MEASURES if any(p.measure == n for p in points)]
    figure, axes = plt.subplots(
        1,
        len(names),
        figsize=(4.2 * len(names) + 2.0, 0.9 + 0.32 * len(labels)),
        dpi=120,
        sharey=True,
        squeeze=False,
    )
    for axis, name in zip(axes.flat, names, strict=True):
        for point in (p for p in points if p.measure == name):
            color = "C3" if point.across_tasks else "C0"
            axis.errorbar(
                point.mean,
                labels.index(point.label),
                # clamped: a rounding error must not make a whisker negative
                xerr=[[max(0.0, point.mean - point.low)], [max(0.0, point.high - point.mean)]],
                fmt="D" if point.across_tasks else "o",
                color=color,
                markerfacecolor=color if point.has_interval else "none",
                capsize=2,
                markersize=4,
            )
        axis.axvline(0.0, color="0.4", linewidth=0.8)
        axis.set_title(report["definitions"][name], fontsize=9)
        axis.set_xlabel("paired difference (normalized score)", fontsize=8)
        axis.grid(axis="x", alpha=0.3)
    pairs = {p.label: p.pairs for p in points}
    axes[0][0].set_yticks(range(len(labels)), [f"{x} ({pairs[x]} pairs)" for x in labels])
    axes[0][0].tick_params(axis="y", labelsize=7)
    axes[0][0].invert_yaxis()
    figure.suptitle(
        f"arm − {report['compare']}: mean with 95% CI (dots: per task; diamonds: mean over "
        "tasks; hollow: no interval, a source with a single pair)",
        fontsize=9,
    )
    figure.tight_layout()
    save_figure_atomic(figure, path)


def write_report(report: dict[str, Any], out: Path) -> dict[str, Path]:
    """report.json/.md/.csv/.tex, curves.png and, where there are comparisons,
    differences.png under `out`, each written atomically."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / name for name in OUTPUTS}
    write_text_atomic(paths["report.json"], json.dumps(report, indent=2) + "\n")
    write_text_atomic(paths["report.md"], markdown(report))
    write_text_atomic(paths["report.csv"], csv_text(report))
    write_text_atomic(paths["report.tex"], latex(report))
    plot_curves(report, paths["curves.png"])
    if difference_points(report):
        plot_differences(report, paths["differences.png"])
    else:
        # a replaced report without comparisons must not leave an earlier report's plot beside it
        paths.pop("differences.png").unlink(missing_ok=True)
    return paths
