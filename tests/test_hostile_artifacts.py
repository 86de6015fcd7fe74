"""A file from another team can never hurt you: hostile artifacts, sources and merged files are
refused with the exact error class (or `hipode validate` exit 1 and the violation's field), one
line without a traceback, and nothing is written, installed or opened because a file said so."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
from pathlib import Path

import h5py
import numpy as np
import pytest
from builders import make_d4rl_file
from test_merge import write_source, write_synthetic
from typer.testing import CliRunner

from hipode_pipeline.artifact import (
    MANIFEST_ATTR,
    content_checksum,
    read_artifact,
    read_manifest,
    seal_manifest,
)
from hipode_pipeline.cli import app
from hipode_pipeline.data.load import load_recorded_source, load_source
from hipode_pipeline.errors import DataFormatError, DatasetNotFoundError
from hipode_pipeline.merge import merge_files, read_merged
from hipode_pipeline.validation import validate_artifact

REFERENCE = Path(__file__).parent / "data" / "reference_artifact.hdf5"
DIGEST = "manifest.manifest_checksum"


# --- helpers ---------------------------------------------------------------------------------


def snapshot(*folders: Path) -> dict[str, int]:
    """Every file under `folders` with its size: what a refused command must leave unchanged."""
    return {
        str(path): path.lstat().st_size
        for folder in folders
        for path in sorted(folder.rglob("*"))
        if path.is_symlink() or path.is_file()
    }


def invoke(args: list[str]):
    result = CliRunner().invoke(app, [str(a) for a in args])
    # a HipodeError ends in typer.Exit (SystemExit); anything else is a crash
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output
    return result


def copy_reference(folder: Path, name: str = "art.hdf5") -> Path:
    path = folder / name
    shutil.copyfile(REFERENCE, path)
    return path


def edit_manifest(path: Path, change, *, reseal: bool = False) -> None:
    """Apply `change` to the parsed manifest (returns the new one, or text to store as is)."""
    with h5py.File(path, "r+") as f:
        edited = change(json.loads(f.attrs[MANIFEST_ATTR]))
        if isinstance(edited, dict):
            edited = json.dumps(seal_manifest(edited) if reseal else edited)
        f.attrs[MANIFEST_ATTR] = edited


def set_key(dotted: str, value):
    def change(manifest):
        target = manifest
        *parents, last = dotted.split(".")
        for part in parents:
            target = target.setdefault(part, {})
        target[last] = value
        return manifest

    return change


def refused_by_readers(path: Path, field: str) -> DataFormatError:
    """read_artifact and validate both name `field`; the file's bytes stay as they were."""
    before = path.read_bytes()
    with pytest.raises(DataFormatError) as caught:
        read_artifact(path)
    assert caught.value.field == field, str(caught.value)
    assert str(path) in str(caught.value)
    report = validate_artifact(path)
    assert not report.valid and field in [v.field for v in report.errors], report.to_dict()
    assert path.read_bytes() == before
    return caught.value


def write_raw_artifact(path: Path, arrays: dict[str, np.ndarray], **manifest) -> Path:
    """An artifact written by hand (the writer refuses what some cases need), sealed."""
    with h5py.File(path, "w") as f:
        for name, array in arrays.items():
            f.create_dataset(name, data=array)
        stored = {
            **manifest,
            "schema": {"name": "hipode-synthetic", "version": "1.1"},
            "checksum": content_checksum(arrays),
        }
        f.attrs[MANIFEST_ATTR] = json.dumps(seal_manifest(stored))
    return path


def reference_arrays(rows: slice = slice(None)) -> dict[str, np.ndarray]:
    artifact = read_artifact(REFERENCE)
    return {
        name: array[rows]
        for name, array in {**artifact.transitions.arrays(), **artifact.diagnostics}.items()
    }


@contextlib.contextmanager
def deadline(seconds: int):
    """Fail instead of hanging when something opens a FIFO after all."""

    def expire(*_):
        raise TimeoutError(f"blocked for {seconds} s: a FIFO was opened")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture
