"""D4RL-format HDF5 files: flat `observations, actions, rewards, terminals[, timeouts,
next_observations]` arrays, as D4RL ships them and as our synthetic artifacts are written.

A file whose manifest says it is a synthetic artifact is read through the artifact schema's rules
(schema, manifest digest, shapes, checksum) before any row is used; a damaged one is refused.
Only datasets stored in the file itself are read: a link, virtual dataset or external storage
naming another file is refused, never followed.

Also home of the HDF5 header checks the Minari loader shares: a field's rank, dtype and size are
checked from the file's metadata before a byte of it is read, so an absurd shape fails fast.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hipode_pipeline.data.transitions import (
    FIELDS,
    SourceInfo,
    Transitions,
    validate_transitions,
)
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.validation import (
    FLOAT32_MAX,
    Findings,
    check_file,
    claims_artifact,
    parse_manifest_text,
    path_problem,
)

FORMAT = "d4rl-hdf5"
REQUIRED_FIELDS = ("observations", "actions", "rewards", "terminals")
# MuJoCo's TimeLimit: D4RL v0 files mark no timeouts, so episodes are cut at this length
DEFAULT_MAX_EPISODE_STEPS = 1000
# No state or action space of a continuous-control task comes near this many features
MAX_FEATURE_DIM = 65_536
# Relative tolerance when checking that s' of a step is the s of the next one
CONTINUITY_RTOL = 1e-6
# File attributes that may name the env and its reference returns (D4RL keeps none; ours do)
ENV_ID_KEYS = ("env_id", "env", "env_name")
MANIFEST_ATTR = "manifest"
# Schema name of the synthetic artifacts stage one writes (rows there are not episodes)
SYNTHETIC_SCHEMA = "hipode-synthetic"


def check_field_header(
    dataset: Any,
    origin: str | Path,
    field: str,
    *,
    rows: int | None,
    feature_dim: int | None = None,
    flag: bool = False,
) -> tuple[int, ...]:
    """Check one HDF5 field (Dataset or low-level DatasetID) from its metadata; return its shape.

    `rows` is the expected first dimension (None: any non-zero); features are 2-D (rows, dim)
    unless `flag` (rewards, terminals, timeouts: (rows,) or (rows, 1)).
    """
    if not isinstance(dataset, h5py.Dataset | h5py.h5d.DatasetID):
        found = (
            "a group (dict-valued spaces are not supported)"
            if isinstance(dataset, h5py.Group)
            else type(dataset).__name__
        )
        raise DataFormatError(origin, field, "an HDF5 dataset of numbers", found)
    dtype = dataset.dtype
    if dtype.kind not in "fiub":
        raise DataFormatError(origin, field, "a numeric or boolean dtype", _dtype_text(dtype))
    shape = tuple(int(d) for d in dataset.shape)
    expected_rows = "N" if rows is None else str(rows)
    if flag:
        if not (len(shape) == 1 or (len(shape) == 2 and shape[1] == 1)):
            raise DataFormatError(
                origin, field, f"a 1-D array ({expected_rows},)", f"shape {shape}"
            )
    else:
        dim_text = "dim" if feature_dim is None else str(feature_dim)
        if len(shape) != 2:
            raise DataFormatError(
                origin, field, f"a 2-D array ({expected_rows}, {dim_text})", f"shape {shape}"
            )
        if not 0 < shape[1] <= MAX_FEATURE_DIM:
            raise DataFormatError(
                origin, field, f"between 1 and {MAX_FEATURE_DIM} features per row", f"shape {shape}"
            )
        if feature_dim is not None and shape[1] != feature_dim:
            raise DataFormatError(
                origin, field, f"shape ({expected_rows}, {feature_dim})", f"shape {shape}"
            )
    if rows is None and shape[0] == 0:
        raise DataFormatError(origin, field, "at least one row", "an empty array (0 rows)")
    if rows is not None and shape[0] != rows:
        raise DataFormatError(
            origin, field, f"{rows} rows (as many as the other fields)", f"shape {shape}"
        )
    return shape


def check_memory(origin: str | Path, field: str, rows: int, obs_dim: int, act_dim: int) -> None:
    """Refuse a dataset whose float32 arrays alone would not fit in this machine's memory."""
    needed = 4 * rows * (2 * obs_dim + act_dim + 3)
    total = _physical_memory_bytes()
    if total and needed > total:
        raise DataFormatError(
            origin,
            field,
            f"a dataset that fits in memory (this machine has {total / 2**30:.1f} GiB)",
            f"{rows:,} rows needing {needed / 2**30:,.1f} GiB",
        )


