"""The artifact schema's rules, checked once: `read_artifact` stops at the first error, `hipode
validate` lists every one.

Nothing in a file is trusted or executed: only hard-linked, numeric, in-file datasets are read,
their declared shapes are checked against sane limits before any bytes are read, and the
manifest is parsed as strict JSON (no NaN or Infinity, no duplicate keys) and must match its own
digest (`manifest_checksum`), which also covers the content checksum.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hipode_pipeline.data.transitions import FIELDS
from hipode_pipeline.errors import DataFormatError, DatasetNotFoundError
from hipode_pipeline.files import path_kind

SCHEMA_NAME = "hipode-synthetic"
SCHEMA_VERSION = "1.2"
# major versions this reader understands; a new major means an incompatible layout
SUPPORTED_MAJORS = (1,)
MANIFEST_ATTR = "manifest"
# the manifest's own digest: since 1.1 (1.0 files have none and are read with a warning)
MANIFEST_CHECKSUM_KEY = "manifest_checksum"
MANIFEST_CHECKSUM_SINCE = (1, 1)
# how the manifest is serialized for its digest: the same text whatever wrote or stored it
CANONICAL_JSON = {
    "sort_keys": True,
    "separators": (",", ":"),
    "ensure_ascii": True,
    "allow_nan": False,
}
# diagnostics every artifact carries, with their dtypes; writers may add more (float32 or int64)
REQUIRED_DIAGNOSTICS = {"dynamics_error": np.float32, "value": np.float32, "source_index": np.int64}
DIAGNOSTIC_DTYPES = (np.dtype(np.float32), np.dtype(np.int64))
TRANSITION_DTYPES = {
    "observations": np.float32,
    "actions": np.float32,
    "rewards": np.float32,
    "next_observations": np.float32,
    "terminals": np.bool_,
    "timeouts": np.bool_,
}
# rank of each transition field: (M, dim) or (M,)
TRANSITION_RANKS = {
    "observations": 2,
    "actions": 2,
    "rewards": 1,
    "next_observations": 2,
    "terminals": 1,
    "timeouts": 1,
}
# manifest keys a reader needs, and their JSON types
REQUIRED_MANIFEST_KEYS = {
    "schema": "object",
    "checksum": "string",
    MANIFEST_CHECKSUM_KEY: "string",
}
# provenance keys `hipode augment` writes; absent is a warning, present with a wrong type an error
RECOMMENDED_MANIFEST_KEYS = {
    "task": "string",
    "env_id": "string",
    "ref_min_score": "number|null",
    "ref_max_score": "number|null",
    "source": "object",
    "created_utc": "string",
    "hyper_parameters": "object",
    "seeds": "object",
    "generators": "object",
    "versions": "object",
    "counts": "object",
}
# sub-keys a reader uses (train, verify, merge, inspect): optional, but an error when mistyped
NESTED_MANIFEST_KEYS = {
    "source": {
        "id": "string",
        "env_id": "string|null",
        "sha256": "sha256 hex",
        "n": "integer",
        "format": "string",
        "ref_min_score": "number|null",
        "ref_max_score": "number|null",
        "recipe": "object",
    },
    "hyper_parameters": {
        "eta": "number",
        "lam": "number",
        "n": "integer",
        "alpha": "number",
        "sigma": "number",
        "batch_size": "integer",
        "penalty": "string",
        "selection": "string",
        "candidates": "string",
        "dynamics_mean": "boolean",
        "uncertainty_check": "boolean",
        "project_next_state": "boolean",
        "profile": "string",
        "generator_config": "object",
        "generator_config_hash": "string",
    },
    "seeds": {
        "seed": "integer",
        "generator_training": "integer",
        "source_order": "integer",
        "sampling": "integer",
        "novelty_sample": "integer",
    },
    "generators": {"device": "string", "checkpoint_hashes": "object", "training_report": "object"},
    "counts": {
        "kept": "integer",
        "candidates": "integer",
        "source_states_drawn": "integer",
        "next_states_sampled": "integer",
        "nonfinite_dropped": "integer",
        "nonfinite_next_states": "integer",
    },
}
# an observation or action wider than this is a corrupt header, not a robot
MAX_FEATURE_DIM = 10_000
# share of the machine's available memory one artifact may take when read
MAX_MEMORY_SHARE = 0.5
CHECKSUM_PATTERN = re.compile(r"^sha256:[0-9a-f]{64}$")
HEX_SHA256_PATTERN = re.compile(r"^[0-9a-f]{64}$")
VERSION_PATTERN = re.compile(r"^(\d+)\.(\d+)$")
FLOAT32_MAX = float(np.finfo(np.float32).max)
_JSON_TYPES = {
    "object": dict,
    "string": str,
    "string|null": (str, type(None)),
    "number": (int, float),
    "number|null": (int, float, type(None)),
    "integer": int,
    "boolean": bool,
    "sha256 hex": str,
}
_JSON_NAMES = {
    dict: "an object",
    list: "a list",
    str: "a string",
    bool: "a boolean",
    int: "an integer",
    float: "a number",
    type(None): "null",
}


@dataclass(frozen=True)
class Violation:
    """One broken rule: what field, what the schema expects, what the file has."""

    field: str  # dataset name, `manifest.<key>`, `file` or `checksum`
    expected: str  # what the schema asks for
    found: str  # what the file holds
    severity: str = "error"  # "error" makes the file invalid; "warning" is a sanity note

    def to_dict(self) -> dict[str, str]:
        return asdict(self)


@dataclass
class ValidationReport:
    """Every violation found in one file."""

    path: Path  # the file checked
    schema: dict[str, Any] | None  # the manifest's schema entry, when it could be read
    violations: list[Violation] = field(default_factory=list)  # errors and warnings, in order

    @property
    def valid(self) -> bool:
        return not any(v.severity == "error" for v in self.violations)

    @property
    def errors(self) -> list[Violation]:
        return [v for v in self.violations if v.severity == "error"]

    def to_dict(self) -> dict[str, Any]:
        return {
            "valid": self.valid,
            "path": str(self.path),
            "schema": self.schema,
            "violations": [v.to_dict() for v in self.violations],
        }


class Findings:
    """Collects violations; in strict mode the first error is raised as a DataFormatError."""

    def __init__(self, path: Path, strict: bool):
        self.path, self.strict, self.items = path, strict, []

    def error(self, name: str, expected: str, found: object) -> None:
        if self.strict:
            raise DataFormatError(self.path, name, expected, found)
        self.items.append(Violation(name, expected, str(found)))

    def warn(self, name: str, expected: str, found: object) -> None:
        self.items.append(Violation(name, expected, str(found), "warning"))


def content_checksum(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over each dataset's name, dtype, shape and bytes: transition fields in D4RL order,
    then diagnostics by name. The manifest is left out (it holds this checksum)."""
    digest = hashlib.sha256()
    names = [*FIELDS, *sorted(name for name in arrays if name not in FIELDS)]
    for name in names:
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
        digest.update(array.data)
    return "sha256:" + digest.hexdigest()


