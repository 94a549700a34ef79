"""How the update runs: one function picks it, says why, and the layout has no import circle."""

import ast
import functools
import importlib
import warnings
from pathlib import Path

import gymnasium as gym
import pytest
import torch as th
from conftest import eager_capture
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import HumanOutputFormat, Logger, configure
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_td3x.experiment.configs.compose import check_config, compose_config, whole_float_problems
from sb3_td3x.experiment.errors import ConfigError
from sb3_td3x.td3x import TD3X, TD3XCritic, TD3XPolicy, UnsupportedActionSpace
from sb3_td3x.td3x.hooks import HOOK_NAMES, HOOKS, changed_hooks, reference_class
from sb3_td3x.td3x.update_paths import choose
from sb3_td3x.td3x.update_paths.choose import AUTO_GRAPHS, choose_update
from sb3_td3x.td3x.update_paths.cuda_graph import GraphedGradientStep, why_not_cuda_graph

PACKAGE = Path(__file__).resolve().parents[2] / "sb3_td3x" / "td3x"


class ScaledCritic(TD3XCritic):
    def forward(self, obs, actions):
        return tuple(2.0 * q for q in super().forward(obs, actions))


class ScaledCriticPolicy(TD3XPolicy):
    def make_critic(self, features_extractor=None):
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return ScaledCritic(**critic_kwargs).to(self.device)


def small(policy="MlpPolicy", **kwargs) -> TD3X:
    kwargs = {"policy_kwargs": {"net_arch": [16]}, "learning_starts": 10, "seed": 0, **kwargs}
    return TD3X(policy, "Pendulum-v1", **kwargs)


def first_update_line(model: TD3X, tmp_path: Path) -> str:
    log_file = tmp_path / "log.txt"
    model.set_logger(Logger(folder=str(tmp_path), output_formats=[HumanOutputFormat(str(log_file))]))
    model.learn(20)
    lines = [line for line in log_file.read_text().splitlines() if line.startswith("update: ")]
    assert len(lines) == 1, lines
    return lines[0]


def test_the_stock_model_logs_the_mlp_update(tmp_path):
    model = small()
    line = first_update_line(model, tmp_path)
    assert line.startswith("update: mlp (MlpUpdate: ") and "exploration: direct_mlp" in line
    assert (model.update_path, model.exploration_path) == ("mlp", "direct_mlp")


def test_a_subclassed_critic_forward_is_named_in_the_update_line(tmp_path):
    model = small(ScaledCriticPolicy)
    line = first_update_line(model, tmp_path)
    assert line.startswith(
        "update: autograd (the critic is a ScaledCritic, not SB3's TD3XCritic (critic.forward overridden by ScaledCritic)"
    )
    assert model.update_path == "autograd" and "critic.forward overridden by ScaledCritic" in model.update_reason
    assert "exploration: direct_mlp" in line  # the actor is SB3's: collection keeps its shortcut


def test_a_hook_set_on_the_instance_is_named(tmp_path):
    model = small()
    model.td_target = lambda rewards, dones, discounts, next_q: rewards
    line = first_update_line(model, tmp_path)
    assert line.startswith("update: autograd (td_target set on the instance")


def test_a_hook_set_after_the_first_train_is_honoured(tmp_path):
    model = small()
    model.learn(20)
    assert model.update_path == "mlp"
    calls = []

    def td_target(rewards, dones, discounts, next_q):
        calls.append(1)
        return rewards

    model.td_target = td_target
    model.learn(10, reset_num_timesteps=False)
    assert model.update_path == "autograd" and "td_target set on the instance" in model.update_reason and calls
    del model.td_target  # back to the stock hook: the fast path again
    model.learn(10, reset_num_timesteps=False)
    assert model.update_path == "mlp"


def test_mlp_update_false_is_the_reason():
    model = small(mlp_update=False)
    choice = choose_update(model)
    assert (choice.path, choice.reason) == ("autograd", "mlp_update=False")


def test_every_reason_is_listed_not_only_the_first():
    model = small(policy_kwargs={"net_arch": [16], "activation_fn": th.nn.Tanh})
    model.critic_loss = lambda current_q, target_q: (current_q.sum(), {})
    reason = choose_update(model).reason
    assert "critic_loss set on the instance" in reason and "not a ReLU MLP" in reason


