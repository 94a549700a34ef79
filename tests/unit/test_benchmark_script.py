"""benchmarks/throughput.py: its in-sequence floors replay what training ran and put the model back; bad arguments
get a message, not a traceback."""

import importlib.util
from pathlib import Path

import pytest
import torch as th

from sb3_td3x import TD3X

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "throughput.py"


@pytest.fixture(scope="module")
def throughput():
    spec = importlib.util.spec_from_file_location("throughput", _PATH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _model(throughput, **kwargs) -> TD3X:
    model = throughput.make_model(
        TD3X, "Pendulum-v1", 0, {"buffer_size": 2_000, "policy_kwargs": {"net_arch": [32, 32]}, **kwargs},
        run_length=1_100,  # a short run's defaults: the eager update, which the replay is for
    )
    model.learn(1_100)  # past the benchmark's learning_starts (1000): the optimizers' states exist
    return model


@pytest.mark.parametrize("flush_denormals", [True, False])
def test_replay_of_all_operators_recomputes_the_recorded_update(throughput, flush_denormals):
    """Replaying every recorded operator, from the state and random numbers the recording started from, gives the
    weights and optimizer states training gave: the chained replay runs the same computation, not just the same
    kernels on stale operands."""
    model = _model(throughput, flush_denormals=flush_denormals)
    state = throughput.state_tensors(model)
    before = [t.clone() for t in state]
    rng = th.get_rng_state()
    replay = throughput.InSequenceReplay(model, "Pendulum-v1", 0)  # records policy_delay real gradient steps
    assert [t.data_ptr() for t in replay.state] == [t.data_ptr() for t in state]
    trained = [t.clone() for t in state]
    assert any(not th.equal(a, b) for a, b in zip(before, trained))
    with th.no_grad():
        for tensor, value in zip(state, before):
            tensor.copy_(value)
        # Poison what the recording computed (not what it read: weights, optimizer states, the buffer), so that a
        # replay reading a recorded intermediate instead of its own output cannot give the trained state.
        outputs = {id(t): t for *_, out in replay.recorded for t in throughput._tensors_out(out)}
        external = {
            leaf.untyped_storage().data_ptr()
            for _, args, _, _ in replay.recorded
            for arg in args
            for leaf in (arg if isinstance(arg, (list, tuple)) else [arg])
            if isinstance(leaf, th.Tensor) and id(leaf) not in outputs
        }
        poisoned = 0
        for tensor in outputs.values():
            if tensor.is_floating_point() and tensor.untyped_storage().data_ptr() not in external:
                tensor.fill_(float("nan"))
                poisoned += 1
        assert poisoned > 20
    th.set_rng_state(rng)
    with replay.flush(replay.flush_on):
        replay.replay("kernels")
    mismatched = [i for i, (a, b) in enumerate(zip(state, trained)) if not th.equal(a, b)]
    assert not mismatched, f"{len(mismatched)} of {len(state)} tensors differ from the recorded update"
    # The outputs are passed on: most operators read an earlier operator's output, not the recorded one.
    plan = replay.plans["kernels"]
    assert sum(1 for *_, links, _dead in plan if links) > len(plan) // 2


def test_timing_puts_the_model_back_and_training_goes_on(throughput):
    model = _model(throughput)
    replay = throughput.InSequenceReplay(model, "Pendulum-v1", 0)
    state = [t.clone() for t in replay.state]
    for which in ("kernels", "products"):
        assert replay.time(which, rounds=3) > 0.0
    rows = replay.breakdown(rounds=3)
    assert all(th.equal(a, b) for a, b in zip(state, replay.state))
    assert rows["_fused_adam_"]["calls_per_step"] == 1.5  # the critics' every step, the actor's every other step
    assert {name for name, row in rows.items() if row["product"]} >= {"addmm", "mm"}  # the eager hooks: nn.Linear
    assert all(row["ms_per_step"] > 0.0 for row in rows.values())
    products = replay.plans["products"]
    assert products and all(call[0] in throughput.PRODUCT_OPS for call in products)
    model.learn(50, reset_num_timesteps=False)
    assert all(th.isfinite(p).all() for p in model.policy.parameters())


def test_compiled_updates_are_not_replayed(throughput):
    assert throughput.InSequenceReplay.applies(_model(throughput))
    assert not throughput.InSequenceReplay.applies(TD3X("MlpPolicy", "Pendulum-v1", compile_update=True))
    auto = _model(throughput)
    auto.update_compiled = True  # compile_update=None (auto) compiled it at the warm-up (a long run's default)
    assert not throughput.InSequenceReplay.applies(auto)


def test_a_benchmark_model_has_the_defaults_of_the_run_it_stands_for(throughput):
    """compile_update=None decides from the run's length: the benchmark's TD3X decides as in a run of --run-length
    steps, so a 1M-step run's default (compiled on a CPU) is what it measures."""
    long = throughput.as_part_of_a_run(TD3X("MlpPolicy", "Pendulum-v1", learning_starts=1000), 1_000_000)
    short = throughput.as_part_of_a_run(TD3X("MlpPolicy", "Pendulum-v1", learning_starts=1000), 50_000)
    assert long.compile_auto_min_steps == 0 and short.compile_auto_min_steps > 10**9


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--td3x", "bf16"], "KEY=VALUE pairs"),
        (["--td3x", "bf17=true"], "TD3X has no argument bf17"),
        (["--td3x", "seed=3"], "seed is the benchmark's"),
        (["--env", "Ant-v0"], "no gymnasium environment 'Ant-v0'"),
        (["--chunks", "0"], "--chunks must be at least 1"),
        (["--warmup", "500"], "--warmup must be past learning_starts=1000"),
    ],
)
def test_bad_arguments_get_a_message_not_a_traceback(throughput, monkeypatch, capsys, argv, message):
    monkeypatch.setattr("sys.argv", ["throughput.py", *argv])
    with pytest.raises(SystemExit) as exit_info:
        throughput.main()
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_sbx_runs_with_the_same_hyperparameters_as_sb3_and_td3x(throughput):
    """SBX's TD3 (an optional peer) is built with SB3's values, not SBX's own defaults (lr 3e-4, 256-256)."""
    peer = throughput.sbx_td3(threads=2)
    if peer is None:
        pytest.skip('sbx-rl is not installed (pip install -e ".[peers]")')
    extra = {"buffer_size": 2_000, "batch_size": 100}
    sb3 = throughput.make_model(throughput.TD3, "Pendulum-v1", 0, extra)
    sbx = throughput.make_model(peer, "Pendulum-v1", 0, extra)
    for name in ("learning_rate", "batch_size", "learning_starts", "tau", "gamma", "policy_delay", "target_policy_noise",
                 "target_noise_clip", "buffer_size", "train_freq", "gradient_steps"):
        assert getattr(sbx, name) == getattr(sb3, name), name
    assert sbx.policy_kwargs["net_arch"] == sb3.policy.net_arch == [400, 300]
    assert (sbx.action_noise._sigma == sb3.action_noise._sigma).all()
