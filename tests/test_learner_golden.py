"""One update of each learner against the papers' formulas, recomputed here in float64.

Every weight (targets included, set apart from the online nets) is fixed, the batch holds rows
with done = 0 and done = 1, and the random draws come from a generator re-seeded identically
here (for CQL that pins the order of its draws, as bitwise resumes do anyway). Each test checks
the reported losses, each gradient (Adam's first moment after one step is (1 - beta1) g), each
parameter delta (Adam's first step is exactly -lr g / (|g| + eps)) and the Polyak targets. Only
the layouts of the parameters are read from the learners, never their loss code: every
parameter is stacked over training seeds (leading axis K), and a layer's weight is (in, out).
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.learners import CQL, IQL, TD3BC, CQLConfig, IQLConfig, TD3BCConfig
from hipode_pipeline.replay import Batch

OBS_DIM, ACT_DIM, BATCH = 3, 2, 6
DONES = [0.0, 1.0, 0.0, 0.0, 1.0, 0.0]  # both kinds, so a target that ignores done fails
RTOL = 1e-5  # fp32 learner against a float64 reference
ADAM_EPS = 1e-8  # Adam's default epsilon (Kingma & Ba)
EPISODES = [(10, "terminal"), (12, "timeout"), (8, "terminal"), (10, "timeout")]


# ---- fixtures: data, weights ------------------------------------------------------------------
def real_data() -> tuple[Transitions, list[float]]:
    """Four episodes with states far from zero mean / unit std, and their returns."""
    rng = np.random.default_rng(11)
    n = sum(length for length, _ in EPISODES)
    scale, shift = np.array([1.0, 5.0, 0.2]), np.array([0.5, -2.0, 3.0])
    obs = (rng.normal(size=(n, OBS_DIM)) * scale + shift).astype(np.float32)
    next_obs = (rng.normal(size=(n, OBS_DIM)) * scale + shift).astype(np.float32)
    actions = rng.uniform(-1, 1, (n, ACT_DIM)).astype(np.float32)
    rewards = rng.normal(3.0, 40.0, n).astype(np.float32)
    terminals, timeouts = np.zeros(n, bool), np.zeros(n, bool)
    returns, start = [], 0
    for length, ending in EPISODES:
        (terminals if ending == "terminal" else timeouts)[start + length - 1] = True
        returns.append(float(rewards[start : start + length].astype(np.float64).sum()))
        start += length
    return Transitions(obs, actions, rewards, next_obs, terminals, timeouts), returns


def golden_batch(max_action: float, seed: int = 5) -> Batch:
    rng = np.random.default_rng(seed)
    scale, shift = np.array([1.0, 5.0, 0.2]), np.array([0.5, -2.0, 3.0])
    as_t = lambda x: torch.as_tensor(np.asarray(x, np.float32))  # noqa: E731
    return Batch(
        as_t(rng.normal(size=(BATCH, OBS_DIM)) * scale + shift),
        as_t(rng.uniform(-max_action, max_action, (BATCH, ACT_DIM))),
        as_t(rng.normal(0.0, 2.0, BATCH)),
        as_t(rng.normal(size=(BATCH, OBS_DIM)) * scale + shift),
        as_t(DONES),
    )


def set_weights(learner, seed: int, scale: float) -> None:
    """Every parameter of every module (targets too, so they differ from the online nets)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for key in sorted(learner.modules):
            for _, p in sorted(learner.modules[key].named_parameters()):
                p.copy_(torch.empty(p.shape).uniform_(-scale, scale, generator=g))


def snapshot(learner, k: int = 0) -> dict[str, dict[str, torch.Tensor]]:
    """Seed k's parameters, without the seed axis."""
    return {
        key: {n: p.detach().double()[k].clone() for n, p in m.named_parameters()}
        for key, m in learner.modules.items()
    }


def as64(x: torch.Tensor) -> torch.Tensor:
    return x.detach().double()


def float64(x: torch.Tensor, k: int = 0) -> torch.Tensor:
    """Seed k's part of a stacked tensor, in float64."""
    return x.detach().double()[k]


