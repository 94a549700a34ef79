"""How the update runs: one function picks it from the machine and the run, says why, and the layout has no import
circle."""

import ast
import sys
from pathlib import Path

import gymnasium as gym
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import HumanOutputFormat, Logger

from sb3_td3x.experiment.configs.compose import check_config, compose_config, whole_float_problems
from sb3_td3x.experiment.errors import ConfigError
from sb3_td3x.td3x import TD3X, TD3XCritic, TD3XPolicy, UnsupportedActionSpace
from sb3_td3x.td3x.hooks import HOOK_NAMES, HOOKS, changed_hooks, reference_class
from sb3_td3x.td3x.update_paths import compiled
from sb3_td3x.td3x.update_paths.choose import choose_update
from sb3_td3x.td3x.update_paths.compiled import why_not_compile

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


def test_a_short_run_logs_the_eager_update_and_why(tmp_path):
    model = small()
    line = first_update_line(model, tmp_path)
    assert line.startswith("update: eager (compile_update=None (auto), not compiled: a run of 10 training steps")
    assert "pays for itself from 100,000" in line and "exploration: actor (the actor module called directly)" in line
    assert (model.update_path, model.exploration_path) == ("eager", "actor")
    assert model.compile_update is None and not model.update_compiled


def test_a_users_change_does_not_enter_the_choice(tmp_path):
    """The same choice, and the same words, for a changed critic, a hook set on the instance and the stock model."""
    changed = small(ScaledCriticPolicy)
    changed.td_target = lambda rewards, dones, discounts, next_q: rewards
    for model in (small(), changed):
        model.compile_auto_min_steps = 0
        choice = choose_update(model)
        assert (choice.path, choice.reason) == ("compiled", "compile_update=None (auto): a run of 0 training steps on a CPU; "
                                                "the hooks as written, one graph")


def test_a_hook_set_after_the_first_train_is_compiled_with_the_rest(dynamo_graphs_only):
    model = small(compile_update=True, batch_size=16)
    model.learn(20)
    assert model.update_path == "compiled"
    calls = []

    def td_target(rewards, dones, discounts, next_q):
        calls.append(1)  # a side effect Dynamo replays at every call
        return rewards

    model.td_target = td_target
    model.learn(10, reset_num_timesteps=False)
    assert model.update_path == "compiled" and len(calls) == 10
    del model.td_target  # back to the stock hook
    model.learn(10, reset_num_timesteps=False)
    assert model.update_path == "compiled" and len(calls) == 10


@pytest.mark.parametrize("kind", ["forward", "forward_pre", "full_backward"])
def test_a_module_hook_registered_after_the_first_compiled_train_runs(kind, dynamo_graphs_only):
    """A hook added to a module after the update was compiled runs at every later step, as eagerly, or the update
    steps aside with the reason: never a graph that silently leaves it out (torch 2.13 skips the guards on module
    hooks unless told not to)."""

    def trained(compile_update):
        model = small(compile_update=compile_update, batch_size=16)
        model.learn(30)
        calls = []
        hook = {"forward": lambda module, args, out: calls.append(1),
                "forward_pre": lambda module, args: calls.append(1),
                "full_backward": lambda module, grad_in, grad_out: calls.append(1)}[kind]
        getattr(model.critic.qf0[0], f"register_{kind}_hook")(hook)
        model.learn(10, reset_num_timesteps=False)
        return model, len(calls)

    (eager, eager_calls), (compiled, compiled_calls) = trained(False), trained(True)
    assert eager_calls > 0 and compiled_calls == eager_calls, (eager_calls, compiled_calls, compiled.update_reason)
    for a, b in zip(compiled.policy.parameters(), eager.policy.parameters()):
        th.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


class PrintingTD3X(TD3X):
    """A hook Dynamo cannot put in one graph: ``.item()`` and a print."""

    def critic_loss(self, current_q, target_q):
        loss, info = super().critic_loss(current_q, target_q)
        print(f"critic loss {loss.item():.3f}")
        return loss, info


