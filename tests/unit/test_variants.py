"""The math of the variants (sb3_td3x.variants) against references written from the papers' and authors' code:

- LAP (TD3LAP): the loss, the priorities and the sampling of sfujim/TD7 (TD7.py, buffer.py), re-stated below on the
  same tensors;
- C51 (TD3C51): FastTD3's projection against a brute-force projection, one atom at a time (Bellemare et al. 2017,
  eq. 7), and its clipped double-Q choice and losses against FastTD3's train.py;
- the sum tree behind prioritised sampling, and the prioritised buffer's options, pickling and importance weights.
"""

from __future__ import annotations

import pickle

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import torch.nn.functional as F
from stable_baselines3.common.logger import configure

from sb3_td3x import TD3X
from sb3_td3x.common.buffers import TensorReplayBuffer, TensorReplayBufferSamples
from sb3_td3x.common.sum_tree import SumTree
from sb3_td3x.variants import TD3C51, TD3LAP, TD3LayerNorm, categorical_projection, lap_huber

OBS = gym.spaces.Box(-5, 5, (3,), dtype=np.float32)
ACT = gym.spaces.Box(-1, 1, (1,), dtype=np.float32)


def small(cls: type[TD3X], **kwargs) -> TD3X:
    kwargs = {"policy_kwargs": {"net_arch": [16]}, "learning_starts": 0, "seed": 0, **kwargs}
    model = cls("MlpPolicy", "Pendulum-v1", **kwargs)
    model.set_logger(configure(None, []))
    return model


def add_transitions(buffer: TensorReplayBuffer, n: int, rng: np.random.Generator) -> None:
    for _ in range(n):
        buffer.add(rng.normal(size=(1, 3)), rng.normal(size=(1, 3)), rng.uniform(-1, 1, (1, 1)), rng.normal(size=1),
                   np.array([False]), [{}])  # fmt: skip


# --- TD7's LAP, re-stated from sfujim/TD7 (commit c1c280d) ------------------------------------------------------------
def td7_lap_huber(x: th.Tensor, min_priority: float = 1) -> th.Tensor:
    """TD7.py, lines 60-61 (x: |TD errors|, shape (batch_size, n_critics))."""
    return th.where(x < min_priority, 0.5 * x.pow(2), min_priority * x).sum(1).mean()


class TD7Priorities:
    """The priorities of TD7's ``buffer.LAP`` (buffer.py, lines 34-35, 47-51, 55-58, 71-77)."""

    def __init__(self, max_size: int):
        self.max_size, self.ptr, self.size = max_size, 0, 0
        self.priority = th.zeros(max_size)
        self.max_priority = 1

    def add(self) -> None:
        self.priority[self.ptr] = self.max_priority
        self.ptr = (self.ptr + 1) % self.max_size
        self.size = min(self.size + 1, self.max_size)

    def sample(self, batch_size: int) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        csum = th.cumsum(self.priority[: self.size], 0)
        val = th.rand(size=(batch_size,)) * csum[-1]
        self.ind = th.searchsorted(csum, val)
        return self.ind, csum, val

    def update_priority(self, priority: th.Tensor) -> None:
        self.priority[self.ind] = priority.reshape(-1).detach()
        self.max_priority = max(float(priority.max()), self.max_priority)

    def reset_max_priority(self) -> None:
        self.max_priority = float(self.priority[: self.size].max())


def test_lap_loss_is_td7s_lap_huber():
    model = small(TD3LAP)
    g = th.Generator().manual_seed(0)
    current_q = th.randn(2, 256, 1, generator=g) * 2  # |TD errors| on both sides of min_priority = 1
    target_q = th.randn(256, 1, generator=g)
    loss, info = model.critic_loss(current_q, target_q)
    td_loss = (current_q.squeeze(2).T - target_q).abs()  # TD7.py, line 252: Q is (batch_size, 2)
    th.testing.assert_close(loss, td7_lap_huber(td_loss))
    th.testing.assert_close(lap_huber(td_loss.T.unsqueeze(2), 1.0), td7_lap_huber(td_loss))
    assert {"critic_loss", "target_q", "q1", "q2"} <= info.keys()
    assert not th.isclose(loss, (current_q - target_q).pow(2).mean(dim=(1, 2)).sum())  # not TD3's MSE


