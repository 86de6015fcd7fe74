"""Where the critics of finished TD3+BC (or IQL) runs stand on the source's falls.

A terminal transition's value is known exactly: its reward, with nothing after it. This reads
each finished run's last checkpoint under the given folder, evaluates the critic (the smaller
of its twin Qs, as TD3 bootstraps) at the source's own state-action pairs, and reports per run:
Q on every source row; Q on the rows that end in a fall (terminal) against their reward; and
Q on the few rows before each fall against the data's return from there to the fall (their
value if the fall is already certain). A critic that has seen few falls (an arm whose
synthetic rows are rarely terminal) would value falls and the states before them higher.

And whether a critic's level is right: at a seeded sample of source states (the same for every
run of a source), the critic's value of the run's own policy, Q(s, π(s)), against that policy's
discounted return when the simulator is put into s and the policy run from there (--horizon
steps; a fall ends it, the time limit does not). Q − return > 0 is overestimation.

    python bench/critic_probe.py bench/evidence/runs/hopper-m-r-f1a408d8
    python bench/critic_probe.py bench/evidence/runs/halfcheetah-m-r-33eba5d6 --learner iql

writes critic_probe.md and .json beside the sweep's report (<folder>/report/<learner>/). IQL's
critics learn scaled rewards where its config normalizes them: their values are divided by that
scale, so every Q here is in the data's reward units. IQL's Q is an in-sample (expectile) value,
not its policy's: its Q − return also holds the gap between the two. Needs the
runs' checkpoint.pt files (not committed: run it in the session that trained them) and the
runs' own source under the dataset root (its sha256 is checked against the runs' records). A
finished run whose checkpoint is gone keeps its row from the previous report (same number of
updates, source and artifact), with the date it was probed: its falls columns always, its
policy-value columns under the same --states and --horizon only.

And, for IQL runs with synthetic data, how much its actor learns from that data: IQL's policy
regresses onto each batch row's action weighted by exp(β · (Q(s, a) − V(s))) (capped), so the
mean weight on the run's synthetic rows against its source rows, at the batch share the run
trained with, gives the synthetic rows' share of the actor's regression. The artifact must be
the run's own (its content checksum is checked against the run's record).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
CHUNK = 32_768  # rows per critic forward: bounded memory on a large source
BEFORE = 5  # rows before a fall whose critic values are compared with the return to the fall
STATES = 32  # source states per run at which the critic is compared with the policy's return
HORIZON = 500  # steps of those returns: the discounted tail beyond is under 1 % at γ = 0.99
STATES_SEED = 0  # which source states: the same for every run of a source
LEARNERS = {"td3bc": "TD3+BC", "iql": "IQL"}  # learners with twin critics Q(s, a)
FALL_KEYS = (
    "q_falls",
    "reward_falls",
    "fall_overestimate",
    "fall_overestimate_share",
    "q_before_falls",
    "return_to_fall",
)


def before_falls(data, discount: float):
    """Rows 1..BEFORE steps before a fall in the same episode (the rows run in episode order,
    each s' the next row's s) and the data's discounted return from each row to the fall: the
    row's value if the fall cannot be avoided from there."""
    import numpy as np

    ends = data.terminals | data.timeouts
    falls = np.flatnonzero(data.terminals)
    rows, returns = [], []
    alive = np.ones(len(falls), bool)
    to_fall = data.rewards[falls].astype(np.float64)
    for k in range(1, BEFORE + 1):
        j = falls - k
        alive &= j >= 0
        j = np.where(alive, j, 0)
        alive &= ~ends[j] & np.all(data.next_observations[j] == data.observations[j + 1], 1)
        to_fall = data.rewards[j] + discount * to_fall
        rows.append(j[alive])
        returns.append(to_fall[alive])
    return np.concatenate(rows), np.concatenate(returns)


def run_folders(root: Path, learner: str = "td3bc") -> list[Path]:
    """The learner's finished runs (scores.json) that still have their checkpoint; run folders
    are named <learner>-seed<k>."""
    return sorted(
        p.parent
        for p in root.rglob("scores.json")
        if (p.parent / "checkpoint.pt").is_file() and p.parent.name.startswith(f"{learner}-seed")
    )


def learner(state: dict, obs_dim: int, act_dim: int, origin: str):
    """The checkpoint's learner (one seed) on the CPU."""
    from hipode_pipeline.learners import learner_class

    cls = learner_class(state["learner"])
    model = cls(
        obs_dim,
        act_dim,
        cls.config_class.from_dict(state["config"]),
        device="cpu",
        seed=int(state["seed"]),
    )
    model.load_seed_states([state], origin=origin)
    return model