def pair(tmp_path, dataset_root):
    """A D4RL source inside the dataset root and an artifact built from it (as `hipode augment`
    would record it: `source.id` as the user typed it)."""
    (dataset_root / "d4rl").mkdir()
    source = write_source(dataset_root / "d4rl" / "src.hdf5")
    artifact = tmp_path / "art.hdf5"
    write_synthetic(artifact, "d4rl/src.hdf5")
    return source, artifact


# --- 1. manifest edits: every provenance key and nested setting is covered by the digest ----

MANIFEST_EDITS = {
    "task": set_key("task", "walker2d-m-r"),
    "env_id": set_key("env_id", "Walker2d-v5"),
    "ref_min_score": set_key("ref_min_score", 0.0),
    "ref_max_score": set_key("ref_max_score", 1.0),
    "source": set_key("source", {"id": "elsewhere", "sha256": "1" * 64}),
    "created_utc": set_key("created_utc", "2030-01-01T00:00:00+00:00"),
    "hyper_parameters": set_key("hyper_parameters", {"eta": 0.5}),
    "seeds": set_key("seeds", {"seed": 7}),
    "generators": set_key("generators", {"device": "cuda"}),
    "versions": set_key("versions", {"hipode_pipeline": "9.9"}),
    "counts": set_key("counts", {"kept": 48, "candidates": 1}),
    "hyper_parameters.eta": set_key("hyper_parameters.eta", 0.9),
    "seeds.seed": set_key("seeds.seed", 1),
    "source.sha256": set_key("source.sha256", "f" * 64),
    "source.id": set_key("source.id", "d4rl/other.hdf5"),
    "schema.version-minor": set_key("schema.version", "1.4"),
    "checksum-of-other-content": set_key("checksum", "sha256:" + "a" * 64),
    "key-added": set_key("note", "added later"),
    "key-removed": lambda m: {k: v for k, v in m.items() if k != "created_utc"},
}


@pytest.mark.parametrize("case", sorted(MANIFEST_EDITS))
def test_edited_manifest_fails_its_digest(case, tmp_path):
    path = copy_reference(tmp_path)
    edit_manifest(path, MANIFEST_EDITS[case])
    refused_by_readers(path, DIGEST)
    with pytest.raises(DataFormatError) as caught:
        read_manifest(path)
    assert caught.value.field == DIGEST
    assert "edited or corrupted" in str(caught.value) and "expected sha256:" in str(caught.value)


def test_edited_manifest_through_the_cli(tmp_path, dataset_root):
    path = copy_reference(tmp_path)
    edit_manifest(path, set_key("hyper_parameters.eta", 0.9))
    before = snapshot(tmp_path)
    result = invoke(["validate", path, "--json"])
    assert result.exit_code == 1
    errors = [
        v["field"] for v in json.loads(result.stdout)["violations"] if v["severity"] == "error"
    ]
    assert errors == [DIGEST]
    for command in (["inspect", path], ["import", path, "--root", dataset_root]):
        result = invoke(command)
        assert result.exit_code == 2 and DIGEST in result.stderr
    assert snapshot(tmp_path) == before
    assert not (dataset_root / "artifacts").exists() or not any(
        (dataset_root / "artifacts").iterdir()
    )


def test_edited_manifest_is_refused_by_merge_and_train(pair, tmp_path):
    source, artifact = pair
    edit_manifest(artifact, set_key("counts.kept", 19))
    before = snapshot(tmp_path)
    merged = tmp_path / "merged.hdf5"
    result = invoke(["merge", source, artifact, "--out", merged])
    assert result.exit_code == 2 and DIGEST in result.stderr
    runs = tmp_path / "runs"
    result = invoke(
        ["train", "hopper-m-r", "--artifact", artifact, "--source", source, "--out", runs]
        + ["--steps", "1", "--eval-episodes", "1", "--device", "cpu"]
    )
    assert result.exit_code == 2 and DIGEST in result.stderr
    assert snapshot(tmp_path) == before and not merged.exists() and not runs.exists()


