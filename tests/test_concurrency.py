"""Two `hipode` processes at once: nothing is replaced without --force, one output is built
once, and what a killed writer leaves behind is cleaned up by the next."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_merge import write_source
from test_sharing import _artifact_from

from hipode_pipeline import files
from hipode_pipeline.errors import OverwriteError
from hipode_pipeline.validation import validate_artifact

REPO = Path(__file__).resolve().parent.parent
# a deadlock guard, not a speed check: on slow CPUs, beside another test worker, two quick
# stage ones in a row take minutes
TIMEOUT = 360

# Runs `hipode ARGS` after a rendezvous: each process waits at its first call to
# datasets_root/use_datasets_root (reached before any existence check, old code and new) until
# all $PARTIES have arrived, so the two really race; $SLOW_COPY holds an import mid-copy.
LAUNCH = """
import os, shutil, sys, time
from pathlib import Path

barrier, parties = Path(os.environ["BARRIER"]), int(os.environ["PARTIES"])

def rendezvous():
    (barrier / str(os.getpid())).touch()
    deadline = time.monotonic() + 60
    while len(list(barrier.iterdir())) < parties and time.monotonic() < deadline:
        time.sleep(0.02)

def once(fn):
    done = []
    def wrapped(*args, **kwargs):
        if not done:
            done.append(rendezvous())
        return fn(*args, **kwargs)
    return wrapped

import hipode_pipeline.augment as augment
import hipode_pipeline.sharing as sharing
import hipode_pipeline.train as train
sharing.datasets_root = once(sharing.datasets_root)
augment.use_datasets_root = once(augment.use_datasets_root)
train.run_folder = once(train.run_folder)
if os.environ.get("SLOW_COPY"):
    copy = shutil.copyfile
    def slow_copy(*args, **kwargs):
        result = copy(*args, **kwargs)
        time.sleep(float(os.environ["SLOW_COPY"]))
        return result
    shutil.copyfile = slow_copy

from hipode_pipeline.__main__ import main
sys.argv = ["hipode", *sys.argv[1:]]
main()
"""


def _start(args, tmp_path, **env):
    barrier = tmp_path / "barrier"
    barrier.mkdir(exist_ok=True)
    return subprocess.Popen(
        [sys.executable, "-c", LAUNCH, *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env={
            **os.environ,
            "BARRIER": str(barrier),
            "PARTIES": "2",
            "OMP_NUM_THREADS": "1",
            "COLUMNS": "400",
            **env,
        },
    )


def _finish(processes):
    results = []
    try:
        for process in processes:
            out, err = process.communicate(timeout=TIMEOUT)
            results.append((process.returncode, out, err))
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.wait()
    return results


def test_two_imports_of_one_name_install_exactly_one(tmp_path, dataset_root):
    # two different valid artifacts that share a file name (from two sources)
    first, second = (
        _artifact_from(
            write_source(tmp_path / f"source_{team}.hdf5", n_episodes=2, length=25, seed=seed),
            tmp_path / team / "shared.hdf5",
        )
        for seed, team in enumerate(("team_a", "team_b"))
    )
    assert first.read_bytes() != second.read_bytes()

    results = _finish(
        [_start(["import", path], tmp_path, SLOW_COPY="1") for path in (first, second)]
    )

    codes = sorted(code for code, _, _ in results)
    assert codes == [0, 2], results
    winner = (first, second)[[code for code, _, _ in results].index(0)]
    _, _, loser_err = next(r for r in results if r[0] == 2)
    assert "already exists" in loser_err and "--force" in loser_err
    assert "Traceback" not in loser_err and len(loser_err.strip().splitlines()) <= 2
    installed = dataset_root / "artifacts" / "shared.hdf5"
    assert installed.read_bytes() == winner.read_bytes()
    assert sorted(p.name for p in installed.parent.iterdir()) == ["shared.hdf5"]


def test_two_augments_into_one_out_build_it_once(tmp_path, dataset_root):
    source = write_source(tmp_path / "source.hdf5", n_episodes=8, length=25)
    out = tmp_path / "out" / "shared.hdf5"
    args = ["augment", "hopper-m-r", "--source", source, "--profile", "quick"]
    args += ["--eta", "0.2", "--out", out, "--json"]

    results = _finish([_start(args, tmp_path), _start(args, tmp_path)])

    assert [code for code, _, _ in results] == [0, 0], [err[-2000:] for _, _, err in results]
    summaries = [json.loads(stdout) for _, stdout, _ in results]
    assert sorted(s["reused_artifact"] for s in summaries) == [False, True]
    builder = next(s for s in summaries if not s["reused_artifact"])
    reuser_index = [s["reused_artifact"] for s in summaries].index(True)
    reuser_err = results[reuser_index][2]
    assert "waiting for another `hipode augment`" in reuser_err
    assert "is up to date" in reuser_err
    assert summaries[reuser_index]["content_checksum"] == builder["content_checksum"]
    # the file is valid, and nothing else is left in the folder
    assert validate_artifact(out).valid
    assert sorted(p.name for p in out.parent.iterdir()) == [
        "shared.hdf5",
        "shared.hdf5.summary.json",
    ]


# Opens a temp file beside argv[1] the way every writer does, then hangs until killed.
HANGING_WRITER = """
import sys, time
from hipode_pipeline.files import atomic_path
with atomic_path(sys.argv[1]) as temp:
    temp.write_bytes(b"half a file")
    print(temp.name, flush=True)
    time.sleep(120)