def per_row(model, evaluate, observations, actions=None):
    """`evaluate(normalized states, actions)` -> one value per row, for every row, on the CPU,
    in chunks (bounded memory on a large source), in the learner's own units. Both arguments
    come as one-seed (1, n, ·) tensors; actions None where `evaluate` needs none."""
    import torch

    values = []
    with torch.no_grad():
        for start in range(0, len(observations), CHUNK):
            obs = model.normalize(torch.as_tensor(observations[start : start + CHUNK]).unsqueeze(0))
            act = None if actions is None else actions[start : start + CHUNK]
            values.append(evaluate(obs, None if act is None else torch.as_tensor(act).unsqueeze(0)))
    return torch.cat(values).numpy()


def in_reward_units(model, evaluate, observations, actions=None):
    """`per_row`, divided by the learner's reward scale so that a learner that scaled its
    rewards reads in the data's units."""
    scale = float(getattr(model, "reward_scale", 1.0))
    return per_row(model, evaluate, observations, actions) / scale


def critic_values(model, observations, actions):
    """min over the twin critics of Q(s, a) for every row, in the data's reward units."""
    return in_reward_units(
        model, lambda obs, act: model.critic(obs, act).amin(1)[0], observations, actions
    )


def start_states(data, env_id: str, count: int):
    """`count` source rows (seeded, without replacement) whose state the observation fully
    gives: rows with a velocity at the env's clipping bound cannot be restored."""
    import numpy as np

    from hipode_pipeline.simulator import clipped_velocity_rows

    exact = np.flatnonzero(~clipped_velocity_rows(env_id, data.observations))
    rng = np.random.default_rng(STATES_SEED)
    return np.sort(rng.choice(exact, size=min(count, len(exact)), replace=False))


# the columns of the policy-value check, in the order it fills them; they hold only for its
# --states and --horizon
POLICY_KEYS = (
    "states",
    "horizon",
    "q_policy",
    "return_policy",
    "q_policy_overestimate",
    "falls_within_horizon",
)


# the columns of the actor-weight check (IQL runs with synthetic data)
ACTOR_KEYS = (
    "weight_source",
    "weight_synthetic",
    "capped_source",
    "capped_synthetic",
    "synthetic_batch_share",
    "synthetic_actor_share",
)


def advantage_weights(model, observations, actions):
    """IQL's actor weight exp(β · (Q_target(s, a) − V(s))), capped as in training, per row; in
    the learner's own (scaled) reward units, as it trained."""
    import torch

    config = model.config

    def weights(obs, act):
        advantage = model.critic_target(obs, act).amin(1)[0] - model.value(obs)[0].squeeze(-1)
        return torch.exp(config.beta * advantage).clamp(max=config.exp_adv_max)

    return per_row(model, weights, observations, actions)


def replay_settings(config: dict) -> tuple[float, str, int]:
    """η, mixing and the synthetic row count a run's sampler was built with, from its record."""
    return (
        float(config.get("eta") or 0),
        config.get("mixing", "mixed"),
        int(config.get("n_synthetic") or 0),
    )


def synthetic_batch_share(config: dict) -> float:
    """The share of synthetic rows in the run's batches, as its sampler drew them."""
    from hipode_pipeline import replay

    eta, mixing, n_synthetic = replay_settings(config)
    n_real, batch = int(config["n_real"]), int(config["batch_size"])
    return replay.synthetic_batch_share(eta, mixing, n_real, n_synthetic, batch)


def actor_weight_check(model, source, synthetic, config: dict) -> dict:
    """The mean actor weight on the source's and the run's synthetic rows, the share of each
    weight at the cap, and the synthetic rows' share of the actor's regression at the run's
    batch share of them."""
    on_source = advantage_weights(model, source.observations, source.actions)
    on_synthetic = advantage_weights(model, synthetic.observations, synthetic.actions)
    share = synthetic_batch_share(config)
    cap = float(model.config.exp_adv_max)
    pulled = share * float(on_synthetic.mean())
    values = (
        float(on_source.mean()),
        float(on_synthetic.mean()),
        float((on_source >= cap).mean()),
        float((on_synthetic >= cap).mean()),
        share,
        pulled / (pulled + (1.0 - share) * float(on_source.mean())),
    )
    return dict(zip(ACTOR_KEYS, values, strict=True))