def test_a_hook_that_breaks_the_graph_runs_eagerly_and_says_why(capsys):
    def trained(compile_update):
        model = PrintingTD3X("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [16]}, learning_starts=10, seed=0,
                             batch_size=16, compile_update=compile_update)
        model.learn(30)
        return model

    fast = trained(True)
    eager = trained(False)
    assert fast.update_path == "eager" and fast.update_compiled
    assert "torch.compile cannot make one graph of it" in fast.update_reason and "the update runs eagerly" in fast.update_reason
    assert capsys.readouterr().out.count("critic loss") == 2 * 20  # every step printed, none lost to a graph
    for a, b in zip(fast.policy.parameters(), eager.policy.parameters()):
        assert th.equal(a, b)


def test_a_step_aside_mid_run_says_from_which_update(dynamo_graphs_only):
    """An update that compiled for a while and then steps aside (here the critic's optimizer replaced by SGD between
    two learn() calls) says from which update and timestep it ran eagerly, so that a run's records do not say it never
    compiled; a step aside at the first compiled update says no more than why."""

    def trained(compile_update):
        model = small(batch_size=16, compile_update=compile_update)
        model.learn(30)
        model.critic.optimizer = th.optim.SGD(model.critic.parameters(), lr=1e-3)
        model.learn(10, reset_num_timesteps=False)
        return model

    fast, eager = trained(True), trained(False)
    assert fast.update_path == "eager"
    assert fast.update_reason.endswith(
        "the SGD optimizer steps only eagerly (compiled: torch's Adam and AdamW) (the critic's optimizer): the update "
        "runs eagerly, as written, from update 21 on (timestep 31; 18 updates ran compiled before)"
    ), fast.update_reason  # of the first 20, two ran eagerly: each optimizer's first step makes Adam's state
    for a, b in zip(fast.policy.parameters(), eager.policy.parameters()):
        th.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    from_the_start = small(batch_size=16, compile_update=True, policy_kwargs={"net_arch": [16], "optimizer_class": th.optim.SGD})
    reason = from_the_start.learn(20).update_reason
    assert from_the_start.update_path == "eager" and reason.endswith("the update runs eagerly, as written"), reason


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
        if name.startswith("sb3_td3x.td3x.update_paths") or name in ("sb3_td3x.td3x.hooks", "sb3_td3x.td3x.optim"):
            assert "sb3_td3x.td3x.td3x" not in graph[name], f"{name} imports TD3X: the paths must not"
    for name, path in modules.items():  # not even for type checking: farm-studio counts those too
        assert "from sb3_td3x.td3x.td3x import" not in path.read_text() or name in (
            "sb3_td3x.td3x.presets", "sb3_td3x.td3x"), name
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


def test_cuda_graph_is_none_true_or_false():
    with pytest.raises(ValueError, match=r"invalid cuda_graph='auto'; cuda_graph must be None \(auto"):
        small(cuda_graph="auto")


def test_on_a_cpu_nothing_is_set_up_for_cuda_graphs():
    model = small()
    assert (model.cuda_graph_request, model.cuda_graph) == (None, False)
    assert not model.replay_buffer.static_sampling
    for group in (*model.actor.optimizer.param_groups, *model.critic.optimizer.param_groups):
        assert group["capturable"] is False and isinstance(group["lr"], float)


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


# --- compile_update=None (auto): compiled on a long run, whatever the code --------------------------------------------
def test_auto_compiles_a_long_run_and_a_resumed_run_decides_as_the_whole_run(tmp_path, dynamo_graphs_only):
    """The run's length is its target less learning_starts: a run stopped part-way and resumed with learn() of the
    rest (reset_num_timesteps=False, as run.py resumes) decides as the uninterrupted run did, from its first step."""

    class StopAt40(BaseCallback):
        def _on_step(self) -> bool:
            return self.num_timesteps < 40

    def build() -> TD3X:
        model = small(batch_size=32)
        model.compile_auto_min_steps = 50  # runs of 50 training steps or more compile
        return model

    whole = build().learn(60)
    assert whole.update_compiled and whole.update_path == "compiled"
    assert whole.update_reason.startswith("compile_update=None (auto): a run of 50 training steps on a CPU")
    stopped = build().learn(60, callback=StopAt40())
    assert stopped.num_timesteps == 40 and stopped.update_compiled  # compiled from its first gradient step
    stopped.save(tmp_path / "stopped")
    resumed = TD3X.load(tmp_path / "stopped", env=stopped.get_env())
    assert resumed.compile_update is None and not resumed.update_compiled  # the request is saved, not the decision
    resumed.compile_auto_min_steps = 50
    resumed.learn(60 - resumed.num_timesteps, reset_num_timesteps=False)
    assert resumed.update_compiled and resumed.update_path == "compiled", resumed.compile_reason
    asked_less = build().learn(40)  # a run of 30 training steps: not compiled
    assert not asked_less.update_compiled and "a run of 30 training steps" in asked_less.compile_reason
    asked_less.learn(20, reset_num_timesteps=False)  # continued to a run of 50: compiled from here
    assert asked_less.update_compiled and asked_less.update_path == "compiled"


