"""The contract between the stages: which artifact a learner's table row asks for, the name stage
one gives it, and how stage two finds and checks it.

An artifact is named by what determines its rows, never by the learner that first asked for it:
<root>/artifacts/<task>-eta<η>-lam<λ>-n<n>-alpha<α>-sigma<σ>[-<variant>…]-seed<stage-one seed>.hdf5
Two learners whose table rows agree (e.g. TD3+BC and CQL on hopper-m-r) share one file.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from hipode_pipeline.errors import (
    ArtifactMismatchError,
    DataFormatError,
    DatasetNotFoundError,
    HipodeError,
)
from hipode_pipeline.paths import datasets_root
from hipode_pipeline.tasks import LEARNERS, Task

# the paper's table of HIPODE settings for each learner (appendix B)
LEARNER_TABLES = {"td3bc": "Table 6", "cql": "Table 5", "iql": "Table 7"}
# d3rlpy algorithms that are one of the paper's learners take that learner's table row
D3RLPY_TABLE_ROWS = {"TD3PlusBC": "td3bc", "IQL": "iql", "CQL": "cql"}
TABLE_FIELDS = ("eta", "lam", "n", "alpha", "sigma")
# how an artifact's rows are proposed: HIPODE, or the plain model-rollout baseline
METHODS = ("hipode", "model-rollouts")


@dataclass(frozen=True)
class ArtifactSettings:
    """The generation settings that tell artifacts of one source and seed apart."""

    eta: float  # synthetic rate: round(eta * N) rows
    lam: float  # selecting rate
    n: int  # candidates per source state
    alpha: float  # negative-sampling penalty weight
    sigma: float  # negative-sampling scope
    penalty: str = "target"  # value-penalty form
    selection: str = "batch"  # top-lambda per batch | global
    candidates: str = "model"  # state-transition model | uniform (ablation)
    dynamics_mean: bool = False  # dynamics check against the ensemble mean
    uncertainty_check: bool = False  # ranking in the ensemble's own predicted stds
    project_next_state: bool = False  # the ensemble's next state written instead of s~'
    profile: str = "full"  # generator budgets
    method: str = "hipode"  # how rows are proposed: HIPODE | plain model rollouts (baseline)

    def variant_tags(self) -> list[str]:
        """Name parts for every setting off its default, in a fixed order."""
        tags = [] if self.method == "hipode" else [self.method]
        if self.penalty != "target":
            tags.append(f"penalty-{self.penalty}")
        if self.selection != "batch":
            tags.append(self.selection)
        if self.candidates != "model":
            tags.append(self.candidates)
        if self.dynamics_mean:
            tags.append("dynmean")
        if self.uncertainty_check:
            tags.append("dynunc")
        if self.project_next_state:
            tags.append("projected")
        if self.profile != "full":
            tags.append(self.profile)
        return tags

    def stem(self, task: str, seed: int, source_tag: str | None = None) -> str:
        parts = [
            task,
            f"eta{self.eta:g}",
            f"lam{self.lam:g}",
            f"n{self.n}",
            f"alpha{self.alpha:g}",
            f"sigma{self.sigma:g}",
            *self.variant_tags(),
            *([f"src{source_tag}"] if source_tag else []),
            f"seed{seed}",
        ]
        return "-".join(parts)

    def table_part(self) -> dict[str, float]:
        return {name: getattr(self, name) for name in TABLE_FIELDS}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_manifest(cls, manifest: dict[str, Any]) -> ArtifactSettings | None:
        """The settings an artifact's manifest records; None when it records none."""
        params = manifest.get("hyper_parameters")
        if not isinstance(params, dict):
            return None
        try:
            return cls(
                eta=float(params["eta"]),
                lam=float(params["lam"]),
                n=int(params["n"]),
                alpha=float(params["alpha"]),
                sigma=float(params["sigma"]),
                penalty=str(params.get("penalty", "target")),
                selection=str(params.get("selection", "batch")),
                candidates=str(params.get("candidates", "model")),
                dynamics_mean=bool(params.get("dynamics_mean", False)),
                uncertainty_check=bool(params.get("uncertainty_check", False)),
                project_next_state=bool(params.get("project_next_state", False)),
                profile=str(params.get("profile", "full")),
                method=str(params.get("method", "hipode")),
            )
        except (KeyError, TypeError, ValueError):
            return None


def table_learner(learner: str) -> str:
    """The table row a learner takes: its own, d3rlpy's TD3PlusBC/IQL/CQL the paper's learner's,
    any other learner TD3+BC's (the paper's main table)."""
    if learner.startswith("d3rlpy:"):
        return D3RLPY_TABLE_ROWS.get(learner.split(":", 1)[1], "td3bc")
    return learner if learner in LEARNERS else "td3bc"


def table_row(task: Task, learner: str) -> dict[str, Any]:
    """Where a learner's settings come from, as the manifest and run config record it."""
    row = table_learner(learner)
    params = task.augment_params(row)
    return {
        "learner": row,
        "table": LEARNER_TABLES[row] if params.from_paper else "defaults.toml",
        "from_paper": params.from_paper,
    }


def table_settings(task: Task, learner: str) -> ArtifactSettings:
    """The artifact `learner`'s table row asks for on `task`."""
    params = task.augment_params(table_learner(learner))
    return ArtifactSettings(
        eta=params.eta, lam=params.lam, n=params.n, alpha=params.alpha, sigma=params.sigma
    )


def artifacts_dir(root: Path | None = None) -> Path:
    return (root or datasets_root()) / "artifacts"


