"""Where the critics of finished TD3+BC runs stand on the source's falls.

A terminal transition's value is known exactly: its reward, with nothing after it. This reads
each finished run's last checkpoint under the given folder, evaluates the critic (the smaller
of its twin Qs, as TD3 bootstraps) at the source's own state-action pairs, and reports per run:
Q on every source row; Q on the rows that end in a fall (terminal) against their reward; and
Q on the few rows before each fall against the data's return from there to the fall (their
value if the fall is already certain). A critic that has seen few falls (an arm whose
synthetic rows are rarely terminal) would value falls and the states before them higher.

    python bench/critic_probe.py bench/evidence/runs/hopper-m-r-f1a408d8

writes critic_probe.md and .json beside the sweep's report (<folder>/report/td3bc/). Needs the
runs' checkpoint.pt files (not committed: run it in the session that trained them) and the
runs' own source under the dataset root (its sha256 is checked against the runs' records).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
CHUNK = 32_768  # rows per critic forward: bounded memory on a large source
BEFORE = 5  # rows before a fall whose critic values are compared with the return to the fall


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


def run_folders(root: Path) -> list[Path]:
    """Finished runs (scores.json) that still have their checkpoint."""
    return sorted(
        p.parent for p in root.rglob("scores.json") if (p.parent / "checkpoint.pt").is_file()
    )


def critic_values(state: dict, observations, actions, origin: str):
    """min over the twin critics of Q(s, a) for every row, on the CPU, in chunks."""
    import torch

    from hipode_pipeline.learners import learner_class

    cls = learner_class(state["learner"])
    model = cls(
        observations.shape[1],
        actions.shape[1],
        cls.config_class.from_dict(state["config"]),
        device="cpu",
        seed=int(state["seed"]),
    )
    model.load_seed_states([state], origin=origin)
    values = []
    with torch.no_grad():
        for start in range(0, len(observations), CHUNK):
            obs = torch.as_tensor(observations[start : start + CHUNK]).unsqueeze(0)
            act = torch.as_tensor(actions[start : start + CHUNK]).unsqueeze(0)
            values.append(model.critic(model.normalize(obs), act).amin(1)[0])
    return torch.cat(values).numpy()


def probe(folder: Path, config: dict, sources: dict) -> dict:
    """One run's row: `config` is its config.json, `sources` maps source ids to loaded sources."""
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
    if state["learner"] != "td3bc":
        raise DataFormatError(checkpoint, "learner", "td3bc", state["learner"])
    q = critic_values(state, source.observations, source.actions, str(checkpoint))
    falls = source.terminals
    q_falls, r_falls = float(q[falls].mean()), float(source.rewards[falls].mean())
    q_all = float(q.mean())
    rows, to_fall = before_falls(source, float(state["config"].get("discount", 0.99)))
    return {
        "run": display_path(folder),
        "arm": folder.parent.name,
        "seed": int(config["seed"]),
        "step": int(state["step"]),
        "rows": len(q),
        "falls": int(falls.sum()),
        "q_mean": q_all,
        "q_falls": q_falls,
        "reward_falls": r_falls,
        "fall_overestimate": q_falls - r_falls,
        "fall_overestimate_share": (q_falls - r_falls) / q_all,
        "rows_before_falls": len(rows),
        "q_before_falls": float(q[rows].mean()),
        "return_to_fall": float(to_fall.mean()),
    }


def table(rows: list[dict]) -> str:
    head = (
        "| arm | seed | step | Q, all source rows | Q at falls | reward at falls | "
        f"Q − reward at falls | as a share of Q | Q, {BEFORE} rows before falls | "
        "their return to the fall |\n|---|---|---|---|---|---|---|---|---|---|\n"
    )
    return head + "".join(
        f"| {r['arm']} | {r['seed']} | {r['step']:,} | {r['q_mean']:.1f} | {r['q_falls']:.1f} | "
        f"{r['reward_falls']:.2f} | {r['fall_overestimate']:.1f} | "
        f"{100 * r['fall_overestimate_share']:.0f} % | {r['q_before_falls']:.1f} | "
        f"{r['return_to_fall']:.1f} |\n"
        for r in rows
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="A sweep folder (bench/evidence/runs/<...>).")
    args = parser.parse_args(argv)
    os.chdir(REPO)
    from hipode_pipeline.data.load import load_source
    from hipode_pipeline.files import write_json_atomic, write_text_atomic
    from hipode_pipeline.paths import datasets_root
    from hipode_pipeline.threads import torch_threads
    from hipode_pipeline.versions import package_versions

    folders = run_folders(args.folder.resolve())
    if not folders:
        sys.exit(f"{args.folder}: no finished run with its checkpoint.pt under it")
    configs = {f: json.loads((f / "config.json").read_text()) for f in folders}
    ids = {config["source_id"] for config in configs.values()}
    sources = {i: load_source(i, datasets_root()) for i in ids}
    start = time.time()
    with torch_threads(1):
        rows = [probe(f, configs[f], sources) for f in folders]
    rows.sort(key=lambda r: (r["arm"], r["seed"]))
    out = args.folder / "report" / "td3bc"
    out.mkdir(parents=True, exist_ok=True)
    record = {
        "command": "python bench/critic_probe.py " + " ".join(argv or sys.argv[1:]),
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "seconds": round(time.time() - start, 1),
        "versions": package_versions(),
        "runs": rows,
    }
    write_json_atomic(out / "critic_probe.json", record)
    write_text_atomic(
        out / "critic_probe.md",
        f"# TD3+BC critics at the source's falls\n\n`{record['command']}` "
        f"({record['date_utc']} UTC). Q: the smaller twin critic at the source's own (s, a); "
        "a fall (terminal row) is worth its reward exactly.\n\n" + table(rows),
    )
    print(table(rows))


if __name__ == "__main__":
    main()
