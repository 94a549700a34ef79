"""GPU layer: what only a CUDA device can run. Skipped without one (CI has none); run on a lent GPU machine with
``bash scripts/gpu_session.sh`` (docs/performance.md has the results).

Each fast path is compared with the plain one from the same seed on the same GPU, and each comparison is shown to
fail when the maths differs:

- ``cuda_graph=True``: the graph replays compute the eager gradient steps (same weights, same random draws), with
  SB3's MLP and with an overridden hook;
- the default of a long run (``cuda_graph=None``, auto): the update compiled as written inside CUDA graphs
  (``torch.compile``'s ``reduce-overhead``), for a stock model and for a hook set on the instance, against the eager
  hooks from the same state;
- the eager update (``compile_update=False``) on the GPU: a seeded ``learn()`` ends where SB3's ``TD3`` on the GPU
  ends;
- ``SeedBatch`` on the GPU (pi(s) of all seeds in one vmapped call, per-seed CUDA generators, each seed's own
  update), its seeds collecting in turn and in threads: each seed ends where its lone run ends.
"""

import numpy as np
import pytest
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import NormalActionNoise

from sb3_td3x import TD3X, SeedBatch

pytestmark = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device (run on a lent GPU machine)")

COLLECT = 300


class HuberTD3X(TD3X):
    """An overridden loss hook: the graphs must capture it as written."""

    def critic_loss(self, current_q, target_q):
        loss = sum(th.nn.functional.smooth_l1_loss(q, target_q) for q in current_q)
        return loss, {"critic_loss": loss.detach()}


def filled(cls=TD3X, **kwargs) -> TD3X:
    """A cuda_graph=True model on the GPU whose buffer holds COLLECT transitions (collection only)."""
    options = dict(learning_starts=COLLECT, buffer_size=COLLECT, batch_size=64, policy_delay=2, seed=0,
                   policy_kwargs={"net_arch": [64, 64]}, learning_rate=lambda progress: 1e-3 * progress,
                   device="cuda", cuda_graph=True) | kwargs
    model = cls("MlpPolicy", "Pendulum-v1", **options)
    model.learn(COLLECT)
    model.set_logger(configure(None, []))
    return model


def eager_twin(cls=TD3X, **kwargs) -> TD3X:
    """The same model whose gradient steps run eagerly: the hooks as written, with the graphs' sampling (on the
    device, from static bounds), capturable Adam and learning rates in device tensors."""
    model = filled(cls, **kwargs)
    model._step_fn = model.gradient_step  # a step set from outside is kept (no graphs)
    model.replay_buffer.refresh_static_bounds()  # the buffer is full: the bounds stay put
    return model


def train(model: TD3X, chunks=(7, 7, 6)) -> dict[str, float]:
    th.cuda.manual_seed(123)
    for n, steps in enumerate(chunks):
        model._current_progress_remaining = 1.0 - 0.25 * n  # the learning rate changes between calls
        model.train(gradient_steps=steps, batch_size=64)
    th.cuda.synchronize()
    return dict(model.logger.name_to_value)


def max_difference(a: TD3X, b: TD3X) -> float:
    return max((x - y).abs().max().item() for x, y in zip(a.policy.state_dict().values(), b.policy.state_dict().values()))


@pytest.mark.parametrize("cls", [TD3X, HuberTD3X], ids=["sb3_mlp", "overridden-critic_loss"])
def test_cuda_graph_replays_compute_the_eager_steps(cls):
    graphed, eager = filled(cls), eager_twin(cls)
    assert max_difference(graphed, eager) == 0.0  # same seed, same collection
    graphed_logged, eager_logged = train(graphed), train(eager)
    assert graphed.update_path == "cuda_graph"
    assert sorted(graphed._step_fn._graphs) == [(64, False), (64, True)]
    for (name, a), b in zip(eager.policy.state_dict().items(), graphed.policy.state_dict().values()):
        th.testing.assert_close(b, a, rtol=1e-5, atol=1e-6, msg=name)
    for optimizer in ("actor", "critic"):
        eager_state = getattr(eager, optimizer).optimizer.state_dict()["state"]
        graphed_state = getattr(graphed, optimizer).optimizer.state_dict()["state"]
        for key, fields in eager_state.items():
            for field, value in fields.items():
                th.testing.assert_close(graphed_state[key][field], value, rtol=1e-5, atol=1e-7)
    for key in ("train/critic_loss", "train/actor_loss", "train/learning_rate"):
        assert graphed_logged[key] == pytest.approx(eager_logged[key], rel=1e-5), key
    assert max_difference(graphed, filled(cls)) > 1e-3  # the steps did train