def manifest_checksum(manifest: dict[str, Any]) -> str:
    """sha256 over the manifest without its own digest, serialized as canonical JSON (sorted
    keys, no whitespace, ASCII only, no NaN): it covers the content `checksum` too, so the
    arrays and their provenance are bound together."""
    body = {key: value for key, value in manifest.items() if key != MANIFEST_CHECKSUM_KEY}
    text = json.dumps(body, **CANONICAL_JSON)
    return "sha256:" + hashlib.sha256(text.encode("ascii")).hexdigest()


def seal_manifest(manifest: dict[str, Any]) -> dict[str, Any]:
    """The manifest with its digest (re)computed: what the writer stores. Anyone can call this,
    so the digest catches accidents and casual edits; it is not a signature."""
    body = {key: value for key, value in manifest.items() if key != MANIFEST_CHECKSUM_KEY}
    return {**body, MANIFEST_CHECKSUM_KEY: manifest_checksum(body)}


def nonfinite_to_null(value: Any) -> Any:
    """JSON has no NaN or Infinity (readers refuse those tokens): such a number becomes null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: nonfinite_to_null(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [nonfinite_to_null(item) for item in value]
    return value


class ManifestSyntaxError(ValueError):
    """Manifest text that strict JSON refuses (NaN, Infinity, duplicate keys, too deep)."""


def _refuse_constant(token: str) -> Any:
    raise ManifestSyntaxError(f"the token {token} (JSON has no NaN or Infinity)")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ManifestSyntaxError(f"the number {text[:40]}, which overflows to infinity")
    return value


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    result: dict[str, Any] = {}
    for key, value in pairs:
        # json.loads would keep the last of two equal keys; other readers may keep the first
        if key in result:
            raise ManifestSyntaxError(f"the key {key[:40]!r} twice in one object")
        result[key] = value
    return result


def parse_manifest_text(text: str) -> Any:
    """Strict JSON: NaN, Infinity, numbers that overflow to infinity and duplicate keys are
    refused (ManifestSyntaxError), as is nesting deeper than the parser's recursion limit."""
    try:
        return json.loads(
            text,
            parse_constant=_refuse_constant,
            parse_float=_finite_float,
            object_pairs_hook=_unique_keys,
        )
    except RecursionError:
        raise ManifestSyntaxError("values nested too deeply to parse") from None