def test_changed_hooks_and_the_reference_class():
    class Sub(TD3X):
        def td_target(self, rewards, dones, discounts, next_q):
            return super().td_target(rewards, dones, discounts, next_q)

    model = Sub("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [8]})
    assert reference_class(model) is TD3X
    # An override that only calls super() is still a change: what it adds cannot be known.
    assert changed_hooks(model) == ["td_target overridden by Sub"]
    assert changed_hooks(small()) == []


def test_the_hook_list_is_the_td3x_methods_and_the_docstring_table():
    assert TD3X.hook_names == HOOK_NAMES == tuple(h.name for h in HOOKS)
    assert len(set(HOOK_NAMES)) == len(HOOK_NAMES)
    for hook in HOOKS:
        assert callable(getattr(TD3X, hook.name)), hook.name
        assert f":meth:`{hook.name}`" in TD3X.__doc__, f"{hook.name} is missing from the TD3X docstring table"


def test_every_fast_path_declares_what_it_replaces_among_the_hooks():
    from sb3_td3x.td3x.update_paths.compiled import FunctionalCompiledUpdate
    from sb3_td3x.td3x.update_paths.exploration import DirectMlpActor
    from sb3_td3x.td3x.update_paths.mlp import MlpUpdate

    for path in (MlpUpdate, FunctionalCompiledUpdate, DirectMlpActor):
        assert set(path.replaces) <= set(HOOK_NAMES), path
    # MlpUpdate writes out every hook of steps 5 to 13; the ones it calls are the model's own.
    assert set(HOOK_NAMES) - set(MlpUpdate.replaces) == {
        "sample_batch", "should_update_actor", "update_actor_target", "update_critic_target"}


def _module_imports(path: Path) -> set[str]:
    """The sb3_td3x modules ``path`` imports at run time (not under ``if TYPE_CHECKING``)."""
    tree = ast.parse(path.read_text())
    found = set()
    for node in tree.body:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            continue
        for sub in ast.walk(node):
            if isinstance(sub, ast.ImportFrom) and sub.module and sub.module.startswith("sb3_td3x"):
                found.add(sub.module)
                found.update(f"{sub.module}.{alias.name}" for alias in sub.names)
            elif isinstance(sub, ast.Import):
                found.update(alias.name for alias in sub.names if alias.name.startswith("sb3_td3x"))
    return found


def test_no_import_circle_in_the_algorithm_package():
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        name = ".".join(path.relative_to(PACKAGE.parents[1]).with_suffix("").parts).removesuffix(".__init__")
        modules[name] = path
    graph = {name: {m for m in _module_imports(path) if m in modules and m != name} for name, path in modules.items()}
    for name in modules:
        if name.startswith("sb3_td3x.td3x.update_paths") or name == "sb3_td3x.td3x.hooks":
            assert "sb3_td3x.td3x.td3x" not in graph[name], f"{name} imports TD3X: the paths must not"
    visiting, done = set(), set()

    def visit(name, trail):
        assert name not in visiting, f"import circle: {' -> '.join(trail + [name])}"
        if name in done:
            return
        visiting.add(name)
        for dep in graph[name]:
            visit(dep, trail + [name])
        visiting.discard(name)
        done.add(name)

    for name in graph:
        visit(name, [])


# cuda_graph=None (auto): CUDA graphs only for a stock, capturable update ------------------------------------------
class TargetOverride(TD3X):
    def update_critic_target(self):
        super().update_critic_target()


class SampleOverride(TD3X):
    def sample_batch(self, batch_size):
        return super().sample_batch(batch_size)


class DictObservation(gym.ObservationWrapper):
    def __init__(self, env):
        super().__init__(env)
        self.observation_space = gym.spaces.Dict({"state": env.observation_space})

    def observation(self, observation):
        return {"state": observation}


def pendulum_vec_normalize() -> VecNormalize:
    return VecNormalize(DummyVecEnv([lambda: gym.make("Pendulum-v1")]))


def with_hook(model: TD3X) -> TD3X:
    """``td_target`` set on the instance, computing the stock target: a change auto must not freeze in a graph."""
    model.td_target = lambda rewards, dones, discounts, next_q: TD3X.td_target(model, rewards, dones, discounts, next_q)
    return model


def with_wrapped_critic(model: TD3X) -> TD3X:
    model.critic.forward = lambda obs, actions, forward=model.critic.forward: forward(obs, actions)
    return model


def with_vec_normalize(model: TD3X) -> TD3X:
    model.set_env(pendulum_vec_normalize())
    return model


def small_then(change):
    """A builder of ``small()`` with ``change(model)`` made after construction."""
    def build():
        model = small()
        change(model)
        return model

    return build


@pytest.mark.parametrize(
    ("build", "reason"),
    [
        (small, None),
        (lambda: small(policy_kwargs={"net_arch": [16], "optimizer_class": th.optim.AdamW}), None),
        (lambda: small(compile_update=True), "compile_update=True"),
        (lambda: small(bf16=True), "bf16=True"),
        (lambda: small(mlp_update=False), "mlp_update=False"),
        (lambda: small(n_steps=3), "the replay buffer is a NStepReplayBuffer, not TD3X's TensorReplayBuffer"),
        (lambda: small(replay_buffer_class=ReplayBuffer), "the replay buffer is a ReplayBuffer, not"),
        (lambda: TD3X("MultiInputPolicy", DictObservation(gym.make("Pendulum-v1")), policy_kwargs={"net_arch": [16]}),
         "the replay buffer is a DictReplayBuffer, not"),
        (lambda: TD3X("MlpPolicy", pendulum_vec_normalize(), policy_kwargs={"net_arch": [16]}),
         "VecNormalize normalises the samples on the host"),
        (lambda: small(policy_kwargs={"net_arch": [16], "optimizer_class": th.optim.SGD}),
         "the actor's optimizer is SGD, not torch's Adam or AdamW"),
        (small_then(lambda m: m.critic.optimizer.register_step_post_hook(lambda *args: None)),
         "step hooks on the critic's optimizer"),
        (lambda: TargetOverride("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [16]}),
         "update_critic_target overridden by TargetOverride"),
        (lambda: SampleOverride("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [16]}),
         "sample_batch overridden by SampleOverride"),
        (small_then(with_hook), "td_target set on the instance"),
        (small_then(with_wrapped_critic), "critic.forward set on the instance"),
        (lambda: small(ScaledCriticPolicy), "critic.forward overridden by ScaledCritic"),
        (lambda: small(policy_kwargs={"net_arch": [16], "activation_fn": th.nn.Tanh}), "not a ReLU MLP"),
        (small_then(lambda m: m.critic.q_networks[0].register_forward_hook(lambda *args: None)),
         "a forward hook on policy.critic.qf0"),
        (small_then(lambda m: m.actor.mu[0].weight.register_hook(lambda grad: grad)), "a gradient hook on actor.mu.0.weight"),
    ],
    ids=["stock", "adamw", "compile_update", "bf16", "mlp_update_false", "n_steps", "sb3_buffer", "dict_obs",
         "vec_normalize", "sgd", "optimizer_hook", "subclass_hook", "sample_batch", "instance_hook", "wrapped_critic",
         "subclassed_critic", "tanh", "module_hook", "gradient_hook"],
)
def test_auto_takes_cuda_graphs_only_for_a_stock_capturable_update(build, reason):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # bf16 on a CPU without bf16 instructions warns (test_acceleration.py)
        model = build()
    assert why_not_cuda_graph(model) == "no CUDA device"  # this machine's
    got = why_not_cuda_graph(model, device="cuda")
    if reason is None:
        assert got is None
    else:
        assert got is not None and reason in got


def test_cuda_graph_is_none_true_or_false():
    with pytest.raises(ValueError, match=r"invalid cuda_graph='auto'; cuda_graph must be None \(auto"):
        small(cuda_graph="auto")


def test_on_a_cpu_auto_is_the_eager_update_of_before(tmp_path):
    model = small()
    assert (model.cuda_graph_request, model.cuda_graph) == (None, False)
    assert model.cuda_graph_reason == "cuda_graph=None (auto): no CUDA device"
    assert not model.replay_buffer.static_sampling
    for group in (*model.actor.optimizer.param_groups, *model.critic.optimizer.param_groups):
        assert group["capturable"] is False and isinstance(group["lr"], float)
    assert first_update_line(model, tmp_path).startswith("update: mlp (MlpUpdate: ")


def pretend_cuda(monkeypatch) -> None:
    """Auto decides as on a CUDA device, and the graphs are captured by the CPU stand-in (``eager_capture``): all but
    the device and the capture itself runs as it would on a GPU."""
    pretend = functools.partial(why_not_cuda_graph, device="cuda")
    monkeypatch.setattr(importlib.import_module("sb3_td3x.td3x.td3x"), "why_not_cuda_graph", pretend)
    monkeypatch.setattr(choose, "why_not_cuda_graph", pretend)
    monkeypatch.setattr(choose, "GraphedGradientStep", functools.partial(GraphedGradientStep, capture=eager_capture))


def set_up_for(model: TD3X) -> str:
    """What the optimizers and the buffer are set up for: "graphs", "eager", or "mixed" (a bug)."""
    groups = [*model.actor.optimizer.param_groups, *model.critic.optimizer.param_groups]
    graphs = [group.get("capturable", False) for group in groups] + [isinstance(group["lr"], th.Tensor) for group in groups]
    graphs.append(model.replay_buffer.static_sampling)
    return "graphs" if all(graphs) else "eager" if not any(graphs) else "mixed"


def test_auto_runs_a_stock_model_in_cuda_graphs(monkeypatch, tmp_path):
    pretend_cuda(monkeypatch)
    model = small()
    assert model.cuda_graph and model.cuda_graph_reason == AUTO_GRAPHS and set_up_for(model) == "graphs"
    line = first_update_line(model, tmp_path)
    assert line.startswith(f"update: cuda_graph ({AUTO_GRAPHS})")
    assert isinstance(model._step_fn, GraphedGradientStep) and sorted(model._step_fn._graphs) == [(256, False), (256, True)]
    assert model._n_updates == 10 and all(th.isfinite(p).all() for p in model.policy.parameters())


@pytest.mark.parametrize(
    ("change", "path", "reason"),
    [
        (with_hook, "autograd", "td_target set on the instance"),
        (with_wrapped_critic, "autograd", "critic.forward set on the instance"),
        (with_vec_normalize, "mlp", "VecNormalize normalises the samples on the host; MlpUpdate: "),
    ],
    ids=["instance_hook", "wrapped_critic", "vec_normalize"],
)
def test_auto_steps_aside_for_a_change_made_after_construction(monkeypatch, change, path, reason):
    """Set up for graphs when built, the model is changed before its first train(): the eager choice runs, set up as
    with cuda_graph=False, and trains what such a model trains from the same seed."""
    pretend_cuda(monkeypatch)
    auto, eager = small(), small(cuda_graph=False)
    assert set_up_for(auto) == "graphs" and set_up_for(eager) == "eager"
    for model in (auto, eager):
        change(model).set_logger(configure(None, []))
        model.set_random_seed(1)  # the same generators (and env seeds) for both
        model.learn(40)
    assert (auto.update_path, eager.update_path) == (path, path)
    assert auto.update_reason.startswith(f"cuda_graph=None (auto) stepped aside from CUDA graphs: {reason}")
    assert not auto.cuda_graph and auto.cuda_graph_reason.startswith("cuda_graph=None (auto) stepped aside")
    assert set_up_for(auto) == "eager"
    for (name, a), b in zip(eager.policy.state_dict().items(), auto.policy.state_dict().values()):
        assert th.equal(a, b), name


def replaced_critic_optimizer(model: TD3X) -> TD3X:
    model.critic.optimizer = th.optim.SGD(model.critic.parameters(), lr=1e-3)
    return model


@pytest.mark.parametrize(
    ("change", "path", "reason"),
    [
        (with_hook, "autograd", "td_target set on the instance"),
        (with_vec_normalize, "mlp", "VecNormalize normalises the samples on the host"),
        (replaced_critic_optimizer, "mlp", "the critic's optimizer is SGD, not torch's Adam or AdamW"),
    ],
    ids=["instance_hook", "vec_normalize", "critic_optimizer"],
)
def test_auto_steps_aside_for_a_change_made_after_the_graphs_ran(monkeypatch, change, path, reason):
    pretend_cuda(monkeypatch)
    model = small()
    model.set_logger(configure(None, []))
    model.learn(20)
    assert model.update_path == "cuda_graph"
    change(model).learn(20, reset_num_timesteps=False)
    assert model.update_path == path and f"stepped aside from CUDA graphs: {reason}" in model.update_reason
    assert set_up_for(model) == "eager" and model._n_updates == 30


def test_a_model_saved_with_auto_loads_where_there_is_no_cuda_and_trains_eagerly(monkeypatch, tmp_path):
    pretend_cuda(monkeypatch)
    model = small()
    model.set_logger(configure(None, []))
    model.learn(20)  # in graphs: the optimizers' states are saved with capturable=True and learning rates in tensors
    model.save(tmp_path / "auto")
    data, _, _ = load_from_zip_file(tmp_path / "auto")
    assert data["cuda_graph_request"] is None and "cuda_graph" not in data and "cuda_graph_reason" not in data
    monkeypatch.undo()  # a machine without CUDA
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        loaded = TD3X.load(tmp_path / "auto", env=gym.make("Pendulum-v1"), device="cpu")
    assert not [w for w in record if "cuda" in str(w.message).lower() or "capturable" in str(w.message)]
    assert loaded.cuda_graph_request is None and loaded.cuda_graph_reason == "cuda_graph=None (auto): no CUDA device"
    assert set_up_for(loaded) == "eager"
    loaded.set_logger(configure(None, []))
    loaded.learn(20)
    assert loaded.update_path == "mlp"


def test_a_model_saved_eagerly_loads_into_cuda_graphs_and_load_takes_cuda_graph(monkeypatch, tmp_path):
    small().save(tmp_path / "eager")  # on this CPU: capturable=False and float learning rates in its optimizer states
    pretend_cuda(monkeypatch)
    loaded = TD3X.load(tmp_path / "eager", env=gym.make("Pendulum-v1"))
    assert loaded.cuda_graph and set_up_for(loaded) == "graphs"  # set up again after the optimizer states were loaded
    loaded.set_logger(configure(None, []))
    loaded.learn(20)
    assert loaded.update_path == "cuda_graph"
    opted_out = TD3X.load(tmp_path / "eager", env=gym.make("Pendulum-v1"), cuda_graph=False)
    assert (opted_out.cuda_graph_request, opted_out.cuda_graph, set_up_for(opted_out)) == (False, False, "eager")
    monkeypatch.undo()
    with pytest.warns(UserWarning, match="cuda_graph=True needs a CUDA device"):
        TD3X.load(tmp_path / "eager", env=gym.make("Pendulum-v1"), cuda_graph=True)


# Drop-in details -----------------------------------------------------------------------------------------------------
def test_an_unsupported_action_space_is_both_errors_with_its_message():
    env = gym.make("CartPole-v1")
    for kind in (ValueError, AssertionError):
        with pytest.raises(kind, match="continuous action space"):
            TD3X("MlpPolicy", env)
    with pytest.raises(UnsupportedActionSpace):
        TD3X("MlpPolicy", "CartPole-v1")


# One source of truth for the hyperparameter checks -----------------------------------------------------------------
@pytest.mark.parametrize("override", ["algo.tau=0", "algo.gradient_steps=0", "algo.tau=1", "algo.gamma=0"])
def test_the_config_accepts_what_the_constructor_accepts(override):
    cfg = compose_config([override])
    check_config(cfg)
    name, value = override.removeprefix("algo.").split("=")
    small(**{name: type(cfg.algo[name])(value)})


@pytest.mark.parametrize("override", ["algo.tau=1.5", "algo.gradient_steps=-2", "algo.policy_delay=0",
                                      "algo.target_noise_clip=-1", "algo.learning_rate=0"])
def test_the_config_refuses_with_the_constructors_words(override):
    name, value = override.removeprefix("algo.").split("=")
    with pytest.raises(ConfigError) as config_error:
        check_config(compose_config([override]))
    with pytest.raises(ValueError) as constructor_error:
        small(**{name: float(value) if "." in value or name in ("tau", "learning_rate", "target_noise_clip") else int(value)})
    allowed = str(constructor_error.value).split(f"{name} must be ")[1].rstrip(".")
    assert f"algo.{name}=" in str(config_error.value) and allowed in str(config_error.value)


def test_a_whole_float_for_an_integer_field_says_how_to_write_it():
    assert whole_float_problems(["total_timesteps=1e6", "algo.buffer_size=2.5e5", "algo.tau=1e-3", "seed=3"]) == [
        "total_timesteps=1e6: total_timesteps is an integer, write total_timesteps=1000000 or total_timesteps=int(1e6)",
        "algo.buffer_size=2.5e5: algo.buffer_size is an integer, write algo.buffer_size=250000 or algo.buffer_size=int(2.5e5)",
    ]
    with pytest.raises(ConfigError, match=r"write total_timesteps=1000000 or total_timesteps=int\(1e6\)"):
        compose_config(["total_timesteps=1e6"])
    cfg = compose_config(["total_timesteps=int(1e6)", "algo.batch_size=256"])  # Hydra's cast
    assert cfg.total_timesteps == 1_000_000 and cfg.algo.batch_size == 256
    with pytest.raises(Exception, match="algo.batch_size=25.5"):  # not a whole number: Hydra's type check refuses it
        compose_config(["algo.batch_size=25.5"])


# --- compile_update=None (auto): compiled where it wins, never a user's change ------------------------------------------
class LongRunTD3X(TD3X):
    """Every run counts as long enough to compile (the threshold is a class attribute a user can set too)."""

    compile_auto_min_steps = 0


def test_auto_does_not_compile_a_short_run_and_says_why(tmp_path):
    model = small()
    line = first_update_line(model, tmp_path)
    assert model.compile_update is None and not model.update_compiled and model.update_path == "mlp"
    assert "compile_update=None (auto), not compiled: a run of 10 training steps" in model.compile_reason
    assert "pays for itself from 100,000" in line


def test_auto_compiles_a_long_stock_run_and_a_resumed_run_decides_as_the_whole_run(tmp_path):
    """The run's length is its target less learning_starts: a run stopped part-way and resumed with learn() of the
    rest (reset_num_timesteps=False, as run.py resumes) decides as the uninterrupted run did, from its first step."""
    from stable_baselines3.common.callbacks import BaseCallback

    class StopAt40(BaseCallback):
        def _on_step(self) -> bool:
            return self.num_timesteps < 40

    def build() -> TD3X:
        model = small(batch_size=32)
        model.compile_auto_min_steps = 50  # runs of 50 training steps or more compile
        return model

    whole = build().learn(60)
    assert whole.update_compiled and whole.update_path == "compiled_mlp"
    assert whole.update_reason.startswith("compile_update=None (auto): a run of 50 training steps on a CPU")
    stopped = build().learn(60, callback=StopAt40())
    assert stopped.num_timesteps == 40 and stopped.update_compiled  # compiled from its first gradient step
    stopped.save(tmp_path / "stopped")
    resumed = TD3X.load(tmp_path / "stopped", env=stopped.get_env())
    assert resumed.compile_update is None and not resumed.update_compiled  # the request is saved, not the decision
    resumed.compile_auto_min_steps = 50
    resumed.learn(60 - resumed.num_timesteps, reset_num_timesteps=False)
    assert resumed.update_compiled and resumed.update_path == "compiled_mlp", resumed.compile_reason
    asked_less = build().learn(40)  # a run of 30 training steps: not compiled
    assert not asked_less.update_compiled and "a run of 30 training steps" in asked_less.compile_reason
    asked_less.learn(20, reset_num_timesteps=False)  # continued to a run of 50: compiled from here
    assert asked_less.update_compiled


@pytest.mark.parametrize(
    ("build", "reason"),
    [
        (lambda: small(mlp_update=False), "mlp_update=False"),
        (lambda: small(policy=ScaledCriticPolicy), "the hooks run as written (the critic is a ScaledCritic, not SB3's TD3XCritic"),
        (lambda: small_then(with_hook)(), "the hooks run as written (td_target set on the instance)"),
        (lambda: small(compile_update=False), "compile_update=False"),
    ],
    ids=["mlp_update_false", "critic_forward", "hook_on_instance", "opted_out"],
)
def test_auto_never_compiles_a_change_or_an_opt_out(monkeypatch, build, reason):
    monkeypatch.setattr(TD3X, "compile_auto_min_steps", 0)
    model = build()
    model.learn(20)
    assert not model.update_compiled and not model.update_path.startswith("compiled")
    assert reason in model.compile_reason


def test_auto_steps_aside_where_there_is_no_cpu_compiler(monkeypatch):
    from torch._inductor import config as inductor_config

    from sb3_td3x.td3x.update_paths import compiled

    monkeypatch.setattr(TD3X, "compile_auto_min_steps", 0)
    compiled.why_no_cpu_compiler.cache_clear()
    try:
        with inductor_config.patch({"cpp.cxx": ("no-such-c++-compiler",)}):
            model = small()
            model.learn(20)
    finally:
        compiled.why_no_cpu_compiler.cache_clear()
    assert not model.update_compiled and model.update_path == "mlp"
    assert "no C++ compiler for torch.compile's CPU backend" in model.compile_reason


def test_auto_compiles_on_a_cpu_only(monkeypatch):
    from sb3_td3x.td3x.update_paths.compiled import why_not_compile

    monkeypatch.setattr(TD3X, "compile_auto_min_steps", 0)
    model = small()
    assert why_not_compile(model) is None
    monkeypatch.setattr(model, "device", th.device("cuda"))
    assert why_not_compile(model) == "auto compiles on a CPU only (device cuda)"


def test_compile_update_is_none_true_or_false():
    with pytest.raises(ValueError, match="invalid compile_update='yes'; compile_update must be None"):
        small(compile_update="yes")