@pytest.mark.parametrize("broken", ["other_gamma", "other_random_draws"])
def test_the_cuda_graph_comparison_fails_when_the_steps_differ(broken):
    graphed = filled()
    eager = eager_twin(gamma=0.5) if broken == "other_gamma" else eager_twin()
    train(graphed)
    if broken == "other_random_draws":  # one more draw before the eager steps: other batches, other noise
        th.cuda.manual_seed(123)
        th.rand(1, device="cuda")
        eager.train(gradient_steps=20, batch_size=64)
    else:
        train(eager)
    assert max_difference(graphed, eager) > 1e-4


def test_cuda_graph_learn_save_load_and_go_on(tmp_path):
    model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=200, seed=1, device="cuda", cuda_graph=True,
                 policy_kwargs={"net_arch": [64, 64]}, train_freq=(2, "step"), gradient_steps=2)
    model.learn(1200)
    assert model.update_path == "cuda_graph" and model._n_updates == 1000
    assert all(th.isfinite(p).all() for p in model.policy.parameters())
    model.save(tmp_path / "graphed.zip")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded = TD3X.load(tmp_path / "graphed.zip", env=model.get_env(), device="cuda")
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    assert loaded.cuda_graph and loaded.replay_buffer.static_sampling
    loaded.learn(200, reset_num_timesteps=False)
    assert loaded.update_path == "cuda_graph" and loaded._n_updates == 1200
    assert all(th.isfinite(p).all() for p in loaded.policy.parameters())


@pytest.mark.parametrize("change", ["stock", "instance_hook"])
def test_the_default_of_a_long_run_compiles_the_hooks_inside_cuda_graphs(change, monkeypatch):
    monkeypatch.setattr(TD3X, "compile_auto_min_steps", 0)  # every run counts as long

    def make(**kwargs) -> TD3X:
        model = TD3X("MlpPolicy", "Pendulum-v1", learning_starts=COLLECT, batch_size=64, seed=2, device="cuda",
                     policy_kwargs={"net_arch": [32, 32]}, **kwargs)
        model.learn(COLLECT)  # collection only
        if change == "instance_hook":
            model.td_target = lambda rewards, dones, discounts, next_q, model=model: TD3X.td_target(
                model, rewards, 0.5 * dones, discounts, next_q)
        model.set_logger(configure(None, []))
        return model

    compiled, eager = make(), make(compile_update=False)
    assert not compiled.cuda_graph  # cuda_graph=True's own graphs are not set up: auto's are torch.compile's
    for model in (compiled, eager):
        np.random.seed(7)
        th.cuda.manual_seed(7)
        model.train(gradient_steps=20, batch_size=64)
    assert compiled.update_path == "compiled", compiled.update_reason
    assert compiled.update_reason.endswith("one graph in CUDA graphs (torch.compile's reduce-overhead)")
    assert eager.update_path == "eager"
    for (name, a), b in zip(eager.policy.state_dict().items(), compiled.policy.state_dict().values()):
        th.testing.assert_close(b, a, rtol=1e-4, atol=1e-5, msg=name)


def sb3_kwargs(**kwargs) -> dict:
    return dict(learning_starts=100, batch_size=32, policy_delay=2, seed=3, device="cuda",
                action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)),
                policy_kwargs=dict(net_arch=[32, 32], optimizer_kwargs=dict(foreach=False))) | kwargs