def claims_artifact(raw: object) -> bool:
    """Whether a file's `manifest` attribute says it is a synthetic artifact (schema name
    hipode-synthetic), however damaged: such a file must pass every artifact rule."""
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", errors="replace")
    if not isinstance(raw, str):
        return False
    try:
        manifest = json.loads(raw)
    except (ValueError, RecursionError):
        # unparseable: still an artifact when it names the schema (a damaged one)
        return SCHEMA_NAME in raw
    schema = manifest.get("schema") if isinstance(manifest, dict) else None
    return isinstance(schema, dict) and schema.get("name") == SCHEMA_NAME


def path_problem(path: str | Path) -> str | None:
    """What is at `path` when it is not a regular file (None when it is), in words."""
    kind = path_kind(path)
    if kind == "a file":
        return None
    if kind.startswith("nothing"):
        return kind.replace("nothing", "nothing at that path", 1)
    if kind in ("a FIFO (named pipe)", "a socket", "a device", "a special file"):
        return f"{kind}, not a regular file"
    return kind


def require_regular_file(path: str | Path, what: str = "artifact file") -> Path:
    """`path` when it is a regular file; else DatasetNotFoundError (nothing there) or
    DataFormatError saying what is there instead (a directory, a FIFO, a symlink loop)."""
    path = Path(path)
    problem = path_problem(path)
    if problem == "nothing at that path":
        raise DatasetNotFoundError(f"{path}: no such {what}")
    if problem is not None:
        raise DataFormatError(path, "file", f"a regular {what} (an HDF5 file)", problem)
    return path


def validate_artifact(path: Path) -> ValidationReport:
    """Check a file against the schema and return every violation (never raises on bad input)."""
    path = Path(path)
    findings = Findings(path, strict=False)
    manifest, _ = check_file(path, findings, read_arrays=True)
    schema = manifest.get("schema") if isinstance(manifest, dict) else None
    return ValidationReport(path, schema if isinstance(schema, dict) else None, findings.items)


