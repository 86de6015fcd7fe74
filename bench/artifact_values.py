"""How each artifact's synthetic transitions look to critics that never saw them.

A critic trained on the source alone (a finished η = 0 run with its checkpoint: the referee) has
its own view of what a transition is worth. For each artifact arm of a sweep folder this reads
the artifact that the arm's runs trained on and reports, under every referee, means over the
synthetic rows of

- the target gap r + γ (1 − d) V(s') − Q(s, a): how much more a row promises than the referee
  values its (s, a) at; a learner bootstraps towards that target, so rows that promise more
  than the data supports lift its critic. Its excess is taken row by row over the gap of the
  source row the synthetic row starts from (its `source_index`), so that which states were
  drawn does not count; the gap over all source rows stands beside it;
- the next-state lift V(s') − V(s'_source) on the rows that bootstrap (not terminal): the
  value of the synthetic next state against that of the source's own next state from the same
  source row.

V is IQL's value net for an IQL referee and Q(s', π(s')) for a TD3+BC one; Q is the smaller
twin. Every value is in the data's reward units (a referee that scaled its rewards is scaled
back).

    python bench/artifact_values.py bench/evidence/runs/walker2d-m-r-7f9d938b --artifacts td3bc

writes artifact_values-<referee>.md and .json under <folder>/report/<artifacts learner>/. Needs the
referee runs' checkpoint.pt files and the artifacts (neither is committed), and the runs' own
source under the dataset root; an artifact or referee of another source is refused.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from critic_probe import (  # noqa: E402
    LEARNERS,
    critic_values,
    in_reward_units,
    learner,
    read_record,
    run_folders,
)

REFEREE_ARM = "eta0"  # the arm whose runs never saw a synthetic row


def artifact_arms(root: Path, learner_name: str) -> dict[str, dict]:
    """arm -> the artifact its finished `learner_name` runs trained on (path and checksum, as
    their config.json records them); arms without an artifact are left out, and an arm whose
    runs disagree on the artifact is refused."""
    from hipode_pipeline.errors import DataFormatError

    arms: dict[str, dict] = {}
    for scores in sorted(root.rglob(f"{learner_name}-seed*/scores.json")):
        config_path = scores.parent / "config.json"
        config = read_record(config_path, "artifact_path", "a run record of `hipode train`")
        if not config["artifact_path"]:
            continue
        arm = scores.parent.parent.name
        seen = arms.setdefault(
            arm,
            {
                "artifact_path": config["artifact_path"],
                "artifact_checksum": config.get("artifact_checksum"),
                "source_id": config.get("source_id"),
                "source_sha256": config.get("source_sha256"),
            },
        )
        if seen["artifact_checksum"] != config.get("artifact_checksum"):
            raise DataFormatError(
                config_path,
                "artifact_checksum",
                f"{seen['artifact_checksum']}, the artifact of the arm's other runs",
                config.get("artifact_checksum"),
            )
    return arms


def load_artifacts(arms: dict[str, dict], source, info) -> dict:
    """arm -> its artifact, read and verified, refused unless it is the one the arm's runs
    recorded, generated from this source, with every `source_index` a row of it."""
    from hipode_pipeline.artifact import read_artifact
    from hipode_pipeline.errors import DataFormatError
    from hipode_pipeline.merge import check_pair

    artifacts = {}
    for arm, record in arms.items():
        path = REPO / record["artifact_path"]
        if record["source_sha256"] != info.sha256:
            raise DataFormatError(
                path,
                "source_sha256",
                f"{info.sha256} (the folder's source)",
                record["source_sha256"],
            )
        artifact = read_artifact(path)  # verifies its own content checksum
        if artifact.manifest["checksum"] != record["artifact_checksum"]:
            raise DataFormatError(
                path,
                "checksum",
                f"{record['artifact_checksum']}, the artifact the {arm} runs trained on "
                "(rebuild it with the sweep)",
                artifact.manifest["checksum"],
            )
        check_pair(source, info, artifact)
        index = artifact.diagnostics["source_index"]
        if index.min() < 0 or index.max() >= len(source):
            raise DataFormatError(
                path,
                "source_index",
                f"rows of the source, 0 to {len(source) - 1}",
                f"{index.min()} to {index.max()}",
            )
        artifacts[arm] = artifact
    return artifacts


def load_referee(folder: Path, source, info, referee: str):
    """A finished η = 0 run's learner and discount, refused unless it is `referee`'s and was
    trained on this source."""
    from hipode_pipeline.errors import DataFormatError
    from hipode_pipeline.run_folder import load_checkpoint

    config = read_record(folder / "config.json", "source_sha256", "a run record of `hipode train`")
    if config["source_sha256"] != info.sha256:
        raise DataFormatError(
            folder / "config.json",
            "source_sha256",
            f"{info.sha256} (the folder's source)",
            config["source_sha256"],
        )
    checkpoint = folder / "checkpoint.pt"
    state = load_checkpoint(checkpoint)["learner"]
    if state["learner"] != referee:
        raise DataFormatError(checkpoint, "learner", f"'{referee}'", state["learner"])
    model = learner(state, source.obs_dim, source.act_dim, str(checkpoint))
    return model, float(state["config"].get("discount", 0.99))


def state_values(model, observations):
    """V(s) for raw observations, in the data's reward units: IQL's value net, else the
    critic's value of the policy's own (clamped) action."""

    def value(obs, _):
        if model.name == "iql":
            return model.value(obs)[0, :, 0]
        action = model._policy_actions(obs).clamp(-model.config.max_action, model.config.max_action)
        return model.critic(obs, action).amin(1)[0]

    return in_reward_units(model, value, observations)


def target_gaps(model, data, discount: float):
    """r + γ (1 − d) V(s') − Q(s, a) per row, and V(s')."""
    next_values = state_values(model, data.next_observations)
    q = critic_values(model, data.observations, data.actions)
    target = data.rewards + discount * (1.0 - data.terminals) * next_values
    return target - q, next_values


def judge(model, source, artifacts: dict, discount: float) -> dict:
    """One referee's view of the source's rows and of each artifact's."""
    source_gap, source_next = target_gaps(model, source, discount)
    row = {"source_gap": float(source_gap.mean()), "arms": {}}
    for arm, artifact in artifacts.items():
        data = artifact.transitions
        gap, next_values = target_gaps(model, data, discount)
        index = artifact.diagnostics["source_index"]
        bootstraps = ~data.terminals  # a terminal row's V(s') enters no target
        lift = next_values[bootstraps] - source_next[index[bootstraps]]
        row["arms"][arm] = {
            "gap": float(gap.mean()),
            "excess": float((gap - source_gap[index]).mean()),
            "next_state_lift": float(lift.mean()) if len(lift) else None,
        }
    return row