# --- 2. the digest itself removed or garbled on a 1.1 file ----------------------------------

DIGEST_DAMAGE = {
    "removed": lambda m: {k: v for k, v in m.items() if k != "manifest_checksum"},
    "not-hex": set_key("manifest_checksum", "sha256:xyz"),
    "a-number": set_key("manifest_checksum", 12345),
    "other-algorithm": set_key("manifest_checksum", "md5:" + "0" * 32),
    "uppercase-hex": lambda m: {**m, "manifest_checksum": m["manifest_checksum"].upper()},
    "well-formed-but-wrong": set_key("manifest_checksum", "sha256:" + "0" * 64),
}


@pytest.mark.parametrize("case", sorted(DIGEST_DAMAGE))
def test_damaged_digest_is_refused(case, tmp_path):
    path = copy_reference(tmp_path)
    edit_manifest(path, DIGEST_DAMAGE[case])
    refused_by_readers(path, DIGEST)


# --- 3. version downgrade to 1.0 ------------------------------------------------------------


def test_downgrade_keeping_the_digest_fails_it(tmp_path):
    # the digest covers the schema entry too
    path = copy_reference(tmp_path)
    edit_manifest(path, set_key("schema.version", "1.0"))
    refused_by_readers(path, DIGEST)


def test_downgrade_without_digest_reads_but_warns_that_nothing_is_authenticated(tmp_path):
    # documented in docs/schema.md: a 1.0 file has no manifest digest, so an edit together with
    # a downgrade is only visible as this warning; the content checksum still holds
    path = copy_reference(tmp_path)

    def downgrade(manifest):
        manifest = {k: v for k, v in manifest.items() if k != "manifest_checksum"}
        manifest["schema"]["version"] = "1.0"
        manifest["hyper_parameters"]["eta"] = 0.9
        return manifest

    edit_manifest(path, downgrade)
    assert read_artifact(path).manifest["hyper_parameters"]["eta"] == 0.9
    result = invoke(["validate", path, "--json"])
    assert result.exit_code == 0
    [warning] = json.loads(result.stdout)["violations"]
    assert (warning["field"], warning["severity"]) == (DIGEST, "warning")
    assert "not authenticated" in warning["expected"] and "1.0" in warning["found"]


# --- 4. NaN / Infinity tokens and other non-strict JSON -------------------------------------

NON_STRICT = {
    "NaN-top-level": lambda m: json.dumps({**m, "ref_min_score": float("nan")}),
    "Infinity-nested": lambda m: json.dumps(set_key("hyper_parameters.eta", float("inf"))(m)),
    "minus-Infinity": lambda m: json.dumps(set_key("counts.kept", float("-inf"))(m)),
    "overflowing-number": lambda m: json.dumps(m).replace('"kept": 48', '"kept": 1e999'),
    "duplicate-key": lambda m: json.dumps(m)[:-1] + ', "task": "walker2d-m-r"}',
}


@pytest.mark.parametrize("case", sorted(NON_STRICT))
def test_non_strict_json_manifest_is_refused(case, tmp_path):
    path = copy_reference(tmp_path)
    edit_manifest(path, NON_STRICT[case])
    error = refused_by_readers(path, "manifest")
    assert "strict JSON" in error.expected


# --- 5. nested and non-object manifests -----------------------------------------------------

NOT_OBJECTS = {
    "string-of-a-string": (lambda m: json.dumps(json.dumps(m)), "a string"),
    "array": (lambda m: json.dumps([m]), "a list"),
    "number": (lambda m: "42", "an integer"),
    "null": (lambda m: "null", "null"),
    "deeply-nested": (lambda m: "[" * 100_000 + "]" * 100_000, "nested too deeply"),
}


