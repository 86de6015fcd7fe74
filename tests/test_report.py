"""`hipode report`: seeds aggregated with rliable (IQM, means, bootstrap CIs), comparisons
against a baseline arm, curves, the output files and clear errors."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import numpy as np
import pytest
from test_train_cli import TINY
from typer.testing import CliRunner

from hipode_pipeline import report as report_module
from hipode_pipeline.cli import app
from hipode_pipeline.errors import DataFormatError, SettingError
from hipode_pipeline.report import (
    build_report,
    curve_panels,
    difference_points,
    find_runs,
    improvement,
    improvement_within_sources,
    interval_estimates,
    plot_curves,
    replicates_text,
    update_count,
    weighted_iqm,
    write_report,
)
from hipode_pipeline.report import markdown as report_markdown

pytest.importorskip("rliable", reason="the report extra (rliable) is not installed")


def write_run(
    folder: Path,
    *,
    data: str,
    seed: int,
    scores: list[float],
    task="hopper-m-r",
    artifact_seed=0,
    method: str | None = None,
    steps: int | None = None,
    source: str | None = None,
    finish: dict | None = None,
):
    folder.mkdir(parents=True)
    evaluations = [{"step": 100 * (i + 1), "score_mean": s} for i, s in enumerate(scores)]
    identity = {"mixing": "mixed", "artifact_seed": artifact_seed, "source_sha256": source or task}
    if method is not None:
        identity["artifact_hyper_parameters"] = {"method": method, "eta": 0.5}
    (folder / "scores.json").write_text(
        json.dumps(
            {
                "task": task,
                "learner": "td3bc",
                "data": data,
                "seed": seed,
                "eta": 0.5,
                "evaluations": evaluations,
                "data_identity": identity,
                **({} if steps is None else {"steps": steps}),
                **(finish or {}),
            }
        )
    )


@pytest.fixture
def two_arms(tmp_path):
    """Four seeds of a baseline and of an arm scoring exactly 5 more on every seed."""
    finals = [10.0, 20.0, 30.0, 40.0]
    for seed, final in enumerate(finals):
        curve = [final / 4, final / 2, final]
        write_run(tmp_path / "runs" / f"source-{seed}", data="source", seed=seed, scores=curve)
        write_run(
            tmp_path / "runs" / f"merged-{seed}",
            data="merged",
            seed=seed,
            scores=[s + 5 for s in curve],
        )
    return tmp_path / "runs"


def test_iqm_mean_and_intervals_over_seeds(two_arms):
    report = build_report(find_runs([two_arms]), k=2, reps=2000)
    groups = {g["data"]: g for g in report["groups"]}
    last = groups["source"]["measures"]["last"]
    # IQM of 10, 20, 30, 40: the mean of the middle half (25); the mean is 25 too
    assert last["iqm"] == pytest.approx(25.0) and last["mean"] == pytest.approx(25.0)
    assert 10 <= last["mean_ci"][0] < 25 < last["mean_ci"][1] <= 40
    assert groups["source"]["seeds"] == [0, 1, 2, 3] and last["n"] == 4
    # mean of the last 2 evaluations, and the curve mean
    assert groups["source"]["measures"]["last_k_mean"]["mean"] == pytest.approx(
        np.mean([(f / 2 + f) / 2 for f in (10, 20, 30, 40)])
    )
    assert groups["merged"]["measures"]["curve_mean"]["mean"] == pytest.approx(
        np.mean([np.mean([f / 4, f / 2, f]) + 5 for f in (10, 20, 30, 40)])
    )
    curve = groups["source"]["curve"]
    assert curve["steps"] == [100, 200, 300]
    assert curve["mean"] == pytest.approx([25 / 4, 25 / 2, 25])
    bounds = zip(curve["ci_low"], curve["mean"], curve["ci_high"], strict=True)
    assert all(lo <= m <= hi for lo, m, hi in bounds)


def test_comparison_pairs_seeds(two_arms):
    report = build_report(find_runs([two_arms]), compare=("data", "source"), reps=2000)
    (entry,) = report["comparisons"]
    assert entry["arm"] == "task=hopper-m-r learner=td3bc data=merged"
    last = entry["measures"]["last"]
    paired = last["paired_difference"]
    assert paired["mean"] == pytest.approx(5.0) and paired["ci"] == pytest.approx([5.0, 5.0])
    assert paired["seeds"] == [0, 1, 2, 3]
    # unpaired, 5 more is not always better (seed 0 at 15 loses to seed 1 at 20): 10 of 16 pairs
    probability = last["probability_of_improvement"]["probability"]
    assert probability == pytest.approx(10 / 16)


def test_intervals_depend_on_their_own_scores_and_seed_only():
    # many distinct scores, so a different resample shows in the interval's bounds
    x = np.random.default_rng(3).normal(30.0, 10.0, size=9)
    y = np.random.default_rng(4).normal(25.0, 10.0, size=7)
    first, first_pi = interval_estimates(x, 2000, 0), improvement(x, y, 2000, 0)
    np.random.seed(12345)  # what a caller, or another group, left in numpy's global stream
    np.random.random(17)
    caller_state = np.random.get_state()
    again, again_pi = interval_estimates(x, 2000, 0), improvement(x, y, 2000, 0)
    assert again["mean_ci"] == first["mean_ci"] and again["iqm_ci"] == first["iqm_ci"]
    assert again_pi["ci"] == first_pi["ci"]
    assert interval_estimates(x, 2000, 1)["mean_ci"] != first["mean_ci"]  # the seed is used
    # the caller's stream is given back where it was, also when drawing the resamples fails
    np.random.set_state(caller_state)
    expected = np.random.random(3)
    np.random.set_state(caller_state)
    interval_estimates(x, 2000, 0)
    improvement(x, y, 2000, 0)
    with pytest.raises(ValueError):
        report_module.rliable_resamples([5, -1], 200, 0)
    assert np.array_equal(np.random.random(3), expected)


def test_intervals_of_one_source_are_rliables():
    # rliable's get_interval_estimates, one Python call per resample, against the resamples
    # drawn as it draws them and computed at once: the same bounds (scores with ties included;
    # arms of unequal and of equal size, which draw their resamples differently)
    import sys

    from rliable import metrics

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
    from report_bootstrap import rliable_interval

    rng = np.random.default_rng(5)
    x, y = rng.normal(30.0, 8.0, size=7).round(0), rng.normal(27.0, 8.0, size=5).round(0)

    def aggregates(scores):
        return np.array([metrics.aggregate_iqm(scores), metrics.aggregate_mean(scores)])

    expected = rliable_interval(x.reshape(-1, 1), aggregates, 300, 11)
    ours = interval_estimates(x, 300, 11)
    assert ours["iqm_ci"] == pytest.approx(expected[:, 0], abs=1e-12)
    assert ours["mean_ci"] == pytest.approx(expected[:, 1], abs=1e-12)
    for other in (y, y[::-1] + 3.0, np.append(y, [27.0, 31.0])):  # 5, 5 and 7 runs
        pair = (x.reshape(-1, 1), other.reshape(-1, 1))
        expected = rliable_interval(pair, metrics.probability_of_improvement, 300, 11)
        assert improvement(x, other, 300, 11)["ci"] == pytest.approx(expected[:, 0], abs=1e-12)


def test_same_seed_twice_in_a_group_is_refused(tmp_path, two_arms):
    write_run(two_arms / "again", data="source", seed=1, scores=[1.0])
    with pytest.raises(DataFormatError, match="one run per seed"):
        build_report(find_runs([two_arms]))


def test_runs_of_different_budgets_are_not_pooled(two_arms):
    for folder in two_arms.iterdir():
        record = json.loads((folder / "scores.json").read_text())
        (folder / "scores.json").write_text(json.dumps({**record, "steps": 300}))
    assert len(build_report(find_runs([two_arms]), k=2, reps=200)["groups"]) == 2
    write_run(two_arms / "longer", data="source", seed=7, scores=[1.0, 2.0], steps=500)
    with pytest.raises(DataFormatError, match=r"longer/scores.json: field 'steps'.*found 500"):
        build_report(find_runs([two_arms]), k=2, reps=200)
    by_budget = build_report(find_runs([two_arms]), by=("data", "steps"), k=2, reps=200)
    assert sorted((g["data"], g["n_runs"]) for g in by_budget["groups"]) == [
        ("merged", 4),
        ("source", 1),
        ("source", 4),
    ]


POOLED = ("task", "learner", "augmentation")


@pytest.fixture
def pooled_arms(tmp_path):
    """Three training seeds of the source alone, and of HIPODE and model rollouts with artifacts
    of two stage-one seeds: HIPODE's artifact seed 0 adds exactly 10 at every training seed, its
    seed 1 takes 10 away; the rollouts add 2 at both."""
    runs = tmp_path / "runs"
    for seed, final in enumerate([30.0, 40.0, 50.0]):
        write_run(runs / "eta0" / f"s{seed}", data="source", seed=seed, scores=[final])
        for artifact_seed, hipode_gain in ((0, 10.0), (1, -10.0)):
            folder = runs / f"hipode-a{artifact_seed}" / f"s{seed}"
            write_run(
                folder,
                data="merged",
                seed=seed,
                scores=[final + hipode_gain],
                artifact_seed=artifact_seed,
                method="hipode",
            )
            write_run(
                runs / f"rollouts-a{artifact_seed}" / f"s{seed}",
                data="merged",
                seed=seed,
                scores=[final + 2.0],
                artifact_seed=artifact_seed,
                method="model-rollouts",
            )
    return runs


def test_pooled_stage_one_seeds_pair_with_the_baseline_and_resample_both_seeds(pooled_arms):
    runs = find_runs([pooled_arms])
    report = build_report(runs, by=POOLED, compare=("augmentation", "none"), reps=4000)
    groups = {g["augmentation"]: g for g in report["groups"]}
    assert set(groups) == {"none", "hipode", "model-rollouts"}
    assert groups["hipode"]["n_runs"] == 6 and groups["hipode"]["artifact_seeds"] == [0, 1]
    assert groups["hipode"]["seeds"] == [0, 1, 2] and groups["none"]["artifact_seeds"] == []
    entries = {e["key"]["augmentation"]: e["measures"]["last"] for e in report["comparisons"]}
    hipode, rollouts = (
        entries["hipode"]["paired_difference"],
        entries["model-rollouts"]["paired_difference"],
    )
    assert hipode["pairs"] == 6 and hipode["artifact_seeds"] == [0, 1]
    assert hipode["mean"] == pytest.approx(0.0)
    # resampling the stage-one seeds draws both artifacts (0), seed 0 twice (+10) or seed 1
    # twice (-10): the interval spans the artifacts' spread, which resampling the six runs as if
    # independent would shrink
    assert hipode["ci"] == pytest.approx([-10.0, 10.0])
    assert rollouts["mean"] == pytest.approx(2.0) and rollouts["ci"] == pytest.approx([2.0, 2.0])
    assert "_means" not in hipode  # the bootstrap samples stay out of report.json


def test_hipode_against_the_rollouts_pairs_runs_of_the_same_stage_one_seed(pooled_arms):
    # the rollouts as the baseline: each HIPODE run meets the rollout run of its own stage-one
    # seed (+10 - 2 on seed 0, -10 - 2 on seed 1), never the other seed's; a third stage-one
    # seed without rollouts (+30) enters neither the pairs nor P(HIPODE > rollouts)
    for seed, final in enumerate([30.0, 40.0, 50.0]):
        write_run(
            pooled_arms / "hipode-a2" / f"s{seed}",
            data="merged",
            seed=seed,
            scores=[final + 30.0],
            artifact_seed=2,
            method="hipode",
        )
    runs = find_runs([pooled_arms])
    report = build_report(runs, by=POOLED, compare=("augmentation", "model-rollouts"), reps=2000)
    entries = {e["key"]["augmentation"]: e["measures"]["last"] for e in report["comparisons"]}
    paired = entries["hipode"]["paired_difference"]
    assert paired["pairs"] == 6 and paired["mean"] == pytest.approx(-2.0)
    assert paired["ci"] == pytest.approx([-12.0, 8.0])
    by_seed = build_report(
        runs, by=(*POOLED, "artifact_seed"), compare=("augmentation", "model-rollouts"), reps=500
    )
    means = {
        e["key"]["artifact_seed"]: e["measures"]["last"]["paired_difference"]["mean"]
        for e in by_seed["comparisons"]
        if e["key"]["augmentation"] == "hipode"
    }
    assert means == {0: pytest.approx(8.0), 1: pytest.approx(-12.0)}
    # couples of one source and stage-one seed: 6 of 9 wins on seed 0, 1 of 9 on seed 1
    probability = entries["hipode"]["probability_of_improvement"]
    assert probability["probability"] == pytest.approx(7 / 18) and probability["sources"] == 1
    # eta0 has no stage-one seed to pair on: no comparison at all
    assert set(entries) == {"hipode"}


@pytest.mark.parametrize("walker_rollouts_seed", [0, 5])
def test_an_arm_without_pairs_on_a_task_gets_no_row_across_tasks(tmp_path, walker_rollouts_seed):
    # eta0 never pairs with the rollouts; with walker2d-m-r's rollouts of another stage-one seed
    # HIPODE pairs on hopper-m-r alone, and a mean over one of two tasks is no mean over tasks
    runs = tmp_path / "runs"
    write_two_tasks(runs, {"hopper-m-r": 5.0, "walker2d-m-r": 15.0}, noise=1.0)
    for task in ("hopper-m-r", "walker2d-m-r"):
        for seed in range(3):
            write_run(
                runs / task / f"r{seed}",
                data="merged",
                seed=seed,
                scores=[30.0],
                task=task,
                artifact_seed=walker_rollouts_seed if task == "walker2d-m-r" else 0,
                method="model-rollouts",
            )
    report = build_report(
        find_runs([runs]), by=POOLED, compare=("augmentation", "model-rollouts"), reps=500
    )
    compared = [(e["key"]["task"], e["key"]["augmentation"]) for e in report["comparisons"]]
    across = [entry["key"]["augmentation"] for entry in report["across_tasks"]]
    if walker_rollouts_seed == 0:
        assert compared == [("hopper-m-r", "hipode"), ("walker2d-m-r", "hipode")]
        assert across == ["hipode"]
    else:
        assert compared == [("hopper-m-r", "hipode")] and across == []


def write_two_tasks(runs: Path, gains: dict[str, float], noise: float) -> None:
    """Three seeds of η = 0 and HIPODE per task; HIPODE's final score is η = 0's plus the
    task's gain plus noise × seed."""
    for task, gain in gains.items():
        for seed, final in enumerate([20.0, 30.0, 45.0]):
            write_run(runs / task / f"s{seed}", data="source", seed=seed, scores=[final], task=task)
            write_run(
                runs / task / f"h{seed}",
                data="merged",
                seed=seed,
                scores=[final + gain + noise * seed],
                task=task,
                method="hipode",
            )