def spread(values) -> dict[str, float] | None:
    """mean, lowest and highest of one measure over the referees; None where a referee has
    none (an artifact of terminal rows only has no lift)."""
    if any(v is None for v in values):
        return None
    return {"mean": sum(values) / len(values), "min": min(values), "max": max(values)}


def summary(per_referee: list[dict], arms: list[str]) -> list[dict]:
    """Per arm, and for the source rows: each measure's spread over the referees."""
    rows = [
        {"arm": arm}
        | {
            key: spread([r["arms"][arm][key] for r in per_referee])
            for key in ("gap", "excess", "next_state_lift")
        }
        for arm in arms
    ]
    return rows + [{"arm": "source rows", "gap": spread([r["source_gap"] for r in per_referee])}]


def table(rows: list[dict], counts: dict[str, int], referees: int) -> str:
    """Per arm and for the source rows: each measure's mean over the referees [lowest, highest]."""

    def cell(stat: dict | None) -> str:
        if stat is None:
            return ""
        return f"{stat['mean']:+.1f} [{stat['min']:+.1f}, {stat['max']:+.1f}]"

    head = (
        f"| rows of | rows | target gap r + γ(1 − d)V(s') − Q(s, a): mean over {referees} "
        f"referee{'s' * (referees > 1)} [lowest, highest] | gap − the gap of its own source row "
        "| next-state lift V(s') − V(s'_source), rows not terminal |\n|---|---|---|---|---|\n"
    )
    return head + "".join(
        f"| {r['arm']} | {counts[r['arm']]:,} | {cell(r['gap'])} | {cell(r.get('excess'))} | "
        f"{cell(r.get('next_state_lift'))} |\n"
        for r in rows
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="A sweep folder (bench/evidence/runs/<...>).")
    parser.add_argument(
        "--artifacts", default="td3bc", choices=sorted(LEARNERS), help="Whose runs' artifacts."
    )
    parser.add_argument(
        "--referee", default="iql", choices=sorted(LEARNERS), help="Whose η = 0 runs judge them."
    )
    args = parser.parse_args(argv)
    root = args.folder.resolve()  # before the chdir: a folder relative to the caller's directory
    os.chdir(REPO)
    from hipode_pipeline.data.load import load_source
    from hipode_pipeline.files import display_path, write_json_atomic, write_text_atomic
    from hipode_pipeline.paths import datasets_root
    from hipode_pipeline.threads import torch_threads
    from hipode_pipeline.versions import package_versions

    arms = artifact_arms(root, args.artifacts)
    referees = [f for f in run_folders(root, args.referee) if f.parent.name == REFEREE_ARM]
    if not arms or not referees:
        sys.exit(
            f"{args.folder}: expected finished {args.artifacts} runs on an artifact and "
            f"{args.referee} η = 0 runs with their checkpoint.pt; found {len(arms)} artifact "
            f"arms and {len(referees)} referees"
        )
    source, info = load_source(next(iter(arms.values()))["source_id"], datasets_root())
    artifacts = load_artifacts(arms, source, info)
    start = time.time()
    per_referee = []
    with torch_threads(1):
        for folder in referees:
            model, discount = load_referee(folder, source, info, args.referee)
            per_referee.append(
                {"run": display_path(folder), "seed": model.seeds[0]}
                | judge(model, source, artifacts, discount)
            )
    rows = summary(per_referee, sorted(artifacts))
    counts = {arm: len(a) for arm, a in artifacts.items()} | {"source rows": len(source.rewards)}
    out = root / "report" / args.artifacts
    out.mkdir(parents=True, exist_ok=True)
    record = {
        "command": "python bench/artifact_values.py " + " ".join(argv or sys.argv[1:]),
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "seconds": round(time.time() - start, 1),
        "versions": package_versions(),
        "artifacts": {arm: arms[arm] | {"rows": counts[arm]} for arm in sorted(arms)},
        "per_referee": per_referee,
        "summary": rows,
    }
    name = f"artifact_values-{args.referee}"
    write_json_atomic(out / f"{name}.json", record)
    text = table(rows, counts, len(per_referee))
    write_text_atomic(
        out / f"{name}.md",
        f"# {LEARNERS[args.artifacts]} artifacts under {LEARNERS[args.referee]} critics that "
        f"never saw them\n\n`{record['command']}` ({record['date_utc']} UTC). Referees: the "
        f"{len(per_referee)} finished {REFEREE_ARM} runs of {LEARNERS[args.referee]} whose "
        f"checkpoint.pt is on disk (training seeds {', '.join(str(r['seed']) for r in per_referee)}"
        "). A positive target gap: the rows promise more than the referee values their (s, a) "
        "at.\n\n" + text,
    )
    print(text)


if __name__ == "__main__":
    main()