def test_compile_update_false_opts_out(monkeypatch):
    monkeypatch.setattr(TD3X, "compile_auto_min_steps", 0)
    model = small(compile_update=False)
    model.learn(20)
    assert not model.update_compiled and model.update_path == "eager" and model.compile_reason == "compile_update=False"


def test_auto_steps_aside_where_there_is_no_cpu_compiler(monkeypatch):
    from torch._inductor import config as inductor_config

    monkeypatch.setattr(TD3X, "compile_auto_min_steps", 0)
    compiled.why_no_cpu_compiler.cache_clear()
    try:
        with inductor_config.patch({"cpp.cxx": ("no-such-c++-compiler",)}):
            model = small()
            model.learn(20)
    finally:
        compiled.why_no_cpu_compiler.cache_clear()
    assert not model.update_compiled and model.update_path == "eager"
    assert "no C++ compiler for torch.compile's CPU backend" in model.compile_reason


def test_auto_asks_about_the_machine_and_the_run_only(monkeypatch):
    monkeypatch.setattr(TD3X, "compile_auto_min_steps", 0)
    model = small()
    assert why_not_compile(model) is None
    monkeypatch.setattr(model, "device", th.device("cuda"))
    assert why_not_compile(model) is None  # on a GPU: compiled inside CUDA graphs
    assert choose_update(model).reason.endswith("one graph in CUDA graphs (torch.compile's reduce-overhead)")
    monkeypatch.setattr(model, "cuda_graph_request", False)
    assert why_not_compile(model) == "cuda_graph=False (on a GPU, auto compiles the update inside CUDA graphs)"
    monkeypatch.setattr(model, "device", th.device("mps"))
    assert why_not_compile(model) == "auto compiles on a CPU or a CUDA GPU (device mps)"
    monkeypatch.setattr(model, "device", th.device("cpu"))
    monkeypatch.setattr(model, "bf16", True)
    assert why_not_compile(model) == "bf16=True (compiled bf16 products are not measured to win)"


def test_compile_update_is_none_true_or_false():
    with pytest.raises(ValueError, match="invalid compile_update='yes'; compile_update must be None"):
        small(compile_update="yes")