def test_comparisons_are_aggregated_over_tasks(tmp_path):
    runs = tmp_path / "runs"
    write_two_tasks(runs, {"hopper-m-r": 5.0, "walker2d-m-r": 15.0}, noise=1.0)  # noise 0, 1, 2
    report = build_report(find_runs([runs]), by=POOLED, compare=("augmentation", "none"), reps=4000)
    (entry,) = report["across_tasks"]
    assert entry["arm"] == "learner=td3bc augmentation=hipode"
    assert entry["tasks"] == ["hopper-m-r", "walker2d-m-r"]
    last = entry["measures"]["last"]
    assert last["mean"] == pytest.approx((5 + 15) / 2 + 1) and last["pairs"] == 6
    # every resample averages the two tasks' resampled seed noise (each within 0..2)
    assert 10.0 <= last["ci"][0] < 11.0 < last["ci"][1] <= 12.0
    # P(improvement) over tasks is the mean of the tasks' own (rliable's aggregate): HIPODE's
    # runs beat 6 of 9 η = 0 runs on hopper-m-r (gain 5) and 8 of 9 on walker2d-m-r (gain 15)
    chance = last["probability_of_improvement"]
    per_task = [c["measures"]["last"]["probability_of_improvement"] for c in report["comparisons"]]
    assert sorted(p["probability"] for p in per_task) == pytest.approx([6 / 9, 8 / 9])
    assert chance["probability"] == pytest.approx((6 / 9 + 8 / 9) / 2)
    low, high = chance["ci"]
    # a mean of two tasks' bootstraps is narrower than the wider of them
    assert 0.0 <= low < chance["probability"] < high <= 1.0
    assert high - low < max(p["ci"][1] - p["ci"][0] for p in per_task)
    assert "_samples" not in json.dumps(report) and "_means" not in json.dumps(report)
    markdown_text = report_markdown(report)
    assert "Across tasks" in markdown_text and "+11.0" in markdown_text
    # the curves: a panel per task (their scores share no scale), arms labelled without it
    panels = curve_panels(report)
    assert list(panels) == ["hopper-m-r", "walker2d-m-r"]
    assert sorted(arm for arm, _ in panels["walker2d-m-r"]) == ["td3bc hipode", "td3bc none"]
    assert all(group["n_runs"] == 3 for _, group in panels["walker2d-m-r"])
    plot_curves(report, tmp_path / "curves.png")
    assert (tmp_path / "curves.png").read_bytes()[:4] == b"\x89PNG"


