"""Rebuild the committed reference artifact and its schema description (only when the schema
changes on purpose: bump SCHEMA_VERSION, update docs/schema.md, then run this).

    python tests/data/make_reference_artifact.py

Files of older minor versions stay committed beside it (LEGACY_REFERENCES), never rebuilt: they
are what the readers must keep reading. Before a bump, copy the current reference to
`reference_artifact_<old version with _>.hdf5` and add it there.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REFERENCE_NAME = "reference_artifact.hdf5"
SCHEMA_NAME = "artifact_schema.json"
# schema version -> committed file written by that version's writer (same content as MANIFEST)
LEGACY_REFERENCES = {"1.0": "reference_artifact_1_0.hdf5", "1.1": "reference_artifact_1_1.hdf5"}
ROWS, OBS_DIM, ACT_DIM = 48, 3, 2
# fixed, so the file's bytes depend only on the writer
MANIFEST = {
    "task": "hopper-m-r",
    "env_id": "Hopper-v5",
    "ref_min_score": -20.272305,
    "ref_max_score": 3234.3,
    "source": {"id": "reference/tiny-v0", "sha256": "0" * 64, "n": 96, "format": "d4rl-hdf5"},
    "created_utc": "2026-01-01T00:00:00+00:00",
    "hyper_parameters": {"eta": 0.5, "lam": 0.2, "n": 10, "alpha": 1.0, "sigma": 1.0},
    "seeds": {"seed": 0},
    "generators": {"device": "cpu"},
    "versions": {"hipode_pipeline": "reference"},
    "counts": {"kept": ROWS, "candidates": ROWS * 5},
}


def reference_content(seed: int = 0):
    """The reference rows: a seeded RNG, so the same arrays every time."""
    from hipode_pipeline.data.transitions import Transitions

    rng = np.random.default_rng(seed)
    transitions = Transitions(
        observations=rng.normal(size=(ROWS, OBS_DIM)).astype(np.float32),
        actions=rng.uniform(-1, 1, (ROWS, ACT_DIM)).astype(np.float32),
        rewards=rng.normal(size=ROWS).astype(np.float32),
        next_observations=rng.normal(size=(ROWS, OBS_DIM)).astype(np.float32),
        terminals=np.arange(ROWS) % 16 == 15,
        timeouts=np.zeros(ROWS, dtype=bool),
    )
    diagnostics = {
        "dynamics_error": rng.random(ROWS).astype(np.float32),
        "value": rng.normal(size=ROWS).astype(np.float32),
        "source_index": rng.integers(0, 96, ROWS),
    }
    return transitions, diagnostics, dict(MANIFEST)


def main(folder: Path = HERE) -> None:
    from hipode_pipeline.artifact import write_artifact
    from hipode_pipeline.files import file_sha256
    from hipode_pipeline.validation import schema_description

    transitions, diagnostics, manifest = reference_content()
    path = folder / REFERENCE_NAME
    write_artifact(path, transitions, diagnostics, manifest, force=True)
    description = schema_description()
    description["reference_file"] = {"name": REFERENCE_NAME, "sha256": file_sha256(path)}
    description["legacy_reference_files"] = {
        version: {"name": name, "sha256": file_sha256(folder / name)}
        for version, name in LEGACY_REFERENCES.items()
    }
    (folder / SCHEMA_NAME).write_text(json.dumps(description, indent=2, sort_keys=True) + "\n")
    print(f"wrote {path} ({path.stat().st_size} bytes) and {folder / SCHEMA_NAME}")


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parent.parent))
    main()
