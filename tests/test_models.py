"""Each generator model learns data of known structure; bounds, clipping, batching, seeding."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hipode_pipeline.data.normalizer import StateNormalizer
from hipode_pipeline.device import fast_bf16, select_device
from hipode_pipeline.errors import DataFormatError, HipodeError
from hipode_pipeline.models import training
from hipode_pipeline.models.cvae import CVAE
from hipode_pipeline.models.dynamics import DynamicsEnsemble
from hipode_pipeline.models.value import ValueEstimator

DS, DA = 4, 2


def make_data(n: int, seed: int, **tensors) -> training.TensorData:
    return training.TensorData(
        {k: torch.as_tensor(v, dtype=torch.float32) for k, v in tensors.items()}, 0.1, 4096, seed
    )


def train(
    name,
    model,
    loss_fn,
    heldout_fn,
    data,
    tmp_path,
    *,
    steps,
    lr=1e-3,
    batch_size=128,
    keep_best="none",
    after_step=None,
    eval_every=50,
    **stopping,
):
    """`training.fit` with the tests' fixed settings; `stopping`: plateau_patience/tolerance."""
    return training.fit(
        name,
        model,
        loss_fn,
        heldout_fn,
        data,
        steps=steps,
        batch_size=batch_size,
        lr=lr,
        weight_decay=0.0,
        seed=0,
        precision="fp32",
        eval_every=eval_every,
        checkpoint_every=10**9,
        checkpoint_path=tmp_path / f"{name}.ckpt.pt",
        keep_best=keep_best,
        after_step=after_step,
        **stopping,
    )


def linear_system(n: int, seed: int = 0):
    """s' = s + 0.3 (A s + B a) + small noise, r = c.s + d.a: every model's target is known."""
    rng = np.random.default_rng(seed)
    A, B = rng.normal(size=(DS, DS)) * 0.3, rng.normal(size=(DA, DS))
    s = rng.normal(size=(n, DS))
    a = rng.uniform(-1, 1, size=(n, DA))
    s_next = s + 0.3 * (s @ A + a @ B) + 0.01 * rng.normal(size=(n, DS))
    r = s @ rng.normal(size=DS) + a @ rng.normal(size=DA) * 3 + 5
    return {"s": s, "a": a, "r": r, "s_next": s_next, "terminal": np.zeros(n)}, (A, B)


def test_state_transition_cvae_learns_a_linear_map(tmp_path):
    arrays, _ = linear_system(3000)
    data = make_data(3000, 0, **arrays)
    with training.seeded_init(0):
        model = CVAE(DS, DS, latent_dim=2 * DS, hidden=128)
    record = train(
        "state",
        model,
        lambda b, g: model.loss(b["s_next"], b["s"], g),
        lambda b: model.loss(b["s_next"], b["s"], torch.Generator().manual_seed(0))[1],
        data,
        tmp_path,
        steps=600,
        keep_best="model",
    )
    assert record.final_heldout_loss < 0.05 * record.initial_heldout_loss
    held = data.heldout()
    samples = model.sample(held["s"], 8, torch.Generator().manual_seed(1))
    assert samples.shape == (len(held["s"]), 8, DS)
    error = (samples.mean(1) - held["s_next"]).pow(2).mean() / held["s_next"].var()
    assert error < 0.05


def test_inverse_action_cvae_recovers_actions_within_bounds(tmp_path):
    arrays, _ = linear_system(3000, seed=1)
    data = make_data(3000, 0, **arrays)
    with training.seeded_init(0):
        model = CVAE(DA, 2 * DS, latent_dim=2 * DS, hidden=128, squash=True)
    model.set_output_bounds(torch.full((DA,), -1.0), torch.full((DA,), 1.0))

    def cond(b):
        return torch.cat([b["s"], b["s_next"]], -1)

    record = train(
        "action",
        model,
        lambda b, g: model.loss(b["a"], cond(b), g),
        lambda b: model.loss(b["a"], cond(b), torch.Generator().manual_seed(0))[1],
        data,
        tmp_path,
        steps=800,
        lr=3e-3,
    )
    assert record.final_heldout_loss < 0.1 * record.initial_heldout_loss
    held = data.heldout()
    samples = model.sample(cond(held), 4, torch.Generator().manual_seed(1))
    assert samples.abs().max() <= 1.0
    # prior samples (not the encoder's posterior) must recover the action: early in training a
    # CVAE with KL weight 0.5 still carries part of it in z, so the bar is "far below trivial"
    assert (samples.mean(1) - held["a"]).pow(2).mean() < 0.3 * held["a"].var()