def test_lap_priorities_and_sampling_are_td7s():
    """Step by step on the same TD errors: the batches TD7's buffer draws from the same uniform numbers, the
    priorities it writes (max over critics, floor 1, exponent 0.4), the priority of new transitions, and its reset
    every 250 updates (TD7.py, line 290). The TD errors depend on the transition only, so that a transition drawn twice
    in a batch gets one priority under both rules (TD7 keeps the last write, TD3X the largest)."""
    model = small(TD3LAP, buffer_size=300, batch_size=32)
    buffer = model.replay_buffer
    assert buffer.prioritized and (buffer.alpha, buffer.min_priority, buffer.max_priority_reset_interval) == (0.4, 1.0, 250)
    reference = TD7Priorities(300)
    rng = np.random.default_rng(0)
    for _ in range(40):
        add_transitions(buffer, 1, rng)
        reference.add()
    mismatched = lowered = 0
    for step in range(1, 601):
        th.manual_seed(step)
        td7_indices, csum, val = reference.sample(32)
        th.manual_seed(step)
        batch = buffer.sample(32)
        assert isinstance(batch, TensorReplayBufferSamples) and batch.weights is None  # LAP: no importance weights
        differ = batch.indices != td7_indices
        # The tree's partial sums round unlike one cumulative sum: a draw on a boundary may take its neighbour.
        if differ.any():
            mismatched += int(differ.sum())
            nearest = (csum[batch.indices[differ].clamp(max=len(csum) - 1)] - val[differ]).abs()
            assert (nearest <= 1e-5 * csum[-1]).all(), f"step {step}: draws differ away from a boundary"
            reference.ind = batch.indices.clone()
        errors = th.rand(300, 2, generator=th.Generator().manual_seed(step)) * 4  # per transition, per critic
        current_q = errors[batch.indices].T.unsqueeze(2)  # (2, batch_size, 1), target 0: |TD error| = errors
        target_q = th.zeros(32, 1)
        model.update_priorities(batch, current_q, target_q)
        reference.update_priority(errors[td7_indices if not differ.any() else reference.ind].max(1)[0].clamp(min=1).pow(0.4))
        if step % 250 == 0:
            before = reference.max_priority
            reference.reset_max_priority()
            lowered += reference.max_priority < before
        if step % 7 == 0:  # new transitions, at the largest priority so far (until the buffer's 300 rows wrap)
            add_transitions(buffer, 1, rng)
            reference.add()
        n = reference.size
        th.testing.assert_close(buffer.priorities.leaves[:n], reference.priority[:n], rtol=0, atol=0, msg=f"step {step}")
        assert float(buffer.max_priority) == pytest.approx(reference.max_priority, rel=1e-7, abs=0), f"step {step}"
        th.testing.assert_close(buffer.priorities.total, buffer.priorities.leaves.sum().reshape(1))
    print(f"draws on a boundary: {mismatched}")
    assert mismatched <= 3
    assert lowered >= 1, "no reset lowered the priority of new transitions: the test would not see them"


@pytest.mark.parametrize("compile_update", [False, True], ids=["eager", "compiled"])
def test_lap_learns_through_the_hooks_with_priorities_written(compile_update, request):
    """The priorities are written by the update, eagerly and inside the compiled graph (sum tree included). Dynamo's
    graph is what holds the write (run by AOTAutograd's eager kernels, as the user-change catalogue runs its changes:
    an Inductor graph costs about 25 s of CPU to compile cold)."""
    if compile_update:
        request.getfixturevalue("dynamo_graphs_only")
    model = small(TD3LAP, learning_starts=50, batch_size=32, compile_update=compile_update)
    model.learn(150)
    assert model.update_path == ("compiled" if compile_update else "eager"), model.update_reason
    leaves = model.replay_buffer.priorities.leaves[:150]
    assert (leaves >= 1.0).all() and (leaves > 1.0).any()  # floor 1 ** 0.4, and TD errors above it written


# --- FastTD3's C51 -----------------------------------------------------------------------------------------------------
def brute_force_projection(probs, rewards, discounts, v_min, v_max) -> th.Tensor:
    """C51's projection one atom at a time (Bellemare et al. 2017, eq. 7): atom j's mass goes to atom i in proportion
    to [1 - |clip(r + discount z_j) - z_i| / dz] clipped to [0, 1]."""
    n_atoms = probs.shape[-1]
    z = [v_min + i * (v_max - v_min) / (n_atoms - 1) for i in range(n_atoms)]
    dz = (v_max - v_min) / (n_atoms - 1)
    out = th.zeros_like(probs, dtype=th.float64)
    for b in range(probs.shape[0]):
        for j in range(n_atoms):
            tz = min(max(float(rewards[b]) + float(discounts[b]) * z[j], v_min), v_max)
            for i in range(n_atoms):
                out[b, i] += float(probs[b, j]) * min(max(1 - abs(tz - z[i]) / dz, 0.0), 1.0)
    return out.float()


