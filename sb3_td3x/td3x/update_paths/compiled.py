"""The update compiled with ``torch.compile``: the hooks as written, one graph per gradient step.

:class:`CompiledUpdate` compiles ``update_from_batch`` (steps 5 to 15: the target, both losses, both optimizer steps,
the Polyak updates) as the model's class and instance define it, whatever the user changed: Dynamo traces the hooks,
the networks' ``forward`` and the optimizer steps of :func:`~sb3_td3x.td3x.optim.minimize` into one graph
(``fullgraph=True``), with the gradients from ``torch.autograd.grad``. Step 4's sampling runs before it, eagerly (the
indices come from numpy's generator, as SB3 draws them); a ``gradient_step`` of the user's own is compiled whole.
Random numbers drawn inside the graph come from torch's generator, as eagerly (``fallback_random``).

Anything Dynamo cannot put in one graph (a graph break: a print, ``.item()``, numpy, ``optimizer.zero_grad()``, an
optimizer other than Adam or AdamW...) stops the compilation before any of it runs: the update then runs eagerly, as
written, and ``update_reason`` says why in one line. It never runs a different computation: a graph that is not the
whole update is never used.

A class the update reads that changes after it was compiled (``TD3X.td_target = my_td_target`` between two
``train()`` calls, a network's class patched or swapped) is compiled again (:class:`_ClassesRead`): Dynamo guards on
the objects it read, not on the methods it found on their classes.

Whether to compile (``compile_update``; ``None``, auto, by default) is :func:`decide_compile`'s: a question about the
machine and the run, never about the user's code (:func:`why_not_compile`).
"""

from __future__ import annotations

import functools
import itertools
import logging
import types
from collections.abc import Callable
from typing import Any

import torch as th

from sb3_td3x.td3x.optim import FIRST_GRADIENT, NO_STATE, PREPARED, prepare
from sb3_td3x.td3x.hooks import changed_hooks
from sb3_td3x.td3x.update_paths.graph_passes import inductor_options

log = logging.getLogger(__name__)

Infos = tuple[dict[str, th.Tensor], dict[str, th.Tensor]]

#: What compiling costs at the first gradient steps (Hopper-v5, 400-300 networks, 2 cores of an AMD EPYC, torch 2.13):
#: said in auto's reason for a short run.
COMPILE_COST = "about 4 s with Inductor's cache warm, 34 s cold"


def training_steps(model: Any) -> int:
    """The environment steps after ``learning_starts`` of the run ``learn()`` was last asked for: its target
    (``_total_timesteps``, counted from the run's start, so the same for a resumed run as for the uninterrupted
    one) less ``learning_starts``. With ``train_freq=1`` and ``gradient_steps=1``, its gradient steps."""
    return max(0, int(getattr(model, "_total_timesteps", 0)) - max(0, int(model.learning_starts)))


@functools.cache
def why_no_cpu_compiler() -> str | None:
    """Why ``torch.compile`` cannot compile for a CPU here (no C++ compiler for Inductor), or ``None``."""
    try:
        from torch._inductor.cpp_builder import get_cpp_compiler

        get_cpp_compiler()
    except Exception as error:  # noqa: BLE001  (torch raises its own error types, which differ between versions)
        return f"no C++ compiler for torch.compile's CPU backend ({type(error).__name__}: {str(error).strip()[:200]})"
    return None


def long_enough(model: Any) -> bool:
    """Whether the run is long enough for auto to compile: ``model.compile_auto_min_steps`` training steps or more."""
    return training_steps(model) >= model.compile_auto_min_steps


def why_not_compile(model: Any) -> str | None:
    """Why ``compile_update=None`` (auto) runs ``model``'s update eagerly, or ``None`` where it compiles it: the
    first condition that fails, in one line. Auto compiles where compiling was measured to win (docs/performance.md):
    on a CPU, or on a GPU inside CUDA graphs (``cuda_graph=None``), in fp32, with a compiler, for a run of at least
    ``model.compile_auto_min_steps`` training steps (:func:`training_steps`), which pays back the compilation
    (:data:`COMPILE_COST`). What the user's code is does not enter it: a change is compiled with the rest."""
    if model.device.type not in ("cpu", "cuda"):
        return f"auto compiles on a CPU or a CUDA GPU (device {model.device})"
    if model.device.type == "cuda" and model.cuda_graph_request is False:
        return "cuda_graph=False (on a GPU, auto compiles the update inside CUDA graphs)"
    if model.bf16:
        return "bf16=True (compiled bf16 products are not measured to win)"
    if not long_enough(model):
        return (
            f"a run of {training_steps(model):,} training steps: compiling ({COMPILE_COST}) pays for itself from "
            f"{int(model.compile_auto_min_steps):,} (compile_update=True compiles any run)"
        )
    return why_no_cpu_compiler() if model.device.type == "cpu" else None


