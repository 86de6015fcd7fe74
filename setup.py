"""Build hook: the wheel carries the top-level stages/*.toml as `hipode_pipeline/stages/`.

The project's metadata is in pyproject.toml. stages/ stays the one place the per-task
configuration is edited; this copies it into the build, so nothing is committed twice.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.errors import FileError

STAGES = Path("stages")  # setuptools runs this file from the project root (or the sdist's)
PACKAGED = ("hipode_pipeline", "stages")


class build_py_with_stages(build_py):
    """build_py that also copies stages/*.toml into the built package."""

    def run(self) -> None:
        super().run()
        if self.editable_mode:
            return  # an editable install reads the checkout's stages/ itself
        for source, target in self._stage_files():
            self.mkpath(str(target.parent))
            self.copy_file(str(source), str(target))

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        outputs = super().get_outputs(include_bytecode)
        if self.editable_mode:
            return outputs
        return [*outputs, *(str(target) for _, target in self._stage_files())]

    def _stage_files(self) -> list[tuple[Path, Path]]:
        files = sorted(STAGES.glob("*.toml"))
        if not (STAGES / "tasks.toml").is_file():
            # a wheel without its configuration installs fine and fails on first use
            raise FileError(
                f"{STAGES.resolve()}: expected tasks.toml and the other per-task *.toml files "
                "to package; build from a checkout or an sdist that has stages/"
            )
        target = Path(self.build_lib, *PACKAGED)
        return [(source, target / source.name) for source in files]


setup(cmdclass={"build_py": build_py_with_stages})
