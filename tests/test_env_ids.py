"""Env ids met in data (D4RL dataset names, older gym versions) map to the Gymnasium env we run;
ids we cannot run are refused when the source is loaded, before any training."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from builders import make_d4rl_file, make_episodes, make_minari_dataset
from typer.testing import CliRunner

from hipode_pipeline.cli import app
from hipode_pipeline.data.load import describe_source, load_source
from hipode_pipeline.envs import canonical_env_id
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.tasks import get_task

LOCOMOTION = {"hopper": "Hopper-v5", "halfcheetah": "HalfCheetah-v5", "walker2d": "Walker2d-v5"}
LOCOMOTION_KINDS = ("random", "medium", "medium-replay", "medium-expert", "expert", "full-replay")
ADROIT = {
    "pen": "AdroitHandPen-v1",
    "door": "AdroitHandDoor-v1",
    "hammer": "AdroitHandHammer-v1",
    "relocate": "AdroitHandRelocate-v1",
}
OLD_GYM = {
    f"{name}-v{version}": f"{name}-v5"
    for name in ("Hopper", "Walker2d", "HalfCheetah")
    for version in (2, 3, 4)
}
D4RL_NAMES = {
    f"{family}-{kind}-v{version}": target
    for family, target in LOCOMOTION.items()
    for kind in LOCOMOTION_KINDS
    for version in (0, 1, 2)
} | {
    f"{family}-{kind}-v{version}": target
    for family, target in ADROIT.items()
    for kind in ("human", "cloned", "expert")
    for version in (0, 1)
}
HOPPER_SHAPE = dict(n=100, obs_dim=11, act_dim=3, seed=0, episode_length=25)
TINY_TRAIN = ["--data", "source", "--steps", "3", "--eval-every", "3", "--eval-episodes", "1"]


@pytest.mark.parametrize(("raw", "expected"), sorted({**D4RL_NAMES, **OLD_GYM}.items()))
def test_d4rl_names_and_old_versions_map_to_the_env_we_run(raw, expected):
    env_id, note = canonical_env_id(raw)

    assert env_id == expected
    assert raw in note and expected in note


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        ("HOPPER-MEDIUM-REPLAY-V2", "Hopper-v5"),
        ("HalfCheetah-Expert-v0", "HalfCheetah-v5"),
        ("Pen-Human-v1", "AdroitHandPen-v1"),
        ("hopper-v3", "Hopper-v5"),
        ("walker2d-v5", "Walker2d-v5"),
    ],
)
def test_mapping_ignores_case(raw, expected):
    assert canonical_env_id(raw)[0] == expected


@pytest.mark.parametrize("raw", [*LOCOMOTION.values(), *ADROIT.values()])
def test_ids_we_run_are_unchanged_without_a_note(raw):
    assert canonical_env_id(raw) == (raw, None)


@pytest.mark.parametrize(
    "raw",
    [
        "hopper-foo-v2",
        "Ant-v2",
        "Ant-v4",
        "CartPole-v1",
        "Foo-v0",
        "pen-medium-v1",
        "hopper-human-v1",
        "Hopper-v1",
        "ant-medium-v2",
        "",
    ],
)
def test_anything_else_is_returned_unchanged(raw):
    assert canonical_env_id(raw) == (raw, None)


def test_a_d4rl_file_named_by_its_dataset_loads_as_v5_with_a_note_naming_the_original(
    tmp_path, capsys
):
    path = tmp_path / "source.hdf5"
    make_d4rl_file(path, attrs={"env": "hopper-medium-replay-v2"}, **HOPPER_SHAPE)

    _, info = load_source(str(path))
    load_source(str(path))  # loaded again in the same process: the note is not repeated

    hopper = get_task("hopper-m-r")
    assert info.env_id == "Hopper-v5"
    assert info.metadata["env_id_original"] == "hopper-medium-replay-v2"
    assert (info.ref_min_score, info.ref_max_score) == (hopper.ref_min_score, hopper.ref_max_score)
    notes = [note for note in info.metadata["notes"] if "hopper-medium-replay-v2" in note]
    assert notes == [
        "env id 'hopper-medium-replay-v2' is a D4RL dataset name; running it as Hopper-v5"
    ]
    assert capsys.readouterr().err.count("hopper-medium-replay-v2") == 1
    assert info.to_dict()["env_id"] == "Hopper-v5"
    json.dumps(info.to_dict())  # still what manifests record
    summary = describe_source(str(path))
    assert (summary["env_id"], summary["env_id_original"]) == (
        "Hopper-v5",
        "hopper-medium-replay-v2",
    )


def test_a_minari_dataset_of_an_old_gym_version_loads_as_v5():
    make_minari_dataset("test/hopper/v2-v0", make_episodes(2, 11, 3, seed=0), env_id="Hopper-v2")

    _, info = load_source("test/hopper/v2-v0")

    assert (info.env_id, info.metadata["env_id_original"]) == ("Hopper-v5", "Hopper-v2")
    assert any("older version" in note for note in info.metadata["notes"])


@pytest.mark.parametrize(
    ("raw", "problem"), [("hopper-foo-v2", "not registered"), ("Ant-v2", "foreign entry point")]
)
def test_an_id_we_cannot_run_is_refused_naming_file_field_and_value(tmp_path, raw, problem):
    path = tmp_path / "source.hdf5"
    make_d4rl_file(path, attrs={"env": raw}, **HOPPER_SHAPE)

    with pytest.raises(DataFormatError) as caught:
        load_source(str(path))

    error = caught.value
    assert (error.path, error.field) == (str(path), "env")
    assert "Hopper-v5" in error.expected and "hopper-medium-replay-v2" in error.expected
    assert raw in str(error.found) and problem in str(error.found)


def test_a_minari_env_spec_we_cannot_run_is_refused():
    make_minari_dataset("test/foo/unknown-v0", make_episodes(2, 11, 3, seed=0), env_id="Foo-v0")

    with pytest.raises(DataFormatError, match=r"metadata.json: field 'env_spec.id'.*'Foo-v0'"):
        load_source("test/foo/unknown-v0")


def test_a_source_of_another_family_than_the_task_is_refused(tmp_path):
    path = tmp_path / "source.hdf5"
    make_d4rl_file(path, attrs={"env_id": "hopper-medium-v2"}, **HOPPER_SHAPE)
    make_minari_dataset(
        "local/hopper/medium-replay-v0", make_episodes(2, 11, 3, seed=0), env_id="Walker2d-v5"
    )

    assert load_source(str(path), task=get_task("hopper-m"))[1].env_id == "Hopper-v5"
    with pytest.raises(DataFormatError, match=r"family walker2d.*'hopper-medium-v2' \(read as"):
        load_source(str(path), task=get_task("walker2d-m"))
    # a task name stands for that task's data
    with pytest.raises(DataFormatError, match=r"task hopper-m-r's family hopper.*Walker2d-v5"):
        load_source("hopper-m-r")


def test_train_on_a_d4rl_named_source_evaluates_on_v5(tmp_path):
    source = tmp_path / "hopper_source.hdf5"
    make_d4rl_file(source, attrs={"env": "hopper-medium-replay-v2"}, **HOPPER_SHAPE)
    common = ["--source", str(source), *TINY_TRAIN, "--out", str(tmp_path), "--root", str(tmp_path)]

    result = CliRunner().invoke(app, ["train", "hopper-m-r", *common, "--json"])

    assert result.exit_code == 0, result.output
    scores = json.loads(result.stdout)
    assert scores["steps"] == 3 and [e["step"] for e in scores["evaluations"]] == [3]
    config = json.loads((Path(scores["run_dir"]) / "config.json").read_text())
    assert config["env_id"] == "Hopper-v5"
    assert "hopper-medium-replay-v2" in result.stderr


@pytest.mark.parametrize("raw", ["hopper-foo-v2", "Ant-v2"])
def test_train_refuses_an_id_we_cannot_run_before_any_run_folder(tmp_path, raw):
    source = tmp_path / "hopper_source.hdf5"
    make_d4rl_file(source, attrs={"env": raw}, **HOPPER_SHAPE)
    common = ["--source", str(source), *TINY_TRAIN, "--out", str(tmp_path), "--root", str(tmp_path)]

    result = CliRunner().invoke(app, ["train", "hopper-m-r", *common])

    assert result.exit_code == 2, result.output
    assert "field 'env'" in result.stderr and raw in result.stderr
    # nothing was written: no task folder, no run folder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["datasets", "hopper_source.hdf5"]