def test_the_c51_projection_is_the_brute_force_one():
    g = th.Generator().manual_seed(0)
    probs = F.softmax(th.randn(10, 51, generator=g) * 2, dim=-1)
    # transitions: ordinary, done (all the mass on r), beyond both ends (clipped), and on the atoms exactly (r = 0,
    # discount 1: FastTD3's fix for an atom landing on the support, at v_min too)
    rewards = th.tensor([[0.7], [-3.1], [2.5], [40.0], [-40.0], [0.0], [0.0], [1.0], [-10.0], [0.3]])
    discounts = th.tensor([[0.99], [0.9], [0.0], [0.99], [0.99], [1.0], [0.5], [1.0], [1.0], [0.97]])
    got = categorical_projection(probs, rewards, discounts, -10.0, 10.0)
    expected = brute_force_projection(probs, rewards, discounts, -10.0, 10.0)
    th.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    th.testing.assert_close(got.sum(-1), th.ones(10))
    # stacked critics (n_critics, batch_size, n_atoms): each projected alike
    both = categorical_projection(th.stack([probs, probs.flip(-1)]), rewards, discounts, -10.0, 10.0)
    th.testing.assert_close(both[0], got)
    flipped = brute_force_projection(probs.flip(-1), rewards, discounts, -10.0, 10.0)
    th.testing.assert_close(both[1], flipped, rtol=1e-5, atol=1e-6)


def test_c51_target_losses_and_estimates_are_fasttd3s():
    model = small(TD3C51, v_min=-20.0, v_max=20.0)
    assert model.critic.q_networks[0][-1].out_features == 101 and len(model.support) == 101
    g = th.Generator().manual_seed(1)
    obs, actions = th.randn(64, 3, generator=g), th.rand(64, 1, generator=g) * 2 - 1
    rewards, dones = th.randn(64, 1, generator=g), (th.rand(64, 1, generator=g) < 0.2).float()
    next_q = model.next_q_values(obs, actions)  # (2, 64, 101) probabilities
    th.testing.assert_close(next_q.sum(-1), th.ones(2, 64))
    target = model.td_target(rewards, dones, 0.99, model.clipped_double_q_value(next_q))
    # FastTD3's train.py, lines 438-456: project both, keep per transition the one of lower mean (ties: the second)
    projected = [categorical_projection(next_q[i], rewards, (1 - dones) * 0.99, -20.0, 20.0) for i in range(2)]
    values = [(p * model.support).sum(-1, keepdim=True) for p in projected]
    th.testing.assert_close(target, th.where(values[0] < values[1], projected[0], projected[1]))
    assert (values[0] < values[1]).any() and (values[0] > values[1]).any()
    # train.py, lines 463-470: the cross-entropies, summed over critics
    logits = model.critic.q_values(obs, actions)
    loss, _ = model.critic_loss(logits, target)
    expected = sum(-th.sum(target * F.log_softmax(logits[i], dim=1), dim=1).mean() for i in range(2))
    th.testing.assert_close(loss, expected)
    # train.py, lines 502-509: the actor maximises the smaller expected value
    loss, _ = model.actor_loss(obs)
    q = model.critic.q_values(obs, model.actor(obs))
    expected = -th.minimum(*((F.softmax(q[i], dim=1) * model.support).sum(1) for i in range(2))).mean()
    th.testing.assert_close(loss, expected)
    # the critics' estimates are the expectations (n_critics, batch_size, 1), what the value-bias measure reads
    batch = TensorReplayBufferSamples(obs, actions, obs, dones, rewards)
    estimates = model.q_value_estimates(batch)
    assert estimates.shape == (2, 64, 1)
    th.testing.assert_close(estimates[0, :, 0], (F.softmax(logits[0], dim=1) * model.support).sum(1))


def test_c51_checks_its_support():
    with pytest.raises(ValueError, match="v_min < v_max"):
        small(TD3C51, v_min=1.0, v_max=-1.0)