def test_seeded_learn_on_the_gpu_matches_sb3_td3_on_the_gpu():
    sb3 = TD3("MlpPolicy", "Pendulum-v1", **sb3_kwargs())
    # cuda_graph=False: the eager update, whose batches are drawn as SB3 draws them (the graphs draw on the device).
    td3x = TD3X("MlpPolicy", "Pendulum-v1", **sb3_kwargs(cuda_graph=False))
    broken = TD3X("MlpPolicy", "Pendulum-v1", **sb3_kwargs(tau=0.02, cuda_graph=False))  # the comparison can fail
    for model in (td3x, broken):
        model.policy.load_state_dict(sb3.policy.state_dict())
    for model in (sb3, td3x, broken):
        model.set_random_seed(11)
        model.learn(400)
    assert td3x.update_path == "eager" and sb3._n_updates == td3x._n_updates == 300
    for (name, expected), got in zip(sb3.policy.state_dict().items(), td3x.policy.state_dict().values()):
        th.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5, msg=name)
    assert max_difference(sb3, broken) > 1e-3


@pytest.mark.parametrize("collect_threads", [1, 3])
def test_seed_batch_on_the_gpu_computes_the_lone_runs(collect_threads):
    def make(seed, cls=TD3X):
        return cls("MlpPolicy", "Pendulum-v1", seed=seed, learning_starts=100, batch_size=64, device="cuda",
                   policy_kwargs={"net_arch": [32, 32]},
                   action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)))

    seeds = (0, 1, 2)
    lone = [make(seed).learn(400) for seed in seeds]
    batch = SeedBatch(make, seeds, collect_threads=collect_threads).learn(400)
    assert batch.collection.endswith("pi(s) batched across seeds")  # the GPU's default
    assert batch.collection.startswith("3 seeds in 3 threads" if collect_threads == 3 else "one seed after the other")
    for i, (model, alone) in enumerate(zip(batch, lone)):
        assert model._n_updates == alone._n_updates == 300
        for (name, a), b in zip(alone.policy.state_dict().items(), model.policy.state_dict().values()):
            th.testing.assert_close(b, a, rtol=1e-4, atol=1e-5, msg=lambda m, name=name, i=i: f"seed {i} {name}: {m}")
    assert max_difference(lone[0], lone[1]) > 1e-2  # the seeds differ: the comparison can fail


def test_seeds_on_a_gpu_run_in_processes_each_its_lone_run(tmp_path):
    """``python run.py seeds=[0,1] device=cuda``: one process per seed (the machine has the cores), sharing the GPU
    through CUDA MPS where the machine has it; each seed's evaluations are those of its lone ``seed=`` run on the GPU
    (to float rounding: a GPU's reductions need not repeat bit for bit)."""
    import csv
    import json
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    run = ["debug=smoke", "env=pendulum", "total_timesteps=600", "algo.learning_starts=150", "eval.freq=300",
           "algo.net_arch=[32,32]", "logger=none", "progress_bar=false", "device=cuda"]

    def run_py(*args: str) -> str:
        done = subprocess.run([sys.executable, "run.py", *run, *args], cwd=repo, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-3000:]
        return done.stdout + done.stderr

    output = run_py("seeds=[0,1]", "seed_processes=2", f"run_dir={tmp_path / 'batch'}")
    assert "in 2 processes" in output
    run_py("seed=1", f"run_dir={tmp_path / 'lone1'}")

    def returns(folder: Path) -> list[float]:
        with open(folder / "evaluations.csv") as file:
            return [float(row["mean_return"]) for row in csv.DictReader(file)]

    summary = json.loads((tmp_path / "batch" / "seed1" / "summary.json").read_text())
    assert summary["trained_together"] == [1] and summary["update_path"] == "eager"  # a short run
    np.testing.assert_allclose(returns(tmp_path / "batch" / "seed1"), returns(tmp_path / "lone1"), rtol=1e-3, atol=1e-2)