def decide_compile(model: Any) -> bool:
    """Whether ``model``'s update is compiled, from ``compile_update`` (``None``: :func:`why_not_compile`); sets
    ``model.update_compiled`` and ``model.compile_reason`` (logged with the update at the first ``train()``)."""
    request = model.compile_update
    if request is None:
        why = why_not_compile(model)
        on = why is None
        reason = (
            f"compile_update=None (auto): a run of {training_steps(model):,} training steps on a {model.device.type.upper()}"
            if on
            else f"compile_update=None (auto), not compiled: {why}"
        )
    else:
        on, reason = bool(request), f"compile_update={bool(request)}"
    model.update_compiled, model.compile_reason = on, reason
    return on


def compile_watch(model: Any) -> tuple[Any, bool]:
    """What :func:`decide_compile` decides from, in short (read at every ``train()`` call, so cheap): the request,
    and for auto whether the run is long enough. When it changes, the update is chosen again."""
    request = model.compile_update
    return request, request is None and long_enough(model)


class CompiledUpdate:
    """
    A gradient step (steps 4 to 15) whose update runs as one compiled graph (see the module's docstring).

    Called as ``step(batch_size, update_actor)``, as :meth:`TD3X.gradient_step`. The first gradient step runs eagerly
    when an optimizer has no state yet (Adam makes it at its first ``step()``), and so does a step under a torch
    dispatch mode (``FlopCounterMode``: torch.compile does not run under one). When the graph cannot be made, this
    step and every later one run eagerly, and :attr:`stepped_aside` holds the reason (``model.update_path`` becomes
    ``"eager"`` and ``model.update_reason`` says why).

    :param model: the TD3X model
    :param mode: ``torch.compile``'s mode (``None``: Inductor's default)
    """

    #: ``torch.compile``'s backend: Inductor. (The catalogue of user changes in the tests also runs Dynamo's graphs
    #: with ``"aot_eager"``, AOTAutograd's graph on eager kernels, to check the capture alone, fast.)
    backend: str = "inductor"
    #: ``torch.compile``'s ``options`` (Inductor's settings), for experiments; none by default. With Inductor's default
    #: mode, :mod:`.graph_passes`'s pass is added unless these name a ``post_grad_custom_post_pass`` (``None``: no pass).
    options: dict[str, Any] | None = None

    def __init__(self, model: Any, mode: str | None = None):
        self.model = model
        self.stepped_aside: str | None = None
        self.first_gradients = 0  # steps run eagerly to make a parameter's Adam state (a bound, should it not come)
        # The updates its compiled graphs made, over the model's life (a choice made again keeps the count): the
        # records of a later step aside say how many (_step_aside), and the tests that the graphs did run.
        model._updates_compiled = getattr(model, "_updates_compiled", 0)
        # In CUDA graphs (reduce-overhead) the outputs live in the graph's memory, which the next replay overwrites:
        # the statistics of a train() call's gradient steps are copied out after each step.
        self.copy_outputs = mode == "reduce-overhead"
        # A gradient_step of the user's own is compiled whole; TD3X's samples eagerly, then runs the compiled update.
        self.whole_step = bool(changed_hooks(model, ("gradient_step",)))
        self.mode = mode
        self.classes_read: _ClassesRead | None = None  # taken after each trace
        self.recompiled: list[str] = []  # why the update was compiled again (a class changed), at most MAX_RECOMPILES
        self._compiled = self._compile()

    #: How many times a changed class compiles the update again before it steps aside (a class attribute that changes
    #: at every step would compile it at every step).
    MAX_RECOMPILES = 8

    def _compile(self) -> dict[bool, Callable[[Any], Infos]]:
        """One compiled function per value of update_actor (each holds one graph, so no guard fails at each call), each
        with a code object of its own: a new pair starts with no graph (:meth:`__call__`, when a class changed)."""
        inductor_default = self.backend == "inductor" and self.mode is None  # torch.compile takes a mode or options
        compile_ = functools.partial(
            th.compile, fullgraph=True, backend=self.backend, mode=self.mode if self.backend == "inductor" else None,
            options=inductor_options(self.options) if inductor_default else self.options,
        )
        return {flag: compile_(_own_code(_step(self.model, flag, self.whole_step))) for flag in (False, True)}

    def __call__(self, batch_size: int, update_actor: bool) -> Infos:
        model = self.model
        optimizers = (model.critic.optimizer, model.actor.optimizer)
        if self.stepped_aside is not None or _dispatch_mode_active():
            return model.gradient_step(batch_size, update_actor)
        for optimizer in optimizers:
            prepare(optimizer)  # a schedule's learning rate, read by the graph from a tensor
            if (why := getattr(optimizer, PREPARED)) == NO_STATE:  # SGD without momentum says what it is, never this
                return model.gradient_step(batch_size, update_actor)  # a first step makes Adam's state
            if isinstance(why, str):
                whose = "critic" if optimizer is optimizers[0] else "actor"
                return self._step_aside(f"{why} (the {whose}'s optimizer)", batch_size, update_actor)
        if self.classes_read is not None and (changed := self.classes_read.changed()) is not None:
            if len(self.recompiled) >= self.MAX_RECOMPILES:
                why = f"{changed}, after {self.MAX_RECOMPILES} such changes each compiled again"
                return self._step_aside(why, batch_size, update_actor)
            self.recompiled.append(changed)
            log.info("TD3X: %s since the update was compiled: compiling it again.", changed)
            self._compiled, self.classes_read = self._compile(), None
        args = (batch_size,) if self.whole_step else (model.sample_batch(batch_size),)  # step 4
        graphs = _graphs_made()
        try:
            with _CompileSettings():
                infos = self._compiled[update_actor](*args)
        except (th._dynamo.exc.TorchDynamoException, th._dynamo.exc.FailOnRecompileLimitHit) as error:
            # Raised while tracing or compiling, before the graph ran: nothing of this step has happened yet.
            if FIRST_GRADIENT in str(error) and self.first_gradients < 100:  # this step eagerly: it makes the state
                self.first_gradients += 1
                return self._eager(*args, update_actor)
            return self._step_aside(why_not_one_graph(error), *args, update_actor)
        model._updates_compiled += 1
        if self.classes_read is None or _graphs_made() != graphs:  # traced now: from the classes as they are now
            self.classes_read = _ClassesRead(model)
        if self.copy_outputs:
            return tuple({key: value.clone() for key, value in info.items()} for info in infos)  # type: ignore[return-value]
        return infos

    def _step_aside(self, why: str, batch_or_size: Any, update_actor: bool) -> Infos:
        """From now on the eager update, ``why`` said once; this step runs eagerly (on the batch already sampled)."""
        model = self.model
        self.stepped_aside = why
        model.update_path = "eager"
        # Where it stepped aside: the records of a long run that compiled for a while must not say it never did.
        ran = model._updates_compiled
        when = (f", from update {model._n_updates:,} on (timestep {model.num_timesteps:,}; {ran:,} updates ran compiled "
                "before)") if ran else ""
        model.update_reason = f"{model.compile_reason}, but {why}: the update runs eagerly, as written{when}"
        log.warning("TD3X: %s.", model.update_reason)
        return self._eager(batch_or_size, update_actor)

    def _eager(self, batch_or_size: Any, update_actor: bool) -> Infos:
        """This step eagerly: sampling too, or on the batch already sampled."""
        if isinstance(batch_or_size, int):
            return self.model.gradient_step(batch_or_size, update_actor)
        return self.model.update_from_batch(batch_or_size, update_actor)