def read_field(dataset: h5py.Dataset, origin: str | Path, field: str) -> np.ndarray:
    """Read a whole field, turning a truncated or corrupt file into a DataFormatError."""
    try:
        return dataset[()]
    except (OSError, RuntimeError, ValueError) as error:
        raise DataFormatError(
            origin, field, "readable data", f"a truncated or corrupt dataset ({error})"
        ) from None


def stored_here(f: h5py.Group, name: str, origin: str | Path) -> Any:
    """`f[name]` when it is a hard link to a dataset stored in this file (or a group); a soft or
    external link, a virtual dataset or external raw storage names another path: refused."""
    link = f.get(name, getlink=True)
    if not isinstance(link, h5py.HardLink):
        target = getattr(link, "filename", None) or getattr(link, "path", "")
        raise DataFormatError(
            origin,
            name,
            "a dataset stored in this file",
            f"a {type(link).__name__} to {target!r} (links out of the file are not followed)",
        )
    node = f[name]
    if isinstance(node, h5py.Dataset) and (node.is_virtual or node.external):
        raise DataFormatError(
            origin,
            name,
            "a dataset stored in this file",
            "a virtual or externally stored dataset (its bytes live in other files)",
        )
    return node


def open_hdf5(path: str | Path, field: str = "file") -> h5py.File:
    """Open an HDF5 file read-only, with a clear error when it is not one (or not a regular
    file: a FIFO is never opened, so it cannot block)."""
    problem = path_problem(path)
    if problem is None and os.stat(path).st_size == 0:
        problem = "an empty file (0 bytes)"
    if problem is not None:
        raise DataFormatError(path, field, "a readable HDF5 file (a regular file)", problem)
    try:
        return h5py.File(path, "r")
    except OSError as error:
        raise DataFormatError(
            path, field, "a readable HDF5 file", f"not HDF5 or damaged ({error})"
        ) from None


def continuity_breaks(
    observations: np.ndarray, next_observations: np.ndarray, ends: np.ndarray
) -> np.ndarray:
    """Rows i inside an episode (no end flag) whose next_observations[i] != observations[i+1]."""
    rows = np.flatnonzero(~ends[:-1])
    if rows.size == 0:
        return rows
    following = observations[rows + 1]
    gap = np.abs(next_observations[rows] - following)
    broken = (gap > CONTINUITY_RTOL * (1.0 + np.abs(following))).any(axis=1)
    return rows[broken]


def infer_timeouts(terminals: np.ndarray, max_episode_steps: int) -> np.ndarray:
    """Timeouts of a file that has none: each max_episode_steps-th step of an episode, unless
    terminal.

    Episodes restart after each terminal and each inferred timeout, so the step counter is the
    index within the run since the last terminal, modulo the episode length.
    """
    n = terminals.shape[0]
    index = np.arange(n)
    # start of each terminal-delimited run: one past the latest terminal before the row
    after_terminal = np.where(terminals, index + 1, 0)
    run_start = np.concatenate(([0], np.maximum.accumulate(after_terminal)[:-1]))
    step_in_run = index - run_start
    return ((step_in_run + 1) % max_episode_steps == 0) & ~terminals