@pytest.mark.parametrize("case", sorted(NOT_OBJECTS))
def test_manifest_that_is_not_an_object_says_so(case, tmp_path):
    change, found = NOT_OBJECTS[case]
    path = copy_reference(tmp_path)
    edit_manifest(path, change)
    error = refused_by_readers(path, "manifest")
    assert "JSON object" in error.expected and found in str(error.found)
    result = invoke(["inspect", path])
    assert result.exit_code == 2 and "complete HDF5 file" not in result.stderr


# --- 6. mistyped sub-fields, in every reader and in `hipode verify` -------------------------

MISTYPED = {
    "source-a-string": ("manifest.source", set_key("source", "d4rl/src.hdf5")),
    "seeds-a-list": ("manifest.seeds", set_key("seeds", [0])),
    "hyper-parameters-a-number": ("manifest.hyper_parameters", set_key("hyper_parameters", 0.9)),
    "eta-a-string": ("manifest.hyper_parameters.eta", set_key("hyper_parameters.eta", "0.9")),
    "seed-a-string": ("manifest.seeds.seed", set_key("seeds.seed", "0")),
    "source-id-a-number": ("manifest.source.id", set_key("source.id", 7)),
    "source-sha256-not-hex": ("manifest.source.sha256", set_key("source.sha256", "abc")),
    "kept-a-float": ("manifest.counts.kept", set_key("counts.kept", 48.5)),
    "n-a-boolean": ("manifest.hyper_parameters.n", set_key("hyper_parameters.n", True)),
}


@pytest.mark.parametrize("case", sorted(MISTYPED))
def test_mistyped_sub_field_is_named(case, tmp_path):
    # re-sealed: the digest is not what catches these, the types are
    field, change = MISTYPED[case]
    path = copy_reference(tmp_path)
    edit_manifest(path, change, reseal=True)
    error = refused_by_readers(path, field)
    # what the value is, in JSON's words: "a string '0.9'", "a list"
    assert str(error.found).startswith(("a ", "an ")) and error.expected.startswith(("a ", "an "))
    with pytest.raises(DataFormatError) as caught:
        read_manifest(path)
    assert caught.value.field == field


VERIFY_NEEDS = {
    "no-source-id": (
        "manifest.source.id",
        lambda m: {**m, "source": {k: v for k, v in m["source"].items() if k != "id"}},
    ),
    "no-env-id": ("manifest.env_id", lambda m: {k: v for k, v in m.items() if k != "env_id"}),
    "eta-a-string": ("manifest.hyper_parameters.eta", set_key("hyper_parameters.eta", "x")),
    "normalizer-eps-a-string": (
        "manifest.hyper_parameters.generator_config.normalizer_eps",
        set_key("hyper_parameters.generator_config", {"normalizer_eps": "tiny"}),
    ),
}


@pytest.mark.parametrize("case", sorted(VERIFY_NEEDS))
def test_verify_names_a_mistyped_or_missing_field(case, pair, tmp_path, dataset_root):
    _, artifact = pair
    field, change = VERIFY_NEEDS[case]
    edit_manifest(artifact, change, reseal=True)
    before = snapshot(tmp_path)
    result = invoke(["verify", artifact, "--sample", "4", "--no-baseline", "--root", dataset_root])
    assert result.exit_code == 2 and f"field '{field}'" in result.stderr, result.stderr
    assert snapshot(tmp_path) == before


# --- 7. zero rows ---------------------------------------------------------------------------


def test_zero_row_artifact_is_an_error(tmp_path, dataset_root):
    path = write_raw_artifact(tmp_path / "empty.hdf5", reference_arrays(slice(0, 0)))
    error = refused_by_readers(path, "observations")
    assert "at least one synthetic transition" in error.expected
    assert invoke(["validate", path]).exit_code == 1
    result = invoke(["inspect", path])
    assert result.exit_code == 2 and "at least one synthetic transition" in result.stderr
    with pytest.raises(DataFormatError, match="at least one synthetic transition"):
        load_source(str(path))