def _dispatch_mode_active() -> bool:
    """Whether a torch dispatch mode is active (``FlopCounterMode``, a tracer's): torch.compile does not run under one,
    so the step runs eagerly, where the mode sees every operator."""
    from torch.utils._python_dispatch import _get_current_dispatch_mode

    return _get_current_dispatch_mode() is not None


def _step(model: Any, update_actor: bool, whole_step: bool) -> Callable[[Any], Infos]:
    """The function compiled: the model's ``update_from_batch`` on a batch, or its own ``gradient_step`` whole."""
    if whole_step:
        return lambda batch_size: model.gradient_step(batch_size, update_actor)
    return lambda batch: model.update_from_batch(batch, update_actor)


def _own_code(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with a code object of its own. Dynamo keeps its compiled graphs, and counts its recompilations (8 at
    most), per code object: each model's update then has its own, instead of every TD3X of the process sharing one
    (a batch of seeds, a sweep, a test session would exhaust it)."""
    code = fn.__code__.replace(co_name=f"td3x_update_{next(_UPDATES)}")
    return types.FunctionType(code, fn.__globals__, code.co_name, fn.__defaults__, fn.__closure__)


_UPDATES = itertools.count()


def _graphs_made() -> int:
    """How many graphs Dynamo has made in this process (one more after a trace)."""
    return th._dynamo.utils.counters["stats"]["unique_graphs"]


class _ClassesRead:
    """The classes of what the update reads (the model, its policy and every module in it, the optimizers, the replay
    buffer, with their bases), as the update was traced, and what each class holds.

    Dynamo guards on the objects the graph read (their ``__dict__``, their class) but not on the methods it found on
    their classes (https://github.com/pytorch/pytorch/issues/197860; a guard per inlined function cost 20% more guard
    time, https://github.com/pytorch/pytorch/pull/126203): a hook replaced on the class (``TD3X.td_target = f``), SB3's
    ``ContinuousCritic.forward`` or ``nn.Linear.forward`` patched after the first compiled step would leave the old
    graph running, silently. :meth:`changed` finds such a change, and the update is then traced again, as written now.
    About 15 us a step with Hopper's networks on a 2-core AMD EPYC Zen 3 (Dynamo's own guards there: 35 to 70 us a
    call). It holds classes, not the objects (a replaced replay buffer must not stay in memory through it)."""

    def __init__(self, model: Any):
        objects = [model, model.critic.optimizer, model.actor.optimizer, model.replay_buffer, *model.policy.modules()]
        classes = dict.fromkeys(cls for obj in objects for cls in type(obj).__mro__)
        classes.pop(object)
        # Each class's namespace (a live view) and what it held: the values are held, so no id is reused.
        self.classes = [(cls, vars(cls), tuple(vars(cls).values())) for cls in classes]

    def changed(self) -> str | None:
        """What changed on a class since the trace, in words, or ``None``."""
        for cls, namespace, values in self.classes:
            try:  # identical values compare equal without __eq__; a replaced array's __eq__ may raise
                same = tuple(namespace.values()) == values
            except Exception:  # noqa: BLE001
                same = False
            if not same:
                names = [name for name, value in namespace.items() if not any(value is v for v in values)]
                return f"{cls.__module__}.{cls.__qualname__} changed ({', '.join(names) or 'an attribute deleted'})"
        return None


class _CompileSettings:
    """Around each call (read when Dynamo traces and Inductor compiles, which any call may do): Dynamo traces
    ``torch.autograd.grad`` (:func:`~sb3_td3x.td3x.optim.minimize`) and guards on the modules' hooks (torch 2.13 skips
    those guards by default: a forward hook registered after the compilation would never run, silently), Inductor
    draws random numbers with torch's generator, as eagerly (the same smoothing noise as the eager update, from the
    same seed), and SB3's ``is_image_space`` is taken as a constant of the observation space it is given (Dynamo guards
    on that space's identity): it compares the space's bounds with numpy, which Dynamo would trace as tensors and then
    refuse the branch on, so that image observations could not be compiled. Set and put back as attributes:
    ``config.patch`` costs a tenth of a millisecond per call."""

    @staticmethod
    @functools.cache
    def settings() -> tuple[tuple[Any, str, Any], ...]:
        # Imported at the first compiled step, not with the package: Dynamo and Inductor take 2 s to import.
        from stable_baselines3.common import preprocessing
        from torch._inductor import config as inductor_config

        return (
            (th._dynamo.config, "trace_autograd_ops", True),
            (th._dynamo.config, "skip_nnmodule_hook_guards", False),
            (inductor_config, "fallback_random", True),
            # What torch.compiler.assume_constant_result sets, for the length of the call only.
            (preprocessing.is_image_space, "_dynamo_marked_constant", True),
        )

    def __enter__(self) -> None:
        settings = self.settings()
        self.saved = [getattr(target, name, _UNSET) for target, name, _ in settings]
        for target, name, value in settings:
            setattr(target, name, value)

    def __exit__(self, *exc: Any) -> None:
        for (target, name, _), value in zip(self.settings(), self.saved):
            if value is _UNSET:
                delattr(target, name)
            else:
                setattr(target, name, value)


_UNSET = object()


def why_not_one_graph(error: BaseException) -> str:
    """The reason, in one line, that Dynamo gave for not putting the update in one graph."""
    if isinstance(error, th._dynamo.exc.FailOnRecompileLimitHit):
        limit = th._dynamo.config.recompile_limit
        return (
            f"torch.compile made {limit} graphs of the update already, its limit (a Python value the hooks read, or "
            "a tensor's shape, changes again and again)"
        )
    text = str(error).strip()
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    head = lines[0] if lines else type(error).__name__
    if head.endswith(":") and len(lines) > 1:  # "backend='inductor' raised:" then the error itself
        head = f"{head} {lines[1]}"
    explanation = next((line.removeprefix("Explanation: ") for line in lines if line.startswith("Explanation:")), "")
    where = next((line for line in reversed(lines) if line.startswith("File ")), "")
    said = f"{head}" + (f" ({explanation})" if explanation and explanation not in head else "")
    if where:
        said += f" at {where.removeprefix('File ')}"
    return f"torch.compile cannot make one graph of it: {said}"[:400]