"""


def _hanging_writers(*targets):
    """Start one writer per target (together: each pays for its imports) and wait until each
    has its temp file; return [(process, temp path)]."""
    processes = [
        subprocess.Popen(
            [sys.executable, "-c", HANGING_WRITER, str(target)],
            stdout=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        for target in targets
    ]
    started = []
    for process, target in zip(processes, targets, strict=True):
        name = process.stdout.readline().strip()
        assert name, "the writer died before opening its temp file"
        started.append((process, target.parent / name))
    return started


def test_a_killed_writers_temp_file_goes_on_the_next_write_a_live_ones_stays(
    tmp_path, dataset_root
):
    source = write_source(tmp_path / "source.hdf5", n_episodes=2, length=25)
    artifact = _artifact_from(source, tmp_path / "inbox" / "new.hdf5")
    folder = dataset_root / "artifacts"
    folder.mkdir()
    (killed, stale), (live, alive) = _hanging_writers(folder / "old.hdf5", folder / "other.hdf5")
    try:
        killed.send_signal(signal.SIGKILL)
        killed.wait(timeout=TIMEOUT)
        assert stale.exists() and alive.exists()

        (code, _, err), *_ = _finish([_start(["import", artifact], tmp_path, PARTIES="1")])

        assert code == 0, err
        assert not stale.exists()
        assert alive.exists()  # its writer still runs: never touched
        assert sorted(p.name for p in folder.iterdir()) == sorted(["new.hdf5", alive.name])
    finally:
        for process in (killed, live):
            process.kill()
            process.wait()


def test_remove_stale_temps_keeps_foreign_and_own_files(tmp_path):
    own = tmp_path / f".a.hdf5.p{os.getpid()}@somewhere-else.abc123.tmp"
    unrelated = tmp_path / ".b.hdf5.tmp"
    for path in (own, unrelated):
        path.write_text("x")
    with files.atomic_path(tmp_path / "c.json") as temp:
        temp.write_text("{}")
        assert files.remove_stale_temps(tmp_path) == []  # our own temp is a live writer's
    # another host's pid cannot be checked here, and names not ours are not ours to remove
    assert own.exists() and unrelated.exists()


def test_a_name_taken_meanwhile_is_never_replaced(tmp_path):
    target = tmp_path / "out" / "x.hdf5"
    with pytest.raises(OverwriteError, match="already exists"):
        with files.atomic_path(target, replace=False) as temp:
            temp.write_text("mine")
            target.write_text("theirs")  # another writer got there first
    assert target.read_text() == "theirs"
    assert [p.name for p in target.parent.iterdir()] == ["x.hdf5"]


def test_a_lock_left_by_a_killed_holder_does_not_block(tmp_path):
    target = tmp_path / "x.hdf5"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from hipode_pipeline.files import output_lock\n"
            "with output_lock(sys.argv[1], command='hipode test'):\n"
            "    print('held', flush=True)\n"
            "    time.sleep(120)\n",
            str(target),
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        assert f"{holder.pid} hipode test" in files.lock_path(target).read_text()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=TIMEOUT)
    with files.output_lock(target, command="hipode test") as waited:
        assert not waited
    assert not files.lock_path(target).exists()


def test_two_identical_trains_write_one_run(tmp_path, dataset_root):
    source = write_source(tmp_path / "source.hdf5", n_episodes=8, length=25)
    args = ["train", "hopper-m-r", "--source", source, "--data", "source", "--steps", "40"]
    args += ["--eval-every", "20", "--eval-episodes", "1", "--out", tmp_path / "runs", "--json"]

    results = _finish([_start(args, tmp_path), _start(args, tmp_path)])

    assert [code for code, _, _ in results] == [0, 0], [err[-2000:] for _, _, err in results]
    scores = [json.loads(stdout) for _, stdout, _ in results]
    assert scores[0]["run_dir"] == scores[1]["run_dir"]
    # one trained it, the other waited and read back the finished run
    assert sorted(s["finished_earlier"] for s in scores) == [False, True]
    lines = (Path(scores[0]["run_dir"]) / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(line)["step"] for line in lines] == [20, 40]


def test_a_waiter_names_a_holder_that_writes_its_record_late(tmp_path, capsys):
    target = tmp_path / "x.hdf5"
    lock = files.lock_path(target)
    lock.touch()
    fd = os.open(lock, os.O_RDWR)

    def holder_writes_record():  # a holder takes the lock, then writes who it is
        time.sleep(0.05)
        os.pwrite(fd, b"4242 hipode augment\n", 0)

    writer = threading.Thread(target=holder_writes_record)
    writer.start()
    try:
        files._say_waiting(fd, target)
    finally:
        writer.join()
        os.close(fd)
    said = capsys.readouterr().err
    assert "waiting for another `hipode augment`" in said and "(pid 4242)" in said