def check_file(
    path: Path, findings: Findings, *, read_arrays: bool
) -> tuple[dict[str, Any] | None, dict[str, np.ndarray]]:
    """Run every rule on `path`; return the manifest and (if `read_arrays`) the arrays."""
    problem = path_problem(path)
    if problem is not None:
        findings.error("file", "an existing artifact file (a regular HDF5 file)", problem)
        return None, {}
    if path.stat().st_size == 0:
        findings.error("file", "a complete HDF5 file", "an empty file (0 bytes)")
        return None, {}
    try:
        with h5py.File(path, "r") as f:
            manifest = check_manifest(f, findings)
            if not read_arrays:
                return manifest, {}
            layout = _check_layout(f, findings)
            arrays = {name: f[name][()] for name in layout}
    except (OSError, KeyError, RuntimeError, ValueError, TypeError) as error:
        # a truncated, overwritten or non-HDF5 file fails inside HDF5 itself
        findings.error("file", "a complete HDF5 file", f"unreadable ({error})")
        return None, {}
    _check_values(arrays, manifest, findings)
    return manifest, arrays


def check_manifest(f: h5py.File, findings: Findings) -> dict[str, Any] | None:
    """The root attribute `manifest`: a strict-JSON object, known schema and major version, keys
    typed, and (from 1.1) a digest that matches."""
    raw = f.attrs.get(MANIFEST_ATTR)
    if raw is None:
        findings.error(
            MANIFEST_ATTR, "a JSON manifest attribute on the file's root", "nothing (missing)"
        )
        return None
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", errors="replace")
    if not isinstance(raw, str):
        findings.error(MANIFEST_ATTR, "a JSON text attribute holding an object", _kind_of(raw))
        return None
    try:
        manifest = parse_manifest_text(raw)
    except ManifestSyntaxError as error:
        findings.error(MANIFEST_ATTR, "a JSON object (strict JSON)", f"{error}")
        return None
    except ValueError as error:
        findings.error(MANIFEST_ATTR, "a JSON object", f"text that is not JSON ({error})")
        return None
    if not isinstance(manifest, dict):
        findings.error(MANIFEST_ATTR, "a JSON object", _json_kind(manifest))
        return None
    schema = manifest.get("schema")
    version = None
    if not isinstance(schema, dict):
        findings.error(
            "manifest.schema",
            f"an object {{'name': '{SCHEMA_NAME}', 'version': ...}}",
            _json_kind(schema),
        )
    else:
        if schema.get("name") != SCHEMA_NAME:
            findings.error("manifest.schema.name", f"'{SCHEMA_NAME}'", repr(schema.get("name")))
        version = _check_version(schema.get("version"), findings)
    checksum = manifest.get("checksum")
    if not (isinstance(checksum, str) and CHECKSUM_PATTERN.match(checksum)):
        findings.error("manifest.checksum", "'sha256:' and 64 hex digits", _short(checksum))
    for key, kind in RECOMMENDED_MANIFEST_KEYS.items():
        if key not in manifest:
            findings.warn(f"manifest.{key}", f"{_article(kind)} (provenance)", "nothing (missing)")
        elif not _is_json_type(manifest[key], kind):
            findings.error(f"manifest.{key}", _article(kind), _json_kind(manifest[key]))
    for key, fields in NESTED_MANIFEST_KEYS.items():
        group = manifest.get(key)
        if not isinstance(group, dict):
            continue
        for name, kind in fields.items():
            if name in group and not _is_json_type(group[name], kind):
                findings.error(f"manifest.{key}.{name}", _article(kind), _json_kind(group[name]))
    _check_manifest_checksum(manifest, version, findings)
    return manifest


