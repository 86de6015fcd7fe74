"""HIPODE: policy-decoupled, high-return data augmentation for offline RL.

The data flows one way, and the modules are named after its steps:

    data/        sources (Minari, D4RL files, collected here) -> Transitions + SourceInfo
    models/      the five generators, trained once per (source, code, config, seed), cached
    generate     Algorithm 1 on arrays: candidates -> argmax V -> inverse models -> top-lambda
    artifact     the synthetic file: schema, checksum, atomic writer, strict reader
    augment      stage one's driver: load -> train or reuse generators -> generate -> write
    contract     which artifact a learner's table row asks for, and its name
    replay       source ⊕ synthetic, sampled as eta-mixed batches
    learners/    TD3+BC, IQL, CQL (and d3rlpy's through the same data)
    evaluate     rollouts in the env, D4RL-normalized scores
    train        stage two's driver: data -> learner -> evaluate -> run folder
    run_folder   a run's identity, folder, checkpoint and scores
    sweep/       many runs (tasks x arms x seeds), locally or on Ray, and their report
    commands/    the thin `hipode` CLI over all of the above
"""

__version__ = "0.1.0"
