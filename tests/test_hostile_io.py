"""Paths of the wrong kind and values too long to print: every command answers with one
bounded line (or a bounded table), never a traceback, and writes or loses nothing."""

from __future__ import annotations

import json
import os
import shutil

import pytest
from test_merge import write_source
from test_sharing import _artifact_from
from typer.testing import CliRunner

from hipode_pipeline import console
from hipode_pipeline.artifact import read_artifact, write_artifact
from hipode_pipeline.cli import app
from hipode_pipeline.sharing import export_artifact, sidecar_path

BIG = 10 * 1024 * 1024  # characters in a hostile manifest value
BIG_TEXT = f"({BIG:,} characters)"
# what any answer to a hostile file may print, all streams together
OUTPUT_LIMIT = 20_000


@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    """A source, its valid artifact, and artifacts whose manifests carry hostile values."""
    folder = tmp_path_factory.mktemp("originals")
    source = write_source(folder / "src.hdf5", n_episodes=2, length=25)
    artifact = _artifact_from(source, folder / "art.hdf5")
    stored = read_artifact(artifact)
    base = {k: v for k, v in stored.manifest.items() if k not in ("schema", "checksum")}
    hostile = {
        "big_task": {"task": "t" * BIG},
        "big_env": {"env_id": "E" * BIG},
        "big_created": {"created_utc": "c" * BIG},
        "markup": {"task": "[/x] [bold]\x1b[2J\x07\nsecond line"},
    }
    for name, change in hostile.items():
        write_artifact(
            folder / f"{name}.hdf5", stored.transitions, stored.diagnostics, {**base, **change}
        )
    return folder


@pytest.fixture
def ws(tmp_path, originals, dataset_root, monkeypatch):
    """A work folder with the files, plus a folder, a plain file and a FIFO to misuse."""
    for item in originals.iterdir():
        shutil.copyfile(item, tmp_path / item.name)
    (tmp_path / "adir").mkdir()
    (tmp_path / "adir" / "kept.txt").write_text("keep me")
    (tmp_path / "afile").write_text("keep me too")
    os.mkfifo(tmp_path / "fifo")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _snapshot(folder):
    """Every path under `folder` with its bytes (None for folders and FIFOs)."""
    found = {}
    for path in sorted(folder.rglob("*")):
        regular = path.is_file() and not path.is_symlink()
        found[path.relative_to(folder).as_posix()] = path.read_bytes() if regular else None
    return found


def _invoke(args):
    result = CliRunner().invoke(app, args)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    text = result.stdout + result.stderr
    assert "Traceback" not in text and len(text) < OUTPUT_LIMIT
    return result


def _one_error_line(result):
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    return lines[0]