# --- 8. names in a file that point outside the dataset root ---------------------------------


@pytest.fixture
def outside(tmp_path):
    """A valid source outside the dataset root: nothing may open it because a file says so."""
    folder = tmp_path / "outside"
    folder.mkdir()
    return write_source(folder / "src.hdf5")


class OpenedFiles:
    """Records every path h5py opens, so a test can tell that one was never touched."""

    def __init__(self, monkeypatch):
        self.paths: list[Path] = []
        original = h5py.File
        recorder = self

        class Recording(original):
            def __init__(self, name, *args, **kwargs):
                if isinstance(name, str | os.PathLike):
                    recorder.paths.append(Path(name).resolve())
                super().__init__(name, *args, **kwargs)

        monkeypatch.setattr(h5py, "File", Recording)


def _source_id_cases(outside: Path, root: Path) -> dict[str, str]:
    (root / "d4rl").mkdir(exist_ok=True)
    link = root / "d4rl" / "link.hdf5"
    if not link.is_symlink():
        link.symlink_to(outside)
    return {
        "absolute": str(outside),
        "dot-dot": os.path.relpath(outside, root),
        "symlink-out-of-root": "d4rl/link.hdf5",
        "minari-id-with-dot-dot": "local/../../outside",
    }


@pytest.mark.parametrize(
    "case", ["absolute", "dot-dot", "symlink-out-of-root", "minari-id-with-dot-dot"]
)
def test_verify_never_opens_a_source_outside_the_root(
    case, outside, tmp_path, dataset_root, monkeypatch
):
    spec = _source_id_cases(outside, dataset_root)[case]
    artifact = tmp_path / "art.hdf5"
    # built from the outside file, then (re-sealed) pointed at it by each spelling
    write_synthetic(artifact, outside)
    edit_manifest(artifact, set_key("source.id", spec), reseal=True)
    opened = OpenedFiles(monkeypatch)
    before = snapshot(tmp_path)
    result = invoke(["verify", artifact, "--sample", "4", "--no-baseline", "--root", dataset_root])
    assert result.exit_code == 2, result.output
    assert "field 'manifest.source.id'" in result.stderr and "inside the dataset root" in (
        " ".join(result.stderr.split())
    )
    assert outside.resolve() not in opened.paths
    assert snapshot(tmp_path) == before


def test_recorded_source_inside_the_root_is_loaded(outside, dataset_root):
    shutil.copyfile(outside, dataset_root / "inside.hdf5")
    transitions, info = load_recorded_source(
        "inside.hdf5", dataset_root, origin="a.hdf5", field="manifest.source.id"
    )
    assert len(transitions) == 100 and info.id == "inside.hdf5"
    with pytest.raises(DataFormatError) as caught:
        load_recorded_source(str(outside), dataset_root, origin="a.hdf5", field="x.id")
    assert caught.value.field == "x.id"


LINKS = {
    "external-link": lambda target: h5py.ExternalLink(str(target), "/observations"),
    "soft-link": lambda target: h5py.SoftLink("/actions"),
}


@pytest.mark.parametrize("case", sorted(LINKS))
def test_source_file_linking_elsewhere_is_refused(case, outside, tmp_path, monkeypatch):
    path = write_source(tmp_path / "linked.hdf5")
    with h5py.File(path, "r+") as f:
        del f["observations"]
        f["observations"] = LINKS[case](outside)
    opened = OpenedFiles(monkeypatch)
    with pytest.raises(DataFormatError) as caught:
        load_source(str(path))
    assert caught.value.field == "observations" and "stored in this file" in caught.value.expected
    assert outside.resolve() not in opened.paths