def test_weighted_iqm_is_rliables_with_equal_weights_and_counts_part_of_a_straddling_run():
    from rliable import metrics

    rng = np.random.default_rng(0)
    values = rng.normal(size=(3, 12))
    equal = np.full(12, 1 / 12)
    expected = [metrics.aggregate_iqm(row[:, None]) for row in values]
    assert weighted_iqm(values, equal) == pytest.approx(expected)
    # four equal runs: the middle half is 2 and 3
    assert weighted_iqm(np.array([1.0, 2.0, 3.0, 100.0]), np.full(4, 0.25)) == pytest.approx(2.5)
    # weights 0.1, 0.4, 0.4, 0.1: the middle half lies within the two heavy runs
    weights = np.array([0.1, 0.4, 0.4, 0.1])
    assert weighted_iqm(np.array([-50.0, 2.0, 4.0, 90.0]), weights) == pytest.approx(3.0)


def test_scores_are_aggregated_over_tasks_each_task_weighing_the_same(tmp_path):
    runs = tmp_path / "runs"
    write_two_tasks(runs, {"hopper-m-r": 5.0, "walker2d-m-r": 15.0}, noise=1.0)
    # a fourth η = 0 seed on hopper-m-r only: tasks, not runs, weigh the same
    write_run(runs / "hopper-m-r" / "s3", data="source", seed=3, scores=[95.0])
    report = build_report(find_runs([runs]), by=POOLED, compare=("augmentation", "none"), reps=2000)
    rows = {row["key"]["augmentation"]: row for row in report["scores_across_tasks"]}
    none = rows["none"]["measures"]["last"]
    assert rows["none"]["n_runs"] == 7 and rows["none"]["tasks"] == ["hopper-m-r", "walker2d-m-r"]
    hopper, walker = np.mean([20.0, 30.0, 45.0, 95.0]), np.mean([20.0, 30.0, 45.0])
    assert none["mean"] == pytest.approx((hopper + walker) / 2)
    assert none["mean_ci"][0] < none["mean"] < none["mean_ci"][1]
    assert none["iqm_ci"][0] <= none["iqm"] <= none["iqm_ci"][1]
    assert "Scores across tasks" in report_markdown(report)