def normalizer(real: Transitions) -> tuple[torch.Tensor, torch.Tensor]:
    """TD3+BC's state normalization: mean and std over the real data, std plus 1e-3."""
    obs = real.observations.astype(np.float64)
    return torch.tensor(obs.mean(0)), torch.tensor(obs.std(0) + 1e-3)


# ---- reference networks (float64, from parameter dicts) ------------------------------------
def mlp(params: dict[str, torch.Tensor], x: torch.Tensor, prefix: str = "") -> torch.Tensor:
    """Linear layers `prefix`weights.i (in, out) and biases.i (1, out) in index order, ReLU
    between them."""
    pattern = re.compile(rf"^{re.escape(prefix)}weights\.(\d+)$")
    index = sorted(int(m.group(1)) for k in params if (m := pattern.match(k)))
    for j, i in enumerate(index):
        x = x @ params[f"{prefix}weights.{i}"] + params[f"{prefix}biases.{i}"][0]
        if j < len(index) - 1:
            x = torch.relu(x)
    return x


def q_value(params: dict[str, torch.Tensor], member: int, s, a) -> torch.Tensor:
    """Critic `member` of the fused twin critic: weights.i[member] is (in, out)."""
    x = torch.cat([s, a], dim=-1)
    layers = sum(1 for k in params if k.startswith("weights."))
    for i in range(layers):
        x = x @ params[f"weights.{i}"][member] + params[f"biases.{i}"][member, 0]
        if i < layers - 1:
            x = torch.relu(x)
    return x.squeeze(-1)