def test_inverse_reward_cvae_learns_raw_rewards(tmp_path):
    arrays, _ = linear_system(3000, seed=2)
    data = make_data(3000, 0, **arrays)
    with training.seeded_init(0):
        model = CVAE(1, 2 * DS, latent_dim=2 * DS, hidden=128, standardize_output=True)
    r = torch.as_tensor(arrays["r"], dtype=torch.float32)
    model.set_output_scale(r.mean().reshape(1), r.std().reshape(1))

    def cond(b):
        return torch.cat([b["s"], b["s_next"]], -1)

    record = train(
        "reward",
        model,
        lambda b, g: model.loss(b["r"][:, None], cond(b), g),
        lambda b: model.loss(b["r"][:, None], cond(b), torch.Generator().manual_seed(0))[1],
        data,
        tmp_path,
        steps=800,
        lr=3e-3,
    )
    assert record.final_heldout_loss < 0.1 * record.initial_heldout_loss
    held = data.heldout()
    samples = model.sample(cond(held), 4, torch.Generator().manual_seed(1))
    assert samples.shape == (len(held["r"]), 4, 1)
    # raw units: the mean reward (about 5) comes back, not the z-scored one
    assert abs(float(samples.mean()) - float(held["r"].mean())) < 0.5
    assert (samples.mean(1)[:, 0] - held["r"]).pow(2).mean() < 0.3 * held["r"].var()


def test_latent_is_clipped_and_actions_stay_in_bounds_for_any_latent():
    with training.seeded_init(0):
        model = CVAE(DA, 2 * DS, latent_dim=8, hidden=32, squash=True, latent_clip=0.5)
    low, high = torch.tensor([-0.5, 0.0]), torch.tensor([0.3, 2.0])
    model.set_output_bounds(low, high)
    z = model.draw_latent(100, 10, torch.Generator().manual_seed(0))
    assert z.abs().max() <= 0.5 and z.abs().max() > 0.4
    model.latent_clip = 1e6
    with torch.no_grad():
        for layer in model.decoder:
            if isinstance(layer, torch.nn.Linear):
                layer.weight.mul_(50)
    samples = model.sample(torch.randn(200, 2 * DS) * 10, 10, torch.Generator().manual_seed(0))
    assert (samples >= low).all() and (samples <= high).all()
    assert (
        samples[..., 0].min() < -0.45 and samples[..., 1].max() > 1.9
    )  # the bounds are reached, not just respected


def test_cvae_sampling_is_reproducible_with_a_generator():
    with training.seeded_init(0):
        model = CVAE(DS, DS, latent_dim=8, hidden=32)
    cond = torch.randn(5, DS)
    one = model.sample(cond, 3, torch.Generator().manual_seed(7))
    two = model.sample(cond, 3, torch.Generator().manual_seed(7))
    other = model.sample(cond, 3, torch.Generator().manual_seed(8))
    assert torch.equal(one, two) and not torch.equal(one, other)


def test_value_learns_rewards_and_bootstraps_along_a_chain(tmp_path):
    # a 6-state chain walked left to right, reward 1 per step, terminal after the last state
    rng = np.random.default_rng(0)
    position = rng.integers(0, 6, size=2000)
    s = np.stack([position / 5.0, np.zeros(2000)], 1) + 0.01 * rng.normal(size=(2000, 2))
    s_next = np.stack([(position + 1) / 5.0, np.zeros(2000)], 1)
    data = make_data(
        2000, 0, s=s, r=np.ones(2000), s_next=s_next, terminal=(position == 5).astype(float)
    )
    with training.seeded_init(0):
        model = ValueEstimator(
            2, hidden=64, gamma=0.9, tau=0.05, target_update_every=1, penalty="l2", alpha=0.0
        )
    record = train(
        "value",
        model,
        lambda b, g: model.loss(b["s"], b["r"], b["s_next"], b["terminal"], g),
        lambda b: model.td_loss(b["s"], b["r"], b["s_next"], b["terminal"]),
        data,
        tmp_path,
        steps=1500,
        lr=3e-3,
        after_step=model.update_target,
    )
    states = torch.tensor([[k / 5.0, 0.0] for k in range(6)])
    values = model(states).detach()
    truth = torch.tensor([sum(0.9**j for j in range(6 - k)) for k in range(6)])
    assert torch.all(values[:-1] > values[1:]), values  # farther from the end is worth more
    assert (values - truth).abs().max() < 0.5, (values, truth)
    assert record.final_heldout_loss < 0.05


