"""Output off a terminal: progress lines in logs are not cut at rich's 80-column fallback."""

from __future__ import annotations

import time

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


def test_progress_prints_plain_lines_off_a_terminal(monkeypatch, capsys):
    from hipode_pipeline import console

    monkeypatch.setenv(console.LINE_EVERY_ENV, "0")
    monkeypatch.setattr(console.err, "_force_terminal", False)
    with console.progress() as prog:
        bar = prog.add_task("train", total=4, rate="", info="")
        for step in range(1, 5):
            prog.update(bar, completed=step, rate=f"{step} upd/s", info="score 1.0")
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("train")]
    assert len(lines) == 4 and lines[-1].startswith("train: 4/4 (100%)")
    assert "upd/s" in lines[0] and "elapsed" in lines[0] and "ETA" not in lines[-1]
    # a finished task prints once, however often it is updated afterwards
    with console.progress() as prog:
        bar = prog.add_task("gen", total=1, rate="", info="")
        prog.update(bar, completed=1)
        prog.update(bar, completed=1)
    assert capsys.readouterr().err.count("gen: 1/1") == 1


def test_progress_lines_are_spaced_in_time(monkeypatch, capsys):
    from hipode_pipeline import console

    monkeypatch.setenv(console.LINE_EVERY_ENV, "3600")
    with console.progress() as prog:
        bar = prog.add_task("train", total=1000, rate="", info="")
        for step in range(1, 1001):
            prog.update(bar, completed=step)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("train")]
    assert lines == [lines[-1]] and lines[-1].startswith("train: 1,000/1,000")


def test_a_task_can_give_its_own_finishing_time(monkeypatch, capsys):
    from rich.console import Console

    monkeypatch.setenv(console.LINE_EVERY_ENV, "0")
    with console.progress() as prog:
        bar = prog.add_task("sweep runs", total=10, rate="", info="", finish_at=None)
        prog.update(bar, advance=1)  # not yet known: no ETA at all
        prog.update(bar, advance=1, finish_at=time.monotonic() + 2 * 3600 + 5 * 60 + 0.5)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("sweep")]
    assert "ETA" not in lines[0] and "ETA 2:05:00" in lines[1]
    # the live display's column counts down to the same deadline between updates
    clock = [100.0]
    monkeypatch.setattr(console.time, "monotonic", lambda: clock[0])
    screen = Console(record=True, width=200, force_terminal=True)
    live = console.Progress(console.RemainingColumn(), console=screen, auto_refresh=False)
    with live:
        live.add_task("x", total=10, finish_at=225.0)
        live.refresh()
        clock[0] += 60.0
        live.refresh()
    text = screen.export_text()
    assert "0:02:05" in text and "0:01:05" in text