def test_source_with_external_storage_is_refused(outside, tmp_path):
    raw = tmp_path / "outside" / "raw.bin"
    raw.write_bytes(np.zeros(100, np.float32).tobytes())
    path = write_source(tmp_path / "external.hdf5")
    with h5py.File(path, "r+") as f:
        del f["rewards"]
        f.create_dataset("rewards", shape=(100,), dtype=np.float32, external=[(str(raw), 0, 400)])
    with pytest.raises(DataFormatError) as caught:
        load_source(str(path))
    assert caught.value.field == "rewards" and "other files" in str(caught.value)


# --- 9. an artifact passed as a source goes through the artifact rules ----------------------


def _flip_a_reward_byte(path: Path) -> None:
    with h5py.File(path, "r") as f:
        offset = f["rewards"].id.get_offset()
    with open(path, "r+b") as f:
        f.seek(offset + 2)
        byte = f.read(1)
        f.seek(offset + 2)
        f.write(bytes([byte[0] ^ 0x01]))


AS_SOURCE = {
    "corrupt-checksum": ("checksum", _flip_a_reward_byte),
    "future-schema-9.0": (
        "manifest.schema.version",
        lambda p: edit_manifest(p, set_key("schema.version", "9.0"), reseal=True),
    ),
    "edited-manifest": (DIGEST, lambda p: edit_manifest(p, set_key("hyper_parameters.eta", 0.9))),
    "nan-token": ("manifest", lambda p: edit_manifest(p, NON_STRICT["NaN-top-level"])),
    "missing-diagnostics": ("value", lambda p: _delete(p, "value")),
}


def _delete(path: Path, name: str) -> None:
    with h5py.File(path, "r+") as f:
        del f[name]


@pytest.mark.parametrize("case", sorted(AS_SOURCE))
def test_artifact_as_source_is_verified(case, tmp_path):
    field, damage = AS_SOURCE[case]
    path = copy_reference(tmp_path)
    damage(path)
    with pytest.raises(DataFormatError) as caught:
        load_source(str(path))
    assert caught.value.field == field, str(caught.value)


def test_artifact_as_source_through_the_cli(pair, tmp_path, dataset_root):
    source, artifact = pair
    bad = copy_reference(tmp_path, "bad.hdf5")
    _flip_a_reward_byte(bad)
    before = snapshot(tmp_path, dataset_root)
    result = invoke(["datasets", "show", bad])
    assert result.exit_code == 2 and "field 'checksum'" in result.stderr
    runs = tmp_path / "runs"
    result = invoke(
        ["train", "hopper-m-r", "--source", bad, "--data", "source", "--out", runs]
        + ["--steps", "1", "--eval-episodes", "1", "--device", "cpu"]
    )
    assert result.exit_code == 2 and "field 'checksum'" in result.stderr
    assert snapshot(tmp_path, dataset_root) == before
    # a valid artifact stays usable where a D4RL file is, fully verified
    shown = invoke(["datasets", "show", artifact, "--json"])
    assert shown.exit_code == 0 and json.loads(shown.stdout)["n"] == 20


# --- 10. merged files: provenance is strict and typed too -----------------------------------


def _merged(pair, tmp_path) -> Path:
    source, artifact = pair
    out = tmp_path / "merged.hdf5"
    merge_files(str(source), artifact, out)
    return out


def _set_provenance(path: Path, change) -> None:
    with h5py.File(path, "r+") as f:
        f.attrs["provenance"] = change(json.loads(f.attrs["provenance"]))


MERGED_DAMAGE = {
    "nan-token": ("provenance", lambda p: json.dumps({**p, "x": float("nan")})),
    "a-list": ("provenance", lambda p: json.dumps([p])),
    "source-a-string": ("provenance.source", lambda p: json.dumps({**p, "source": "x"})),
    "embedded-manifest-edited": (
        "provenance.artifact.manifest_checksum",
        lambda p: json.dumps(set_key("artifact.hyper_parameters", {"eta": 0.9})(p)),
    ),
}


