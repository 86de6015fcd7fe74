"""Errors a user can act on: each names what is wrong and what was expected.

The CLI turns any `HipodeError` into a one-paragraph message on stderr and a non-zero exit
code; everything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path


class HipodeError(Exception):
    """Base of every error caused by the user's input, files or environment."""

    exit_code = 2


class DataFormatError(HipodeError):
    """A dataset or artifact file does not have the content we need."""

    def __init__(self, path: str | Path, field: str, expected: str, found: object = None):
        self.path, self.field, self.expected, self.found = str(path), field, expected, found
        message = f"{path}: field '{field}': expected {expected}"
        if found is not None:
            message += f", found {found}"
        super().__init__(message)

    def __reduce__(self):
        # rebuilt from its fields: a worker process's error reaches the parent whole
        return type(self), (self.path, self.field, self.expected, self.found)


class UnknownTaskError(HipodeError):
    """A task name that is not in the registry."""


class DatasetNotFoundError(HipodeError):
    """A dataset id or path that does not exist locally."""


class OverwriteError(HipodeError):
    """An output already exists and the user did not pass --force."""


class ArtifactMismatchError(HipodeError):
    """An artifact that exists but was built with settings other than the run asks for."""


class SettingError(HipodeError):
    """A setting, profile name or override outside its valid range."""


class TrainingDivergedError(HipodeError):
    """A model's weights became NaN or infinite during training."""


class UnsafeEnvError(HipodeError):
    """An environment id that is unknown or would run code from outside gymnasium."""


class TrainingInterrupted(HipodeError):
    """Ctrl-C during training: the state was checkpointed; rerunning resumes."""

    exit_code = 130


class MissingExtraError(HipodeError):
    """A feature that needs an optional extra the installation lacks (e.g. `adroit`)."""


class DeviceUnavailableError(HipodeError):
    """The user asked for a device this machine does not have."""


class NotCollectableError(HipodeError):
    """A task whose data cannot be built here (only MuJoCo locomotion can)."""


class CollectionBusyError(HipodeError):
    """Another process is collecting into the same work folder."""


class CollectionInterrupted(HipodeError):
    """Training stopped on purpose after a checkpoint (STOP_AFTER_STEPS); rerun to resume."""


class InstallationError(HipodeError):
    """The installed package lacks files it ships with (its stages/ configuration)."""