def _check_manifest_checksum(
    manifest: dict[str, Any], version: tuple[int, int] | None, findings: Findings
) -> None:
    field_name = f"manifest.{MANIFEST_CHECKSUM_KEY}"
    stored = manifest.get(MANIFEST_CHECKSUM_KEY, None)
    since = ".".join(map(str, MANIFEST_CHECKSUM_SINCE))
    if MANIFEST_CHECKSUM_KEY not in manifest:
        if version is not None and version < MANIFEST_CHECKSUM_SINCE:
            # a 1.0 file predates the digest: readable, but its provenance is unauthenticated
            findings.warn(
                field_name,
                f"a manifest digest (schema {since} and later); without one this manifest is "
                "not authenticated: its settings, seeds and source could have been edited "
                "without detection",
                f"nothing: schema {version[0]}.{version[1]} predates it",
            )
        elif version is not None:
            findings.error(
                field_name,
                f"'sha256:' and 64 hex digits over the manifest (schema {since} and later carry "
                "one)",
                "nothing (missing)",
            )
        return
    if not (isinstance(stored, str) and CHECKSUM_PATTERN.match(stored)):
        findings.error(field_name, "'sha256:' and 64 hex digits", _short(stored))
        return
    computed = manifest_checksum(manifest)
    if stored != computed:
        findings.error(
            field_name,
            f"{computed} (the digest of the manifest as stored)",
            f"{stored}: the manifest was edited or corrupted after it was written",
        )


def _check_version(version: object, findings: Findings) -> tuple[int, int] | None:
    """(major, minor) of a version this reader reads; None (and an error) otherwise."""
    supported = ", ".join(f"{major}.x" for major in SUPPORTED_MAJORS)
    match = VERSION_PATTERN.match(version) if isinstance(version, str) else None
    if match is None:
        findings.error(
            "manifest.schema.version",
            f"a version 'MAJOR.MINOR' (this reader: {supported})",
            _short(version),
        )
        return None
    if int(match.group(1)) not in SUPPORTED_MAJORS:
        findings.error(
            "manifest.schema.version",
            f"major version {supported} (this reader reads {SCHEMA_VERSION}); rebuild the file "
            "with this version's `hipode augment` or read it with a newer hipode",
            repr(version),
        )
        return None
    return int(match.group(1)), int(match.group(2))


def _check_layout(f: h5py.File, findings: Findings) -> list[str]:
    """From HDF5 metadata only: which datasets are safe and sane to read. Returns their names."""
    readable = []
    for name in f:
        link = f.get(name, getlink=True)
        if not isinstance(link, h5py.HardLink):
            findings.error(name, "a dataset stored in this file", f"a {type(link).__name__}")
            continue
        node = f[name]
        if not isinstance(node, h5py.Dataset):
            findings.error(name, "a dataset", "a group")
            continue
        if node.is_virtual or node.external:
            findings.error(name, "a dataset stored in this file", "data kept in other files")
            continue
        if node.dtype.kind not in "fiub" or node.dtype.fields is not None:
            findings.error(name, "a numeric or boolean dataset", f"dtype {node.dtype}")
            continue
        expected = TRANSITION_DTYPES.get(name) or REQUIRED_DIAGNOSTICS.get(name)
        if expected is not None and node.dtype != np.dtype(expected):
            findings.error(name, f"dtype {np.dtype(expected)}", node.dtype)
        elif expected is None and node.dtype not in DIAGNOSTIC_DTYPES:
            findings.error(name, "a float32 or int64 diagnostics dataset", f"dtype {node.dtype}")
        readable.append(name)
    for name in FIELDS:
        if name not in f:
            findings.error(name, "a dataset in the file", "nothing (missing)")
    for name in REQUIRED_DIAGNOSTICS:
        if name not in f:
            findings.error(name, "a diagnostics dataset in the file", "nothing (missing)")
    shapes = {name: f[name].shape for name in readable}
    sizes = {n: float(np.prod(shapes[n], dtype=np.float64)) * f[n].dtype.itemsize for n in readable}
    budget = _available_memory() * MAX_MEMORY_SHARE
    if sum(sizes.values()) > budget:
        largest = max(sizes, key=sizes.get)
        findings.error(
            largest,
            f"arrays that fit in memory (at most {budget / 1e9:.1f} GB in all)",
            f"shape {shapes[largest]}: {sum(sizes.values()) / 1e9:,.1f} GB declared; nothing read",
        )
        return []
    _check_shapes(shapes, findings)
    # a dataset with an absurd declared shape is never read, even when others are
    return [n for n in readable if _sane_shape(shapes[n])]