def load_d4rl_hdf5(
    path: str | Path,
    *,
    max_episode_steps: int = DEFAULT_MAX_EPISODE_STEPS,
) -> tuple[Transitions, SourceInfo]:
    """Load a D4RL-format file; the SourceInfo's refs and env id are the file's own.

    Without `timeouts` (v0 files) they are inferred by episode length. Without
    `next_observations` the successor of row i is row i+1, and rows whose successor is unknown
    (the last row, timeout rows) are dropped as D4RL's qlearning_dataset does; the episode end
    such a row carried moves to the row before it. Reference scores not found in the file are
    None here: `load_source` completes them from the task registry.
    """
    origin = str(path)
    if max_episode_steps < 1:
        raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
    notes: list[str] = []
    with open_hdf5(path) as f:
        is_artifact = claims_artifact(f.attrs.get(MANIFEST_ATTR))
    if is_artifact:
        raw, file_metadata = _read_artifact_rows(Path(path))
        n, has_timeouts, has_next = len(raw["observations"]), True, True
    else:
        raw, file_metadata, has_timeouts, has_next = _read_d4rl_rows(path, origin)
        n = raw["observations"].shape[0]
    _check_float32_range(raw, origin)
    with np.errstate(over="ignore"):
        full = validate_transitions(raw, origin)
    terminals, timeouts = full.terminals, full.timeouts
    if not has_timeouts:
        timeouts = infer_timeouts(terminals, max_episode_steps)
        notes.append(
            f"no timeouts field: inferred {int(timeouts.sum())} "
            f"at episode length {max_episode_steps}"
        )
    ends = terminals | timeouts
    independent_rows = is_synthetic_artifact(file_metadata)
    if independent_rows:
        notes.append("a synthetic artifact: rows are independent transitions, not episodes")
    if has_next:
        broken = (
            np.empty(0, dtype=np.int64)
            if independent_rows
            else continuity_breaks(full.observations, full.next_observations, ends)
        )
        if broken.size:
            row = int(broken[0])
            raise DataFormatError(
                origin,
                "next_observations",
                f"next_observations[{row}] == observations[{row + 1}] inside an episode "
                f"(row {row} has no terminal or timeout)",
                f"a different state at {broken.size} row(s), first at row {row}",
            )
        transitions = Transitions(
            observations=full.observations,
            actions=full.actions,
            rewards=full.rewards,
            next_observations=full.next_observations,
            terminals=terminals,
            timeouts=timeouts,
        )
        dropped = 0
    else:
        transitions, dropped = _shift_next_observations(full, terminals, timeouts, origin)
        notes.append(
            f"no next_observations field: used the next row's observation and dropped {dropped} "
            "transition(s) whose successor is not in the file (last row, timeouts)"
        )
        terminal_rows = int(transitions.terminals.sum())
        if terminal_rows:
            notes.append(
                f"{terminal_rows} terminal row(s) carry the next row's observation as s' "
                "(the true one is not in the file)"
            )
    if not (transitions.terminals[-1] or transitions.timeouts[-1]):
        notes.append("the last transition ends no episode (no terminal or timeout)")
    info = SourceInfo(
        id=origin,
        env_id=_env_id_from(file_metadata),
        ref_min_score=_ref_from(file_metadata, "ref_min_score"),
        ref_max_score=_ref_from(file_metadata, "ref_max_score"),
        sha256=transitions.sha256(),
        n=len(transitions),
        format=FORMAT,
        metadata={
            "file_metadata": file_metadata,
            "file_rows": n,
            "dropped_transitions": dropped,
            "timeouts_inferred": not has_timeouts,
            "max_episode_steps": max_episode_steps,
            "episodes": _count_episodes(transitions),
            "notes": notes,
        },
    )
    return transitions, info