def test_the_compiled_update_adds_each_bias_after_its_product():
    """graph_passes.bias_after_product: a CPU addmm in float32 becomes mm + add (the bias added by the next pointwise
    kernel), computing x @ w + b as eagerly written, and a baddbmm bmm + add; a bfloat16 one, or one with alpha or
    beta, is left as it is. test_user_changes.py's test_auto_compiles_a_long_run... checks that the compiled default
    runs no addmm."""
    from torch.fx.experimental.proxy_tensor import make_fx

    from sb3_td3x.td3x.update_paths.graph_passes import bias_after_product, cpu_passes, inductor_options

    def through_the_pass(fn, product, *args):
        graph_module = make_fx(fn, tracing_mode="fake")(*args)
        assert product in [node.target for node in graph_module.graph.nodes]  # traced as the fused product
        bias_after_product(graph_module.graph)
        graph_module.recompile()
        targets = [node.target for node in graph_module.graph.nodes if node.op == "call_function"]
        return graph_module, targets

    aten = th.ops.aten
    for dtype, alpha, rewritten in ((th.float32, 1, True), (th.float64, 1, True), (th.bfloat16, 1, False),
                                    (th.float32, 2, False)):  # fmt: skip
        x, w, b = th.randn(8, 5, dtype=dtype), th.randn(3, 5, dtype=dtype), th.randn(3, dtype=dtype)
        graph_module, targets = through_the_pass(lambda x, w, b: th.addmm(b, x, w.t(), alpha=alpha).relu(),
                                                aten.addmm.default, x, w, b)
        assert (aten.addmm.default not in targets) == rewritten, (dtype, alpha)
        if rewritten:
            assert aten.mm.default in targets and aten.add.Tensor in targets
            assert th.equal(graph_module(x, w, b), (x @ w.t() + b).relu())
    x, w, b = th.randn(2, 8, 5), th.randn(2, 3, 5), th.randn(2, 1, 3)  # two networks stacked: baddbmm, bmm + add
    graph_module, targets = through_the_pass(lambda x, w, b: th.baddbmm(b, x, w.mT).relu(), aten.baddbmm.default,
                                            x, w, b)
    assert aten.baddbmm.default not in targets and aten.bmm.default in targets
    assert th.equal(graph_module(x, w, b), (th.bmm(x, w.mT) + b).relu())
    assert inductor_options(None) == {"post_grad_custom_post_pass": cpu_passes()}
    mine = object()
    assert inductor_options({"post_grad_custom_post_pass": mine}) == {"post_grad_custom_post_pass": mine}
    assert inductor_options({"post_grad_custom_post_pass": None}) == {"post_grad_custom_post_pass": None}  # none
    cpu_passes.cache_clear()  # a torch whose Inductor has no custom passes: compiled without them, not a crash
    with pytest.MonkeyPatch.context() as patched:
        patched.setitem(sys.modules, "torch._inductor.custom_graph_pass", None)
        assert cpu_passes() is None and inductor_options(None) is None and inductor_options({"a": 1}) == {"a": 1}
    cpu_passes.cache_clear()
    assert inductor_options(None) == {"post_grad_custom_post_pass": cpu_passes()}


def test_the_compiled_update_computes_only_the_part_of_a_product_it_reads():
    """graph_passes.products_read_in_part: a product read only through a slice of its columns (the actor's gradient
    through the critic's first layer keeps the action's columns of the concatenated input) or of its rows computes
    that part alone, with the same numbers to rounding; a product read twice, or by a strided slice, one whose left-out
    part is small (Hopper-v5's), or one in bfloat16 (not measured), is left whole."""
    from torch.fx.experimental.proxy_tensor import make_fx

    from sb3_td3x.td3x.update_paths.graph_passes import products_read_in_part

    aten = th.ops.aten
    th.manual_seed(0)
    grad, weight = th.randn(256, 400), th.randn(400, 113)  # Ant-v5's first layer: 105 observation, 8 action columns
    hopper = th.randn(100, 400), th.randn(400, 14)  # 11 and 3: 440,000 multiply-adds left out, too few to pay
    for fn, rewritten, args in ((lambda g, w: th.mm(g, w)[:, 105:], True, (grad, weight)),
                                (lambda g, w: th.mm(g, w)[4:9], True, (grad, weight)),
                                (lambda g, w: th.mm(g, w)[:, -8:], True, (grad, weight)),
                                (lambda g, w: th.mm(g, w)[:, ::2], False, (grad, weight)),
                                (lambda g, w: (lambda p: (p[:, 105:], p.sum()))(th.mm(g, w)), False, (grad, weight)),
                                (lambda g, w: th.mm(g, w)[:, 11:], False, hopper),
                                (lambda g, w: th.mm(g, w)[:, 105:], False, (grad.bfloat16(), weight.bfloat16()))):  # fmt: skip
        graph_module = make_fx(fn, tracing_mode="fake")(*args)
        products = [node for node in graph_module.graph.nodes if node.target == aten.mm.default]
        whole = {tuple(node.meta["val"].shape) for node in products}
        products_read_in_part(graph_module.graph)
        graph_module.graph.lint()
        graph_module.recompile()
        after = {tuple(node.meta["val"].shape) for node in graph_module.graph.nodes if node.target == aten.mm.default}
        assert (after != whole) == rewritten, after
        expected = fn(*args)
        got = graph_module(*args)
        for g, e in zip(got if isinstance(got, tuple) else (got,), expected if isinstance(expected, tuple) else (expected,)):
            th.testing.assert_close(g, e)  # the same sums (the BLAS may block them otherwise)
    # Through Inductor, with the three rewrites: as compiled without them.
    from sb3_td3x.td3x.update_paths.graph_passes import cpu_passes

    # Two code objects: two compilations, whatever Dynamo's cache would make of one function compiled twice.
    twins = (lambda g, w: th.mm(g, w)[:, 105:].relu(), lambda g, w: th.mm(g, w)[:, 105:].relu())
    with_pass, without = (th.compile(fn, backend="inductor", options={"post_grad_custom_post_pass": post})(grad, weight)
                          for fn, post in zip(twins, (cpu_passes(), None)))  # fmt: skip
    th.testing.assert_close(with_pass, without)


