"""`hipode verify`: how authentic synthetic transitions are, judged by the MuJoCo simulator itself.

For a seeded sample of an artifact's transitions the simulator is put into each synthetic state,
stepped with the synthetic action, and its next state and reward are compared with the synthetic
ones. The same is done for plain model rollouts (random source state, action from a behaviour
CVAE, next state and reward from the artifact's own dynamics ensemble), the usual model-based
augmentation, so the two can be compared.

Definitions (per transition):
- next-state error: mean over dimensions of |s'_synthetic - s'_simulator| / std, std being the
  source's per-dimension next-state std: "how many source stds off, per dimension, on average".
- reward error: |r_synthetic - r_simulator| in reward units.
- within tolerance: next-state error <= tolerance and reward error <= tolerance * source reward
  std (default tolerance 0.1: a tenth of a std per dimension).
- novelty: L2 distance from s'_synthetic to the nearest source state, in z-scored units (the
  same measure `hipode augment` reports).

Everything read from the artifact's manifest is data: the env id is checked against gymnasium's
own registry before an env is built, and the source it names (`source.id`) is opened only inside
the dataset root (`load_recorded_source`), unless the caller names the source itself.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hipode_pipeline import console
from hipode_pipeline.artifact import read_artifact
from hipode_pipeline.contract import ArtifactSettings
from hipode_pipeline.data.load import load_recorded_source, load_source
from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.device import select_device
from hipode_pipeline.diagnose import STD_EPS, matched_novelty, stage_diagnosis, state_errors
from hipode_pipeline.envs import termination_rule
from hipode_pipeline.errors import DataFormatError, OverwriteError, SettingError
from hipode_pipeline.files import (
    file_sha256,
    save_figure_atomic,
    write_text_atomic,
)
from hipode_pipeline.generate import novelty
from hipode_pipeline.models.cvae import CVAE
from hipode_pipeline.models.generators import (
    MODEL_NAMES,
    GeneratorConfig,
    Generators,
    cache_dir_for,
    train_generators,
)
from hipode_pipeline.paths import use_datasets_root
from hipode_pipeline.rollouts import BehaviourCVAEConfig, behaviour_cvae, rollout_step
from hipode_pipeline.seeding import derive_seed
from hipode_pipeline.simulator import check_env_id, clipped_velocity_rows, step_from_observations

# a tenth of a source std per next-state dimension (and of the reward std) counts as authentic
DEFAULT_TOLERANCE = 0.1
SUMMARY_QUANTITIES = ("next_state_error", "reward_error", "novelty")


@dataclass(frozen=True, eq=False)
class TransitionChecks:
    """Per-transition comparison of one set of transitions with the simulator."""

    next_state_error: np.ndarray  # (K,) mean |Δs'| / source next-state std
    reward_error: np.ndarray  # (K,) |Δr| in reward units
    within_tolerance: np.ndarray  # (K,) bool
    novelty: np.ndarray  # (K,) L2 to the nearest source state, z-scored units
    terminal_agrees: np.ndarray  # (K,) bool: terminal flag equals the simulator's terminated
    clipped_input: np.ndarray  # (K,) bool: input velocities at the env's observation clip bound
    simulator_seconds: float  # wall time of the simulator steps
    rows: np.ndarray | None = (
        None  # (K,) row indices: into the artifact (HIPODE), source (baseline)
    )
    simulated_next: np.ndarray | None = None  # (K, ds) the simulator's next states (not saved)

    def summary(self) -> dict[str, Any]:
        n = int(self.next_state_error.size)
        result: dict[str, Any] = {"n": n}
        for name in SUMMARY_QUANTITIES:
            values = getattr(self, name).astype(np.float64)
            result[f"{name}_mean"] = float(values.mean())
            result[f"{name}_median"] = float(np.median(values))
            result[f"{name}_p90"] = float(np.quantile(values, 0.9))
        result["within_tolerance"] = float(self.within_tolerance.mean())
        result["terminal_agreement"] = float(self.terminal_agrees.mean())
        result["clipped_input_rows"] = int(self.clipped_input.sum())
        # rows whose input velocities were not clipped: there the simulator's answer is exact
        exact = ~self.clipped_input
        result["exact_ground_truth_share"] = float(exact.mean())
        if exact.any():
            result["next_state_error_median_exact_rows"] = float(
                np.median(self.next_state_error[exact])
            )
            result["next_state_error_mean_exact_rows"] = float(
                self.next_state_error[exact].astype(np.float64).mean()
            )
        result["simulator_rows_per_second"] = n / max(self.simulator_seconds, 1e-9)
        return result

    def arrays(self) -> dict[str, list]:
        return {
            "row": None if self.rows is None else self.rows.astype(int).tolist(),
            "next_state_error": _rounded(self.next_state_error),
            "reward_error": _rounded(self.reward_error),
            "novelty": _rounded(self.novelty),
            "terminal_agrees": self.terminal_agrees.astype(bool).tolist(),
        }


# the artifact's rows in tables and plots; a manifest without settings shows as "artifact"
METHOD_LABELS = {"hipode": "HIPODE", "model-rollouts": "model-rollout artifact"}


def method_label(method: str | None) -> str:
    """How an artifact's sample is named: by the method that made it."""
    return METHOD_LABELS.get(method, "artifact")