def _read_d4rl_rows(
    path: str | Path, origin: str
) -> tuple[dict[str, np.ndarray], dict[str, Any], bool, bool]:
    """The raw fields of a plain D4RL file, headers checked before any bytes are read."""
    with open_hdf5(path) as f:
        for name in REQUIRED_FIELDS:
            if name not in f:
                present = ", ".join(sorted(f.keys())) or "no fields"
                raise DataFormatError(
                    origin, name, "a dataset field", f"nothing (missing; file has {present})"
                )
        has_timeouts = "timeouts" in f
        has_next = "next_observations" in f
        present = [*REQUIRED_FIELDS, *(["timeouts"] if has_timeouts else [])]
        present += ["next_observations"] if has_next else []
        nodes = {name: stored_here(f, name, origin) for name in present}
        obs_shape = check_field_header(nodes["observations"], origin, "observations", rows=None)
        n, obs_dim = obs_shape
        act_dim = check_field_header(nodes["actions"], origin, "actions", rows=n)[1]
        for name in ("rewards", "terminals"):
            check_field_header(nodes[name], origin, name, rows=n, flag=True)
        if has_timeouts:
            check_field_header(nodes["timeouts"], origin, "timeouts", rows=n, flag=True)
        if has_next:
            check_field_header(
                nodes["next_observations"],
                origin,
                "next_observations",
                rows=n,
                feature_dim=obs_dim,
            )
        check_memory(origin, "observations", n, obs_dim, act_dim)
        raw = {name: read_field(nodes[name], origin, name) for name in REQUIRED_FIELDS}
        raw["timeouts"] = (
            read_field(nodes["timeouts"], origin, "timeouts") if has_timeouts else np.zeros(n, bool)
        )
        # a placeholder when absent, so one validate call checks every field read
        raw["next_observations"] = (
            read_field(nodes["next_observations"], origin, "next_observations")
            if has_next
            else raw["observations"]
        )
        file_metadata = read_file_metadata(f)
    return raw, file_metadata, has_timeouts, has_next


def _read_artifact_rows(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A synthetic artifact's six fields, after every rule `read_artifact` applies (schema,
    manifest digest, shapes, finiteness, checksum): the first broken one is raised."""
    manifest, arrays = check_file(path, Findings(path, strict=True), read_arrays=True)
    with open_hdf5(path) as f:
        file_metadata = read_file_metadata(f)
    # the verified manifest, not a lenient re-parse of the attribute
    file_metadata[MANIFEST_ATTR] = manifest
    return {name: arrays[name] for name in FIELDS}, file_metadata


def _check_float32_range(raw: dict[str, np.ndarray], origin: str) -> None:
    """A wider float beyond float32's range would become inf when cast: say so, not "inf"."""
    for name, array in raw.items():
        if array.dtype.kind != "f" or array.dtype.itemsize <= 4:
            continue
        with np.errstate(invalid="ignore"):
            beyond = np.isfinite(array) & (np.abs(array) > FLOAT32_MAX)
        if beyond.any():
            first = np.argwhere(beyond)[0]
            value = float(array[tuple(first)])
            raise DataFormatError(
                origin,
                name,
                f"values within float32's range (|x| <= {FLOAT32_MAX:.3g}; rows are float32)",
                f"{int(beyond.sum())} value(s) that overflow float32, first {value:.3g} at row "
                f"{int(first[0])} ({array.dtype})",
            )


def _shift_next_observations(
    full: Transitions, terminals: np.ndarray, timeouts: np.ndarray, origin: str
) -> tuple[Transitions, int]:
    """s'[i] = s[i+1]; drop rows without a known successor, moving their episode end one row up."""
    n = len(full)
    keep = ~timeouts
    keep[-1] = False
    if not keep.any():
        raise DataFormatError(
            origin,
            "next_observations",
            "the field, or rows whose successor is the next row",
            "neither (no usable transition)",
        )
    next_observations = np.empty_like(full.observations)
    next_observations[:-1] = full.observations[1:]
    next_observations[-1] = full.observations[-1]
    moved_timeouts = timeouts.copy()
    # a dropped row that ended an episode: its predecessor (same episode) is now that episode's last
    dropped_ends = np.flatnonzero(~keep & (terminals | timeouts))
    predecessors = dropped_ends[dropped_ends > 0] - 1
    predecessors = predecessors[keep[predecessors] & ~terminals[predecessors]]
    moved_timeouts[predecessors] = True
    transitions = Transitions(
        observations=full.observations[keep],
        actions=full.actions[keep],
        rewards=full.rewards[keep],
        next_observations=next_observations[keep],
        terminals=terminals[keep],
        timeouts=moved_timeouts[keep],
    )
    return transitions, int(n - keep.sum())