def test_tasks_are_resampled_independently_in_the_mean_over_tasks(tmp_path):
    runs = tmp_path / "runs"
    # two tasks with the same pairs: each task's bootstrap drew the same indices from one seed
    write_two_tasks(runs, {"hopper-m-r": 5.0, "walker2d-m-r": 5.0}, noise=4.0)
    report = build_report(find_runs([runs]), by=POOLED, compare=("augmentation", "none"), reps=4000)
    one = report["comparisons"][0]["measures"]["last"]["paired_difference"]["ci"]
    assert report["comparisons"][1]["measures"]["last"]["paired_difference"]["ci"] == one
    (across,) = report["across_tasks"]
    both = across["measures"]["last"]["ci"]
    # the mean of two independent resamples spreads 1/sqrt(2) as wide as one task's; aligned
    # resamples would give the one task's interval back
    assert 0.55 < (both[1] - both[0]) / (one[1] - one[0]) < 0.85


def unrecorded_source(folder: Path) -> None:
    path = folder / "scores.json"
    record = json.loads(path.read_text())
    del record["data_identity"]["source_sha256"]
    path.write_text(json.dumps(record))


def test_scores_over_tasks_weigh_each_task_the_same_and_resample_within_it(tmp_path):
    runs = tmp_path / "runs"
    # two runs on one task and four on the other: weights 1/4 and 1/8; sorted 0 | 1 2 3 4 | 10,
    # the middle half of the weight is 1, 2, 3 and 4 (1/8 each)
    for seed, score in enumerate([0.0, 10.0]):
        write_run(runs / f"a{seed}", data="source", seed=seed, scores=[score], task="hopper-m-r")
    for seed, score in enumerate([1.0, 2.0, 3.0, 4.0]):
        write_run(runs / f"b{seed}", data="source", seed=seed, scores=[score], task="walker2d-m-r")
    (row,) = build_report(find_runs([runs]), by=POOLED, reps=500)["scores_across_tasks"]
    assert row["measures"]["last"]["iqm"] == pytest.approx(2.5)
    assert row["measures"]["last"]["mean"] == pytest.approx((5.0 + 2.5) / 2)
    assert row["sources"] == 2 and row["n_runs"] == 6
    # runs that name no source are still resampled within their own task, never across tasks
    runs = tmp_path / "unnamed"
    for task, base in (("hopper-m-r", 0.0), ("walker2d-m-r", 100.0)):
        for seed in range(4):
            folder = runs / task / f"s{seed}"
            write_run(folder, data="source", seed=seed, scores=[base + seed], task=task)
            unrecorded_source(folder)
    (row,) = build_report(find_runs([runs]), by=POOLED, reps=1000)["scores_across_tasks"]
    low, high = row["measures"]["last"]["iqm_ci"]
    assert row["measures"]["last"]["iqm"] == pytest.approx((2 + 3 + 100 + 101) / 4)
    assert 49.0 < low <= high < 54.0