def default_artifact_path(
    task: Task,
    settings: ArtifactSettings,
    *,
    seed: int = 0,
    root: Path | None = None,
    source_tag: str | None = None,
) -> Path:
    """Where `hipode augment` writes an artifact of these settings by default."""
    return artifacts_dir(root) / f"{settings.stem(task.name, seed, source_tag)}.hdf5"


def differences(expected: ArtifactSettings, found: ArtifactSettings | None) -> list[str]:
    """'eta 0.5 (expected 0.05)'-style notes for every setting that differs."""
    if found is None:
        return ["no generation settings recorded"]
    return [
        f"{name} {getattr(found, name)!r} (expected {getattr(expected, name)!r})"
        for name in expected.to_dict()
        if getattr(found, name) != getattr(expected, name)
    ]


def manifest_matches(
    manifest: dict[str, Any],
    *,
    task: Task,
    source_sha256: str,
    seed: int,
    expected: ArtifactSettings,
) -> list[str]:
    """What keeps an artifact from being the one a learner's table row asks for (empty: none).
    Only the table's settings must agree; the profile and ablation variants are reported apart."""
    problems = []
    if manifest.get("task") != task.name:
        problems.append(f"task {manifest.get('task')!r} (expected {task.name!r})")
    source = manifest.get("source") if isinstance(manifest.get("source"), dict) else {}
    if source.get("sha256") != source_sha256:
        problems.append(f"source sha256 {str(source.get('sha256'))[:16]}… (another dataset)")
    seeds = manifest.get("seeds") if isinstance(manifest.get("seeds"), dict) else {}
    if seeds.get("seed") != seed:
        problems.append(f"stage-one seed {seeds.get('seed')!r} (expected {seed})")
    found = ArtifactSettings.from_manifest(manifest)
    # the table's settings, and no ablation variant: only the generator profile may differ
    compared = [d for d in differences(expected, found) if d.split(" ")[0] != "profile"]
    return problems + (compared if found is not None else ["no generation settings recorded"])


def find_artifact(
    task: Task,
    learner: str,
    *,
    source_sha256: str,
    artifact_seed: int,
    root: Path | None = None,
    source_tag: str | None = None,
    source_spec: str | None = None,
) -> tuple[Path, dict[str, Any]]:
    """The artifact `learner`'s table row asks for, from stage-one seed `artifact_seed`: the
    default-named file, else any artifact of the task whose manifest matches (full profile
    first). Stops with the difference and the command that builds the right one otherwise."""
    from hipode_pipeline.artifact import read_manifest

    expected = table_settings(task, learner)
    row = table_learner(learner)
    extra = [f"--learner {row}"] if row != "td3bc" else []
    extra += [f"--seed {artifact_seed}"] if artifact_seed else []
    # the build command must name the same source and root, or it builds another file
    extra += [f"--source {source_spec}"] if source_spec else []
    extra += [f"--root {root}"] if root is not None else []
    build = " ".join([f"hipode augment {task.name}", *extra])
    if not source_spec and root is None:
        make_args = f' ARGS="--seed {artifact_seed}"' if artifact_seed else ""
        learner_arg = f" LEARNER={row}" if row != "td3bc" else ""
        build += f"` (or `make augment TASK={task.name}{learner_arg}{make_args}`"
    folder = artifacts_dir(root)
    default = default_artifact_path(
        task, expected, seed=artifact_seed, root=root, source_tag=source_tag
    )
    # every artifact in the folder, whatever its name (an imported one keeps the sender's)
    candidates = [default] + sorted(path for path in folder.glob("*.hdf5") if path != default)
    matching, mismatched = [], []
    for path in candidates:
        if not path.is_file():
            continue
        try:
            manifest = read_manifest(path)
        except (DataFormatError, DatasetNotFoundError, HipodeError) as error:
            if path.name.startswith(f"{task.name}-"):
                mismatched.append((path, [f"unreadable ({str(error)[:120]})"]))
            continue
        problems = manifest_matches(
            manifest,
            task=task,
            source_sha256=source_sha256,
            seed=artifact_seed,
            expected=expected,
        )
        if problems:
            if manifest.get("task") == task.name:  # other tasks' files are not worth listing
                mismatched.append((path, problems))
        else:
            matching.append((path, manifest))
    if matching:
        # the default-named file first, then full-profile files, then others (quick)
        def rank(item: tuple[Path, dict[str, Any]]) -> tuple[int, int, str]:
            found = ArtifactSettings.from_manifest(item[1])
            return (item[0] != default, bool(found and found.variant_tags()), item[0].name)

        return min(matching, key=rank)
    wanted = ", ".join(f"{k} {v:g}" for k, v in expected.table_part().items())
    origin = f"{learner}'s {table_row(task, learner)['table']} row for {task.name}: {wanted}"
    if not mismatched:
        raise DatasetNotFoundError(
            f"no synthetic artifact for {task.name} under {folder} ({origin}, stage-one seed "
            f"{artifact_seed}); run `{build}` first, pass --artifact FILE, "
            "or train on --data source"
        )
    shown = "; ".join(
        f"{path.name}: {', '.join(problems[:4])}" for path, problems in mismatched[:3]
    )
    raise ArtifactMismatchError(
        f"no artifact under {folder} matches {origin}, stage-one seed {artifact_seed}; "
        f"present: {shown}. Build the right one with `{build}`, or pass --artifact FILE to "
        "train on a given file anyway"
    )