def read_file_metadata(f: h5py.File) -> dict[str, Any]:
    """Small JSON-able file attributes and `metadata/` scalars; weights and arrays are skipped."""
    found: dict[str, Any] = {}
    for key, value in f.attrs.items():
        found[key] = _jsonable(value)
    if isinstance(found.get(MANIFEST_ATTR), str):
        try:
            found[MANIFEST_ATTR] = parse_manifest_text(found[MANIFEST_ATTR])
        except ValueError:
            # not an artifact's (those are checked by the artifact rules): kept as text
            pass
    # a link named metadata could point into another file: only a group stored here is read
    link = f.get("metadata", getlink=True)
    group = f.get("metadata") if isinstance(link, h5py.HardLink) else None
    if isinstance(group, h5py.Group):

        def visit(name: str, item: Any) -> None:
            small = isinstance(item, h5py.Dataset) and item.size <= 16
            # bytes kept in other files are not read, however small
            if small and not (item.is_virtual or item.external) and item.dtype.kind in "fiubSOU":
                found[f"metadata/{name}"] = _jsonable(item[()])

        group.visititems(visit)
    return found


def is_synthetic_artifact(file_metadata: dict[str, Any]) -> bool:
    """Whether the file's manifest names the synthetic-artifact schema."""
    manifest = file_metadata.get(MANIFEST_ATTR)
    schema = manifest.get("schema") if isinstance(manifest, dict) else None
    return isinstance(schema, dict) and schema.get("name") == SYNTHETIC_SCHEMA


def env_id_entry(file_metadata: dict[str, Any]) -> tuple[str, str] | None:
    """(field, env id) of the first place in the file's metadata that names the env, or None."""
    manifest = file_metadata.get(MANIFEST_ATTR)
    candidates = [(key, file_metadata.get(key)) for key in ENV_ID_KEYS]
    candidates += [(f"metadata/{key}", file_metadata.get(f"metadata/{key}")) for key in ENV_ID_KEYS]
    if isinstance(manifest, dict):
        candidates.insert(0, (f"{MANIFEST_ATTR}.env_id", manifest.get("env_id")))
    return next(((k, c) for k, c in candidates if isinstance(c, str) and c), None)


def _env_id_from(file_metadata: dict[str, Any]) -> str | None:
    entry = env_id_entry(file_metadata)
    return entry[1] if entry else None


def _ref_from(file_metadata: dict[str, Any], key: str) -> float | None:
    manifest = file_metadata.get(MANIFEST_ATTR)
    values = [file_metadata.get(key), file_metadata.get(f"metadata/{key}")]
    if isinstance(manifest, dict):
        values.insert(0, manifest.get(key))
    return next((v for v in map(float_or_none, values) if v is not None), None)


def float_or_none(value: Any) -> float | None:
    """A finite float, or None for anything else (missing, text, NaN)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if np.isfinite(number) else None


def _count_episodes(transitions: Transitions) -> int:
    ends = transitions.terminals | transitions.timeouts
    return int(ends.sum()) + int(not ends[-1])


def _jsonable(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()] if value.size <= 16 else f"array{value.shape}"
    if isinstance(value, np.generic):
        return value.item()
    return value


def _dtype_text(dtype: np.dtype) -> str:
    if h5py.check_string_dtype(dtype) is not None or dtype.kind in "SUO":
        return f"a string dtype ({dtype})"
    return f"dtype {dtype}"


def _physical_memory_bytes() -> int:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 0