def test_a_source_with_a_single_pair_leaves_the_pooled_difference_without_an_interval(tmp_path):
    # two sources of one task; the hipode arm has two training seeds on each, the rollout arm
    # one: sources are strata, so a lone pair would enter every resample unchanged
    runs = tmp_path / "runs"
    for source, shift in (("a", 4.0), ("b", -6.0)):
        for seed in (0, 1):
            base = 20.0 + 3 * seed
            for data, method, final in (
                ("source", None, base),
                ("merged", "hipode", base + shift + seed),
                ("merged", "model-rollouts", base + shift),
            ):
                if method == "model-rollouts" and seed == 1:
                    continue
                name = f"{source}-{method or 'none'}-{seed}"
                write_run(
                    runs / name, data=data, seed=seed, scores=[final], method=method, source=source
                )
    report = build_report(find_runs([runs]), by=POOLED, compare=("augmentation", "none"), reps=500)
    entries = {e["key"]["augmentation"]: e["measures"]["last"] for e in report["comparisons"]}
    rollouts = entries["model-rollouts"]["paired_difference"]
    assert rollouts["pairs"] == 2 and rollouts["mean"] == pytest.approx(-1.0)
    assert rollouts["ci"] is None
    hipode = entries["hipode"]["paired_difference"]
    assert hipode["pairs"] == 4 and hipode["ci"][0] < hipode["mean"] < hipode["ci"][1]
    assert "-1.0 (no interval)" in report_markdown(report)


def test_a_group_spanning_sources_resamples_runs_within_each_source(tmp_path):
    # source a's runs end at 10 and 20, b's both at 50: resampled within its source, a resample
    # holds two of a's and two of b's, so its mean is 30, 32.5 or 35; pooled as one, it would
    # swing from 10 to 50
    runs = tmp_path / "runs"
    for source, finals in (("a", (10.0, 20.0)), ("b", (50.0, 50.0))):
        for seed, final in enumerate(finals):
            write_run(
                runs / f"{source}-{seed}",
                data="source",
                seed=seed,
                scores=[final, final],
                source=source,
            )
    report = build_report(find_runs([runs]), by=POOLED, reps=2000)
    (group,) = report["groups"]
    last = group["measures"]["last"]
    assert group["sources"] == 2 and last["mean"] == pytest.approx(32.5)
    assert last["mean_ci"] == pytest.approx([30.0, 35.0])
    assert group["curve"]["ci_low"] == pytest.approx([30.0, 30.0])
    assert group["curve"]["ci_high"] == pytest.approx([35.0, 35.0])
    # a source with a single run: nothing to resample there, so no interval and no band
    write_run(runs / "c-0", data="source", seed=0, scores=[25.0, 25.0], source="c")
    report = build_report(find_runs([runs]), by=POOLED, reps=200)
    (group,) = report["groups"]
    assert group["measures"]["last"]["mean_ci"] is None
    assert group["measures"]["last"]["mean"] == pytest.approx(155 / 5)
    assert group["curve"]["ci_low"] is None and group["curve"]["ci_high"] is None
    assert "31.0 (no interval)" in report_markdown(report)
    plot_curves(report, tmp_path / "curves.png")  # draws the mean without a band
    assert (tmp_path / "curves.png").read_bytes()[:4] == b"\x89PNG"


def write_arm_and_baseline(folder: Path, scores: dict[str, tuple]) -> tuple[list, list]:
    """Per source, HIPODE runs ("<source>-h<seed>") and η = 0 runs ("<source>-n<seed>") with
    the given final scores; returns the arm's runs and the baseline's, as read back."""
    for source, (arm, baseline) in scores.items():
        for name, data, method, finals in (
            ("h", "merged", "hipode", arm),
            ("n", "source", None, baseline),
        ):
            for seed, final in enumerate(finals):
                write_run(
                    folder / f"{source}-{name}{seed}",
                    data=data,
                    seed=seed,
                    scores=[final],
                    method=method,
                    source=source,
                )
    found = find_runs([folder])
    return [r for r in found if "-h" in r.path.name], [r for r in found if "-n" in r.path.name]


def test_probability_of_improvement_compares_runs_of_the_same_source_only(tmp_path):
    # the arm beats the baseline on both sources, but source b scores far below source a:
    # comparing across sources would count b's arm runs as losing to a's baseline runs
    runs = tmp_path / "runs"
    write_arm_and_baseline(
        runs, {"a": ([60.0, 62.0], [50.0, 52.0]), "b": ([20.0, 22.0], [10.0, 12.0])}
    )
    # a source only the baseline ran is left out: there is nothing of the arm's to compare
    write_run(runs / "c-n0", data="source", seed=0, scores=[90.0], source="c")
    report = build_report(find_runs([runs]), by=POOLED, compare=("augmentation", "none"), reps=500)
    (entry,) = report["comparisons"]
    within = entry["measures"]["last"]["probability_of_improvement"]
    assert within == {
        "probability": pytest.approx(1.0),
        "ci": pytest.approx([1.0, 1.0]),
        "sources": 2,
    }
    pooled = improvement(
        np.array([60.0, 62.0, 20.0, 22.0]), np.array([50.0, 52.0, 10.0, 12.0]), 500, 0
    )
    assert pooled["probability"] == pytest.approx(12 / 16)  # what ignoring the sources gives
    # the sources are strata: each resamples its own runs, so a's spread shows in the interval
    arm, base = write_arm_and_baseline(
        tmp_path / "spread",
        {"a": ([60.0, 62.0, 49.0], [50.0, 52.0, 51.0]), "b": ([20.0, 22.0], [10.0, 12.0])},
    )
    # a: 60 and 62 beat all three, 49 none: 6 of 9; b: 4 of 4
    spread = improvement_within_sources(arm, base, "last", 1, 2000, 0)
    assert spread["probability"] == pytest.approx(10 / 13) and spread["sources"] == 2
    assert spread["ci"][0] < 10 / 13 < spread["ci"][1] == pytest.approx(1.0)
    # one run of the arm on a source: no spread to resample there
    lone = improvement_within_sources(arm[:1] + arm[3:], base, "last", 1, 500, 0)
    assert lone["ci"] is None and lone["sources"] == 2
    assert improvement_within_sources(arm[:1], base[3:], "last", 1, 500, 0) is None
    # exact: a's arm runs 60 and 49 beat both baseline runs or neither, b's always win, so a
    # resample within the sources reads 4, 6 or 8 of 8 (49 twice: one time in four)
    mine, theirs = write_arm_and_baseline(
        tmp_path / "exact", {"a": ([60.0, 49.0], [50.0, 52.0]), "b": ([20.0, 22.0], [10.0, 12.0])}
    )
    result = improvement_within_sources(mine, theirs, "last", 1, 4000, 0)
    assert result["probability"] == pytest.approx(6 / 8)
    assert result["ci"] == pytest.approx([0.5, 1.0])
    # ties count one half: a 3.5 of 4, b 0.5 of 1
    mine, theirs = write_arm_and_baseline(
        tmp_path / "ties", {"a": ([50.0, 60.0], [50.0, 40.0]), "b": ([10.0], [10.0])}
    )
    tied = improvement_within_sources(mine, theirs, "last", 1, 500, 0)
    assert tied == {"probability": pytest.approx(4 / 5), "ci": None, "sources": 2, "_samples": None}


