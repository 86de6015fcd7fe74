"""Every bad input fails with a HipodeError whose message names the file and the field."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from builders import make_d4rl_file, make_episodes, make_minari_dataset

from hipode_pipeline.data.load import load_source
from hipode_pipeline.errors import DataFormatError, DatasetNotFoundError

N, OBS_DIM, ACT_DIM = 24, 5, 2


def _d4rl_case(name: str):
    """(overrides, field the error must name) for one malformed D4RL file."""
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(N, OBS_DIM)).astype(np.float32)
    with_nan = obs.copy()
    with_nan[7, 2] = np.nan
    rewards_inf = np.ones(N, dtype=np.float32)
    rewards_inf[3] = np.inf
    cases = {
        "missing key": ({"actions": None}, "actions"),
        "wrong shape": ({"actions": np.zeros((N, 0), np.float32)}, "actions"),
        "wrong rank": ({"observations": np.zeros(N, np.float32)}, "observations"),
        "mismatched lengths": ({"rewards": np.zeros(N + 3, np.float32)}, "rewards"),
        "NaN": ({"observations": with_nan}, "observations"),
        "inf": ({"rewards": rewards_inf}, "rewards"),
        "string dtype": ({"actions": np.array([b"up"] * N)}, "actions"),
        "non-0/1 terminals": ({"terminals": np.full(N, 2, np.int64)}, "terminals"),
        "fractional timeouts": ({"timeouts": np.full(N, 0.5, np.float32)}, "timeouts"),
        "next obs of another dim": (
            {"next_observations": np.zeros((N, OBS_DIM + 1), np.float32)},
            "next_observations",
        ),
        "empty dataset": (
            {
                name: np.zeros((0, OBS_DIM), np.float32)
                for name in ("observations", "next_observations")
            }
            | {"actions": np.zeros((0, ACT_DIM), np.float32)}
            | {name: np.zeros(0, np.float32) for name in ("rewards", "terminals", "timeouts")},
            "observations",
        ),
    }
    return cases[name]


def _assert_names(error: pytest.ExceptionInfo, path, field: str) -> None:
    message = str(error.value)
    assert str(path) in message, message
    assert f"field '{field}'" in message, message
    assert "expected" in message, message


@pytest.mark.parametrize(
    "case",
    [
        "missing key",
        "wrong shape",
        "wrong rank",
        "mismatched lengths",
        "NaN",
        "inf",
        "string dtype",
        "non-0/1 terminals",
        "fractional timeouts",
        "next obs of another dim",
        "empty dataset",
    ],
)
def test_malformed_d4rl_file(tmp_path, case):
    overrides, field = _d4rl_case(case)
    path = tmp_path / "bad.hdf5"
    make_d4rl_file(path, n=N, obs_dim=OBS_DIM, act_dim=ACT_DIM, seed=0, **overrides)

    with pytest.raises(DataFormatError) as error:
        load_source(str(path))

    _assert_names(error, path, field)
    assert error.value.field == field


def test_broken_episode_continuity_names_the_row(tmp_path):
    path = tmp_path / "broken.hdf5"
    truth = make_d4rl_file(path, n=N, obs_dim=OBS_DIM, act_dim=ACT_DIM, seed=0)
    assert not (truth["terminals"][5] or truth["timeouts"][5])
    next_observations = truth["next_observations"].copy()
    next_observations[5] += 0.5
    make_d4rl_file(
        path, n=N, obs_dim=OBS_DIM, act_dim=ACT_DIM, seed=0, next_observations=next_observations
    )

    with pytest.raises(DataFormatError) as error:
        load_source(str(path))

    _assert_names(error, path, "next_observations")
    assert "row 5" in str(error.value) and "observations[6]" in str(error.value)


@pytest.mark.parametrize(
    ("shape", "expected"),
    [((4, 10**9), "features per row"), ((10**13, OBS_DIM), "fits in memory")],
)
def test_absurd_shapes_fail_before_anything_is_read(tmp_path, shape, expected):
    path = tmp_path / "absurd.hdf5"
    with h5py.File(path, "w") as f:
        # chunked and never written: the file stays tiny whatever the declared shape
        f.create_dataset("observations", shape=shape, dtype="f4", chunks=(1, 1))
        for name, dims in (
            ("actions", (shape[0], 1)),
            ("rewards", (shape[0],)),
            ("terminals", (shape[0],)),
        ):
            f.create_dataset(name, shape=dims, dtype="f4", chunks=(1,) * len(dims))

    with pytest.raises(DataFormatError) as error:
        load_source(str(path))

    _assert_names(error, path, "observations")
    assert expected in str(error.value)


def test_not_an_hdf5_file(tmp_path):
    path = tmp_path / "notes.hdf5"
    path.write_text("observations,actions\n1,2\n")

    with pytest.raises(DataFormatError) as error:
        load_source(str(path))

    _assert_names(error, path, "file")


def test_truncated_file(tmp_path):
    path = tmp_path / "cut.hdf5"
    make_d4rl_file(path, n=500, obs_dim=OBS_DIM, act_dim=ACT_DIM, seed=0)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])

    with pytest.raises(DataFormatError) as error:
        load_source(str(path))

    _assert_names(error, path, "file")
    assert "truncated" in str(error.value)


def test_missing_file_says_where_it_looked(tmp_path, dataset_root):
    with pytest.raises(DatasetNotFoundError, match="absent.hdf5") as error:
        load_source(str(tmp_path / "absent.hdf5"))
    assert str(dataset_root) in str(error.value)


def test_unknown_minari_id_says_where_it_looked_and_what_to_do(dataset_root):
    with pytest.raises(DatasetNotFoundError) as error:
        load_source("mujoco/hopper/medium-v0")
    message = str(error.value)
    assert str(dataset_root / "mujoco/hopper/medium-v0" / "data" / "metadata.json") in message
    assert "copy the dataset" in message


def test_unknown_task_suggests_close_names(dataset_root):
    with pytest.raises(DatasetNotFoundError) as error:
        load_source("hoper-m-r")
    assert "hopper-m-r" in str(error.value) and str(dataset_root) in str(error.value)


def test_task_without_local_data_says_how_to_collect_it(dataset_root):
    with pytest.raises(DatasetNotFoundError) as error:
        load_source("walker2d-m")
    assert "hipode collect walker2d-m" in str(error.value)
    assert "local/walker2d/medium-v0" in str(error.value)


def test_path_tricks_are_not_minari_ids(dataset_root):
    with pytest.raises(DatasetNotFoundError):
        load_source("../outside/data-v0")


def _minari_dataset(dataset_id: str) -> tuple:
    episodes = make_episodes(3, OBS_DIM, ACT_DIM, seed=0, lengths=[4, 6, 5])
    folder = make_minari_dataset(dataset_id, episodes)
    return folder / "data" / "main_data.hdf5", folder / "data" / "metadata.json"


def _replace(h5_path, name: str, value) -> None:
    with h5py.File(h5_path, "a") as f:
        del f[name]
        if isinstance(value, dict):
            group = f.create_group(name)
            for key, array in value.items():
                group[key] = array
        else:
            f[name] = value


@pytest.mark.parametrize(
    ("damage", "field"),
    [
        (
            lambda h5: _replace(h5, "episode_1/observations", np.zeros((6, OBS_DIM))),
            "episode_1/observations",
        ),
        (
            lambda h5: _replace(h5, "episode_2/actions", np.zeros((5, ACT_DIM + 1))),
            "episode_2/actions",
        ),
        (
            lambda h5: _replace(h5, "episode_1/observations", np.full((7, OBS_DIM), np.nan)),
            "episode_1/observations",
        ),
        (lambda h5: _replace(h5, "episode_0/terminations", np.full(4, 3)), "terminals"),
        (
            lambda h5: _replace(h5, "episode_0/observations", {"pos": np.zeros((5, 2))}),
            "episode_0/observations",
        ),
        (
            lambda h5: _replace(h5, "episode_2/rewards", np.array(["a"] * 5, dtype="S1")),
            "episode_2/rewards",
        ),
    ],
    ids=[
        "observations not T+1",
        "action dims differ",
        "NaN",
        "non-0/1 terminations",
        "dict space",
        "string rewards",
    ],
)
def test_malformed_minari_episode(damage, field):
    h5_path, _ = _minari_dataset("test/hopper/damaged-v0")
    damage(h5_path)

    with pytest.raises(DataFormatError) as error:
        load_source("test/hopper/damaged-v0")

    _assert_names(error, h5_path, field)


def test_minari_metadata_that_is_not_json():
    _, metadata_path = _minari_dataset("test/hopper/bad-metadata-v0")
    metadata_path.write_text("{not json")

    with pytest.raises(DataFormatError) as error:
        load_source("test/hopper/bad-metadata-v0")

    _assert_names(error, metadata_path, "metadata")


def test_minari_total_steps_that_do_not_match_the_episodes():
    _, metadata_path = _minari_dataset("test/hopper/bad-steps-v0")
    metadata = json.loads(metadata_path.read_text())
    metadata["total_steps"] = 12
    metadata_path.write_text(json.dumps(metadata))

    with pytest.raises(DataFormatError) as error:
        load_source("test/hopper/bad-steps-v0")

    _assert_names(error, metadata_path, "total_steps")


def test_minari_missing_episode_group():
    h5_path, _ = _minari_dataset("test/hopper/lost-episode-v0")
    with h5py.File(h5_path, "a") as f:
        del f["episode_2"]

    with pytest.raises(DataFormatError) as error:
        load_source("test/hopper/lost-episode-v0")

    _assert_names(error, h5_path, "episode_2")