@dataclass(eq=False)
class VerifyReport:
    """What `hipode verify` found: HIPODE's sample and the plain-rollout baseline side by side."""

    artifact: str  # the verified file
    artifact_sha256: str  # sha256 of its bytes
    env_id: str  # the simulator used
    source_id: str  # the source dataset the artifact was built from
    source_sha256: str  # its content hash (checked against the manifest)
    seed: int  # seed of the samples, the behaviour CVAE's sampling and the dynamics' sampling
    tolerance: float  # next-state (and reward, in reward stds) tolerance
    hipode: TransitionChecks  # the artifact's sampled transitions
    baseline: TransitionChecks | None  # plain model rollouts, None with --no-baseline
    baseline_details: dict[str, Any]  # behaviour CVAE record, dynamics provenance
    seconds: dict[str, float]  # wall time per phase
    # per-stage errors, matched-novelty comparison, model-scaled tolerance (needs the baseline)
    analysis: dict[str, Any] | None = None
    json_path: str | None = None  # where the report was written
    png_path: str | None = None  # where the plot was written
    # how the artifact was made (its manifest's settings); None where it records none
    method: str | None = "hipode"

    @property
    def artifact_label(self) -> str:
        """The artifact's rows are named by how it was made: a model-rollout artifact is no
        HIPODE sample."""
        return method_label(self.method)

    def rows(self) -> list[list[Any]]:
        """Table rows: the artifact's sample, then the baseline."""
        rows = [_table_row(self.artifact_label, self.hipode.summary())]
        if self.baseline is not None:
            rows.append(_table_row("plain model rollout", self.baseline.summary()))
        return rows

    def to_dict(self, *, per_transition: bool = True) -> dict[str, Any]:
        data: dict[str, Any] = {
            "artifact": self.artifact,
            "artifact_sha256": self.artifact_sha256,
            "env_id": self.env_id,
            "source_id": self.source_id,
            "source_sha256": self.source_sha256,
            "seed": self.seed,
            "tolerance": self.tolerance,
            "method": self.method,
            "definitions": {
                "next_state_error": "mean over dims of |s'_synthetic - s'_simulator| / "
                "source next-state std",
                "reward_error": "|r_synthetic - r_simulator|, reward units",
                "within_tolerance": "next_state_error <= tolerance and "
                "reward_error <= tolerance * source reward std",
                "novelty": "L2 from s'_synthetic to the nearest source state, z-scored",
                "terminal_agreement": "synthetic terminal flag == simulator's terminated",
            },
            "hipode": self.hipode.summary(),
            "baseline": None if self.baseline is None else self.baseline.summary(),
            "baseline_details": self.baseline_details,
            "analysis": self.analysis,
            "seconds": self.seconds,
            "json": self.json_path,
            "png": self.png_path,
        }
        if per_transition:
            data["per_transition"] = {
                "hipode": self.hipode.arrays(),
                "baseline": None if self.baseline is None else self.baseline.arrays(),
            }
        return data


