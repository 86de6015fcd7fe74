"""Where the per-task configuration is read from: the checkout's stages/, else the package's."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from hipode_pipeline import paths
from hipode_pipeline.cli import app
from hipode_pipeline.errors import InstallationError
from hipode_pipeline.tasks import all_tasks

REPO = Path(__file__).resolve().parent.parent


def _layout(tmp_path: Path, *, checkout: bool, packaged: bool) -> Path:
    """A fake install: <tmp>/hipode_pipeline/paths.py with the stages/ folders asked for."""
    package = tmp_path / "hipode_pipeline"
    package.mkdir()
    if checkout:
        (tmp_path / "pyproject.toml").write_text("")
        (tmp_path / "stages").mkdir()
        (tmp_path / "stages" / "tasks.toml").write_text("")
    if packaged:
        (package / "stages").mkdir()
        (package / "stages" / "tasks.toml").write_text("")
    return package / "paths.py"


def test_checkout_stages_folder_is_read_in_a_source_tree():
    assert paths.stages_dir() == REPO / "stages"


@pytest.mark.parametrize(
    ("checkout", "packaged", "expected"),
    [
        (True, True, "stages"),
        (False, True, "hipode_pipeline/stages"),
        # a stages/ folder beside an installed package, without a pyproject.toml, is not ours
        ("no-pyproject", True, "hipode_pipeline/stages"),
    ],
)
def test_stages_dir_prefers_the_checkout_then_the_package(
    tmp_path, monkeypatch, checkout, packaged, expected
):
    module = _layout(tmp_path, checkout=bool(checkout), packaged=packaged)
    if checkout == "no-pyproject":
        (tmp_path / "pyproject.toml").unlink()
    monkeypatch.setattr(paths, "__file__", str(module))
    assert paths.stages_dir() == tmp_path / expected


def test_missing_configuration_is_a_clear_error_from_the_cli(tmp_path):
    module = _layout(tmp_path, checkout=False, packaged=False)
    all_tasks.cache_clear()  # the registry is read once per process
    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(paths, "__file__", str(module))
            with pytest.raises(InstallationError, match="reinstall") as error:
                paths.stages_dir()
            result = CliRunner().invoke(app, ["tasks"])
    finally:
        all_tasks.cache_clear()
    assert str(tmp_path / "hipode_pipeline" / "stages") in str(error.value)
    assert result.exit_code == 2
    assert "reinstall" in result.stderr and "Traceback" not in result.output