# (args, exit code, what the one line must say); {name} is a path in the work folder
PATH_KIND_CASES = {
    "export-out-dir": (["export", "art.hdf5", "--out", "adir"], 2, ["--out adir", "a directory"]),
    "export-out-dir-force": (
        ["export", "art.hdf5", "--out", "adir", "--force"],
        2,
        ["--out adir", "expected a file path, found a directory"],
    ),
    "export-out-under-file": (
        ["export", "art.hdf5", "--out", "afile/x.hdf5"],
        2,
        ["--out afile/x.hdf5", "expected a folder at afile, found a file"],
    ),
    "export-out-fifo-force": (
        ["export", "art.hdf5", "--out", "fifo", "--force"],
        2,
        ["--out fifo", "a FIFO"],
    ),
    "export-sidecar-dir-force": (
        ["export", "art.hdf5", "--out", "copy.hdf5", "--force"],
        2,
        ["copy.hdf5.sha256", "a directory"],
    ),
    "export-d4rl-out-dir": (
        ["export", "art.hdf5", "--d4rl", "--source", "src.hdf5", "--out", "adir", "--force"],
        2,
        ["--out adir", "a directory"],
    ),
    "merge-out-dir-force": (
        ["merge", "src.hdf5", "art.hdf5", "--out", "adir", "--force"],
        2,
        ["--out adir", "a directory"],
    ),
    "merge-out-under-file": (
        ["merge", "src.hdf5", "art.hdf5", "--out", "afile/m.hdf5"],
        2,
        ["--out afile/m.hdf5", "found a file"],
    ),
    "merge-out-fifo-force": (
        ["merge", "src.hdf5", "art.hdf5", "--out", "fifo", "--force"],
        2,
        ["--out fifo", "a FIFO"],
    ),
    "merge-root-file": (
        ["merge", "src.hdf5", "art.hdf5", "--out", "m.hdf5", "--root", "afile"],
        2,
        ["--root afile", "expected a folder, found a file"],
    ),
    "import-root-file": (["import", "art.hdf5", "--root", "afile"], 2, ["--root afile"]),
    "import-root-under-file": (
        ["import", "art.hdf5", "--root", "afile/sub"],
        2,
        ["--root afile/sub", "expected a folder at afile, found a file"],
    ),
    "import-artifacts-is-file": (
        ["import", "art.hdf5", "--root", "root_with_file"],
        2,
        ["root_with_file/artifacts", "found a file"],
    ),
    "import-target-dir-force": (
        ["import", "art.hdf5", "--root", "root_with_dir", "--force"],
        2,
        ["root_with_dir/artifacts/art.hdf5", "a directory"],
    ),
    "import-file-is-dir": (["import", "adir"], 2, ["adir", "found a directory"]),
    "import-file-is-fifo": (["import", "fifo"], 2, ["fifo", "FIFO"]),
    "datasets-list-root-file": (["datasets", "list", "--root", "afile"], 2, ["--root afile"]),
    "datasets-list-json-root-file": (
        ["datasets", "list", "--root", "afile", "--json"],
        2,
        ["--root afile"],
    ),
    "datasets-show-root-file": (
        ["datasets", "show", "src.hdf5", "--root", "afile"],
        2,
        ["--root afile", "found a file"],
    ),
    "verify-out-dir-file": (
        ["verify", "art.hdf5", "--out-dir", "afile"],
        2,
        ["--out-dir afile", "expected a folder, found a file"],
    ),
    "verify-out-dir-under-file": (
        ["verify", "art.hdf5", "--out-dir", "afile/reports"],
        2,
        ["--out-dir afile/reports", "found a file"],
    ),
    "collect-root-file": (["collect", "hopper-m-r", "--root", "afile"], 2, ["--root afile"]),
    "augment-root-file": (
        ["augment", "hopper-m-r", "--source", "src.hdf5", "--root", "afile"],
        2,
        ["--root afile", "found a file"],
    ),
    "augment-root-fifo": (
        ["augment", "hopper-m-r", "--source", "src.hdf5", "--root", "fifo"],
        2,
        ["--root fifo", "a FIFO"],
    ),
    "train-root-file": (
        ["train", "hopper-m-r", "--data", "source", "--root", "afile"],
        2,
        ["--root afile", "found a file"],
    ),
    "sweep-root-file": (["sweep", "--root", "afile"], 2, ["--root afile", "found a file"]),
}


@pytest.mark.parametrize("case", sorted(PATH_KIND_CASES))
def test_a_path_of_the_wrong_kind_is_one_clear_error(ws, case):
    args, code, needles = PATH_KIND_CASES[case]
    (ws / "copy.hdf5.sha256").mkdir()
    (ws / "root_with_file").mkdir()
    (ws / "root_with_file" / "artifacts").write_text("not a folder")
    (ws / "root_with_dir" / "artifacts" / "art.hdf5").mkdir(parents=True)
    before = _snapshot(ws)

    result = _invoke(args)

    assert result.exit_code == code, result.output
    line = _one_error_line(result)
    for needle in needles:
        assert needle in line
    assert result.stdout == ""
    assert _snapshot(ws) == before


def test_a_dataset_root_variable_naming_a_file_is_one_clear_error(ws, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(ws / "afile"))
    before = _snapshot(ws)

    result = _invoke(["datasets", "list"])

    assert result.exit_code == 2
    assert "$MINARI_DATASETS_PATH" in _one_error_line(result)
    assert "expected a folder, found a file" in result.stderr
    assert _snapshot(ws) == before


