"""The sweep's rate and finishing time come from the runs trained by this call, not from runs
read back from an earlier one (which arrive at once and would make the sweep look fast)."""

from __future__ import annotations

import time

from hipode_pipeline import console
from hipode_pipeline.sweep import driver
from hipode_pipeline.sweep.worker import FINISHED_EARLIER


def test_pace_counts_only_runs_trained_here(monkeypatch):
    now = [1000.0]
    monkeypatch.setattr(driver.time, "monotonic", lambda: now[0])
    pace = driver.Pace(to_train=6)  # of 10 runs, 4 finished in an earlier call
    for _ in range(4):  # read back in the first second
        pace.add({"status": FINISHED_EARLIER})
    assert pace.fields() == {"rate": "", console.ETA_FIELD: None}
    now[0] += 1200.0  # two runs trained side by side in 20 minutes
    pace.add({"status": "trained"})
    pace.add({"status": "resumed from step 5000"})
    fields = pace.fields()
    assert fields["rate"] == "6.0 runs/h"
    assert fields[console.ETA_FIELD] == now[0] + 4 * 600.0  # four runs left at 10 min each
    for _ in range(4):
        pace.add({"status": "trained"})
    assert pace.fields()[console.ETA_FIELD] == now[0]


def test_a_sweep_with_nothing_to_train_has_no_time_left():
    pace = driver.Pace(to_train=0)
    pace.add({"status": FINISHED_EARLIER})
    fields = pace.fields()
    assert fields["rate"] == "" and fields[console.ETA_FIELD] <= time.monotonic()