def policy_value_check(model, data, env_id: str, rows, horizon: int, discount: float) -> dict:
    """Q(s, π(s)) at the source rows `rows` against π's discounted return from s."""
    from hipode_pipeline.simulator import policy_returns

    if not len(rows):
        return {}
    observations = data.observations[rows]
    actions = model.act(observations)
    q = critic_values(model, observations, actions)
    returns, steps = policy_returns(
        env_id, observations, model.act, horizon=horizon, discount=discount
    )
    values = (
        len(rows),
        horizon,
        float(q.mean()),
        float(returns.mean()),
        float((q - returns).mean()),
        int((steps < horizon).sum()),
    )
    return dict(zip(POLICY_KEYS, values, strict=True))


def probe(
    folder: Path,
    config: dict,
    sources: dict,
    states: int = STATES,
    horizon: int = HORIZON,
    artifacts: dict | None = None,
) -> dict:
    """One run's row: `config` is its config.json, `sources` maps source ids to loaded sources;
    `states` source states (0: none) at which Q is checked against the policy's return;
    `artifacts` maps artifact checksums to their synthetic rows (an IQL run trained on one gets
    the actor-weight check)."""
    from hipode_pipeline.errors import DataFormatError
    from hipode_pipeline.files import display_path
    from hipode_pipeline.run_folder import load_checkpoint

    source, info = sources[config["source_id"]]
    if info.sha256 != config.get("source_sha256"):
        raise DataFormatError(
            folder / "config.json",
            "source_sha256",
            f"{info.sha256} (the source under the dataset root; rebuild the run's own source)",
            config.get("source_sha256"),
        )
    checkpoint = folder / "checkpoint.pt"
    state = load_checkpoint(checkpoint)["learner"]
    if state["learner"] not in LEARNERS:
        raise DataFormatError(checkpoint, "learner", f"one of {sorted(LEARNERS)}", state["learner"])
    model = learner(state, source.obs_dim, source.act_dim, str(checkpoint))
    q = critic_values(model, source.observations, source.actions)
    falls = source.terminals
    q_all = float(q.mean())
    discount = float(state["config"].get("discount", 0.99))
    rows, to_fall = before_falls(source, discount)
    fall_values = dict.fromkeys(FALL_KEYS)  # a source without falls (HalfCheetah): none
    if falls.any():
        q_falls, r_falls = float(q[falls].mean()), float(source.rewards[falls].mean())
        fall_values = {
            "q_falls": q_falls,
            "reward_falls": r_falls,
            "fall_overestimate": q_falls - r_falls,
            "fall_overestimate_share": (q_falls - r_falls) / q_all,
            "q_before_falls": float(q[rows].mean()),
            "return_to_fall": float(to_fall.mean()),
        }
    check = {}
    if states:
        env_id = config["env_id"]
        starts = start_states(source, env_id, states)
        check = policy_value_check(model, source, env_id, starts, horizon, discount)
    synthetic = (artifacts or {}).get(config.get("artifact_checksum"))
    if state["learner"] == "iql" and synthetic is not None and trains_on_synthetic(config):
        check |= actor_weight_check(model, source, synthetic, config)
    return {
        "run": display_path(folder),
        "source_sha256": config.get("source_sha256"),
        "artifact_checksum": config.get("artifact_checksum"),
        "arm": folder.parent.name,
        "seed": int(config["seed"]),
        "step": int(state["step"]),
        "rows": len(q),
        "falls": int(falls.sum()),
        "q_mean": q_all,
        "rows_before_falls": len(rows),
        **fall_values,
        **check,
    }


def trains_on_synthetic(config: dict) -> bool:
    """Whether the run drew synthetic rows into its batches (hipode_pipeline.replay's rule)."""
    from hipode_pipeline.replay import uses_synthetic

    return uses_synthetic(*replay_settings(config))


def run_artifacts(configs: dict) -> dict:
    """The synthetic rows of every run that trained on an artifact, by content checksum, each
    read and verified once and checked to be the artifact the run recorded."""
    from hipode_pipeline.artifact import read_artifact
    from hipode_pipeline.errors import DataFormatError

    artifacts = {}
    for folder, config in configs.items():
        checksum = config.get("artifact_checksum")
        if not trains_on_synthetic(config) or checksum in artifacts:
            continue
        artifact = read_artifact(REPO / config["artifact_path"])
        if artifact.manifest.get("checksum") != checksum:
            raise DataFormatError(
                artifact.path,
                "checksum",
                f"{checksum} (the artifact that {folder / 'config.json'} trained on)",
                artifact.manifest.get("checksum"),
            )
        artifacts[checksum] = artifact.transitions
    return artifacts


