"""Malformed artifacts: every one is refused with the file and the broken field named, by
read_artifact (DataFormatError) and by `hipode validate` (exit 1, violation listed); a writer
killed mid-write never leaves a file that validates."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from hipode_pipeline.artifact import MANIFEST_ATTR, read_artifact, seal_manifest, write_artifact
from hipode_pipeline.cli import app
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.validation import validate_artifact

M, OBS_DIM, ACT_DIM = 32, 3, 2
FLOAT_FIELDS = (
    "observations",
    "actions",
    "rewards",
    "next_observations",
    "dynamics_error",
    "value",
)
REQUIRED = (
    "observations",
    "actions",
    "rewards",
    "next_observations",
    "terminals",
    "timeouts",
    "dynamics_error",
    "value",
    "source_index",
)


def _valid_artifact(path: Path) -> Path:
    rng = np.random.default_rng(7)
    transitions = Transitions(
        observations=rng.normal(size=(M, OBS_DIM)).astype(np.float32),
        actions=rng.uniform(-1, 1, (M, ACT_DIM)).astype(np.float32),
        rewards=rng.normal(size=M).astype(np.float32),
        next_observations=rng.normal(size=(M, OBS_DIM)).astype(np.float32),
        terminals=np.arange(M) % 8 == 7,
        timeouts=np.zeros(M, dtype=bool),
    )
    diagnostics = {
        "dynamics_error": rng.random(M).astype(np.float32),
        "value": rng.normal(size=M).astype(np.float32),
        "source_index": rng.integers(0, 100, M),
    }
    write_artifact(path, transitions, diagnostics, {"task": "hopper-m-r", "counts": {"kept": M}})
    return path


# --- mutations: each takes a valid file's path and breaks it in one way --------------------


def _truncate(fraction):
    def mutate(path):
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * fraction)])

    return mutate


def _replace(name, data=None, **create):
    def mutate(path):
        with h5py.File(path, "r+") as f:
            if name in f:
                del f[name]
            if data is not None or create:
                f.create_dataset(name, data=data, **create)

    return mutate


def _set_value(name, value):
    def mutate(path):
        with h5py.File(path, "r+") as f:
            array = f[name][()]
            array.flat[len(array.flat) // 2] = value
            f[name][...] = array

    return mutate


def _manifest(change):
    """Edit the manifest and re-seal its digest, so the case tests its own rule (an edit the
    digest catches is in test_hostile_artifacts.py)."""

    def mutate(path):
        with h5py.File(path, "r+") as f:
            text = change(json.loads(f.attrs[MANIFEST_ATTR]))
            try:
                edited = json.loads(text)
            except ValueError:
                edited = None
            if isinstance(edited, dict):
                text = json.dumps(seal_manifest(edited))
            f.attrs[MANIFEST_ATTR] = text

    return mutate


def _with_schema(schema):
    return _manifest(lambda m: json.dumps({**m, "schema": schema}))


def _delete_manifest(path):
    with h5py.File(path, "r+") as f:
        del f.attrs[MANIFEST_ATTR]


def _numeric_manifest(path):
    with h5py.File(path, "r+") as f:
        f.attrs[MANIFEST_ATTR] = np.arange(3)


def _flip_byte(path):
    with h5py.File(path, "r") as f:
        offset = f["observations"].id.get_offset()
    with open(path, "r+b") as f:
        f.seek(offset + 5)
        byte = f.read(1)
        f.seek(offset + 5)
        f.write(bytes([byte[0] ^ 0x10]))


def _link(name, link):
    def mutate(path):
        with h5py.File(path, "r+") as f:
            f[name] = link

    return mutate


def _group(path):
    with h5py.File(path, "r+") as f:
        f.create_group("extras")


CASES = {
    "zero-length": (lambda p: p.write_bytes(b""), "file"),
    "truncated-10%": (_truncate(0.1), "file"),
    "truncated-50%": (_truncate(0.5), "file"),
    "truncated-90%": (_truncate(0.9), "file"),
    "random-bytes": (lambda p: p.write_bytes(np.random.default_rng(0).bytes(4096)), "file"),
    "not-hdf5": (lambda p: p.write_text('{"observations": [[1, 2, 3]]}'), "file"),
    **{f"missing-{name}": (_replace(name), name) for name in REQUIRED},
    "observations-float64": (_replace("observations", np.zeros((M, OBS_DIM))), "observations"),
    "actions-int32": (_replace("actions", np.zeros((M, ACT_DIM), np.int32)), "actions"),
    "terminals-float32": (_replace("terminals", np.zeros(M, np.float32)), "terminals"),
    "source_index-float32": (_replace("source_index", np.zeros(M, np.float32)), "source_index"),
    "rewards-big-endian": (_replace("rewards", np.zeros(M, ">f4")), "rewards"),
    "rewards-rank-2": (_replace("rewards", np.zeros((M, 1), np.float32)), "rewards"),
    "observations-rank-1": (_replace("observations", np.zeros(M, np.float32)), "observations"),
    "actions-rows-mismatch": (
        _replace("actions", np.zeros((M - 1, ACT_DIM), np.float32)),
        "actions",
    ),
    "next_observations-dim": (
        _replace("next_observations", np.zeros((M, OBS_DIM + 1), np.float32)),
        "next_observations",
    ),
    "value-rows-mismatch": (_replace("value", np.zeros(M + 3, np.float32)), "value"),
    **{f"nan-{name}": (_set_value(name, np.nan), name) for name in FLOAT_FIELDS},
    **{f"inf-{name}": (_set_value(name, -np.inf), name) for name in FLOAT_FIELDS},
    "manifest-missing": (_delete_manifest, "manifest"),
    "manifest-not-json": (_manifest(lambda m: "{not json"), "manifest"),
    "manifest-json-list": (_manifest(lambda m: json.dumps([m])), "manifest"),
    "manifest-numeric-attribute": (_numeric_manifest, "manifest"),
    "manifest-without-schema": (
        _manifest(lambda m: json.dumps({k: v for k, v in m.items() if k != "schema"})),
        "manifest.schema",
    ),
    "schema-wrong-name": (_with_schema({"name": "d4rl", "version": "1.0"}), "schema.name"),
    "schema-major-2": (_with_schema({"name": "hipode-synthetic", "version": "2.0"}), "version"),
    "schema-version-malformed": (
        _with_schema({"name": "hipode-synthetic", "version": "v1"}),
        "version",
    ),
    "schema-version-number": (
        _with_schema({"name": "hipode-synthetic", "version": 1.0}),
        "version",
    ),
    "checksum-missing": (
        _manifest(lambda m: json.dumps({k: v for k, v in m.items() if k != "checksum"})),
        "manifest.checksum",
    ),
    "checksum-wrong": (
        _manifest(lambda m: json.dumps({**m, "checksum": "sha256:" + "0" * 64})),
        "checksum",
    ),
    "manifest-task-not-string": (
        _manifest(lambda m: json.dumps({**m, "task": 7})),
        "manifest.task",
    ),
    "flipped-data-byte": (_flip_byte, "checksum"),
    "absurd-rows": (
        _replace("observations", shape=(10**13, OBS_DIM), dtype=np.float32, chunks=(1024, OBS_DIM)),
        "observations",
    ),
    "absurd-obs-dim": (
        _replace("observations", shape=(M, 50_000), dtype=np.float32, chunks=(M, 1024)),
        "observations",
    ),
    "rewards-vlen-strings": (_replace("rewards", ["x"] * M, dtype=h5py.string_dtype()), "rewards"),
    "extra-vlen-strings": (_replace("notes", ["x"] * M, dtype=h5py.string_dtype()), "notes"),
    "extra-float64": (_replace("score", np.zeros(M)), "score"),
    "extra-compound": (
        _replace("pairs", np.zeros(M, dtype=[("a", "f4"), ("b", "i8")])),
        "pairs",
    ),
    "extra-group": (_group, "extras"),
    "external-link": (_link("outside", h5py.ExternalLink("elsewhere.hdf5", "/data")), "outside"),
    "soft-link": (_link("alias", h5py.SoftLink("/rewards")), "alias"),
}


@pytest.fixture(scope="module")
def valid_bytes(tmp_path_factory):
    return _valid_artifact(tmp_path_factory.mktemp("valid") / "valid.hdf5").read_bytes()


def test_there_are_enough_distinct_cases():
    assert len(CASES) >= 30


@pytest.mark.parametrize("case", sorted(CASES))
def test_malformed_file_is_refused_with_file_and_field(case, tmp_path, valid_bytes):
    mutate, field = CASES[case]
    path = tmp_path / "broken.hdf5"
    path.write_bytes(valid_bytes)
    mutate(path)
    with pytest.raises(DataFormatError) as error:
        read_artifact(path)
    assert str(path) in str(error.value)
    assert field in error.value.field
    result = CliRunner().invoke(app, ["validate", str(path), "--json"])
    assert result.exit_code == 1, result.output
    report = json.loads(result.stdout)
    assert report["valid"] is False and report["path"] == str(path)
    errors = [v for v in report["violations"] if v["severity"] == "error"]
    assert any(field in v["field"] for v in errors), errors


def test_validate_lists_every_violation_not_only_the_first(tmp_path, valid_bytes):
    path = tmp_path / "broken.hdf5"
    path.write_bytes(valid_bytes)
    for mutate in (
        _set_value("rewards", np.nan),
        _replace("actions"),
        _replace("value", np.zeros(M)),
    ):
        mutate(path)
    fields = [v.field for v in validate_artifact(path).errors]
    assert {"rewards", "actions", "value"} <= set(fields)


# --- a writer killed mid-write -------------------------------------------------------------

WRITER = """
import sys, time
import h5py, numpy as np
from hipode_pipeline.artifact import write_artifact
from hipode_pipeline.data.transitions import Transitions

