"""The task registry matches the paper's tables and fails helpfully."""

import pytest
from typer.testing import CliRunner

from hipode_pipeline.cli import app
from hipode_pipeline.errors import UnknownTaskError
from hipode_pipeline.tasks import all_tasks, get_task


def test_every_table_task_is_registered():
    names = set(all_tasks())
    for env in ("hopper", "halfcheetah", "walker2d"):
        for kind in ("r", "m", "m-r", "m-e", "e"):
            assert f"{env}-{kind}" in names
    assert {"door-h", "hammer-h", "pen-h", "relocate-h"} <= names


@pytest.mark.parametrize(
    ("name", "learner", "eta", "lam", "learner_alpha"),
    [
        ("hopper-m-r", "td3bc", 0.5, 0.2, 2.5),  # Table 6
        ("walker2d-m-e", "td3bc", 0.05, 0.2, 2.5),
        ("pen-h", "td3bc", 0.8, 0.2, 0.001),
        ("halfcheetah-m-r", "cql", 0.2, 1.0, 10.0),  # Table 5
        ("walker2d-m-r", "cql", 0.4, 1.0, 10.0),
        ("hopper-m-r", "iql", 0.05, 1.0, None),  # Table 7
        ("walker2d-m", "iql", 0.1, 1.0, None),
        ("hopper-m-e", "iql_v2", 0.2, 1.0, None),  # Table 8
    ],
)
def test_paper_hyper_parameters(name, learner, eta, lam, learner_alpha):
    params = get_task(name).augment_params(learner)
    assert (params.eta, params.lam, params.learner_alpha) == (eta, lam, learner_alpha)
    assert (params.n, params.alpha, params.sigma) == (10, 1.0, 1.0)
    assert params.from_paper


def test_long_names_and_references():
    task = get_task("hopper-medium-replay-v0")
    assert task.name == "hopper-m-r"
    assert task.env_id == "Hopper-v5"
    assert task.local_dataset_id == "local/hopper/medium-replay-v0"
    assert task.normalized_score(task.ref_min_score) == pytest.approx(0.0)
    assert task.normalized_score(task.ref_max_score) == pytest.approx(100.0)


def test_tasks_without_paper_values_fall_back_to_defaults():
    params = get_task("hopper-r").augment_params("iql")
    assert not params.from_paper
    assert (params.eta, params.lam) == (0.2, 0.2)


def test_unknown_task_lists_close_matches():
    with pytest.raises(UnknownTaskError, match="hopper-m-r"):
        get_task("hoper-m-r")


def test_tasks_cli_json():
    result = CliRunner().invoke(app, ["tasks", "--json"])
    assert result.exit_code == 0
    assert "hopper-m-r" in result.stdout
