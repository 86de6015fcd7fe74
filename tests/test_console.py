"""Output off a terminal: progress lines in logs are not cut at rich's 80-column fallback."""

from __future__ import annotations

from hipode_pipeline import console

INFO = "kept 95,232/95,232  median e 0.033 (z-scored units)"


def test_log_output_is_wide_unless_columns_is_set(monkeypatch, capsys):
    monkeypatch.delenv("COLUMNS", raising=False)
    log = console._console(stderr=True)
    assert not log.is_terminal and log.width >= 120
    monkeypatch.setattr(console, "err", log)  # the module's own was made at import time
    with console.progress() as prog:
        task = prog.add_task("generate", total=10, rate="12,921 candidates/s", info=INFO)
        prog.update(task, advance=10)
    assert INFO in capsys.readouterr().err
    monkeypatch.setenv("COLUMNS", "100")
    assert console._console(stderr=True).width == 100