@pytest.mark.parametrize("penalty", ["target", "l2"])
def test_negative_sampling_lowers_off_data_values(tmp_path, penalty):
    rng = np.random.default_rng(0)
    s = rng.normal(size=(2000, DS)) * 0.3
    data = make_data(2000, 0, s=s, r=np.ones(2000), s_next=s, terminal=np.ones(2000))
    gaps = {}
    for alpha in (0.0, 1.0):
        with training.seeded_init(0):
            model = ValueEstimator(DS, hidden=64, penalty=penalty, alpha=alpha, sigma=1.0)
        train(
            f"value-{alpha}",
            model,
            lambda b, g, m=model: m.loss(b["s"], b["r"], b["s_next"], b["terminal"], g),
            lambda b, m=model: m.td_loss(b["s"], b["r"], b["s_next"], b["terminal"]),
            data,
            tmp_path,
            steps=600,
            lr=3e-3,
            after_step=model.update_target,
        )
        states = torch.as_tensor(s, dtype=torch.float32)
        off = states + (
            torch.rand(states.shape, generator=torch.Generator().manual_seed(3)) * 2 - 1
        )
        with torch.no_grad():
            gaps[alpha] = float(model(states).mean() - model(off).mean())
    assert gaps[1.0] > gaps[0.0] + 0.3, gaps


def test_value_rejects_unknown_penalty():
    with pytest.raises(ValueError, match="contrastive"):
        ValueEstimator(DS, penalty="huber")


def test_dynamics_learns_a_linear_system(tmp_path):
    arrays, _ = linear_system(3000, seed=3)
    data = make_data(3000, 0, **arrays)
    with training.seeded_init(0):
        model = DynamicsEnsemble(DS, DA, members=3, hidden=(64, 64))
    r = arrays["r"]
    model.set_reward_scale(float(r.mean()), float(r.std()))
    record = train(
        "dynamics",
        model,
        lambda b, g: model.loss(b["s"], b["a"], b["r"], b["s_next"], g),
        lambda b: model.heldout_losses(b["s"], b["a"], b["r"], b["s_next"]),
        data,
        tmp_path,
        steps=800,
        keep_best="member",
    )
    assert record.final_heldout_loss < record.initial_heldout_loss - 2.0  # NLL: a log-scale drop
    held = data.heldout()
    model.eval()
    next_mean, reward_mean = model.sample(held["s"], held["a"], use_mean=True)
    delta = held["s_next"] - held["s"]
    assert (next_mean - held["s_next"]).pow(2).mean() < 0.05 * delta.var()
    assert (reward_mean - held["r"]).pow(2).mean() < 0.05 * held["r"].var()
    one, r_one = model.sample(held["s"], held["a"], torch.Generator().manual_seed(0))
    two, r_two = model.sample(held["s"], held["a"], torch.Generator().manual_seed(0))
    assert torch.equal(one, two) and torch.equal(r_one, r_two)
    assert not torch.equal(one, next_mean)


def test_ensemble_members_differ_and_batched_forward_equals_each_member():
    with training.seeded_init(0):
        model = DynamicsEnsemble(DS, DA, members=4, hidden=(32, 32)).eval()
    s, a = torch.randn(16, DS), torch.rand(16, DA) * 2 - 1
    mean, log_std = model.stats(s, a)
    assert mean.shape == (4, 16, DS + 1)
    for member in range(4):
        m_mean, m_log_std = model.member_stats(member, s, a)
        torch.testing.assert_close(mean[member], m_mean)
        torch.testing.assert_close(log_std[member], m_log_std)
    assert not torch.allclose(mean[0], mean[1])
    first = model.hidden_layers[0].weight
    assert not torch.equal(first[0], first[1])