@pytest.mark.parametrize("case", sorted(MERGED_DAMAGE))
def test_damaged_merged_file_is_refused(case, pair, tmp_path):
    field, change = MERGED_DAMAGE[case]
    path = _merged(pair, tmp_path)
    _set_provenance(path, change)
    with pytest.raises(DataFormatError) as caught:
        read_merged(path)
    assert caught.value.field == field, str(caught.value)


def test_merged_file_linking_elsewhere_is_refused(pair, outside, tmp_path):
    path = _merged(pair, tmp_path)
    # a target that would read fine: only refusing the link keeps it from being used
    target = outside.with_name("rewards.hdf5")
    with h5py.File(target, "w") as f:
        f["rewards"] = np.zeros(120, np.float32)
    with h5py.File(path, "r+") as f:
        del f["rewards"]
        f["rewards"] = h5py.ExternalLink(str(target), "/rewards")
    with pytest.raises(DataFormatError) as caught:
        read_merged(path)
    assert caught.value.field == "rewards" and "not followed" in str(caught.value)


# --- 11. what is at the path: a directory, a FIFO, a symlink loop, an empty file ------------


def _path_kind(kind: str, folder: Path) -> Path:
    path = folder / "thing.hdf5"
    if kind == "directory":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "symlink-loop":
        path.symlink_to(folder / "other.hdf5")
        (folder / "other.hdf5").symlink_to(path)
    elif kind == "dangling-symlink":
        path.symlink_to(folder / "gone.hdf5")
    elif kind == "empty-file":
        path.write_bytes(b"")
    return path


PATH_KINDS = {
    "directory": "a directory",
    "fifo": "not a regular file",
    "symlink-loop": "a symlink loop",
    "dangling-symlink": "dangling",
    "empty-file": "an empty file",
}


@pytest.mark.parametrize("kind", sorted(PATH_KINDS))
def test_path_kind_is_named(kind, tmp_path):
    path = _path_kind(kind, tmp_path)
    expected = PATH_KINDS[kind]
    with deadline(20):
        report = validate_artifact(path)
        [error] = report.errors
        assert error.field == "file" and expected in error.found, report.to_dict()
        result = invoke(["validate", path])
        assert result.exit_code == 1
        result = invoke(["inspect", path])
        assert result.exit_code == 2 and expected in " ".join(result.stderr.split())
        with pytest.raises(DataFormatError) as caught:
            read_artifact(path)
        assert expected in str(caught.value)
        with pytest.raises(DataFormatError) as caught:
            load_source(str(path))
        assert expected in str(caught.value)
        if kind != "empty-file":
            with pytest.raises(DataFormatError) as caught:
                read_merged(path)
            assert expected in str(caught.value)
    # only a path with nothing at all is "not found"
    with pytest.raises(DatasetNotFoundError, match="no such artifact file"):
        read_artifact(tmp_path / "absent.hdf5")


# --- 12. values beyond float32 --------------------------------------------------------------


def test_float64_source_beyond_float32_says_it_overflows(tmp_path):
    path = tmp_path / "huge.hdf5"
    truth = make_d4rl_file(path, n=20, obs_dim=3, act_dim=2, seed=0)
    rewards = truth["rewards"].astype(np.float64)
    rewards[5] = 1e300
    with h5py.File(path, "r+") as f:
        del f["rewards"]
        f["rewards"] = rewards
    with pytest.raises(DataFormatError) as caught:
        load_source(str(path))
    assert caught.value.field == "rewards"
    assert "overflow float32" in str(caught.value) and "row 5" in str(caught.value)
    assert "NaN" not in str(caught.value)


def test_artifact_value_beyond_float32_is_reported_as_infinite(tmp_path):
    path = copy_reference(tmp_path)
    with h5py.File(path, "r+") as f, np.errstate(over="ignore"):
        # HDF5 converts 1e300 to float32's inf: the file holds inf, and the message says why
        f["rewards"][3] = 1e300
    error = refused_by_readers(path, "rewards")
    assert "1 infinite" in str(error.found) and "float32" in str(error.found)
    assert "NaN" not in str(error.found)
