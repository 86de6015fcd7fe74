"""Does HIPODE help TD3+BC? Both arms, the same seeds, the same update budget.

`hipode sweep` with this repository's folders as defaults: run folders under bench/out/quality,
the report (quality.md, quality.json, quality.png) in bench/results, where the committed
evidence lives (bench/RESULTS.md, docs/evidence.md). `python bench/quality.py --help` lists
the arms, ablations and engines. The seeds of an arm train together in one process as one
stacked model (--seeds-per-process N caps how many; 1: one process per run).

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python bench/quality.py --tasks hopper-m-r \
        --seeds 0-4 --steps 50000 --workers 2
    python bench/quality.py --budget paper --engine ray --address auto    # a cluster, 1M steps
    python bench/quality.py --alpha=-1,0,1,2,4,8 --uniform --lam 0.2,1.0  # ablations
    python bench/quality.py --penalty l2,contrastive --union   # default penalty form, mixing
"""

from __future__ import annotations

import os

# OpenMP reads its wait policy once, when torch loads (the import below): busy-waiting starves
# a shared machine
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path  # noqa: E402

from hipode_pipeline.commands.sweep import sweep_app  # noqa: E402

REPO = Path(__file__).resolve().parent.parent

app = sweep_app(
    program="python bench/quality.py",
    out_default=REPO / "bench" / "out" / "quality",
    results_default=REPO / "bench" / "results",
)

if __name__ == "__main__":
    app()