def read_record(path: Path, field: str, expected: str) -> dict:
    """A JSON object from `path` whose `field` holds what `expected` says; anything else is
    refused by name (a file is data: parsed, never run)."""
    from hipode_pipeline.errors import DataFormatError

    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise DataFormatError(path, field, expected, f"unreadable JSON ({error})") from None
    if not isinstance(record, dict) or field not in record:
        raise DataFormatError(path, field, expected, "no such field")
    return record


def previous_report(path: Path) -> dict:
    """The critic_probe.json that this run replaces, checked to hold dated probe rows."""
    from hipode_pipeline.errors import DataFormatError

    expected = "a list of probe rows written by bench/critic_probe.py"
    record = read_record(path, "runs", expected)
    if not isinstance(record.get("date_utc"), str):
        raise DataFormatError(path, "date_utc", "the date the rows were probed", "none")
    rows = record["runs"]
    keys = ("run", "arm", "seed", "step")
    if not isinstance(rows, list) or not all(
        isinstance(r, dict) and all(k in r for k in keys) for r in rows
    ):
        raise DataFormatError(path, "runs", f"{expected}, each with {', '.join(keys)}")
    return record


def carried_rows(previous: dict, probed: list[dict], states: int, horizon: int) -> list[dict]:
    """Rows of the previous report (`previous`, its parsed JSON) for runs that were not probed
    now because their checkpoint is gone: a run still finished (scores.json), with as many
    updates, the same source and artifact as when it was probed. Its policy-value columns are
    kept only under the same check settings (`states`: the number of states the fresh rows were
    checked at, 0 for none; `horizon`); the falls columns always. Each keeps its probe date."""
    fresh = {(REPO / row["run"]).resolve() for row in probed}
    kept = []
    for row in previous["runs"]:
        folder = (REPO / str(row["run"])).resolve()
        if folder in fresh or (folder / "checkpoint.pt").is_file():
            continue  # probed now, or probed again when its checkpoint is back
        if not (folder / "scores.json").is_file():
            continue
        config = read_record(folder / "config.json", "seed", "a run record of `hipode train`")
        if config.get("steps", row["step"]) != row["step"]:
            continue  # trained further since: its old row is stale
        if any(
            k in row and config.get(k) != row[k] for k in ("source_sha256", "artifact_checksum")
        ):
            continue  # trained again on other data since
        if (row.get("horizon"), row.get("states")) != (horizon, states):
            # the falls columns hold under any check setting; the policy check's do not
            row = {k: v for k, v in row.items() if k not in POLICY_KEYS}
        kept.append({**row, "probed_utc": row.get("probed_utc", previous["date_utc"])})
    return kept


def probe_dates(rows: list[dict]) -> str:
    """When the rows were probed, with how many each time."""
    counts = Counter(row["probed_utc"] for row in rows)
    return "; ".join(f"{date} UTC: {n} run{'s' * (n > 1)}" for date, n in sorted(counts.items()))


def table(rows: list[dict]) -> str:
    """The falls table (Q alone for runs whose source has no falls), and the policy-value table
    where the rows have it."""
    without = [r for r in rows if r["q_falls"] is None]
    text = falls_table([r for r in rows if r["q_falls"] is not None])
    if without:
        text += (
            "\nNo falls (terminal rows) in the source of these runs, so nothing to value at "
            "falls:\n\n| arm | seed | step | Q, all source rows |\n|---|---|---|---|\n"
        )
        text += "".join(
            f"| {r['arm']} | {r['seed']} | {r['step']:,} | {r['q_mean']:.1f} |\n" for r in without
        )
    text += policy_table([r for r in rows if "q_policy" in r])
    return text + actor_table([r for r in rows if "synthetic_actor_share" in r])


def falls_table(rows: list[dict]) -> str:
    """Q at the falls and the rows before them against their reward and return; empty without
    rows."""
    if not rows:
        return ""
    head = (
        "| arm | seed | step | Q, all source rows | Q at falls | reward at falls | "
        f"Q − reward at falls | as a share of Q | Q, {BEFORE} rows before falls | "
        "their return to the fall |\n|---|---|---|---|---|---|---|---|---|---|\n"
    )
    falls = "".join(
        f"| {r['arm']} | {r['seed']} | {r['step']:,} | {r['q_mean']:.1f} | "
        f"{r['q_falls']:.1f} | {r['reward_falls']:.2f} | {r['fall_overestimate']:.1f} | "
        f"{100 * r['fall_overestimate_share']:.0f} % | {r['q_before_falls']:.1f} | "
        f"{r['return_to_fall']:.1f} |\n"
        for r in rows
    )
    return head + falls


