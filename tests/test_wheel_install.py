"""A real wheel, installed into a fresh virtual environment, runs without the source checkout.

The wheel must carry stages/*.toml inside the package; the checkout's own files must not leak
into the fresh environment (its site-packages lists only the dependencies' folders).
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest
from builders import make_d4rl_file

REPO = Path(__file__).resolve().parent.parent


def _run(command: list[str], cwd: Path, env: dict[str, str], timeout: int = 300):
    return subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )


def _dependency_dirs() -> list[str]:
    """This interpreter's site-packages folders, minus any that would import the checkout."""
    found = [*site.getsitepackages(), sysconfig.get_path("purelib"), sysconfig.get_path("platlib")]
    keep = []
    for folder in dict.fromkeys(Path(f).resolve() for f in found):
        if folder.is_dir() and folder != REPO and not (folder / "hipode_pipeline").exists():
            keep.append(str(folder))
    return keep


def _build_wheel(tmp_path: Path, env: dict[str, str]) -> Path:
    wheels, build = tmp_path / "wheels", tmp_path / "build"
    # setuptools' build and egg-info folders go to tmp_path: the checkout gets no build/, no
    # stale copy of a deleted module, and two test runs at once do not share a folder
    config = tmp_path / "build.cfg"
    config.write_text(f"[build]\nbuild_base = {build}\n[egg_info]\negg_base = {tmp_path}\n")
    command = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation"]
    done = _run(
        [*command, "-q", "-w", str(wheels), str(REPO)],
        cwd=tmp_path,
        env={**env, "DIST_EXTRA_CONFIG": str(config)},
    )
    if done.returncode != 0 and "No module named" in done.stderr:
        pytest.skip(f"cannot build a wheel here (pip or setuptools missing): {done.stderr[-300:]}")
    assert done.returncode == 0, done.stderr
    (wheel,) = wheels.glob("hipode_pipeline-*.whl")
    return wheel


@pytest.fixture
def scratch(tmp_path):
    """tmp_path, emptied afterwards: a wheel, a build folder and a virtual environment."""
    yield tmp_path
    for child in tmp_path.iterdir():
        shutil.rmtree(child) if child.is_dir() else child.unlink()


def test_wheel_installs_and_runs_outside_the_checkout(scratch):
    tmp_path = scratch
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["OMP_NUM_THREADS"] = "1"  # one thread per test worker on a shared machine
    wheel = _build_wheel(tmp_path, env)

    prefix = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(prefix)
    python, hipode = prefix / "bin" / "python", prefix / "bin" / "hipode"
    installed = _run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "-q"]
        + ["--no-deps", "--no-index", str(wheel)],
        cwd=tmp_path,
        env=env,
    )
    assert installed.returncode == 0, installed.stderr
    purelib = _run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        cwd=tmp_path,
        env=env,
    ).stdout.strip()
    # the dependencies (torch, h5py, mujoco, ...) come from this interpreter's site-packages
    (Path(purelib) / "dependencies.pth").write_text("\n".join(_dependency_dirs()) + "\n")

    work = tmp_path / "elsewhere"
    work.mkdir()
    show = (
        "import hipode_pipeline as h, hipode_pipeline.paths as p; print(h.__file__, p.stages_dir())"
    )
    where = _run([str(python), "-c", show], cwd=work, env=env)
    assert where.returncode == 0, where.stderr
    module, stages = (Path(p) for p in where.stdout.split())
    assert module == Path(purelib) / "hipode_pipeline" / "__init__.py"
    assert stages == Path(purelib) / "hipode_pipeline" / "stages"
    assert {p.name for p in stages.glob("*.toml")} == {p.name for p in (REPO / "stages").iterdir()}

    tasks = _run([str(hipode), "tasks"], cwd=work, env={**env, "COLUMNS": "200"})
    assert tasks.returncode == 0, tasks.stderr
    assert "hopper-m-r" in tasks.stdout

    source, out, root = tmp_path / "hopper.hdf5", tmp_path / "a.hdf5", tmp_path / "root"
    make_d4rl_file(source, n=3_000, obs_dim=11, act_dim=3, seed=0, episode_length=200)
    augment = [str(hipode), "augment", "hopper-m-r", "--profile", "quick", "--json"]
    done = _run(
        [*augment, "--source", str(source), "--root", str(root), "--out", str(out)],
        cwd=work,
        env={**env, "MINARI_DATASETS_PATH": str(root)},
    )
    assert done.returncode == 0, done.stderr
    assert out.is_file() and json.loads(done.stdout)["artifact"] == str(out)
    assert not list(work.iterdir())  # nothing written to the working folder