def _check_shapes(shapes: dict[str, tuple[int, ...]], findings: Findings) -> None:
    observations = shapes.get("observations")
    if observations is None or len(observations) != 2 or observations[1] == 0:
        if observations is not None:
            findings.error("observations", "a 2-D array (M, obs_dim)", observations)
        m = next((s[0] for s in shapes.values() if len(s) >= 1), None)
        obs_dim = None
    else:
        m, obs_dim = observations
    if m == 0:
        findings.error("observations", "at least one synthetic transition (M >= 1)", "0 rows")
    actions = shapes.get("actions")
    act_dim = actions[1] if actions is not None and len(actions) == 2 else None
    for name, dim in (("observations", obs_dim), ("actions", act_dim)):
        if dim is not None and dim > MAX_FEATURE_DIM:
            findings.error(name, f"at most {MAX_FEATURE_DIM} columns", f"{dim}")
    for name, shape in shapes.items():
        rank = TRANSITION_RANKS.get(name, 1)
        if name == "observations" and obs_dim is None:
            continue
        expected = {
            "observations": (m, obs_dim),
            "next_observations": (m, obs_dim),
            "actions": (m, act_dim if act_dim else "act_dim"),
        }.get(name, (m,))
        # a width is only compared when it is known (observations or actions readable)
        known_width = isinstance(expected[-1], int)
        if (
            len(shape) != rank
            or (m is not None and shape[0] != m)
            or (rank == 2 and known_width and shape[1] != expected[1])
        ):
            findings.error(name, f"shape {expected}".replace("'", ""), shape)
        elif rank == 2 and shape[1] == 0:
            findings.error(name, "at least one column", shape)


def _sane_shape(shape: tuple[int, ...]) -> bool:
    return (
        len(shape) in (1, 2)
        and all(0 <= d for d in shape)
        and (len(shape) == 1 or shape[1] <= MAX_FEATURE_DIM)
    )


def _check_values(
    arrays: dict[str, np.ndarray], manifest: dict[str, Any] | None, findings: Findings
) -> None:
    for name, array in arrays.items():
        if array.dtype.kind == "f":
            bad = ~np.isfinite(array)
            if bad.any():
                first = int(np.argwhere(bad)[0][0])
                nan, inf = int(np.isnan(array).sum()), int(np.isinf(array).sum())
                found = ", ".join(
                    text for count, text in ((nan, f"{nan} NaN"), (inf, f"{inf} infinite")) if count
                )
                # a value beyond float32's range is stored as inf by HDF5's conversion
                hint = " (a value beyond float32's ±3.4e38 is stored as inf)" if inf else ""
                findings.error(name, "finite values", f"{found} (first at row {first}){hint}")
    terminals, timeouts = arrays.get("terminals"), arrays.get("timeouts")
    if terminals is not None and timeouts is not None and terminals.shape == timeouts.shape:
        both = int((terminals.astype(bool) & timeouts.astype(bool)).sum())
        if both:
            findings.warn("terminals", "rows that are not also timeouts", f"{both} rows both")
    source_index = arrays.get("source_index")
    if source_index is not None and source_index.dtype.kind in "iu" and (source_index < 0).any():
        findings.warn("source_index", "row numbers >= 0", f"{int((source_index < 0).sum())} < 0")
    if manifest is None:
        return
    counts = manifest.get("counts")
    rows = arrays["observations"].shape[0] if "observations" in arrays else None
    if isinstance(counts, dict) and isinstance(counts.get("kept"), int) and rows is not None:
        if counts["kept"] != rows:
            findings.warn("manifest.counts.kept", f"{rows} (the rows in the file)", counts["kept"])
    stated = manifest.get("checksum")
    # a missing or malformed checksum is already reported; comparing it would say so twice
    complete = all(name in arrays for name in (*FIELDS, *REQUIRED_DIAGNOSTICS))
    if complete and isinstance(stated, str) and CHECKSUM_PATTERN.match(stated):
        checksum = content_checksum(arrays)
        if stated != checksum:
            findings.error(
                "checksum",
                f"{stated} (the manifest's)",
                f"{checksum}: the content was changed or corrupted",
            )