def leaves(params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {n: p.clone().requires_grad_(True) for n, p in params.items()}


def grads(loss: torch.Tensor, params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    found = torch.autograd.grad(loss, list(params.values()), allow_unused=True)
    return {
        n: torch.zeros_like(p) if g is None else g
        for (n, p), g in zip(params.items(), found, strict=True)
    }


def adam_first_step(params, gradients, lr: float) -> dict[str, torch.Tensor]:
    """Adam's first step with bias correction: m̂ = g, v̂ = g², so Δθ = -lr g / (|g| + eps)."""
    return {
        n: p.detach() - lr * gradients[n] / (gradients[n].abs() + ADAM_EPS)
        for n, p in params.items()
    }


def polyak(target, online, tau: float) -> dict[str, torch.Tensor]:
    return {n: (1 - tau) * target[n] + tau * online[n] for n in target}


# ---- comparisons ------------------------------------------------------------------------------
def assert_metric(metrics, name: str, expected: torch.Tensor, k: int = 0) -> None:
    got = metrics[name]
    assert isinstance(got, torch.Tensor) and got.dim() == 1, name  # one value per seed
    np.testing.assert_allclose(float(got[k]), float(expected.detach()), rtol=RTOL, err_msg=name)


def assert_step(
    learner, module: str, optimizer: str, before, gradients, lr: float, k: int = 0
) -> None:
    """Per tensor: the learner's gradient (from Adam's first moment) is the reference one, and
    its weights moved by Adam's first step on that gradient."""
    opt = learner.optimizers[optimizer]
    beta1 = opt.param_groups[0]["betas"][0]
    for name, p in learner.modules[module].named_parameters():
        g_expected = gradients[name]
        g_got = opt.state[p]["exp_avg"].double()[k] / (1 - beta1)
        # absolute slack for entries that cancel to ~0: fp32 rounding of the larger terms
        atol = 1e-6 * float(g_expected.abs().max()) + 1e-12
        np.testing.assert_allclose(
            g_got.numpy(), g_expected.numpy(), rtol=RTOL, atol=atol, err_msg=f"grad {module}.{name}"
        )
        # Adam's step on the learner's own gradient: a near-zero entry's step is sensitive to
        # its fp32 rounding, which the gradient check above already bounds
        np.testing.assert_allclose(
            (float64(p, k) - before[module][name]).numpy(),
            (-lr * g_got / (g_got.abs() + ADAM_EPS)).numpy(),
            rtol=RTOL,
            atol=1e-7,  # about the float32 spacing of the weights (|w| < 1)
            err_msg=f"delta {module}.{name}",
        )


def assert_params(learner, module: str, expected, atol: float = 1e-7, k: int = 0) -> None:
    for name, p in learner.modules[module].named_parameters():
        np.testing.assert_allclose(
            float64(p, k).numpy(),
            expected[name].numpy(),
            rtol=RTOL,
            atol=atol,
            err_msg=f"{module}.{name}",
        )


# ---- TD3+BC -----------------------------------------------------------------------------------
TD3BC_CONFIG = dict(
    hidden_dim=8,
    discount=0.9,
    tau=0.1,
    alpha=2.5,
    actor_lr=0.03,
    critic_lr=0.05,
    policy_noise=0.5,
    noise_clip=0.3,
    policy_freq=1,  # actor and targets move in this very update
    max_action=1.5,
    bf16=False,  # fp32, so the float64 reference matches to 1e-5
)


def td3bc_reference(before, batch: Batch, mean, std, normal: torch.Tensor, c: TD3BCConfig):
    """TD3+BC (Fujimoto & Gu 2021, Alg. 1 and Eq. 3; actor MSE as in the authors' code)."""
    s, s2 = (
        (as64(batch.observations) - mean) / std,
        (as64(batch.next_observations) - mean) / std,
    )
    a, r, d = as64(batch.actions), as64(batch.rewards), as64(batch.dones)
    ma = c.max_action
    # target policy smoothing: eps ~ clip(N(0, sigma), -c, c), both in units of max_action
    eps = (c.policy_noise * normal.double()).clamp(-c.noise_clip, c.noise_clip) * ma
    next_a = (ma * torch.tanh(mlp(before["actor_target"], s2)) + eps).clamp(-ma, ma)
    ct = before["critic_target"]
    y = r + c.discount * (1 - d) * torch.minimum(
        q_value(ct, 0, s2, next_a), q_value(ct, 1, s2, next_a)
    )

    critic = leaves(before["critic"])
    q1, q2 = q_value(critic, 0, s, a), q_value(critic, 1, s, a)
    critic_loss = ((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean()
    critic_grads = grads(critic_loss, critic)
    critic_after = adam_first_step(before["critic"], critic_grads, c.critic_lr)

    # the actor step reads Q1 of the critic as just updated
    actor = leaves(before["actor"])
    pi = ma * torch.tanh(mlp(actor, s))
    q_pi = q_value(critic_after, 0, s, pi)
    lmbda = c.alpha / q_pi.abs().mean().detach()
    actor_loss = -lmbda * q_pi.mean() + ((pi - a) ** 2).mean()
    actor_grads = grads(actor_loss, actor)
    actor_after = adam_first_step(before["actor"], actor_grads, c.actor_lr)
    return {
        "metrics": {
            "critic_loss": critic_loss,
            "q_mean": torch.cat([q1, q2]).mean(),
            "actor_loss": actor_loss,
        },
        "critic": (critic_grads, c.critic_lr),
        "actor": (actor_grads, c.actor_lr),
        "critic_target": polyak(ct, critic_after, c.tau),
        "actor_target": polyak(before["actor_target"], actor_after, c.tau),
        "noise_clipped": bool((c.policy_noise * normal).abs().gt(c.noise_clip).any()),
        "action_clamped": bool(next_a.abs().ge(ma).any()),
    }


def test_td3bc_one_update_matches_the_paper():
    c = TD3BCConfig(**TD3BC_CONFIG)
    real, _ = real_data()
    learner = TD3BC(OBS_DIM, ACT_DIM, c, device="cpu", seed=0)
    learner.fit_statistics(real)
    set_weights(learner, seed=1, scale=1.0)
    before = snapshot(learner)
    batch = golden_batch(c.max_action)
    learner.generators[0].manual_seed(42)
    normal = torch.randn((BATCH, ACT_DIM), generator=torch.Generator().manual_seed(42))
    expected = td3bc_reference(before, batch, *normalizer(real), normal, c)
    # the fixture exercises the noise clip and the action clamp
    assert expected["noise_clipped"] and expected["action_clamped"]

    assert_td3bc_update(learner, learner.update(batch), before, expected)


def assert_td3bc_update(learner, metrics, before, expected, k: int = 0) -> None:
    """Seed k's losses, critic and actor steps and both Polyak targets as the reference's."""
    for name, value in expected["metrics"].items():
        assert_metric(metrics, name, value, k=k)
    assert_step(learner, "critic", "critic", before, *expected["critic"], k=k)
    assert_step(learner, "actor", "actor", before, *expected["actor"], k=k)
    assert_params(learner, "critic_target", expected["critic_target"], k=k)
    assert_params(learner, "actor_target", expected["actor_target"], k=k)


def stacked(batches: list[Batch]) -> Batch:
    """One (K, B, ...) batch of the seeds' own batches."""
    return Batch(*(torch.stack(f) for f in zip(*batches, strict=True)))


def test_td3bc_stacked_seeds_each_match_the_paper():
    """Two seeds in one stacked learner, each with its own weights, batch and noise: each
    seed's update is the paper's on its own numbers (lambda, losses, Adam, targets per seed)."""
    c = TD3BCConfig(**TD3BC_CONFIG)
    real, _ = real_data()
    learner = TD3BC(OBS_DIM, ACT_DIM, c, device="cpu", seed=[0, 1])
    learner.fit_statistics(real)
    set_weights(learner, seed=1, scale=1.0)
    before = [snapshot(learner, k) for k in range(2)]
    batches = [golden_batch(c.max_action), golden_batch(c.max_action, seed=6)]
    expected = []
    for k, draw_seed in enumerate((42, 43)):
        learner.generators[k].manual_seed(draw_seed)
        normal = torch.randn((BATCH, ACT_DIM), generator=torch.Generator().manual_seed(draw_seed))
        expected.append(td3bc_reference(before[k], batches[k], *normalizer(real), normal, c))
    assert not torch.equal(before[0]["actor"]["weights.0"], before[1]["actor"]["weights.0"])

    metrics = learner.update(stacked(batches))

    for k in range(2):
        assert_td3bc_update(learner, metrics, before[k], expected[k], k=k)


def test_td3bc_delays_actor_and_targets():
    c = TD3BCConfig(**{**TD3BC_CONFIG, "policy_freq": 2})
    real, _ = real_data()
    learner = TD3BC(OBS_DIM, ACT_DIM, c, device="cpu", seed=0)
    learner.fit_statistics(real)
    set_weights(learner, seed=1, scale=0.6)
    before = snapshot(learner)
    metrics = learner.update(golden_batch(c.max_action))
    assert "actor_loss" not in metrics
    for key in ("actor", "actor_target", "critic_target"):
        for name, p in learner.modules[key].named_parameters():
            assert torch.equal(float64(p), before[key][name]), (key, name)
    assert "actor_loss" in learner.update(golden_batch(c.max_action))


# ---- IQL --------------------------------------------------------------------------------------
IQL_CONFIG = dict(
    hidden_dim=8,
    discount=0.9,
    tau=0.1,
    beta=10.0,  # large enough that some exp(beta A) reach the cap with these weights
    expectile=0.7,
    exp_adv_max=100.0,
    actor_lr=0.03,
    critic_lr=0.05,
    value_lr=0.02,
    max_steps=10,
    max_action=1.5,
    normalize_reward=True,  # CORL's locomotion scaling, so the scale is exercised
)


def iql_reference(before, batch: Batch, mean, std, reward_scale: float, c: IQLConfig):
    """IQL (Kostrikov et al. 2022, Eqs. 5-7; rewards scaled by 1000 / return range, CORL)."""
    s, s2 = (
        (as64(batch.observations) - mean) / std,
        (as64(batch.next_observations) - mean) / std,
    )
    a, d = as64(batch.actions), as64(batch.dones)
    r = as64(batch.rewards) * reward_scale
    ct = before["critic_target"]
    target_q = torch.minimum(q_value(ct, 0, s, a), q_value(ct, 1, s, a))

    value = leaves(before["value"])
    u = target_q - mlp(value, s).squeeze(-1)
    # expectile regression: L2_tau(u) = |tau - 1(u < 0)| u^2
    value_loss = ((c.expectile - (u < 0).double()).abs() * u**2).mean()
    value_grads = grads(value_loss, value)

    # Q towards r + gamma (1 - done) V(s'), V as it was before its own step
    y = r + c.discount * (1 - d) * mlp(before["value"], s2).squeeze(-1)
    critic = leaves(before["critic"])
    q1, q2 = q_value(critic, 0, s, a), q_value(critic, 1, s, a)
    critic_loss = ((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean()
    critic_grads = grads(critic_loss, critic)
    critic_after = adam_first_step(before["critic"], critic_grads, c.critic_lr)

    # advantage-weighted regression with exp(beta A) capped
    advantage = u.detach()
    weights = torch.exp(c.beta * advantage).clamp(max=c.exp_adv_max)
    actor = leaves(before["actor"])
    log_std = leaves(before["actor_log_std"])
    mu = c.max_action * torch.tanh(mlp(actor, s))
    if c.deterministic_policy:
        nll = ((mu - a) ** 2).sum(-1)
    else:
        ls = log_std["log_std"].clamp(-20.0, 2.0)
        nll = (0.5 * ((a - mu) / ls.exp()) ** 2 + ls + 0.5 * math.log(2 * math.pi)).sum(-1)
    actor_loss = (weights * nll).mean()
    both = grads(actor_loss, {**actor, **log_std})
    actor_grads = {n: both[n] for n in actor}
    log_std_grads = {n: both[n] for n in log_std}
    return {
        "metrics": {
            "value_loss": value_loss,
            "critic_loss": critic_loss,
            "actor_loss": actor_loss,
            "q_mean": torch.cat([q1, q2]).mean(),
        },
        "value": (value_grads, c.value_lr),
        "critic": (critic_grads, c.critic_lr),
        "critic_target": polyak(ct, critic_after, c.tau),
        "actor": (actor_grads, c.actor_lr),
        "log_std": (log_std_grads, c.actor_lr),
        "advantage": advantage,
        "weights_capped": weights.eq(c.exp_adv_max),
    }


@pytest.mark.parametrize("deterministic", [False, True])
def test_iql_one_update_matches_the_paper(deterministic):
    c = IQLConfig(**IQL_CONFIG, deterministic_policy=deterministic)
    real, returns = real_data()
    learner = IQL(OBS_DIM, ACT_DIM, c, device="cpu", seed=0)
    learner.fit_statistics(real)
    reward_scale = 1000.0 / (max(returns) - min(returns))
    assert learner.reward_scale == pytest.approx(reward_scale, rel=1e-9)
    set_weights(learner, seed=3, scale=0.6)
    before = snapshot(learner)
    batch = golden_batch(c.max_action)
    expected = iql_reference(before, batch, *normalizer(real), reward_scale, c)
    # both sides of the expectile and both sides of the cap are exercised
    adv, capped = expected["advantage"], expected["weights_capped"]
    assert (adv < 0).any() and (adv > 0).any() and capped.any() and not capped.all()

    metrics = learner.update(batch)

    for name, value in expected["metrics"].items():
        assert_metric(metrics, name, value)
    assert_step(learner, "value", "value", before, *expected["value"])
    assert_step(learner, "critic", "critic", before, *expected["critic"])
    assert_params(learner, "critic_target", expected["critic_target"])
    assert_step(learner, "actor", "actor", before, *expected["actor"])
    if deterministic:
        assert torch.equal(float64(learner.log_std), before["actor_log_std"]["log_std"])
    else:
        assert_step(learner, "actor_log_std", "actor", before, *expected["log_std"])
    # cosine schedule: the first step used actor_lr, the next uses lr (1 + cos(pi / T)) / 2
    next_lr = c.actor_lr * (1 + math.cos(math.pi / c.max_steps)) / 2
    assert learner.optimizers["actor"].param_groups[0]["lr"] == pytest.approx(next_lr, rel=1e-9)


# ---- CQL --------------------------------------------------------------------------------------
CQL_CONFIG = dict(
    hidden_dim=8,
    discount=0.9,
    tau=0.1,
    cql_alpha=3.0,
    cql_n_actions=3,
    cql_temp=0.7,
    policy_lr=0.02,
    critic_lr=0.05,
    critic_hidden_layers=2,
    actor_hidden_layers=2,
    max_action=1.0,
)


def tanh_gaussian(params, s, eps, max_action: float):
    """a = max_action tanh(u), u = mu + sigma eps; log pi(u) - sum log(1 - tanh(u)^2)."""
    out = mlp(params, s, "net.")
    mu, raw = out[..., :ACT_DIM], out[..., ACT_DIM:]
    log_std = (params["log_std_scale"] * raw + params["log_std_offset"]).clamp(-20.0, 2.0)
    u = mu + log_std.exp() * eps
    log_gauss = -0.5 * ((u - mu) / log_std.exp()) ** 2 - log_std - 0.5 * math.log(2 * math.pi)
    log_pi = log_gauss.sum(-1) - torch.log(1 - torch.tanh(u) ** 2).sum(-1)
    return max_action * torch.tanh(u), log_pi


def cql_reference(before, batch: Batch, mean, std, draws, c: CQLConfig):
    """CQL(H) with importance-sampled logsumexp (Kumar et al. 2020, Eq. 4 and App. F) on SAC."""
    s, s2 = (
        (as64(batch.observations) - mean) / std,
        (as64(batch.next_observations) - mean) / std,
    )
    a, r, d = as64(batch.actions), as64(batch.rewards), as64(batch.dones)
    eps_pi, eps_next, uniform, eps_proposals = (x.double() for x in draws)
    target_entropy = -float(ACT_DIM)
    n = c.cql_n_actions

    # SAC temperature and actor, against the critics before this update
    log_alpha = leaves(before["entropy"])
    actor = leaves(before["actor"])
    new_a, log_pi = tanh_gaussian(actor, s, eps_pi, c.max_action)
    alpha = before["entropy"]["log_alpha"].exp() if c.auto_entropy else torch.tensor(1.0)
    alpha_loss = -(log_alpha["log_alpha"] * (log_pi.detach() + target_entropy)).mean()
    q_new = torch.minimum(
        q_value(before["critic"], 0, s, new_a), q_value(before["critic"], 1, s, new_a)
    )
    actor_loss = (alpha * log_pi - q_new).mean()
    actor_grads = grads(actor_loss, actor)

    with torch.no_grad():
        next_a, next_log_pi = tanh_gaussian(before["actor"], s2, eps_next, c.max_action)
        ct = before["critic_target"]
        target_q = torch.minimum(q_value(ct, 0, s2, next_a), q_value(ct, 1, s2, next_a))
        if c.backup_entropy:
            target_q = target_q - alpha * next_log_pi
        y = r + c.discount * (1 - d) * target_q
        # proposals: uniform, pi(.|s'), pi(.|s), each scored at s and divided by its density
        sampled, sampled_log_pi = tanh_gaussian(
            before["actor"],
            torch.cat([s, s2]).unsqueeze(1).expand(-1, n, -1),
            eps_proposals,
            c.max_action,
        )
        current, next_proposals = sampled[:BATCH], sampled[BATCH:]
        current_log_pi, next_proposals_log_pi = sampled_log_pi[:BATCH], sampled_log_pi[BATCH:]
        proposals = torch.cat([uniform, next_proposals, current], dim=1)
        uniform_log_density = torch.full((BATCH, n), ACT_DIM * math.log(1 / (2 * c.max_action)))
        # every density in action units, like the uniform's (2 max_action)^-da
        to_action_units = ACT_DIM * math.log(c.max_action)
        log_density = torch.cat(
            [
                uniform_log_density.double(),
                next_proposals_log_pi - to_action_units,
                current_log_pi - to_action_units,
            ],
            1,
        )

    critic = leaves(before["critic"])
    td, gap, q_data = [], [], []
    for k in (0, 1):
        qk = q_value(critic, k, s, a)
        q_proposals = q_value(critic, k, s.unsqueeze(1).expand(-1, 3 * n, -1), proposals)
        ood = c.cql_temp * torch.logsumexp((q_proposals - log_density) / c.cql_temp, dim=1)
        td.append(((qk - y) ** 2).mean())
        gap.append((ood - qk).mean())
        q_data.append(qk)
    critic_loss = sum(t + c.cql_alpha * g for t, g in zip(td, gap, strict=True))
    critic_grads = grads(critic_loss, critic)
    critic_after = adam_first_step(before["critic"], critic_grads, c.critic_lr)
    alpha_grads = grads(alpha_loss, log_alpha)
    return {
        "metrics": {
            "critic_loss": critic_loss,
            "td_loss": td[0] + td[1],
            "cql_gap": (gap[0] + gap[1]) / 2,
            "actor_loss": actor_loss,
            "alpha": alpha,
            "q_mean": torch.cat(q_data).mean(),
        },
        "critic": (critic_grads, c.critic_lr),
        "critic_target": polyak(ct, critic_after, c.tau),
        "actor": (actor_grads, c.policy_lr),
        "entropy": (alpha_grads, c.policy_lr),
    }


def cql_draws(seed: int, n: int, max_action: float):
    """The update's draws in its order: pi(.|s), pi(.|s'), uniform, proposals at s then s'."""
    g = torch.Generator().manual_seed(seed)
    eps_pi = torch.randn((BATCH, ACT_DIM), generator=g)
    eps_next = torch.randn((BATCH, ACT_DIM), generator=g)
    uniform = torch.empty((BATCH, n, ACT_DIM)).uniform_(-max_action, max_action, generator=g)
    eps_proposals = torch.randn((2 * BATCH, n, ACT_DIM), generator=g)
    return eps_pi, eps_next, uniform, eps_proposals


@pytest.mark.parametrize(
    "variant",
    [
        {},
        {"backup_entropy": True},
        {"auto_entropy": False},
        # proposals of every kind weighed by their density in action units, also off [-1, 1]
        {"max_action": 2.0},
    ],
    ids=["default", "backup", "fixed_alpha", "max_action_2"],
)
def test_cql_one_update_matches_the_paper(variant):
    c = CQLConfig(**{**CQL_CONFIG, **variant})
    real, _ = real_data()
    learner = CQL(OBS_DIM, ACT_DIM, c, device="cpu", seed=0)
    learner.fit_statistics(real)
    set_weights(learner, seed=3, scale=0.6)
    before = snapshot(learner)
    batch = golden_batch(c.max_action)
    learner.generators[0].manual_seed(77)
    draws = cql_draws(77, c.cql_n_actions, c.max_action)
    expected = cql_reference(before, batch, *normalizer(real), draws, c)

    assert_cql_update(learner, learner.update(batch), before, expected, c)


def assert_cql_update(learner, metrics, before, expected, c: CQLConfig, k: int = 0) -> None:
    """Seed k's losses, critic, actor and temperature steps and the Polyak target."""
    for name, value in expected["metrics"].items():
        assert_metric(metrics, name, value, k=k)
    assert_step(learner, "critic", "critic", before, *expected["critic"], k=k)
    assert_params(learner, "critic_target", expected["critic_target"], k=k)
    assert_step(learner, "actor", "actor", before, *expected["actor"], k=k)
    if c.auto_entropy:
        assert_step(learner, "entropy", "entropy", before, *expected["entropy"], k=k)
    else:
        assert torch.equal(float64(learner.log_alpha, k), before["entropy"]["log_alpha"])


def test_cql_stacked_seeds_each_match_the_paper():
    """Two CQL seeds in one stacked learner: per-seed temperature, draws and conservative term."""
    c = CQLConfig(**CQL_CONFIG)
    real, _ = real_data()
    learner = CQL(OBS_DIM, ACT_DIM, c, device="cpu", seed=[0, 1])
    learner.fit_statistics(real)
    set_weights(learner, seed=3, scale=0.6)
    before = [snapshot(learner, k) for k in range(2)]
    batches = [golden_batch(c.max_action), golden_batch(c.max_action, seed=8)]
    expected = []
    for k, draw_seed in enumerate((77, 78)):
        learner.generators[k].manual_seed(draw_seed)
        draws = cql_draws(draw_seed, c.cql_n_actions, c.max_action)
        expected.append(cql_reference(before[k], batches[k], *normalizer(real), draws, c))

    metrics = learner.update(stacked(batches))

    for k in range(2):
        assert_cql_update(learner, metrics, before[k], expected[k], c, k=k)