def test_one_run_or_one_pair_is_reported_without_an_interval(tmp_path):
    runs = tmp_path / "runs"
    write_two_tasks(runs, {"hopper-m-r": 5.0, "walker2d-m-r": -15.0}, noise=2.0)
    # rollouts: one run per task, so one pair per task, and a mean over two single pairs
    for task, final in (("hopper-m-r", 22.0), ("walker2d-m-r", 17.0)):
        write_run(
            runs / task / "r0",
            data="merged",
            seed=0,
            scores=[final],
            task=task,
            method="model-rollouts",
        )
    report = build_report(find_runs([runs]), by=POOLED, compare=("augmentation", "none"), reps=500)
    groups = {(g["task"], g["augmentation"]): g["measures"]["last"] for g in report["groups"]}
    single, pooled = groups["hopper-m-r", "model-rollouts"], groups["hopper-m-r", "hipode"]
    assert single["n"] == 1 and single["iqm"] == single["mean"] == pytest.approx(22.0)
    assert single["iqm_ci"] is None and single["mean_ci"] is None and single["std"] is None
    assert pooled["std"] > 0
    assert pooled["mean_ci"][0] < pooled["mean"] < pooled["mean_ci"][1]
    entries = {
        (e["key"]["task"], e["key"]["augmentation"]): e["measures"]["last"]
        for e in report["comparisons"]
    }
    hopper = entries["hopper-m-r", "model-rollouts"]
    assert hopper["paired_difference"]["mean"] == pytest.approx(2.0)
    assert hopper["paired_difference"]["pairs"] == 1 and hopper["paired_difference"]["ci"] is None
    assert hopper["probability_of_improvement"] == {
        "probability": pytest.approx(1 / 3),
        "ci": None,
        "sources": 1,
    }
    across = {e["key"]["augmentation"]: e["measures"]["last"] for e in report["across_tasks"]}
    assert across["model-rollouts"]["mean"] == pytest.approx((2.0 - 3.0) / 2)
    assert across["model-rollouts"]["ci"] is None and across["hipode"]["ci"] is not None
    text = report_markdown(report)
    assert "22.0 (no interval)" in text and "+2.0 (no interval)" in text
    assert "-0.5 (no interval)" in text and "0.33 (no interval)" in text
    assert "[22.0, 22.0]" not in text and "[+2.0, +2.0]" not in text
    points = {p.label: p for p in difference_points(report) if p.measure == "last"}
    rollouts = points["mean of 2 tasks · td3bc · model-rollouts"]
    assert not rollouts.has_interval and rollouts.low == rollouts.high == rollouts.mean
    assert points["mean of 2 tasks · td3bc · hipode"].has_interval
    paths = write_report(report, tmp_path / "report")
    assert paths["differences.png"].read_bytes()[:4] == b"\x89PNG"
    csv_rows = paths["report.csv"].read_text().splitlines()
    assert any(
        row.startswith("hopper-m-r,td3bc,model-rollouts,last,1,22.0,,,22.0,,") for row in csv_rows
    )
    assert "22.0 (no interval)" in paths["report.tex"].read_text()


def test_differences_plot_shows_every_paired_difference_and_each_mean_over_tasks(tmp_path):
    runs = tmp_path / "runs"
    # per-seed noise: a real interval
    write_two_tasks(runs, {"hopper-m-r": 5.0, "walker2d-m-r": -15.0}, noise=2.0)
    # rollouts on one task and one seed: no interval, and no mean over tasks (it would repeat
    # that task's row)
    write_run(
        runs / "hopper-m-r" / "r0", data="merged", seed=0, scores=[22.0], method="model-rollouts"
    )
    report = build_report(find_runs([runs]), by=POOLED, compare=("augmentation", "none"), reps=500)
    last = {p.label: p for p in difference_points(report) if p.measure == "last"}
    assert list(last) == [
        "hopper-m-r · td3bc · hipode",
        "hopper-m-r · td3bc · model-rollouts",
        "walker2d-m-r · td3bc · hipode",
        "mean of 2 tasks · td3bc · hipode",
    ]
    entries = {
        (e["key"]["task"], e["key"]["augmentation"]): e["measures"]["last"]["paired_difference"]
        for e in report["comparisons"]
    }
    walker = last["walker2d-m-r · td3bc · hipode"]
    expected = entries["walker2d-m-r", "hipode"]
    assert (walker.mean, [walker.low, walker.high], walker.pairs) == (
        expected["mean"],
        expected["ci"],
        3,
    )
    assert walker.low < walker.mean < walker.high and walker.mean == pytest.approx(-15.0 + 2.0)
    assert last["hopper-m-r · td3bc · model-rollouts"].pairs == 1
    mean = last["mean of 2 tasks · td3bc · hipode"]
    (across,) = report["across_tasks"][:1]
    assert [mean.low, mean.high] == across["measures"]["last"]["ci"] and mean.pairs == 6
    assert mean.mean == pytest.approx((5.0 - 15.0) / 2 + 2.0) and mean.across_tasks
    assert not walker.across_tasks
    # a report.json written before across-task rows carried their keys gives the same points
    old = json.loads(json.dumps(report))
    for entry in old["across_tasks"]:
        del entry["key"]
    assert difference_points(old) == difference_points(report)
    out = tmp_path / "report"
    paths = write_report(report, out)
    assert paths["differences.png"].read_bytes()[:4] == b"\x89PNG"
    # replaced by a report without comparisons: the earlier plot does not stay behind
    write_report(build_report(find_runs([runs]), by=POOLED, reps=500), out)
    assert not (out / "differences.png").exists() and (out / "curves.png").is_file()