def _is_json_type(value: object, kind: str) -> bool:
    if isinstance(value, bool) and kind != "boolean":
        return False
    if kind == "sha256 hex":
        return isinstance(value, str) and bool(HEX_SHA256_PATTERN.match(value))
    return isinstance(value, _JSON_TYPES[kind])


def _article(kind: str) -> str:
    """'an object', 'a string|null', 'a sha256 hex (64 hex digits)': what a key must hold."""
    if kind == "sha256 hex":
        return "a sha256 (64 lowercase hex digits)"
    return f"{'an' if kind[0] in 'aeiou' else 'a'} {kind}"


def _short(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _json_kind(value: object) -> str:
    """What a JSON value is, for messages: `a string '0.9'`, `a list`, `null`."""
    kind = _JSON_NAMES.get(type(value), type(value).__name__)
    if isinstance(value, dict | list):
        return kind
    return kind if value is None else f"{kind} {_short(value)}"


def _kind_of(raw: object) -> str:
    """What an HDF5 attribute holds when it is not text."""
    if isinstance(raw, np.ndarray):
        return f"an array of {raw.dtype} with shape {raw.shape}"
    return f"a {type(raw).__name__} value"


def _available_memory() -> float:
    """Bytes of memory free for a read (physical pages available; a generous guess elsewhere)."""
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 8e9


def schema_description() -> dict[str, Any]:
    """The rules above as data: what tests/data/artifact_schema.json pins and docs/schema.md
    describes."""
    datasets = [
        {
            "name": name,
            "dtype": np.dtype(TRANSITION_DTYPES[name]).name,
            "shape": ["M", "obs_dim" if "observations" in name else "act_dim"]
            if TRANSITION_RANKS[name] == 2
            else ["M"],
            "required": True,
        }
        for name in FIELDS
    ]
    datasets += [
        {"name": name, "dtype": np.dtype(dtype).name, "shape": ["M"], "required": True}
        for name, dtype in sorted(REQUIRED_DIAGNOSTICS.items())
    ]
    return {
        "schema": {"name": SCHEMA_NAME, "version": SCHEMA_VERSION},
        "supported_majors": list(SUPPORTED_MAJORS),
        "manifest_attribute": MANIFEST_ATTR,
        "datasets": datasets,
        "extra_datasets": {"dtypes": [d.name for d in DIAGNOSTIC_DTYPES], "shape": ["M"]},
        "manifest": {
            "required": dict(REQUIRED_MANIFEST_KEYS),
            "recommended": dict(RECOMMENDED_MANIFEST_KEYS),
            "nested": {key: dict(fields) for key, fields in NESTED_MANIFEST_KEYS.items()},
            "json": "strict: no NaN, Infinity or overflowing numbers, no duplicate keys",
        },
        "manifest_checksum": {
            "key": MANIFEST_CHECKSUM_KEY,
            "since": ".".join(map(str, MANIFEST_CHECKSUM_SINCE)),
            "over": f"the manifest without '{MANIFEST_CHECKSUM_KEY}', checksum included",
            "canonical_json": {
                k: list(v) if isinstance(v, tuple) else v for k, v in CANONICAL_JSON.items()
            },
            "older_minor_without_it": "read, with a warning: not authenticated",
        },
        "limits": {"max_feature_dim": MAX_FEATURE_DIM, "max_memory_share": MAX_MEMORY_SHARE},
    }