def test_each_member_trains_on_its_own_half_of_the_batch():
    with training.seeded_init(0):
        model = DynamicsEnsemble(DS, DA, members=4, hidden=(16,))
    s, a, r, s2 = torch.randn(512, DS), torch.rand(512, DA), torch.randn(512), torch.randn(512, DS)
    _, nll = model.loss(s, a, r, s2, torch.Generator().manual_seed(0))
    with torch.no_grad():
        losses = model.member_losses(s, a, r, s2)
    # the same generator state reproduces the halves the loss drew
    scores = torch.rand((4, 512), generator=torch.Generator().manual_seed(0))
    halves = scores.argsort(dim=1)[:, :256]
    expected = losses.gather(1, halves).mean()
    torch.testing.assert_close(nll.detach(), expected)
    assert not torch.isclose(expected, losses.mean())
    assert all(len(set(h.tolist())) == 256 for h in halves)  # 256 distinct rows each
    assert len(set(halves[0].tolist()) & set(halves[1].tolist())) < 200  # and not the same half


def test_spectral_norm_option_caps_each_members_largest_singular_value():
    from hipode_pipeline.models.dynamics import EnsembleLinear

    with training.seeded_init(0):
        layer = EnsembleLinear(3, 8, 6, spectral_norm=True)
    with torch.no_grad():
        layer.weight.mul_(torch.tensor([1.0, 5.0, 0.2])[:, None, None])
        for _ in range(20):  # training forwards refine the singular-vector estimates
            layer(torch.randn(3, 4, 8))
    layer.eval()
    norms = torch.linalg.matrix_norm(layer.effective_weight().detach(), ord=2)
    torch.testing.assert_close(norms, torch.ones(3), atol=1e-3, rtol=0)
    x = torch.randn(3, 4, 8)
    torch.testing.assert_close(layer(x)[1], layer.member_forward(1, x[1]))


def test_per_member_best_weights_are_kept_member_by_member():
    with training.seeded_init(0):
        model = DynamicsEnsemble(DS, DA, members=3, hidden=(8,))
    old = {k: v.clone() for k, v in model.state_dict().items()}
    best = training._BestWeights("member", torch.ones(3), {k: v.clone() for k, v in old.items()})
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)
    best.update(model, torch.tensor([0.5, 2.0, 0.5]))
    weight = best.state["hidden_layers.0.weight"]
    now = model.state_dict()["hidden_layers.0.weight"]
    assert torch.equal(weight[0], now[0]) and torch.equal(weight[2], now[2])
    assert torch.equal(weight[1], old["hidden_layers.0.weight"][1])
    assert torch.equal(best.loss, torch.tensor([0.5, 1.0, 0.5]))


def test_state_normalizer_round_trips_numpy_and_torch(tmp_path):
    states = np.random.default_rng(0).normal(3.0, 2.0, size=(500, 3)).astype(np.float32)
    states[:, 2] = 7.0  # a constant dimension stays finite thanks to eps
    norm = StateNormalizer.fit(states)
    assert norm.std[2] == pytest.approx(1e-3)
    z = norm.normalize(states)
    assert isinstance(z, np.ndarray) and np.allclose(z[:, :2].mean(0), 0, atol=1e-4)
    t = norm.normalize(torch.from_numpy(states))
    assert isinstance(t, torch.Tensor) and np.allclose(t.numpy(), z, atol=1e-5)
    np.testing.assert_allclose(norm.denormalize(z), states, rtol=1e-5, atol=1e-4)
    norm.save(tmp_path / "normalizer.json")
    loaded = StateNormalizer.load(tmp_path / "normalizer.json")
    assert np.array_equal(loaded.mean, norm.mean) and np.array_equal(loaded.std, norm.std)
    (tmp_path / "bad.json").write_text('{"mean": [0.0], "std": [0.0]}')
    with pytest.raises(DataFormatError, match="bad.json.*std"):
        StateNormalizer.load(tmp_path / "bad.json")


@pytest.mark.parametrize(
    ("capability", "native"), [((7, 5), False), ((8, 0), True), ((9, 0), True)]
)
def test_bf16_counts_as_native_on_a_gpu_only_from_ampere(monkeypatch, capability, native):
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda device=None: capability)
    assert fast_bf16(torch.device("cuda")) is native


def test_select_device():
    assert select_device("cpu").type == "cpu"
    assert select_device().type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(HipodeError, match="expected"):
        select_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(HipodeError, match="CUDA"):
            select_device("cuda")