TABLE_COLUMNS = [
    "data",
    "n",
    "next-state err mean",
    "next-state err median",
    "reward err mean",
    "reward err median",
    "within tol %",
    "novelty mean",
    "novelty median",
    "terminal agree %",
]


def _table_row(name: str, s: dict[str, Any]) -> list[Any]:
    return [
        name,
        s["n"],
        s["next_state_error_mean"],
        s["next_state_error_median"],
        s["reward_error_mean"],
        s["reward_error_median"],
        round(100 * s["within_tolerance"], 1),
        s["novelty_mean"],
        s["novelty_median"],
        round(100 * s["terminal_agreement"], 1),
    ]


def _rounded(values: np.ndarray) -> list[float | None]:
    """Six significant digits; a non-finite value becomes null, so the file stays strict JSON."""
    return [float(f"{v:.6g}") if np.isfinite(v) else None for v in np.asarray(values, np.float64)]


def output_paths(artifact: Path, out_dir: Path | None = None) -> tuple[Path, Path]:
    """(<out_dir>/<artifact name>.verify.json, .verify.png); out_dir defaults to the artifact's."""
    folder = Path(out_dir) if out_dir is not None else Path(artifact).parent
    name = Path(artifact).name
    return folder / f"{name}.verify.json", folder / f"{name}.verify.png"


def check_transitions(
    env_id: str,
    transitions: Transitions,
    *,
    next_state_std: np.ndarray,
    reward_std: float,
    normalizer: StateNormalizer,
    source_norm: torch.Tensor,
    tolerance: float,
    seed: int,
    origin: str | Path,
    progress=None,
    label: str = "simulate",
) -> TransitionChecks:
    """Step the simulator from every row of `transitions` and compare (see the module doc)."""
    bar = None
    if progress is not None:
        bar = progress.add_task(label, total=len(transitions), rate="", info="")
    started = time.perf_counter()

    def advance(done: int) -> None:
        if bar is not None:
            elapsed = time.perf_counter() - started
            progress.update(bar, completed=done, rate=console.rate_text(done, elapsed, "rows"))

    sim_next, sim_rewards, sim_terminated = step_from_observations(
        env_id,
        transitions.observations,
        transitions.actions,
        origin=origin,
        progress_callback=advance,
    )
    seconds = time.perf_counter() - started
    state_error = state_errors(transitions.next_observations, sim_next, next_state_std)
    reward_error = np.abs(transitions.rewards.astype(np.float64) - sim_rewards)
    # a non-finite synthetic value is as far from the simulator as it gets
    reward_error = np.where(np.isfinite(reward_error), reward_error, np.inf)
    within = (state_error <= tolerance) & (reward_error <= tolerance * (reward_std + STD_EPS))
    next_norm = normalizer.normalize(transitions.next_observations.astype(np.float32))
    distances = novelty(
        next_norm.astype(np.float32), source_norm, sample=len(transitions), seed=seed
    )
    return TransitionChecks(
        next_state_error=state_error,
        reward_error=reward_error,
        within_tolerance=within,
        novelty=distances.astype(np.float64),
        terminal_agrees=transitions.terminals.astype(bool) == sim_terminated,
        clipped_input=clipped_velocity_rows(env_id, transitions.observations),
        simulator_seconds=seconds,
        simulated_next=sim_next,
    )