@pytest.mark.parametrize("name", ["big_task", "big_env", "big_created"])
def test_inspect_cuts_a_huge_manifest_value(ws, name, monkeypatch):
    monkeypatch.setattr(console.out, "width", 400)  # room for a cut value on one line
    before = _snapshot(ws)

    result = _invoke(["inspect", f"{name}.hdf5"])

    assert result.exit_code == 0, result.stderr
    assert result.stdout.count(BIG_TEXT) == 1
    assert _snapshot(ws) == before
    # --json is one file's record, asked for on purpose: it keeps the value whole
    key = {"big_task": "task", "big_env": "env_id", "big_created": "created_utc"}[name]
    whole = CliRunner().invoke(app, ["inspect", f"{name}.hdf5", "--json"])
    assert len(json.loads(whole.stdout)["manifest"][key]) == BIG


def _install_hostile_artifacts(ws, dataset_root):
    (dataset_root / "artifacts").mkdir()
    for name in ("big_task", "big_env", "markup", "art"):
        shutil.copyfile(ws / f"{name}.hdf5", dataset_root / "artifacts" / f"{name}.hdf5")


@pytest.mark.parametrize("as_json", [False, True], ids=["table", "json"])
def test_datasets_list_cuts_huge_values(ws, dataset_root, as_json, monkeypatch):
    _install_hostile_artifacts(ws, dataset_root)
    monkeypatch.setattr(console.out, "width", 400)  # room for a cut value on one line
    before = _snapshot(ws)

    result = _invoke(["datasets", "list", *(["--json"] if as_json else [])])

    assert result.exit_code == 0, result.stderr
    if as_json:
        rows = {row["id"]: row for row in json.loads(result.stdout)}
        assert rows["artifacts/big_task.hdf5"]["task"].endswith(BIG_TEXT)
        assert rows["artifacts/big_env.hdf5"]["env_id"].endswith(BIG_TEXT)
        assert rows["artifacts/art.hdf5"]["task"] == "hopper-m-r"
    else:
        assert result.stdout.count(BIG_TEXT) == 2
    assert _snapshot(ws) == before


@pytest.mark.parametrize("command", ["inspect", "datasets list"])
def test_markup_and_terminal_escapes_from_a_file_print_as_text(
    ws, dataset_root, command, monkeypatch
):
    _install_hostile_artifacts(ws, dataset_root)
    # wide enough that no cell wraps, whatever the temporary paths' lengths
    monkeypatch.setattr(console.out, "width", 2000)
    args = ["inspect", "markup.hdf5"] if command == "inspect" else ["datasets", "list"]

    result = _invoke(args)

    assert result.exit_code == 0, result.stderr
    assert "[/x]" in result.stdout and "\\x1b[2J" in result.stdout
    assert "\x1b" not in result.stdout and "\x07" not in result.stdout


def test_an_error_quoting_a_huge_value_is_one_short_line(ws):
    before = _snapshot(ws)

    result = _invoke(["merge", "src.hdf5", "big_env.hdf5", "--out", "merged.hdf5"])

    assert result.exit_code == 2
    line = _one_error_line(result)
    assert "big_env.hdf5" in line and "field 'manifest.env_id'" in line and BIG_TEXT in line
    assert len(line) < 1500
    assert _snapshot(ws) == before


def test_an_import_with_a_huge_sidecar_is_one_short_line(ws, dataset_root):
    exported = ws / "inbox" / "art.hdf5"
    export_artifact(ws / "art.hdf5", exported)
    sidecar_path(exported).write_text("f" * BIG)
    before = _snapshot(ws)

    result = _invoke(["import", str(exported)])

    assert result.exit_code == 2
    line = _one_error_line(result)
    assert "art.hdf5.sha256" in line and "field 'sha256'" in line and "64 hex digits" in line
    assert len(line) < 1500
    assert _snapshot(ws) == before
    assert not (dataset_root / "artifacts").exists()


def test_an_error_naming_a_path_with_a_newline_stays_one_line(ws):
    result = _invoke(["inspect", "two\nlines\x1b[31m.hdf5"])

    assert result.exit_code == 2
    line = _one_error_line(result)
    assert "two\\nlines\\x1b[31m.hdf5" in line and "\x1b" not in result.stderr