def test_curves_of_two_learners_get_panels_of_their_own(tmp_path):
    curve = {"steps": [0, 100_000, 200_000], "mean": [1.0, 2.0, 3.0]}
    curve |= {"ci_low": [0.5, 1.5, 2.5], "ci_high": [1.5, 2.5, 3.5]}
    groups = [
        {"task": task, "learner": learner, "augmentation": arm, "n_runs": 2, "curve": curve}
        for task in ("halfcheetah-m-r", "hopper-m-r")
        for learner in ("iql", "td3bc")
        for arm in ("none", "hipode")
        if (task, learner) != ("hopper-m-r", "iql")
    ]
    report = {"by": ["task", "learner", "augmentation"], "groups": groups}
    panels = curve_panels(report)
    titles = ["halfcheetah-m-r · iql", "halfcheetah-m-r · td3bc", "hopper-m-r · td3bc"]
    assert list(panels) == titles
    assert [arm for arm, _ in panels["halfcheetah-m-r · iql"]] == ["none", "hipode"]
    one_task = {"by": report["by"], "groups": [g for g in groups if g["task"] == "hopper-m-r"]}
    assert list(curve_panels(one_task)) == [""]  # one task, one learner: one panel
    assert [update_count(v) for v in (0, 50_000, 200_000, 1_000_000, 500)] == [
        "0",
        "50k",
        "200k",
        "1M",
        "500",
    ]
    plot_curves(report, tmp_path / "curves.png")
    assert (tmp_path / "curves.png").read_bytes()[:4] == b"\x89PNG"


def test_runs_without_a_recorded_method_are_labelled(tmp_path, two_arms):
    groups = {r.keys["data"]: r.keys["augmentation"] for r in find_runs([two_arms])}
    # the fixture's merged runs carry no artifact hyper-parameters at all
    assert groups == {"source": "none", "merged": "unknown"}


def test_bad_inputs_are_named(tmp_path, two_arms):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataFormatError, match="scores.json"):
        find_runs([tmp_path / "empty"])
    bad = two_arms / "bad"
    bad.mkdir()
    (bad / "scores.json").write_text('{"seed": 0, "evaluations": [{"step": 1, "score_mean": "x"}]}')
    with pytest.raises(DataFormatError, match=r"evaluations\[0\]\.score_mean"):
        find_runs([bad])
    with pytest.raises(SettingError, match="--compare"):
        build_report(find_runs([two_arms / "source-0"]), compare=("eta", "0.5"))
    for finish, field in (
        ({"cpu": 7}, "cpu"),
        ({"finished_utc": "2026-01-01T09:30:00"}, "finished_utc"),  # no offset
        ({"load_average": ["high"]}, "load_average"),
    ):
        folder = tmp_path / f"bad-{field}"
        write_run(folder, data="source", seed=0, scores=[1.0], finish=finish)
        with pytest.raises(DataFormatError, match=f"field '{field}'"):
            find_runs([folder])


@pytest.fixture
def recorded_runs(tmp_path):
    """Four runs of one arm: two on CPU A (one finished at +02:00), one on CPU B without a
    finish time, one recording none of it (written before runs recorded their machine)."""
    finishes = [
        {"cpu": "CPU A", "finished_utc": "2026-01-02T14:00:00+02:00", "load_average": [2.5, 2, 1]},
        {"cpu": "CPU A", "finished_utc": "2026-01-01T09:30:00+00:00", "load_average": [1.0, 1, 1]},
        {"cpu": "CPU B", "load_average": [4.25, 3, 2]},
        {},
    ]
    for seed, finish in enumerate(finishes):
        folder = tmp_path / "runs" / f"source-{seed}"
        write_run(folder, data="source", seed=seed, scores=[seed, 2.0 * seed], finish=finish)
    return tmp_path / "runs"


def test_the_runs_summary_says_on_which_cpus_when_and_under_what_load(recorded_runs):
    report = build_report(find_runs([recorded_runs]), reps=200)
    assert report["runs"] == {
        "n_runs": 4,
        "cpus": {"CPU A": 2, "CPU B": 1, "not recorded": 1},
        "finished_utc": {
            "earliest": "2026-01-01T09:30:00+00:00",
            "latest": "2026-01-02T12:00:00+00:00",
            "not_recorded": 2,
        },
        "load_average_1min": {"min": 1.0, "max": 4.25, "not_recorded": 1},
    }
    # without the command's block (when, by what command and code), only the runs' lines
    assert "Written" not in report_markdown(report)