def plain_rollouts(
    source: Transitions,
    generators: Generators,
    policy: CVAE,
    *,
    env_id: str,
    count: int,
    seed: int,
    use_mean: bool,
) -> tuple[Transitions, np.ndarray]:
    """One-step model rollouts from `count` random source states: a ~ behaviour CVAE,
    (s', r) ~ the dynamics ensemble, terminal by the env's own rule on s'; also the source rows
    the states came from."""
    rng = np.random.default_rng(derive_seed(seed, "verify-baseline-states"))
    rows = np.sort(rng.choice(len(source), size=min(count, len(source)), replace=False))
    device = generators.device
    sampling = torch.Generator(device=device).manual_seed(derive_seed(seed, "verify-baseline"))
    states = source.observations[rows]
    with torch.no_grad():
        states_norm = generators.normalizer.normalize(torch.as_tensor(states, device=device))
        actions, next_norm, rewards = rollout_step(
            generators, policy, states_norm, sampling, use_mean
        )
    next_states = generators.normalizer.denormalize(next_norm.float().cpu().numpy())
    next_states = next_states.astype(np.float32)
    terminal = termination_rule(env_id, source.obs_dim, origin=f"source (env {env_id})")
    rollouts = Transitions(
        observations=states.astype(np.float32),
        actions=actions.float().cpu().numpy().astype(np.float32),
        rewards=rewards.float().cpu().numpy().astype(np.float32),
        next_observations=next_states,
        terminals=terminal(next_states),
        timeouts=np.zeros(len(rows), dtype=np.bool_),
    )
    return rollouts, rows


def analyse(
    generators: Generators,
    env_id: str,
    synthetic: Transitions,
    hipode: TransitionChecks,
    baseline: TransitionChecks,
    source: Transitions,
    *,
    next_state_std: np.ndarray,
    reward_std: float,
    generator_seed: int,
    sample: int,
    seed: int,
    origin: str,
) -> dict[str, Any]:
    """Per-stage errors (`diagnose`), HIPODE against the baseline at matched novelty on rows
    whose ground truth is exact, and both judged at a tolerance scaled to the dynamics model's
    own one-step error on held-out real transitions."""
    stages = stage_diagnosis(
        generators,
        env_id,
        synthetic,
        hipode.simulated_next,
        source,
        next_state_std=next_state_std,
        reward_std=reward_std,
        generator_seed=generator_seed,
        sample=sample,
        seed=seed,
        origin=origin,
    )
    mine, theirs = ~hipode.clipped_input, ~baseline.clipped_input
    model_tolerance = stages["ensemble_one_step_on_real"]["median"]
    return {
        "stages": stages,
        "matched_novelty_exact_rows": matched_novelty(
            hipode.novelty[mine],
            hipode.next_state_error[mine],
            baseline.novelty[theirs],
            baseline.next_state_error[theirs],
        ),
        "model_tolerance": {
            "definition": "the dynamics ensemble's median one-step next-state error on "
            "held-out real transitions (source stds per dimension)",
            "value": model_tolerance,
            "hipode_within": float((hipode.next_state_error <= model_tolerance).mean()),
            "baseline_within": float((baseline.next_state_error <= model_tolerance).mean()),
        },
    }


def _artifact_generators(
    artifact_path: Path,
    manifest: dict[str, Any],
    source: Transitions,
    source_sha256: str,
    root: Path,
    device: torch.device,
    show_progress: bool,
) -> tuple[Generators, dict[str, Any]]:
    """The generators the artifact was made with (from the cache when present)."""
    recorded = _manifest_value(artifact_path, manifest, "hyper_parameters.generator_config", dict)
    seed = _manifest_value(artifact_path, manifest, "seeds.generator_training", int)
    try:
        config = GeneratorConfig.from_dict(recorded)
    except (KeyError, TypeError, ValueError, SettingError) as error:
        raise DataFormatError(
            artifact_path,
            "manifest.hyper_parameters.generator_config",
            "the generator config the artifact was made with (GeneratorConfig's fields)",
            str(error) or repr(error),
        ) from None
    cache_root = root / "cache" / "generators"
    cache_dir = cache_dir_for(cache_root, source_sha256, config, seed)
    cached = all((cache_dir / f"{name}.pt").exists() for name in MODEL_NAMES)
    if not cached:
        console.err.print(
            f"the artifact's generators are not cached under {cache_dir}; training them again "
            "(this takes as long as `hipode augment` did)"
        )
    generators = train_generators(
        source,
        source_sha256,
        config,
        cache_root=cache_root,
        seed=seed,
        device=device,
        show_progress=show_progress,
    )
    stored_hash = (manifest.get("generators") or {}).get("checkpoint_hashes", {}).get("dynamics")
    details = {
        "generators_cache": cache_dir.name,
        "generators_were_cached": cached,
        "dynamics_sha256": generators.checkpoint_hashes["dynamics"],
        "dynamics_matches_artifact": stored_hash == generators.checkpoint_hashes["dynamics"],
        "dynamics_sampling": "ensemble mean"
        if _dynamics_mean(artifact_path, manifest)
        else "random member's Gaussian sample",
    }
    return generators, details


