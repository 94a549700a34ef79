"""How the update runs: one function picks it, says why, and the layout has no import circle."""

import ast
from pathlib import Path

import gymnasium as gym
import pytest
import torch as th
from stable_baselines3.common.logger import HumanOutputFormat, Logger

from sb3_td3x.experiment.errors import ConfigError
from sb3_td3x.experiment.schemas import check_config, compose_config, whole_float_problems
from sb3_td3x.td3x import TD3X, TD3XCritic, TD3XPolicy, UnsupportedActionSpace
from sb3_td3x.td3x.hooks import HOOK_NAMES, HOOKS, changed_hooks, reference_class
from sb3_td3x.td3x.update_paths.choose import choose_update

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