original = h5py.Group.create_dataset
def slow_create(self, *args, **kwargs):
    node = original(self, *args, **kwargs)
    self.file.flush()
    print("dataset written", flush=True)
    time.sleep(60)
    return node
h5py.Group.create_dataset = slow_create  # holds the writer mid-file, so the kill lands there

m = 200_000
rng = np.random.default_rng(0)
transitions = Transitions(
    observations=rng.normal(size=(m, 11)).astype(np.float32),
    actions=rng.normal(size=(m, 3)).astype(np.float32),
    rewards=rng.normal(size=m).astype(np.float32),
    next_observations=rng.normal(size=(m, 11)).astype(np.float32),
    terminals=np.zeros(m, bool), timeouts=np.zeros(m, bool),
)
diagnostics = {"dynamics_error": np.zeros(m, np.float32), "value": np.zeros(m, np.float32),
               "source_index": np.arange(m)}
write_artifact(sys.argv[1], transitions, diagnostics, {"task": "hopper-m-r"})
"""


def test_killed_writer_leaves_nothing_that_validates(tmp_path):
    target = tmp_path / "big.hdf5"
    process = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(target)],
        stdout=subprocess.PIPE,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        cwd=Path(__file__).resolve().parent.parent,
    )
    try:
        # blocks until the first dataset is on disk (EOF, and a failure, if the writer died)
        assert b"dataset written" in process.stdout.readline()
        temps = list(tmp_path.glob(".big.hdf5.*.tmp"))
        assert len(temps) == 1 and temps[0].stat().st_size > 0
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    assert not target.exists()
    # the cleanup story: the leftover is hidden, named .<name>.*.tmp, and never validates
    for temp in tmp_path.glob(".big.hdf5.*.tmp"):
        assert not validate_artifact(temp).valid
        result = CliRunner().invoke(app, ["validate", str(temp)])
        assert result.exit_code == 1