def policy_table(rows: list[dict]) -> str:
    """Q(s, π(s)) against π's return per run; empty when no row has it."""
    if not rows:
        return ""
    head = (
        f"\nAt {rows[0]['states']} source states (the same for every run), the critic's value of "
        f"the run's own policy against that policy's return in the simulator ({rows[0]['horizon']} "
        "steps):\n\n| arm | seed | Q(s, π(s)) | return of π from s | Q − return | falls within "
        "the horizon |\n|---|---|---|---|---|---|\n"
    )
    return head + "".join(
        f"| {r['arm']} | {r['seed']} | {r['q_policy']:.1f} | {r['return_policy']:.1f} | "
        f"{r['q_policy_overestimate']:+.1f} | {r['falls_within_horizon']} of {r['states']} |\n"
        for r in rows
    )


def actor_table(rows: list[dict]) -> str:
    """IQL's actor weights on source and synthetic rows per run; empty when no row has them."""
    if not rows:
        return ""
    head = (
        "\nIQL's actor weights exp(β · (Q − V)) on the source's rows and on the run's synthetic "
        "rows, and the synthetic rows' share of the actor's regression at their share of the "
        "batch:\n\n| arm | seed | mean weight, source | mean weight, synthetic | at the cap, "
        "source / synthetic | synthetic share of the batch | synthetic share of the actor's "
        "regression |\n|---|---|---|---|---|---|---|\n"
    )
    return head + "".join(
        f"| {r['arm']} | {r['seed']} | {r['weight_source']:.1f} | {r['weight_synthetic']:.1f} | "
        f"{100 * r['capped_source']:.1f} % / {100 * r['capped_synthetic']:.1f} % | "
        f"{100 * r['synthetic_batch_share']:.1f} % | {100 * r['synthetic_actor_share']:.1f} % |\n"
        for r in rows
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="A sweep folder (bench/evidence/runs/<...>).")
    parser.add_argument(
        "--states", type=int, default=STATES, help="Source states for Q vs the return (0: none)."
    )
    parser.add_argument("--horizon", type=int, default=HORIZON, help="Steps of those returns.")
    parser.add_argument("--learner", default="td3bc", choices=sorted(LEARNERS), help="Whose runs.")
    args = parser.parse_args(argv)
    if args.states < 0 or args.horizon < 1:
        sys.exit(f"expected --states ≥ 0 and --horizon ≥ 1, found {args.states}, {args.horizon}")
    root = args.folder.resolve()  # before the chdir: a folder relative to the caller's directory
    os.chdir(REPO)
    from hipode_pipeline.data.load import load_source
    from hipode_pipeline.files import write_json_atomic, write_text_atomic
    from hipode_pipeline.paths import datasets_root
    from hipode_pipeline.threads import torch_threads
    from hipode_pipeline.versions import package_versions

    folders = run_folders(root, args.learner)
    if not folders:
        sys.exit(f"{args.folder}: no finished {args.learner} run with its checkpoint.pt under it")
    configs = {
        f: read_record(f / "config.json", "seed", "a run record of `hipode train`") for f in folders
    }
    ids = {config["source_id"] for config in configs.values()}
    sources = {i: load_source(i, datasets_root()) for i in ids}
    artifacts = run_artifacts(configs) if args.learner == "iql" else {}
    start = time.time()
    now = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    with torch_threads(1):
        rows = [
            probe(f, configs[f], sources, args.states, args.horizon, artifacts) for f in folders
        ]
    rows = [{**row, "probed_utc": now} for row in rows]
    out = root / "report" / args.learner
    previous = out / "critic_probe.json"
    if previous.is_file():
        checked = next((row["states"] for row in rows if "states" in row), args.states)
        rows += carried_rows(previous_report(previous), rows, checked, args.horizon)
    rows.sort(key=lambda r: (r["arm"], r["seed"]))
    out.mkdir(parents=True, exist_ok=True)
    record = {
        "command": "python bench/critic_probe.py " + " ".join(argv or sys.argv[1:]),
        "date_utc": now,
        "seconds": round(time.time() - start, 1),
        "versions": package_versions(),
        "runs": rows,
    }
    write_json_atomic(out / "critic_probe.json", record)
    write_text_atomic(
        out / "critic_probe.md",
        f"# {LEARNERS[args.learner]} critics at the source's falls\n\n`{record['command']}` "
        f"({record['date_utc']} UTC; rows probed {probe_dates(rows)}). Q: the smaller twin "
        "critic at the source's own (s, a); a fall (terminal row) is worth its reward "
        "exactly.\n\n" + table(rows),
    )
    print(table(rows))


if __name__ == "__main__":
    main()
