"""Where a training run's metrics go besides metrics.jsonl: TensorBoard or Weights & Biases,
through their own libraries (the `tensorboard` and `wandb` extras). W&B runs offline unless
WANDB_MODE says otherwise, so it works without a network; `wandb sync` uploads later."""

from __future__ import annotations

import contextlib
import importlib.util
import os
from pathlib import Path
from typing import Any

from hipode_pipeline.errors import MissingExtraError, SettingError

LOGGERS = ("none", "tensorboard", "wandb")


class NullLogger:
    def log(self, step: int, metrics: dict[str, Any]) -> None:
        pass

    def close(self) -> None:
        pass


class TensorBoardLogger:
    """Scalars under <run>/tensorboard, one tag per metric."""

    def __init__(self, run_dir: Path, config: dict[str, Any]):
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=str(run_dir / "tensorboard"))
        self.writer.add_text("config", _config_text(config), 0)

    def log(self, step: int, metrics: dict[str, Any]) -> None:
        for name, value in _scalars(metrics).items():
            self.writer.add_scalar(name, value, step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


class WandbLogger:
    """One W&B run per training run, in <run>/wandb, offline by default."""

    def __init__(self, run_dir: Path, config: dict[str, Any]):
        import wandb

        self.run = wandb.init(
            project="hipode",
            name=run_dir.name,
            dir=str(run_dir),
            config=config,
            mode=os.environ.get("WANDB_MODE", "offline"),
            reinit="create_new",
        )

    def log(self, step: int, metrics: dict[str, Any]) -> None:
        self.run.log(_scalars(metrics), step=step)

    def close(self) -> None:
        self.run.finish()


def close_loggers(loggers: list) -> None:
    """Close every logger of a training group, each even if another fails. W&B's `finish()`
    can return before its service has written the run's file, and its atexit hook does not
    run in every worker process: after the last W&B run of the group is finished, one
    teardown waits for the writes (once, as it would finish any run still open)."""
    with contextlib.ExitStack() as stack:
        if any(isinstance(logger, WandbLogger) for logger in loggers):
            import wandb

            stack.callback(wandb.teardown)  # registered first: runs last
        for logger in loggers:
            stack.callback(logger.close)


def make_logger(kind: str, run_dir: Path, config: dict[str, Any]):
    check_logger(kind)
    if kind == "tensorboard":
        return TensorBoardLogger(run_dir, config)
    if kind == "wandb":
        return WandbLogger(run_dir, config)
    return NullLogger()


def check_logger(kind: str) -> None:
    """Refuse an unknown logger or a missing library (named with its extra) before any work."""
    if kind not in LOGGERS:
        raise SettingError(f"--logger: expected one of {LOGGERS}, found {kind!r}")
    # each logger's library is the extra of the same name
    if kind != "none" and importlib.util.find_spec(kind) is None:
        raise MissingExtraError(f"--logger {kind} needs {kind}: pip install -e '.[{kind}]'")


def _scalars(metrics: dict[str, Any]) -> dict[str, float]:
    """Numbers only, grouped by kind (train/…, eval/…); lists and None are left out."""
    out = {}
    for name, value in metrics.items():
        if name == "step" or isinstance(value, bool) or not isinstance(value, int | float):
            continue
        group = "eval" if name.startswith("eval_") else "train"
        out[f"{group}/{name.removeprefix('eval_')}"] = float(value)
    return out


def _config_text(config: dict[str, Any]) -> str:
    import json

    return "```\n" + json.dumps(config, indent=2, default=str)[:20_000] + "\n```"