def test_the_compiled_update_computes_each_scalar_once(monkeypatch):
    """graph_passes.scalars_once, on torch's own Adam step as the compiled update traces it (functional adam, one
    tensor at a time, the step count a tensor): each 0-d value a pointwise op computes (the bias corrections) reaches
    the parameter-sized ops through an as_strided of its own, which Inductor computes into a buffer once; 0-d ops that
    read it stay as they were, and the step computes what it computed before, eagerly and through Inductor. Shown to
    fail with the scalar's input read in the scalar's place."""
    from torch.fx.experimental.proxy_tensor import make_fx
    from torch.optim.adam import adam

    from sb3_td3x.td3x.update_paths.graph_passes import cpu_passes, scalars_once

    def adam_step(param, grad, exp_avg, exp_avg_sq, step, lr):
        param, exp_avg, exp_avg_sq, step = param.clone(), exp_avg.clone(), exp_avg_sq.clone(), step.clone()
        adam([param], [grad], [exp_avg], [exp_avg_sq], [], [step], foreach=False, capturable=True, lr=lr, beta1=0.9,
             beta2=0.999, eps=1e-8, weight_decay=0.0, amsgrad=False, maximize=False)  # fmt: skip
        return param, exp_avg, exp_avg_sq, step

    th.manual_seed(0)
    args = (th.randn(30, 4), th.randn(30, 4), th.randn(30, 4), th.rand(30, 4), th.tensor(7.0), th.tensor(1e-3))
    with monkeypatch.context() as patched:  # as Dynamo traces it: capturable on a CPU is for compiled steps only
        patched.setattr(th.compiler, "is_compiling", lambda: True)
        # Three traces: one rewritten here, two compiled below (two code objects: two compilations).
        graph_module, *traced = (make_fx(adam_step, tracing_mode="fake")(*args) for _ in range(3))
        before = graph_module(*args)
    scalars_once(graph_module.graph)
    graph_module.recompile()
    nodes = [node for node in graph_module.graph.nodes if node.op == "call_function"]
    once = [node for node in nodes if node.target == th.ops.aten.as_strided.default]
    assert once, "no scalar was computed once"
    for node in nodes:
        val = node.meta["val"]
        for arg in node.all_input_nodes:
            if isinstance(val, th.Tensor) and val.dim() > 0 and arg.op == "call_function" and arg.meta["val"].dim() == 0:
                assert arg in once, f"{node} reads the 0-d {arg} inline"  # a parameter-sized op reads only buffers
    assert len(once) == 2  # Adam's: -sqrt(1 - beta2^t) * lr / (1 - beta1^t), and eps over its step size
    for got, expected in zip(graph_module(*args), before):
        assert th.equal(got, expected)
    # Through Inductor (its lowering of the as_strided): the same step as Inductor without the pass.
    with_pass, without = (th.compile(module, backend="inductor", options={"post_grad_custom_post_pass": post})(*args)
                          for module, post in zip(traced, (cpu_passes(), None)))  # fmt: skip
    for got, expected in zip(with_pass, without):
        assert th.equal(got, expected)