def _manifest_value(path: Path, manifest: dict[str, Any], dotted: str, kind: type) -> Any:
    """`manifest[a][b]...` when present with type `kind`; else a DataFormatError naming
    `manifest.<dotted>` (the readers check types of keys that are present; this one is needed)."""
    value: Any = manifest
    for part in dotted.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    ok = isinstance(value, kind) and not (isinstance(value, bool) and kind is not bool)
    if not ok:
        names = {str: "a string", int: "an integer", dict: "an object", bool: "a boolean"}
        raise DataFormatError(
            path,
            f"manifest.{dotted}",
            f"{names.get(kind, kind.__name__)} (hipode verify needs it)",
            "nothing (missing)" if value is None else f"{type(value).__name__} {value!r:.60}",
        )
    return value


def _dynamics_mean(path: Path, manifest: dict[str, Any]) -> bool:
    params = _manifest_value(path, manifest, "hyper_parameters", dict)
    value = params.get("dynamics_mean", False)
    if not isinstance(value, bool):
        raise DataFormatError(
            path, "manifest.hyper_parameters.dynamics_mean", "a boolean", repr(value)
        )
    return value


def verify_artifact(
    path: str | Path,
    *,
    sample: int = 2000,
    seed: int = 0,
    tolerance: float = DEFAULT_TOLERANCE,
    baseline: bool = True,
    root: Path | None = None,
    out_dir: Path | None = None,
    force: bool = False,
    behaviour: BehaviourCVAEConfig | None = None,
    device: str | None = None,
    show_progress: bool = True,
    source_spec: str | None = None,
) -> VerifyReport:
    """Check a seeded sample of `sample` synthetic transitions (and as many plain model
    rollouts unless `baseline` is False) against the simulator; write the JSON report and the
    novelty-vs-authenticity PNG (atomically; existing outputs need `force`).

    The source is the one the manifest names (`source.id`, resolved only inside the dataset
    root), or `source_spec` when the caller gives one; its content hash must match the
    manifest's."""
    if sample < 1:
        raise SettingError(f"verify setting 'sample': expected a positive integer, found {sample}")
    if not (tolerance > 0 and np.isfinite(tolerance)):
        raise SettingError(
            f"verify setting 'tolerance': expected a positive number, found {tolerance}"
        )
    path = Path(path)
    json_path, png_path = output_paths(path, out_dir)
    existing = [str(p) for p in (json_path, png_path) if p.exists()]
    if existing and not force:
        raise OverwriteError(f"{', '.join(existing)} already exist(s); pass --force to replace")
    seconds: dict[str, float] = {}
    clock = time.perf_counter()
    # the artifact and the fields used below are checked before anything is created or trained
    artifact = read_artifact(path)
    manifest = artifact.manifest
    env_id = _manifest_value(path, manifest, "env_id", str)
    # the id came from a file: refuse anything gymnasium does not implement before building it
    check_env_id(env_id, origin=path)
    source_id = _manifest_value(path, manifest, "source.id", str)
    source_sha256 = _manifest_value(path, manifest, "source.sha256", str)
    eps = _normalizer_eps(path, manifest)
    settings = ArtifactSettings.from_manifest(manifest)
    method = None if settings is None else settings.method
    if baseline:
        _manifest_value(path, manifest, "hyper_parameters.generator_config", dict)
        _manifest_value(path, manifest, "seeds.generator_training", int)
        _dynamics_mean(path, manifest)
    root = use_datasets_root(root)
    if source_spec is None:
        source, info = load_recorded_source(
            source_id, root, origin=path, field="manifest.source.id"
        )
    else:
        source, info = load_source(source_spec, root)
    if info.sha256 != source_sha256:
        raise DataFormatError(
            path,
            "manifest.source.sha256",
            f"the content hash of the source it was built from ({info.id})",
            f"{info.sha256} in the local copy, {source_sha256} in the manifest",
        )
    seconds["load"] = time.perf_counter() - clock

    torch_device = select_device(device)
    normalizer = StateNormalizer.fit(source.observations, eps=eps)
    source_norm = normalizer.normalize(torch.as_tensor(source.observations, device=torch_device))
    next_state_std = source.next_observations.astype(np.float64).std(axis=0)
    reward_std = float(source.rewards.astype(np.float64).std())
    rng = np.random.default_rng(derive_seed(seed, "verify-sample"))
    picked = np.sort(rng.choice(len(artifact), size=min(sample, len(artifact)), replace=False))
    synthetic = Transitions(
        **{name: array[picked] for name, array in artifact.transitions.arrays().items()}
    )
    common = dict(
        next_state_std=next_state_std,
        reward_std=reward_std,
        normalizer=normalizer,
        source_norm=source_norm,
        tolerance=tolerance,
        seed=seed,
        origin=path,
    )
    details: dict[str, Any] = {}
    analysis = None
    with console.progress(disable=not show_progress) as prog:
        clock = time.perf_counter()
        hipode_checks = check_transitions(
            env_id,
            synthetic,
            progress=prog,
            label=f"simulate {method_label(method)}",
            **common,
        )
        hipode_checks = dataclasses.replace(hipode_checks, rows=picked)
        seconds["simulate_hipode"] = time.perf_counter() - clock
        baseline_checks = None
        if baseline:
            clock = time.perf_counter()
            generators, details = _artifact_generators(
                path, manifest, source, info.sha256, root, torch_device, show_progress
            )
            policy, record = behaviour_cvae(
                source,
                generators.normalizer,
                behaviour or BehaviourCVAEConfig(),
                cache_dir=generators.cache_dir,
                seed=seed,
                device=torch_device,
                progress=prog,
            )
            details["behaviour_cvae"] = record
            rollouts, baseline_rows = plain_rollouts(
                source,
                generators,
                policy,
                env_id=env_id,
                count=len(synthetic),
                seed=seed,
                use_mean=_dynamics_mean(path, manifest),
            )
            seconds["baseline_models"] = time.perf_counter() - clock
            clock = time.perf_counter()
            baseline_checks = check_transitions(
                env_id, rollouts, progress=prog, label="simulate baseline", **common
            )
            baseline_checks = dataclasses.replace(baseline_checks, rows=baseline_rows)
            seconds["simulate_baseline"] = time.perf_counter() - clock
            clock = time.perf_counter()
            analysis = analyse(
                generators,
                env_id,
                synthetic,
                hipode_checks,
                baseline_checks,
                source,
                next_state_std=next_state_std,
                reward_std=reward_std,
                generator_seed=_manifest_value(path, manifest, "seeds.generator_training", int),
                sample=len(synthetic),
                seed=seed,
                origin=str(path),
            )
            seconds["diagnose"] = time.perf_counter() - clock
    report = VerifyReport(
        artifact=str(path),
        artifact_sha256=file_sha256(path),
        env_id=env_id,
        source_id=info.id,
        source_sha256=info.sha256,
        seed=seed,
        tolerance=tolerance,
        hipode=hipode_checks,
        baseline=baseline_checks,
        baseline_details=details,
        seconds=seconds,
        analysis=analysis,
        json_path=str(json_path),
        png_path=str(png_path),
        method=method,
    )
    clock = time.perf_counter()
    json_path.parent.mkdir(parents=True, exist_ok=True)
    plot_novelty_vs_error(report, png_path)
    seconds["write"] = time.perf_counter() - clock
    seconds["total"] = sum(v for k, v in seconds.items() if k != "total")
    report.seconds = {name: round(value, 3) for name, value in seconds.items()}
    _write_json_atomic(json_path, report.to_dict())
    return report