# --- networks built by the hooks ---------------------------------------------------------------------------------------
def test_layernorm_critics_are_built_by_the_q_network_hook():
    model = small(TD3LayerNorm)
    for critic in (model.critic, model.critic_target):
        for q_net in critic.q_networks:
            assert [type(m).__name__ for m in q_net] == ["Linear", "LayerNorm", "ReLU", "Linear"]
    assert [type(m).__name__ for m in model.actor.mu] == ["Linear", "ReLU", "Linear", "Tanh"]  # the actor is TD3's
    params = {id(p) for p in model.critic.optimizer.param_groups[0]["params"]}
    assert all(id(p) in params for q in model.critic.q_networks for p in q.parameters())  # trained by the optimizer
    th.testing.assert_close(model.critic.qf0[1].weight, model.critic_target.qf0[1].weight)  # targets start as copies


def test_stock_networks_draw_sb3s_initial_weights():
    """No hook overridden: SB3's actor and critics build their networks themselves (the same weights from a seed)."""
    from stable_baselines3 import TD3

    sb3 = TD3("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [16]}, seed=0)
    ours = small(TD3X)
    for (name, expected), got in zip(sb3.policy.state_dict().items(), ours.policy.state_dict().values()):
        th.testing.assert_close(got, expected, rtol=0, atol=0, msg=name)


# --- the sum tree ------------------------------------------------------------------------------------------------------
# backend: find and set through torch.compile (a compiled update's, outside its graph), with AOTAutograd's eager kernels:
# the same sums to the bit, so any difference is the compiled form's (set writes repeated leaves another way there).
BACKENDS = pytest.mark.parametrize("backend", [None, "aot_eager"], ids=["eager", "compiled"])


@BACKENDS
@pytest.mark.parametrize("size", [5, 32, 1000, 40_000])
def test_the_sum_tree_finds_what_searchsorted_finds(size, backend):
    g = th.Generator().manual_seed(size)
    leaves = th.randint(0, 5, (size,), generator=g).float()  # integers: every sum exact, ties and zeros included
    tree = SumTree(size, with_maxima=True)
    tree.backend = backend
    tree.set(th.arange(size), leaves)
    th.testing.assert_close(tree.total, leaves.sum().reshape(1), rtol=0, atol=0)
    assert float(tree.max) == float(leaves.max())
    mass = th.rand(20_000, generator=g) * tree.total
    mass[:3] = th.tensor([0.0, float(leaves[0]), float(tree.total) - 1e-3])  # the edges
    found = tree.find(mass)
    expected = th.searchsorted(leaves.cumsum(0), mass)
    zero_mass = mass == 0  # searchsorted may stop on a leaf of 0 there; the tree goes on to the first leaf above 0
    assert th.equal(found[~zero_mass], expected[~zero_mass])
    assert (leaves[found] > 0).all()


@BACKENDS
def test_the_sum_tree_keeps_the_larger_value_of_a_repeated_index_and_sums_from_children(backend):
    tree = SumTree(100, with_maxima=True)
    tree.backend = backend
    tree.set(th.tensor([3, 7, 3, 3]), th.tensor([2.0, 5.0, 9.0, 4.0]))
    assert float(tree.leaves[3]) == 9.0 and float(tree.total) == 14.0 and float(tree.max) == 9.0
    tree.set(th.tensor([3]), th.tensor([1.0]))  # lowered: the maximum and the sums follow
    assert float(tree.total) == 6.0 and float(tree.max) == 5.0
    clone = pickle.loads(pickle.dumps(tree))
    assert all(th.equal(a, b) for a, b in zip(clone.sums, tree.sums))
    assert clone.maxima[0] is clone.sums[0]  # the leaves stay shared
    assert clone.backend == backend  # a resumed run's tree runs as the run's did


# --- the prioritised buffer ------------------------------------------------------------------------------------------
def test_prioritised_buffer_options_are_checked():
    for kwargs, match in [
        ({"alpha": -1.0}, "alpha"),
        ({"alpha": 0.6, "beta": -0.1}, "beta"),
        ({"alpha": 0.6, "min_priority": 0.0}, "min_priority"),
        ({"alpha": 0.6, "max_priority_reset_interval": -1}, "max_priority_reset_interval"),
        ({"alpha": 0.6, "optimize_memory_usage": True, "handle_timeout_termination": False}, "optimize_memory_usage"),
        ({"n_steps": 0}, "n_steps"),
        ({"beta": 0.4}, "pass alpha"),  # an option of prioritised sampling, without it
        ({"n_steps": 3, "optimize_memory_usage": True, "handle_timeout_termination": False}, "optimize_memory_usage"),
    ]:
        with pytest.raises(ValueError, match=match):
            TensorReplayBuffer(50, OBS, ACT, **kwargs)
    with pytest.raises(ValueError, match="samples uniformly"):
        TensorReplayBuffer(50, OBS, ACT).update_priorities(th.tensor([0]), th.tensor([1.0]))
    with pytest.raises(ValueError, match="prioritised sampling is an option of TD3X's TensorReplayBuffer"):
        small(TD3X, replay_buffer_class=__import__("stable_baselines3").common.buffers.ReplayBuffer,
              replay_buffer_kwargs={"alpha": 0.6})  # fmt: skip


def test_prioritised_sampling_follows_the_priorities_and_gives_importance_weights():
    buffer = TensorReplayBuffer(64, OBS, ACT, n_envs=2, alpha=0.5, beta=0.4)
    rng = np.random.default_rng(0)
    for _ in range(10):
        buffer.add(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), rng.uniform(-1, 1, (2, 1)), rng.normal(size=2),
                   np.array([False, False]), [{}, {}])  # fmt: skip
    rows = th.arange(20)
    buffer.update_priorities(rows, (rows + 1).float().pow(2))  # mass (i + 1) ** 2 ** 0.5 = i + 1
    th.manual_seed(0)
    batch = buffer.sample(200_000)
    frequencies = th.bincount(batch.indices, minlength=20).float() / 200_000
    th.testing.assert_close(frequencies, (rows + 1).float() / 210, rtol=0.05, atol=2e-3)
    th.testing.assert_close(batch.observations, buffer.observations[batch.indices // 2, batch.indices % 2])
    # (N P(i)) ** -beta over the batch's largest: (p_i / min p) ** -beta
    mass = (batch.indices + 1).float()
    th.testing.assert_close(batch.weights.squeeze(1), (mass / mass.min()).pow(-0.4))
    assert float(batch.weights.max()) == 1.0


def test_priorities_are_pickled_with_the_buffer_and_follow_its_device(tmp_path):
    model = small(TD3LAP, learning_starts=20, batch_size=16)
    model.learn(60)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    other = small(TD3LAP)
    other.load_replay_buffer(tmp_path / "buffer.pkl")
    before, after = model.replay_buffer, other.replay_buffer
    assert after.random_streams is other.random_streams  # draws from the loading model's streams
    for tree in ("sums", "maxima"):
        assert all(th.equal(a, b) for a, b in zip(getattr(after.priorities, tree), getattr(before.priorities, tree)))
    assert th.equal(after.max_priority, before.max_priority) and th.equal(after.priority_updates, before.priority_updates)
    th.manual_seed(3)
    drawn = after.sample(32).indices
    th.manual_seed(3)
    assert th.equal(drawn, before.sample(32).indices)
    after.device = "cpu"
    assert after.sample(4).indices.device.type == "cpu"


def test_importance_weights_reach_the_critic_loss_and_a_two_argument_loss_is_refused():
    seen = []

    class Watching(TD3X):
        def critic_loss(self, current_q, target_q, weights=None):
            seen.append(weights)
            return super().critic_loss(current_q, target_q, weights)

    model = small(Watching, learning_starts=30, batch_size=16, replay_buffer_kwargs={"alpha": 0.6, "beta": 0.4})
    model.learn(40)
    assert len(seen) == 10 and all(w is not None and w.shape == (16, 1) for w in seen)
    current_q, target_q = th.randn(2, 16, 1), th.randn(16, 1)
    weights = th.rand(16, 1)
    loss, _ = TD3X.critic_loss(model, current_q, target_q, weights)
    th.testing.assert_close(loss, ((current_q - target_q).pow(2) * weights).mean(dim=(1, 2)).sum())
    unweighted = (current_q - target_q).pow(2).mean(dim=(1, 2)).sum()
    th.testing.assert_close(TD3X.critic_loss(model, current_q, target_q)[0], unweighted)

    class TwoArguments(TD3X):  # the README's Huber loss: it cannot weigh the transitions
        def critic_loss(self, current_q, target_q):
            return super().critic_loss(current_q, target_q)

    with pytest.raises(ValueError, match="takes no `weights`: add a `weights=None` argument"):
        small(TwoArguments, replay_buffer_kwargs={"alpha": 0.6, "beta": 0.4}).learn(10)
    small(TwoArguments, learning_starts=5, batch_size=4, replay_buffer_kwargs={"alpha": 0.6}).learn(10)  # beta 0: fine