def test_the_cli_records_when_by_what_command_and_code_it_wrote(tmp_path, recorded_runs):
    out = tmp_path / "report"
    args = ["report", str(recorded_runs), "--out", str(out), "--reps", "200", "--seed", "3"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    written = json.loads((out / "report.json").read_text())["written"]
    # the arguments as passed, in the command's order, after the program's name
    command = shlex.join(["hipode", *args[:2], "--reps", "200", "--seed", "3", "--out", str(out)])
    assert written["command"] == command
    assert {"git_commit", "git_modified", "numpy"} <= set(written["versions"])
    markdown = (out / "report.md").read_text()
    assert f"by `{command}`; code: " in markdown
    cpus = "- 4 runs, trained on CPUs: CPU A (2 runs), CPU B (1 run), not recorded (1 run).\n"
    assert cpus in markdown
    assert (
        "- Finished between 2026-01-01T09:30:00+00:00 and 2026-01-02T12:00:00+00:00 (UTC); "
        "2 runs without a finish time." in markdown
    )
    assert "- 1-minute load average at their finish: 1.00 to 4.25; 1 run without one." in markdown


def test_cli_writes_every_format_and_refuses_to_overwrite(tmp_path, two_arms):
    out = tmp_path / "report"
    args = ["report", str(two_arms), "--compare", "data=source", "--out", str(out), "--reps", "500"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    for name in ("report.json", "report.md", "report.csv", "report.tex"):
        assert (out / name).stat().st_size > 0
    assert (out / "curves.png").read_bytes()[:4] == b"\x89PNG"
    markdown = (out / "report.md").read_text()
    assert "IQM [95% CI]" in markdown and "over seeds, not evaluation episodes" in markdown
    assert "\\begin{tabular}" in (out / "report.tex").read_text()
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 2 and "--force" in again.output


def test_report_on_real_training_runs(tmp_path, tiny_pair, monkeypatch):
    """Two seeds of two arms trained for a few updates, then reported; the run records name
    their folders and artifact relative to the working directory (run folders get committed)."""
    source, artifact = tiny_pair
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    for data in ("source", "merged"):
        result = runner.invoke(
            app,
            [
                "train",
                "hopper-m-r",
                "--source",
                source,
                "--artifact",
                str(artifact),
                "--data",
                data,
                "--seeds",
                "0-1",
                *TINY,
                "--out",
                str(tmp_path / "runs"),
            ],
        )
        assert result.exit_code == 0, result.output
    out = tmp_path / "report"
    result = runner.invoke(
        app, ["report", str(tmp_path / "runs"), "--compare", "data=source", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    report = json.loads((out / "report.json").read_text())
    assert sorted(g["data"] for g in report["groups"]) == ["merged", "source"]
    assert all(g["seeds"] == [0, 1] for g in report["groups"])
    assert report["comparisons"][0]["measures"]["last"]["paired_difference"]["seeds"] == [0, 1]
    assert (out / "curves.png").is_file()
    records = sorted((tmp_path / "runs").rglob("*.json"))
    assert len(records) == 8  # config.json and scores.json of four runs
    for record in records:
        assert str(tmp_path) not in record.read_text(), record
    merged = json.loads(next((tmp_path / "runs").rglob("*merged*/scores.json")).read_text())
    assert merged["data_identity"]["artifact_path"] == "art.hdf5"
    assert merged["run_dir"].startswith("runs/hopper-m-r/")


def test_arms_split_by_stage_one_seed_pair_with_the_one_baseline(pooled_arms):
    runs = find_runs([pooled_arms])
    by = (*POOLED, "artifact_seed")
    report = build_report(runs, by=by, compare=("augmentation", "none"), reps=2000)
    groups = {(g["augmentation"], g["artifact_seed"]): g for g in report["groups"]}
    assert set(groups) == {
        ("none", None),
        *((a, s) for a in ("hipode", "model-rollouts") for s in (0, 1)),
    }
    assert groups[("none", None)]["n_runs"] == 3
    diffs = {
        (e["key"]["augmentation"], e["key"]["artifact_seed"]): e["measures"]["last"]
        for e in report["comparisons"]
    }
    assert set(diffs) == set(groups) - {("none", None)}
    for (arm, artifact_seed), measure in diffs.items():
        expected = 2.0 if arm == "model-rollouts" else (10.0 if artifact_seed == 0 else -10.0)
        paired = measure["paired_difference"]
        assert paired["pairs"] == 3 and paired["artifact_seeds"] == [artifact_seed]
        assert paired["mean"] == pytest.approx(expected)
        assert paired["ci"] == pytest.approx([expected, expected])
    # P(a run beats a baseline run), over 30, 40, 50 against 40, 50, 60 and 20, 30, 40
    assert diffs[("hipode", 0)]["probability_of_improvement"]["probability"] == pytest.approx(7 / 9)
    assert diffs[("hipode", 1)]["probability_of_improvement"]["probability"] == pytest.approx(2 / 9)
    text = report_markdown(report)
    assert "artifact_seed=-" in text and "| none | - |" in text


def test_the_runs_column_names_a_grid_only_when_the_runs_fill_it():
    def group(seeds, artifact_seeds, sources, n_runs):
        return {
            "seeds": seeds,
            "artifact_seeds": artifact_seeds,
            "sources": sources,
            "n_runs": n_runs,
        }

    assert replicates_text(group([1, 2, 3, 4, 5], [0, 1], 1, 10)) == "10 (5 × 2)"
    assert replicates_text(group([0, 1, 2, 3, 4], [], 2, 10)) == "10 (5 × 2 sources)"
    assert replicates_text(group([0, 1, 2, 3, 4], [0, 1], 2, 20)) == "20 (5 × 2 × 2 sources)"
    # training seeds 1-3 of one artifact and 1-2 of the other: 5 runs, not a 3 × 2 grid
    assert replicates_text(group([1, 2, 3], [0, 1], 1, 5)) == "5 (of 3 × 2)"
    assert replicates_text(group([0], [], 1, 1)) == "1 (1)"