def _normalizer_eps(path: Path, manifest: dict[str, Any]) -> float:
    """The generators' normalizer eps from the manifest (the default when not recorded)."""
    params = manifest.get("hyper_parameters")
    config = params.get("generator_config") if isinstance(params, dict) else None
    value = (config or {}).get("normalizer_eps", GeneratorConfig().normalizer_eps)
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
        raise DataFormatError(
            path,
            "manifest.hyper_parameters.generator_config.normalizer_eps",
            "a positive number",
            repr(value),
        )
    return float(value)


def plot_novelty_vs_error(report: VerifyReport, path: Path) -> None:
    """Scatter of novelty (x) against next-state error vs the simulator (y, log), HIPODE and the
    baseline, with the tolerance as a line; written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6.4, 4.8), dpi=120)
    # log scale: errors span decades, and an exact transition would sit at -inf
    floor = 1e-6
    series = [(report.artifact_label, report.hipode, "tab:blue")]
    if report.baseline is not None:
        series.append(("plain model rollout", report.baseline, "tab:orange"))
    for label, checks, color in series:
        shown = np.isfinite(checks.next_state_error)
        axes.scatter(
            checks.novelty[shown],
            np.maximum(checks.next_state_error[shown], floor),
            s=6,
            alpha=0.5,
            color=color,
            label=f"{label} (median {np.median(checks.next_state_error):.3g})",
            edgecolors="none",
        )
    axes.axhline(report.tolerance, color="gray", linestyle="--", linewidth=1, label="tolerance")
    axes.set_yscale("log")
    axes.set_xlabel("novelty: L2 to nearest source state (z-scored)")
    axes.set_ylabel("next-state error vs simulator (source stds, mean over dims)")
    axes.set_title(f"{Path(report.artifact).name} ({report.env_id}): authenticity vs novelty")
    axes.legend(loc="best", fontsize=8)
    save_figure_atomic(figure, path)


STAGE_COLUMNS = ["stage", "rows", "median", "mean", "p90"]


def stage_rows(report: VerifyReport) -> list[list[Any]]:
    """The per-stage errors (source stds per dimension) as table rows."""
    stages = (report.analysis or {}).get("stages", {})
    kept, rows_kept = stages.get("kept", {}), len(report.hipode.next_state_error)
    named = [
        ("kept: total vs simulator", rows_kept, kept.get("total")),
        ("kept: ensemble vs simulator", rows_kept, kept.get("ensemble_on_kept_rows")),
        ("kept: check distance", rows_kept, kept.get("check_distance")),
        ("real: inverse action", stages.get("heldout_rows"), stages.get("inverse_action_on_real")),
        (
            "real: recorded action",
            stages.get("heldout_rows"),
            stages.get("recorded_action_on_real"),
        ),
        (
            "real: ensemble one step",
            stages.get("heldout_rows"),
            stages.get("ensemble_one_step_on_real"),
        ),
    ]
    return [
        [name, rows, *(round(values[k], 4) for k in ("median", "mean", "p90"))]
        for name, rows, values in named
        if values
    ]


SUMMARY_COLUMNS = [
    "artifact",
    "env",
    "HIPODE median (exact rows)",
    "HIPODE mean (exact rows)",
    "baseline median (exact rows)",
    "baseline mean (exact rows)",
    "matched-novelty ratio",
    "model tolerance",
    "HIPODE within model tol %",
    "baseline within model tol %",
    "exact rows %",
    "ensemble 1-step median",
    "inverse action median",
]


def summary_row(report: VerifyReport) -> list[Any]:
    """One artifact's line of the across-artifact table (needs the baseline's analysis)."""
    mine = report.hipode.summary()
    theirs = report.baseline.summary() if report.baseline is not None else {}
    analysis = report.analysis or {}
    stages = analysis.get("stages", {})
    tolerance = analysis.get("model_tolerance", {})

    def pick(data: dict, *keys: str) -> Any:
        for key in keys:
            data = data.get(key) if isinstance(data, dict) else None
        return None if data is None else round(float(data), 4)

    within = [tolerance.get(k) for k in ("hipode_within", "baseline_within")]
    return [
        Path(report.artifact).name,
        report.env_id,
        pick(mine, "next_state_error_median_exact_rows"),
        pick(mine, "next_state_error_mean_exact_rows"),
        pick(theirs, "next_state_error_median_exact_rows"),
        pick(theirs, "next_state_error_mean_exact_rows"),
        pick(analysis, "matched_novelty_exact_rows", "median_ratio"),
        pick(tolerance, "value"),
        *[None if w is None else round(100 * w, 1) for w in within],
        round(100 * mine["exact_ground_truth_share"], 1),
        pick(stages, "ensemble_one_step_on_real", "median"),
        pick(stages, "inverse_action_on_real", "median"),
    ]


def summary_paths(out_dir: Path) -> tuple[Path, Path]:
    return out_dir / "verify-summary.json", out_dir / "verify-summary.png"


def write_summary(reports: list[VerifyReport], out_dir: Path) -> tuple[Path, Path]:
    """The across-artifact table as JSON, and per artifact HIPODE's and the baseline's median
    error in each shared novelty bin as one plot (atomically)."""
    json_path, png_path = summary_paths(out_dir)
    rows = [dict(zip(SUMMARY_COLUMNS, summary_row(r), strict=True)) for r in reports]
    out_dir.mkdir(parents=True, exist_ok=True)
    _write_json_atomic(
        json_path,
        {
            "columns": SUMMARY_COLUMNS,
            "rows": rows,
            "reports": [r.json_path for r in reports],
            "definitions": {
                "exact rows": "rows whose input velocities were not at the observation's "
                "clipping bound, so the simulator's answer is exact",
                "matched-novelty ratio": "median over shared novelty bins of HIPODE's median "
                "next-state error / the baseline's, exact rows only",
                "model tolerance": "the dynamics ensemble's median one-step error on held-out "
                "real transitions",
            },
        },
    )
    plot_matched_novelty(
        [(Path(r.artifact).name.split("-eta")[0], r.analysis) for r in reports], png_path
    )
    return json_path, png_path


def plot_matched_novelty(series: list[tuple[str, dict[str, Any] | None]], path: Path) -> None:
    """Per (label, analysis): HIPODE's and the baseline's median error in each shared novelty
    bin, one colour per label, as PNG (atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7.2, 4.8), dpi=120)
    for index, (name, analysis) in enumerate(series):
        bins = ((analysis or {}).get("matched_novelty_exact_rows") or {}).get("bins", [])
        centers = [b["novelty_from"] for b in bins]
        color = f"C{index % 10}"
        for key, style, label in (
            ("hipode_median", "-", "HIPODE"),
            ("baseline_median", "--", "plain"),
        ):
            values = [b[key] if b[key] is not None else np.nan for b in bins]
            axes.plot(centers, values, style, marker="o", color=color, label=f"{name} {label}")
    axes.set_yscale("log")
    axes.set_xlabel("novelty bin (lower edge, z-scored L2 to the nearest source state)")
    axes.set_ylabel("median next-state error vs simulator (source stds)")
    axes.set_title("authenticity at matched novelty, exact rows")
    axes.legend(fontsize=7)
    save_figure_atomic(figure, path)


def _write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    write_text_atomic(
        path, json.dumps(data, indent=2, sort_keys=True, default=_json_default) + "\n"
    )


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if dataclasses.is_dataclass(value):
        return asdict(value)
    return str(value)
