"""TD3X: TD3 as an SB3 ``OffPolicyAlgorithm`` whose every step is an overridable hook."""

from __future__ import annotations

import contextlib
import inspect
import math
import warnings
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.noise import ActionNoise, NormalActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, ReplayBufferSamples, Schedule, TensorDict
from stable_baselines3.common.utils import FloatSchedule, get_parameters_by_name, update_learning_rate

from sb3_td3x.common import denormals
from sb3_td3x.common.buffers import TensorReplayBuffer
from sb3_td3x.common.core_waits import CoreWaits
from sb3_td3x.common.random_streams import RandomStreams
from sb3_td3x.td3x.hooks import HOOK_NAMES, changed_hooks
from sb3_td3x.td3x.optim import minimize
from sb3_td3x.td3x.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, TD3XPolicy, networks_built_by
from sb3_td3x.td3x.update_paths.choose import choose_update
from sb3_td3x.td3x.update_paths.compiled import compile_watch
from sb3_td3x.td3x.update_paths.cuda_graph import why_not_capture
from sb3_td3x.td3x.update_paths.exploration import why_not_direct
from sb3_td3x.td3x.update_paths.precision import autocast_context, bf16_on_cpu_warning

SelfTD3X = TypeVar("SelfTD3X", bound="TD3X")
Obs = th.Tensor | TensorDict


class UnsupportedActionSpace(ValueError, AssertionError):
    """An action space TD3 cannot act in (not a bounded Box). Both a ``ValueError`` and an ``AssertionError``: SB3's
    algorithms assert on unsupported action spaces, and code written for them catches ``AssertionError``."""


class TD3X(OffPolicyAlgorithm):
    """
    Twin Delayed DDPG (TD3), with every step of the algorithm an overridable method.

    Fujimoto, van Hoof and Meger (2018), "Addressing Function Approximation Error in Actor-Critic Methods",
    ICML. Paper: https://arxiv.org/abs/1802.09477 -- reference code: https://github.com/sfujim/TD3

    ``train()`` reads as the algorithm (step numbers from the course notes in ``shared/seeds``):

    ====  =================================================  =======================================
    step  what                                               hook
    ====  =================================================  =======================================
    2     the actor's network pi_phi (and its target's)      :meth:`actor_network`
    3     each critic's network Q_theta_i (and targets')     :meth:`q_network`
    4     sample a batch (s, a, r, s', d)                     :meth:`sample_batch`
    5     a' = pi_phi'(s')                                    :meth:`target_actions`
    6     a' <- clip(a' + clip(N(0, sigma~), -c, c))          :meth:`target_policy_smoothing_noise`
    7     Q'_i(s', a') for each critic target                 :meth:`next_q_values`
    8     min_i Q'_i(s', a')  (clipped double-Q)              :meth:`clipped_double_q_value`
    9     y = r + gamma (1 - d) min_i Q'_i(s', a')            :meth:`td_target`
    10    Q_i(s, a) for each critic                           :meth:`current_q_values`
    11    L = sum_i MSE(Q_i(s, a), y)                         :meth:`critic_loss`
    12    gradient step on the critics                        :meth:`optimize_critic`
    12    then: the batch's new priorities (prioritised)      :meth:`update_priorities`
    13    every ``policy_delay`` steps: J = -Q_1(s, pi(s))    :meth:`should_update_actor`,
                                                              :meth:`actor_loss`, :meth:`optimize_actor`
    14    phi' <- tau phi + (1 - tau) phi'  (actor target)    :meth:`update_actor_target`
    15    theta'_i <- tau theta_i + (1 - tau) theta'_i        :meth:`update_critic_target`
    5-9   the TD target y, without gradient                   :meth:`compute_target_q`
    5-15  the updates from a sampled batch                    :meth:`update_from_batch`
    4-15  one gradient step, the steps above in order         :meth:`gradient_step`
    ====  =================================================  =======================================

    Steps 1 to 3 (replay buffer, actor and critic networks and their targets) are built by SB3's
    ``OffPolicyAlgorithm._setup_model`` and :class:`~sb3_td3x.td3x.policies.TD3XPolicy`, the networks by the hooks of
    steps 2 and 3 where a subclass overrides them (a LayerNorm critic is one short override). The replay buffer is
    :class:`~sb3_td3x.common.buffers.TensorReplayBuffer` for Box observations: its batches also carry their rows
    (``indices``) and, prioritised with ``beta > 0``, importance ``weights``, which :meth:`update_from_batch` passes
    to :meth:`critic_loss`; ``n_steps > 1`` gives it SB3's n-step returns, and ``replay_buffer_kwargs={"alpha": ...}``
    prioritised sampling, whose priorities :meth:`update_priorities` writes after each critic step.

    Losses return ``(loss, info)`` and never step optimizers or touch target networks. Every constructor argument of
    SB3's :class:`~stable_baselines3.TD3` has the same name, meaning and default here; the additions are explicit
    switches (``critic_learning_rate``, ``target_policy_smoothing``, ``clipped_double_q``) so that DDPG and the
    paper's ablations are presets (:mod:`sb3_td3x.td3x.presets`). Departures from SB3's TD3 and from the paper are
    listed in ``docs/departures.md``.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, MultiInputPolicy, or a policy class)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: learning rate for Adam; used for the actor, and for the critics unless
        ``critic_learning_rate`` is given. It can be a function of the current progress remaining (from 1 to 0)
    :param buffer_size: size of the replay buffer
    :param learning_starts: how many steps of the model to collect transitions for before learning starts
    :param batch_size: Minibatch size for each gradient update
    :param tau: the soft update coefficient ("Polyak update", between 0 and 1)
    :param gamma: the discount factor, in [0, 1]
    :param train_freq: Update the model every ``train_freq`` steps. Alternatively pass a tuple of frequency and unit
        like ``(5, "step")`` or ``(2, "episode")``.
    :param gradient_steps: How many gradient steps to do after each rollout (see ``train_freq``).
        ``-1`` means as many gradient steps as steps done in the environment during the rollout.
    :param action_noise: the action noise added to the actor's actions for exploration (None by default)
    :param replay_buffer_class: Replay buffer class to use (for instance ``HerReplayBuffer``).
        If ``None``, it will be automatically selected.
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation.
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
    :param n_steps: n-step returns when ``replay_buffer_class`` is ``None``: the tensor buffer's, the same as SB3's
        ``NStepReplayBuffer`` (SB3's ``NStepReplayBuffer`` itself for observations it does not store)
    :param policy_delay: the actor and the target networks are updated once every ``policy_delay`` gradient steps
        (the critics at every step). ``1`` turns delayed policy updates off.
    :param target_policy_noise: Standard deviation sigma~ of the Gaussian target policy smoothing noise
    :param target_noise_clip: Limit c for the absolute value of the target policy smoothing noise
    :param stats_window_size: Window size for the rollout logging
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation (``net_arch``, ``n_critics``...)
    :param verbose: Verbosity level: 0 for no output, 1 for info messages, 2 for debug messages
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run. "auto" picks the GPU if there is one.
    :param critic_learning_rate: learning rate (or schedule) of the critics' optimizer;
        ``None`` uses ``learning_rate`` as SB3's TD3 does
    :param target_policy_smoothing: add clipped Gaussian noise to the target action (step 6). ``False`` gives
        DDPG's target action a' = pi_phi'(s')
    :param clipped_double_q: use the minimum over the critic targets in the TD target (step 8). ``False`` uses the
        first critic target only, as DDPG does
    :param bf16: opt-in: the forward passes of the update under bf16 autocast (AMX on recent x86 CPUs, tensor cores on
        GPUs), with fp32 weights, gradients, optimizer states and losses. A CPU without AMX runs them slower than fp32
        (in software without AVX512-BF16, tens of times slower; with AVX512-BF16 alone, measured slower): TD3X warns there
    :param compile_update: run the update (steps 5 to 15: the hooks as written, both optimizer steps included) as one
        ``torch.compile`` graph (:class:`~sb3_td3x.td3x.update_paths.compiled.CompiledUpdate`). ``None`` (auto, the
        default) compiles on a CPU or a GPU, in fp32, with a C++ compiler, for a run of at least
        :attr:`compile_auto_min_steps` training steps (:func:`~sb3_td3x.td3x.update_paths.compiled.why_not_compile`:
        the machine and the run, never the code); ``True`` compiles any run, ``False`` none. Code Dynamo cannot put in
        one graph runs eagerly, with the reason. ``update_compiled``, ``compile_reason``, ``update_path`` and
        ``update_reason`` say what ran and why (logged once; docs/how_it_is_fast.md)
    :param cuda_graph: on a GPU, ``None`` (auto) runs the compiled update in CUDA graphs (``reduce-overhead``);
        ``True`` captures ``gradient_step`` as it is in CUDA graphs of its own
        (:class:`~sb3_td3x.td3x.update_paths.cuda_graph.GraphedGradientStep`: what the hooks decide in Python is
        decided once, at the capture; an error on a CPU); ``False`` never uses graphs (``cuda_graph_reason`` says why)
    :param flush_denormals: on a CPU, flush denormal floats to zero during ``train()`` on every torch thread
        (:func:`~sb3_td3x.common.denormals.flush_denormals`): Adam's second moment makes them from tiny gradients, and
        each costs a hundred cycles; the process's setting is restored after each call
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    #: The names of the hooks, steps 4 to 15 (:data:`sb3_td3x.td3x.hooks.HOOKS`).
    hook_names: ClassVar[tuple[str, ...]] = HOOK_NAMES
    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: TD3XPolicy
    #: ``compile_update=None`` (auto) compiles a run of at least this many training steps (``total_timesteps`` less
    #: ``learning_starts``): on a 2-core AMD EPYC the compiled update saves about 0.5 ms per step against the eager
    #: hooks (Hopper-v5, 400-300 networks), and its compilation costs 34 s cold, 4 s with Inductor's cache warm
    #: (docs/performance.md).
    compile_auto_min_steps: ClassVar[int] = 100_000

    def __init__(
        self,
        policy: str | type[TD3XPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-3,
        buffer_size: int = 1_000_000,  # 1e6
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        policy_delay: int = 2,
        target_policy_noise: float = 0.2,
        target_noise_clip: float = 0.5,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        critic_learning_rate: float | Schedule | None = None,
        target_policy_smoothing: bool = True,
        clipped_double_q: bool = True,
        bf16: bool = False,
        compile_update: bool | None = None,
        cuda_graph: bool | None = None,
        flush_denormals: bool = True,
        _init_setup_model: bool = True,
    ):
        self._check_hyperparameters(**locals())  # each range check takes its argument by name
        env = self._checked_env(env, verbose)
        super().__init__(
            policy, env, learning_rate, buffer_size, learning_starts, batch_size, tau, gamma, train_freq, gradient_steps,
            action_noise=action_noise, replay_buffer_class=replay_buffer_class, replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage, n_steps=n_steps, policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size, tensorboard_log=tensorboard_log, verbose=verbose, device=device, seed=seed,
            sde_support=False, supported_action_spaces=None, support_multi_env=True)  # fmt: skip
        self.policy_delay = policy_delay
        self.target_noise_clip = target_noise_clip
        self.target_policy_noise = target_policy_noise
        self.critic_learning_rate = critic_learning_rate
        self.target_policy_smoothing = target_policy_smoothing
        self.clipped_double_q = clipped_double_q
        self.bf16 = bf16
        self.compile_update = compile_update  # what was asked: None (auto), True or False; saved with the model
        self.update_compiled = False  # whether the update is compiled: decided at the first train() of a learn()
        self.compile_reason: str | None = None
        self.cuda_graph_request = cuda_graph  # what was asked: None (auto), True or False; saved with the model
        self.cuda_graph = False  # whether the update runs in CUDA graphs: decided by _setup_model
        self.flush_denormals = flush_denormals
        self._n_actor_updates = 0  # actor (delayed) updates done so far; saved with the model
        self._check_cuda_graph_setup()
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------------------------------------------------
    # Set-up (steps 1-3: replay buffer, actor, critics and their targets)
    # ------------------------------------------------------------------------------------------------------------
    def set_random_seed(self, seed: int | None = None) -> None:
        """SB3's, which seeds the global generators: into the model's own streams when they are detached."""
        streams = self.__dict__.get("random_streams")
        with streams.installed() if streams is not None else contextlib.nullcontext():
            super().set_random_seed(seed)

    def _link_replay_buffer_streams(self) -> None:
        if isinstance(self.replay_buffer, TensorReplayBuffer):
            self.replay_buffer.random_streams = self.random_streams  # step 4's indices

    def _check_cuda_graph_setup(self) -> None:
        if self.cuda_graph_request is not True:
            return
        if self.device.type != "cuda":
            raise ValueError(f"cuda_graph=True needs a CUDA device, got device={self.device}; use device='cuda'.")
        if self.compile_update is True:
            raise ValueError("cuda_graph=True and compile_update=True are exclusive: choose one.")

    @classmethod
    def _checked_env(cls, env: GymEnv | str | None, verbose: int) -> GymEnv | None:
        """The env made as SB3 makes it, its action space checked here: SB3 only asserts on one TD3 cannot act in."""
        env = maybe_make_env(env, verbose)
        if env is not None:  # None: a saved model loading without its env
            cls._check_action_space(env.action_space)
        return env

    @staticmethod
    def _check_action_space(action_space: spaces.Space) -> None:
        if not isinstance(action_space, spaces.Box):
            raise UnsupportedActionSpace(
                f"TD3X needs a continuous action space (gymnasium.spaces.Box), got {action_space!r}. "
                "For discrete actions use DQN, or wrap the env so that it takes continuous actions."
            )
        if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
            raise UnsupportedActionSpace(
                f"TD3X needs a bounded action space, got low={action_space.low}, high={action_space.high}. "
                "Wrap the env with gymnasium.wrappers.RescaleAction or give the action space finite bounds."
            )

    @classmethod
    def _check_hyperparameters(cls, **values: Any) -> None:
        """Fail at construction, with a message naming the parameter and its allowed range."""
        problems = cls.hyperparameter_problems(**values)
        if problems:
            name, allowed = problems[0]
            raise ValueError(f"TD3X: invalid {name}={values[name]!r}; {name} must be {allowed}.")
        noise = values["action_noise"]  # an object (not in the configs' checks): SB3 would fail at learn()'s first step
        if noise is not None and not (callable(noise) and callable(getattr(noise, "reset", None))):
            raise ValueError(
                f"TD3X: invalid action_noise={noise!r}; action_noise must be None or an ActionNoise such as "
                "stable_baselines3.common.noise.NormalActionNoise(mean=np.zeros(n_actions), sigma=0.1 * np.ones(n_actions))."
            )

    @staticmethod
    def hyperparameter_problems(**values: Any) -> list[tuple[str, str]]:
        """The constructor's range checks, the one source of truth (the experiment configs use them too): a list of
        ``(name, what it must be)`` for each invalid value among ``values`` (every checked argument must be given)."""

        def number(x: Any) -> bool:
            return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)

        def integer(x: Any, least: int) -> bool:
            return isinstance(x, (int, np.integer)) and not isinstance(x, bool) and x >= least

        def rate(x: Any) -> bool:
            return (number(x) and math.isfinite(x) and x > 0) or (callable(x) and not number(x))

        def fraction(x: Any) -> bool:
            return number(x) and 0.0 <= x <= 1.0

        def non_negative(x: Any) -> bool:
            return number(x) and math.isfinite(x) and x >= 0

        def switch(x: Any) -> bool:
            return x is None or flag(x)

        def flag(x: Any) -> bool:  # a string such as "False" would be taken as true
            return isinstance(x, (bool, np.bool_))

        def frequency(x: Any) -> bool:  # SB3's forms: n, (n, "step" or "episode"), or its TrainFreq (a named tuple)
            if not isinstance(x, tuple):
                return integer(x, 1)
            return len(x) == 2 and integer(x[0], 1) and str(getattr(x[1], "value", x[1])) in ("step", "episode")

        schedule = "a positive finite float or a schedule (a callable of the progress remaining)"
        noise = "a finite float >= 0 (use target_policy_smoothing=False to switch smoothing off)"
        checks = (
            ("learning_rate", rate, schedule),
            ("critic_learning_rate", lambda x: x is None or rate(x), f"None (the actor's) or {schedule}"),
            ("buffer_size", lambda x: integer(x, 1), "an integer >= 1"),
            ("learning_starts", lambda x: integer(x, 0), "an integer >= 0"),
            ("batch_size", lambda x: integer(x, 1), "an integer >= 1"),
            ("tau", fraction, "a float in [0, 1]"),
            ("gamma", fraction, "a float in [0, 1]"),
            ("train_freq", frequency, "an integer >= 1, or (n, 'step') or (n, 'episode') with n >= 1"),
            ("gradient_steps", lambda x: integer(x, -1),
             "an integer >= 0, or -1 (as many gradient steps as environment steps)"),
            ("n_steps", lambda x: integer(x, 1), "an integer >= 1"),
            ("policy_delay", lambda x: integer(x, 1), "an integer >= 1 (1 updates the actor at every gradient step)"),
            ("target_policy_noise", non_negative, noise),
            ("target_noise_clip", non_negative, noise),
            ("optimize_memory_usage", flag, "True or False"),
            ("target_policy_smoothing", flag, "True or False"),
            ("clipped_double_q", flag, "True or False"),
            ("bf16", flag, "True or False (True: the update's forward passes under bf16 autocast)"),
            ("flush_denormals", flag, "True or False"),
            ("compile_update", switch, "None (auto: compiled on a long run, on a CPU or in CUDA graphs), True or False"),
            ("cuda_graph", switch, "None (auto: a GPU's compiled update in CUDA graphs), True or False"),
        )
        return [(name, allowed) for name, ok, allowed in checks if not ok(values[name])]

    def _setup_model(self) -> None:
        if self.replay_buffer_class is None and isinstance(self.observation_space, spaces.Box):
            # Step 1: the replay buffer, kept as tensors on the training device (SB3's other buffers otherwise), with
            # n-step returns as SB3 sets up its NStepReplayBuffer.
            self.replay_buffer_class = TensorReplayBuffer
            if self.n_steps > 1:
                self.replay_buffer_kwargs.update({"n_steps": self.n_steps, "gamma": self.gamma})
        self._check_replay_buffer_options()
        request = self.cuda_graph_request
        # cuda_graph=True's graphs of their own (auto's are torch.compile's, inside the compiled update).
        self.cuda_graph = request is True and self.device.type == "cuda"
        if request is True and not self.cuda_graph:
            # Construction on a CPU already failed (__init__); this is a GPU-trained model loaded without a GPU.
            warnings.warn(f"cuda_graph=True needs a CUDA device, got {self.device}: training steps run eagerly instead.")
        if self.bf16 and (slow_bf16 := bf16_on_cpu_warning(self.device)) is not None:
            warnings.warn(slow_bf16)
        optimizer_kwargs = dict(self.policy_kwargs.get("optimizer_kwargs") or {})
        if self.cuda_graph:
            # CUDA graphs need the optimizer's step counter on the device.
            optimizer_kwargs["capturable"] = True
        else:
            optimizer_kwargs.pop("capturable", None)
        if optimizer_kwargs or "optimizer_kwargs" in self.policy_kwargs:
            self.policy_kwargs["optimizer_kwargs"] = optimizer_kwargs
        # Steps 2 and 3: the networks of the hooks a subclass overrides (SB3's own otherwise, so that a seeded TD3X
        # draws SB3's initial weights).
        builders = {role: getattr(self, hook) for role, hook in (("actor", "actor_network"), ("critic", "q_network"))
                    if changed_hooks(self, (hook,))}  # fmt: skip
        buffer_class = self.replay_buffer_class
        takes_n_steps = isinstance(buffer_class, type) and issubclass(buffer_class, (TensorReplayBuffer, NStepReplayBuffer))
        with networks_built_by(builders), warnings.catch_warnings():
            if takes_n_steps and self.replay_buffer_kwargs.get("n_steps") == self.n_steps:
                # SB3 warns that a replay_buffer_class of one's own ignores n_steps: this one takes it (and a model saved
                # with SB3's NStepReplayBuffer, loaded, has it as its class).
                warnings.filterwarnings("ignore", message=r"`n_steps=\d+` is ignored because a custom `replay_buffer_class`")
            super()._setup_model()
        # The generators TD3X's own code draws from: the global ones, as SB3's, until a SeedBatch detaches them.
        self.random_streams = RandomStreams(self.device)
        self._link_replay_buffer_streams()
        self._step_fn: Any = None
        # Which update train() runs and why, set at its first call (update_paths.choose.choose_update): "eager" (the
        # hooks as written), "compiled" (the same, one torch.compile graph) or "cuda_graph" (cuda_graph=True).
        self.update_path: str | None = None
        self.update_reason: str | None = None
        self._create_aliases()
        self._critic_lr_schedule = None if self.critic_learning_rate is None else FloatSchedule(self.critic_learning_rate)
        update_learning_rate(self.critic.optimizer, self.critic_lr_schedule(1))
        if request is None:
            on_gpu = "a compiled update runs in torch.compile's CUDA graphs" if self.device.type == "cuda" else "no CUDA device"
            self._use_cuda_graph(False, f"cuda_graph=None (auto): {on_gpu}")
        elif request and not self.cuda_graph:
            self._use_cuda_graph(False, f"cuda_graph=True, but no CUDA device ({self.device})")
        elif request and (why := why_not_capture(self)) is not None:
            raise ValueError(f"cuda_graph=True cannot capture this model's gradient step: {why}.")
        else:
            self._use_cuda_graph(request, f"cuda_graph={request}: gradient_step as it is, captured in CUDA graphs")

    def _check_replay_buffer_options(self) -> None:
        """Prioritised sampling and n-step returns are options of TD3X's tensor buffer: a clear error where another
        buffer would receive them."""
        options = sorted({"alpha", "beta", "min_priority", "max_priority_reset_interval"} & self.replay_buffer_kwargs.keys())
        buffer_class = self.replay_buffer_class
        if options and not (isinstance(buffer_class, type) and issubclass(buffer_class, TensorReplayBuffer)):
            name = "SB3's choice for these observations" if buffer_class is None else buffer_class.__name__
            raise ValueError(
                f"replay_buffer_kwargs {options}: prioritised sampling is an option of TD3X's TensorReplayBuffer, which "
                f"stores Box observations, but the replay buffer is {name} (observation space {self.observation_space})."
            )

    def _setup_learn(self, *args: Any, **kwargs: Any) -> tuple[int, Any]:
        """SB3's, after checking that the critic loss takes the importance weights the replay buffer samples."""
        weighted = getattr(self.replay_buffer, "prioritized", False) and getattr(self.replay_buffer, "beta", 0)
        if weighted and "weights" not in inspect.signature(self.critic_loss).parameters:
            raise ValueError(
                f"The replay buffer samples importance weights (beta={self.replay_buffer.beta}), but the critic_loss of "
                f"{type(self).__name__} takes no `weights`: add a `weights=None` argument (shape (batch_size, 1)) and "
                "weigh each transition's loss by it, or set beta=0."
            )
        return super()._setup_learn(*args, **kwargs)

    def _use_cuda_graph(self, on: bool, reason: str) -> None:
        """Set the model up for gradient steps in CUDA graphs (``on``) or eager ones, and record it with ``reason``.

        Graphs need Adam's step counters on the device (``capturable=True``: set in the param groups before the first
        step, or after a state is loaded), the learning rates in device tensors (a float would be baked into the
        graphs; :meth:`_update_learning_rate` fills them in place) and the replay buffer sampled from bounds kept in
        device tensors. Eager steps take floats, ``capturable=False`` and SB3's sampling: what ``cuda_graph=False``
        builds. Called by ``_setup_model`` and after loading parameters.
        """
        self.cuda_graph, self.cuda_graph_reason = on, reason
        schedules = {self.actor.optimizer: self.lr_schedule, self.critic.optimizer: self.critic_lr_schedule}
        for optimizer, schedule in schedules.items():
            if "capturable" in optimizer.defaults:  # Adam, AdamW and the like; never added to an optimizer without it
                optimizer.defaults["capturable"] = on
            for group in optimizer.param_groups:
                if "capturable" in group:
                    group["capturable"] = on
                if on and not isinstance(group["lr"], th.Tensor):
                    group["lr"] = th.tensor(float(group["lr"]), device=self.device)
                elif not on and isinstance(group["lr"], th.Tensor):
                    # From the schedule, as _update_learning_rate sets it: the tensor holds it rounded to float32.
                    group["lr"] = schedule(self._current_progress_remaining)
        buffer = self.replay_buffer
        if isinstance(buffer, TensorReplayBuffer) and on != buffer.static_sampling:
            buffer.enable_static_sampling() if on else buffer.disable_static_sampling()

    @property
    def critic_lr_schedule(self) -> Schedule:
        """The critics' learning-rate schedule: ``critic_learning_rate``'s, or the actor's when it is None."""
        schedule = self.__dict__.get("_critic_lr_schedule")
        return self.lr_schedule if schedule is None else schedule

    @critic_lr_schedule.setter
    def critic_lr_schedule(self, schedule: Schedule | None) -> None:
        self._critic_lr_schedule = schedule

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.actor_target = self.policy.actor_target
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target
        # Target networks only ever change through the Polyak update: they never need gradients.
        self.actor_target.requires_grad_(False)
        self.critic_target.requires_grad_(False)
        # Parameters and batch-norm running statistics, in matching order, for the Polyak updates.
        self._actor_params = list(self.actor.parameters())
        self._actor_target_params = list(self.actor_target.parameters())
        self._critic_params = list(self.critic.parameters())
        self._critic_target_params = list(self.critic_target.parameters())
        self._actor_batch_norm_stats = get_parameters_by_name(self.actor, ["running_"])
        self._actor_batch_norm_stats_target = get_parameters_by_name(self.actor_target, ["running_"])
        self._critic_batch_norm_stats = get_parameters_by_name(self.critic, ["running_"])
        self._critic_batch_norm_stats_target = get_parameters_by_name(self.critic_target, ["running_"])

    # Steps 2-3: the networks ----------------------------------------------------------------------------------
    def actor_network(
        self, features_dim: int, action_dim: int, net_arch: list[int], activation_fn: type[th.nn.Module]
    ) -> th.nn.Module:
        """Step 2: the network of the actor pi_phi (and of its target), from the features of s to an action in
        [-1, 1]: SB3's MLP, ``Linear, activation, ..., Linear, Tanh``. The policy calls it for the actor's ``mu`` when
        a subclass overrides it; otherwise SB3's ``Actor`` builds this very network itself (the same initial weights
        from a seed as SB3's TD3).

        :param features_dim: the width of the features extractor's output
        :param action_dim: the number of action dimensions
        :param net_arch: the widths of the hidden layers (``policy_kwargs["net_arch"]``, the actor's)
        :param activation_fn: the hidden layers' activation (``policy_kwargs["activation_fn"]``)
        :return: a module mapping (batch_size, features_dim) to (batch_size, action_dim)
        """
        return th.nn.Sequential(*create_mlp(features_dim, action_dim, net_arch, activation_fn, squash_output=True))

    def q_network(self, input_dim: int, net_arch: list[int], activation_fn: type[th.nn.Module]) -> th.nn.Module:
        """Step 3: the network of one critic Q_theta_i (and of its target), from the features of s joined with a to
        the critic's output: SB3's MLP, ``Linear, activation, ..., Linear`` to one value. Called ``n_critics`` times
        for the critics and again for their targets when a subclass overrides it; otherwise SB3's
        ``ContinuousCritic`` builds this network itself. A LayerNorm critic is
        ``create_mlp(..., post_linear_modules=[nn.LayerNorm])``; a distributional one returns one logit per atom.

        :param input_dim: features_dim + action_dim
        :param net_arch: the widths of the hidden layers (the critics')
        :param activation_fn: the hidden layers' activation
        :return: a module mapping (batch_size, input_dim) to (batch_size, 1) (or the width the other hooks expect)
        """
        return th.nn.Sequential(*create_mlp(input_dim, 1, net_arch, activation_fn))

    # ------------------------------------------------------------------------------------------------------------
    # The training loop: a short list of named steps
    # ------------------------------------------------------------------------------------------------------------
    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        # Detached streams (a SeedBatch's) as the global ones, for hooks that draw from those.
        with self.random_streams.installed():
            self._train(gradient_steps, batch_size)

    def _train(self, gradient_steps: int, batch_size: int) -> None:
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])

        # Detached tensors, averaged once after the loop: no host-device synchronisation per gradient step.
        critic_infos: list[dict[str, th.Tensor]] = []
        actor_infos: list[dict[str, th.Tensor]] = []
        step = self._gradient_step_fn()
        with denormals.flush_denormals(self.device.type == "cpu" and getattr(self, "flush_denormals", True)):
            for _ in range(gradient_steps):
                self._n_updates += 1
                update_actor = self.should_update_actor(self._n_updates)  # step 13: delayed policy updates
                critic_info, actor_info = step(batch_size, update_actor)
                critic_infos.append(critic_info)
                if update_actor:
                    self._n_actor_updates += 1
                    actor_infos.append(actor_info)

        self._log_train_infos(critic_infos, actor_infos)
        if self.device.type == "cpu":  # threads that wait for cores held by other work: said once
            if "_core_waits" not in self.__dict__:
                self._core_waits = CoreWaits()
            self._core_waits.warn_once()

    def gradient_step(self, batch_size: int, update_actor: bool) -> tuple[dict[str, th.Tensor], dict[str, th.Tensor]]:
        """One gradient step: steps 4 to 15 in order; the actor and the targets only when ``update_actor``.

        :return: the detached statistics of the critic loss and of the actor loss (empty without actor update)
        """
        batch = self.sample_batch(batch_size)  # step 4
        return self.update_from_batch(batch, update_actor)  # steps 5-15

    def update_from_batch(
        self, batch: ReplayBufferSamples, update_actor: bool
    ) -> tuple[dict[str, th.Tensor], dict[str, th.Tensor]]:
        """Steps 5 to 15 on a sampled batch: critic update, then (when ``update_actor``) actor and target updates.

        A batch with importance weights (``batch.weights``, prioritised sampling with ``beta > 0``) passes them to
        :meth:`critic_loss` as ``weights=``; any other calls it with two arguments, as always.
        """
        with self._autocast():
            target_q = self.compute_target_q(batch)  # steps 5-9
            current_q = self.current_q_values(batch)  # step 10
        weights = getattr(batch, "weights", None)
        if weights is None:
            critic_loss, critic_info = self.critic_loss(current_q, target_q)  # step 11
        else:
            critic_loss, critic_info = self.critic_loss(current_q, target_q, weights=weights)
        self.optimize_critic(critic_loss)  # step 12
        self.update_priorities(batch, current_q, target_q)  # a prioritised buffer's new priorities
        if not update_actor:
            return critic_info, {}
        with self._autocast():
            actor_loss, actor_info = self.actor_loss(batch.observations)  # step 13
        self.optimize_actor(actor_loss)
        self.update_critic_target()  # step 15
        self.update_actor_target()  # step 14
        return critic_info, actor_info

    def _autocast(self) -> contextlib.AbstractContextManager:
        return autocast_context(self.device, self.bf16, cache=not self.cuda_graph)

    def _gradient_step_fn(self) -> Callable[[int, bool], tuple[dict[str, th.Tensor], dict[str, th.Tensor]]]:
        """The gradient step ``train()`` runs, chosen once (:func:`~sb3_td3x.td3x.update_paths.choose.choose_update`)
        and logged: the hooks eagerly, compiled or in CUDA graphs (``update_path``, ``update_reason``)."""
        # Chosen again when a hook is set on the instance, or a network, an optimizer, the replay buffer or the
        # VecNormalize wrapper is replaced after the choice (a cheap check per train() call; changes inside a module
        # after the first train() are not seen: set them before it).
        watched = (self.actor, self.critic, self.actor_target, self.critic_target, self._instance_hooks(),
                   self.actor.optimizer, self.critic.optimizer, self.replay_buffer, self._vec_normalize_env,
                   compile_watch(self))  # fmt: skip
        chosen_for = self.__dict__.get("_step_fn_for")  # None for a step set from outside (tests): kept
        if self._step_fn is None or (chosen_for is not None and chosen_for != watched):
            choice = choose_update(self)
            self.update_path, self.update_reason, self._step_fn = choice.path, choice.reason, choice.step
            self._step_fn_for = watched
            _, exploration, exploration_reason = self._exploration()
            self.logger.info(f"update: {self.update_path} ({self.update_reason}); exploration: {exploration} ({exploration_reason})")
        return self._step_fn

    def _instance_hooks(self) -> tuple[tuple[str, Any], ...]:
        """The hooks set on this instance (``model.td_target = fn``), with what they are set to."""
        return tuple((name, self.__dict__[name]) for name in HOOK_NAMES if name in self.__dict__)

    # Step 4 ------------------------------------------------------------------------------------------------------
    def sample_batch(self, batch_size: int) -> ReplayBufferSamples:
        """Step 4: sample a batch of transitions (s, a, r, s', d) from the replay buffer."""
        return self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr,return-value]

    # Steps 5-9 ---------------------------------------------------------------------------------------------------
    @th.no_grad()
    def compute_target_q(self, batch: ReplayBufferSamples) -> th.Tensor:
        """Steps 5 to 9: the critics' regression target y, without gradient. Returns shape (batch_size, 1)."""
        next_actions = self.target_actions(batch.next_observations)  # steps 5-6
        next_q = self.next_q_values(batch.next_observations, next_actions)  # step 7
        next_q = self.clipped_double_q_value(next_q)  # step 8
        # For n-step replay, the discount is gamma ** n (when no early termination)
        discounts = batch.discounts if getattr(batch, "discounts", None) is not None else self.gamma
        return self.td_target(batch.rewards, batch.dones, discounts, next_q)  # step 9

    def target_actions(self, next_observations: Obs) -> th.Tensor:
        """Steps 5 and 6: a' = clip(pi_phi'(s') + eps, -1, 1) with eps the target policy smoothing noise.

        Actions live in the policy's normalised space, so the environment's bounds are [-1, 1].
        """
        next_actions = self.actor_target(next_observations)  # (batch_size, action_dim)
        if self.target_policy_smoothing:
            next_actions = next_actions + self.target_policy_smoothing_noise(next_actions)
        return next_actions.clamp(-1.0, 1.0)

    def target_policy_smoothing_noise(self, actions: th.Tensor) -> th.Tensor:
        """Step 6: eps = clip(N(0, sigma~), -c, c), drawn with the shape of the batch of actions (paper eq. 14)."""
        noise = th.randn_like(actions) * self.target_policy_noise
        return noise.clamp(-self.target_noise_clip, self.target_noise_clip)

    def next_q_values(self, next_observations: Obs, next_actions: th.Tensor) -> th.Tensor:
        """Step 7: Q'_i(s', a') for every critic target. Returns shape (n_critics, batch_size, 1)."""
        return self.critic_target.q_values(next_observations, next_actions)

    def clipped_double_q_value(self, next_q: th.Tensor) -> th.Tensor:
        """Step 8: min_i Q'_i(s', a') (clipped double Q-learning, paper eq. 10), or Q'_1 when it is switched off.

        :param next_q: shape (n_critics, batch_size, 1)
        :return: shape (batch_size, 1)
        """
        if self.clipped_double_q:
            return next_q.min(dim=0).values
        return next_q[0]

    def td_target(
        self, rewards: th.Tensor, dones: th.Tensor, discounts: th.Tensor | float, next_q: th.Tensor
    ) -> th.Tensor:
        """Step 9: y = r + gamma * (1 - d) * min_i Q'_i(s', a'). All tensors of shape (batch_size, 1)."""
        not_done = 1.0 - dones
        return rewards + not_done * discounts * next_q

    # Steps 10-12 -------------------------------------------------------------------------------------------------
    def current_q_values(self, batch: ReplayBufferSamples) -> th.Tensor:
        """Step 10: Q_i(s, a) for every critic. Returns shape (n_critics, batch_size, 1)."""
        return self.critic.q_values(batch.observations, batch.actions)

    def q_value_estimates(self, batch: ReplayBufferSamples) -> th.Tensor:
        """The critics' estimates of Q(s, a) as numbers, shape (n_critics, batch_size, 1): what measures of the critics
        read (overestimation). Not a step of the update: :meth:`current_q_values` for TD3's critics; a critic whose
        output is not the value (a distributional one: its logits) gives its expectation instead."""
        return self.current_q_values(batch)

    def critic_loss(
        self, current_q: th.Tensor, target_q: th.Tensor, weights: th.Tensor | None = None
    ) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        """Step 11: L(theta) = sum_i MSE(Q_i(s, a), y), the sum over critics of the mean squared TD error.

        :param current_q: shape (n_critics, batch_size, 1)
        :param target_q: shape (batch_size, 1), no gradient
        :param weights: importance-sampling weights of a prioritised batch, shape (batch_size, 1): each squared error
            is weighted by its transition's. Passed only where the batch has them (``beta > 0``), so an override with
            two arguments keeps working everywhere else
        :return: the loss and detached statistics for logging
        """
        # In fp32 also under bf16 autocast (a no-op otherwise)
        td_errors = current_q.float() - target_q.float().unsqueeze(0)  # (n_critics, batch_size, 1)
        squared = td_errors.pow(2) if weights is None else td_errors.pow(2) * weights.float()
        loss = squared.mean(dim=(1, 2)).sum()
        info = {"critic_loss": loss.detach(), "target_q": target_q.float().mean()}
        q_means = current_q.detach().float().mean(dim=(1, 2))  # (n_critics,)
        for i in range(current_q.shape[0]):
            info[f"q{i + 1}"] = q_means[i]
        return loss, info

    def optimize_critic(self, loss: th.Tensor) -> None:
        """Step 12: one gradient step of the critics' optimizer on the critic loss (:func:`~sb3_td3x.td3x.optim.minimize`:
        ``zero_grad``, ``backward``, ``step``, and the same step when the update is compiled)."""
        minimize(self.critic.optimizer, loss)

    @th.no_grad()
    def update_priorities(self, batch: ReplayBufferSamples, current_q: th.Tensor, target_q: th.Tensor) -> None:
        """After step 12, for a prioritised replay buffer: the batch's new priorities, max_i |Q_i(s, a) - y| (TD7's
        LAP, sfujim/TD7 TD7.py lines 252 and 262), written with
        :meth:`~sb3_td3x.common.buffers.TensorReplayBuffer.update_priorities`, which raises them to the buffer's
        ``alpha``. Does nothing for a batch without ``indices`` or a buffer that samples uniformly.

        :param batch: the batch of steps 5 to 11 (``batch.indices``: its rows in the buffer)
        :param current_q: shape (n_critics, batch_size, 1), as given to :meth:`critic_loss`
        :param target_q: shape (batch_size, 1)
        """
        indices = getattr(batch, "indices", None)
        if indices is None or not getattr(self.replay_buffer, "prioritized", False):
            return
        td_errors = (current_q.detach().float() - target_q.float().unsqueeze(0)).abs()  # (n_critics, batch_size, 1)
        self.replay_buffer.update_priorities(indices, td_errors.amax(dim=0).squeeze(1))  # type: ignore[union-attr]

    # Step 13 -----------------------------------------------------------------------------------------------------
    def should_update_actor(self, n_updates: int) -> bool:
        """Step 13 (delayed policy updates): update the actor and the targets once every ``policy_delay`` steps."""
        return n_updates % self.policy_delay == 0

    def actor_loss(self, observations: Obs) -> tuple[th.Tensor, dict[str, th.Tensor]]:
        """Step 13: J(phi) = -mean Q_1(s, pi_phi(s)) (deterministic policy gradient, paper eq. 6).

        The gradient reaches the actor's parameters only (:meth:`optimize_actor` asks for those): the critic gets none
        (a features extractor shared with the actor, ``share_features_extractor=True``, is the actor's and trains).
        """
        loss = -self.critic.q1_forward(observations, self.actor(observations)).float().mean()
        return loss, {"actor_loss": loss.detach()}

    def optimize_actor(self, loss: th.Tensor) -> None:
        """Step 13: one gradient step of the actor's optimizer on the actor loss (:func:`~sb3_td3x.td3x.optim.minimize`):
        the gradient of the loss with respect to the actor's parameters only."""
        minimize(self.actor.optimizer, loss)

    # Steps 14-15 -------------------------------------------------------------------------------------------------
    @th.no_grad()
    def update_actor_target(self) -> None:
        """Step 14: phi' <- tau * phi + (1 - tau) * phi', and copy the batch-norm running statistics."""
        self._polyak(self._actor_params, self._actor_target_params, self.tau)
        self._polyak(self._actor_batch_norm_stats, self._actor_batch_norm_stats_target, 1.0)

    @th.no_grad()
    def update_critic_target(self) -> None:
        """Step 15: theta'_i <- tau * theta_i + (1 - tau) * theta'_i, and copy the batch-norm running statistics."""
        self._polyak(self._critic_params, self._critic_target_params, self.tau)
        self._polyak(self._critic_batch_norm_stats, self._critic_batch_norm_stats_target, 1.0)

    @staticmethod
    def _polyak(params: list[th.Tensor], target_params: list[th.Tensor], tau: float) -> None:
        """target <- target + tau * (param - target), in place, in one fused call for all the tensors."""
        if len(params) != len(target_params):
            raise RuntimeError(f"Polyak update: {len(params)} parameters but {len(target_params)} target parameters")
        if params:
            th._foreach_lerp_(target_params, params, tau)

    # ------------------------------------------------------------------------------------------------------------
    # Collection: the exploration policy
    # ------------------------------------------------------------------------------------------------------------
    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """The exploration action a = clip(pi(s) + noise, -1, 1) in the normalised action space, and its env scaling.

        The same actions as SB3's ``_sample_action`` (uniform random before ``learning_starts``), pi(s) computed by
        calling the actor module on the observation instead of ``predict()`` followed by ``scale_action()``, where
        SB3's predict path is as written (:meth:`_exploration`); SB3's own method otherwise.
        """
        action_noise = self._own_stream_noise(action_noise)
        if self.num_timesteps < learning_starts or not isinstance(self._last_obs, np.ndarray):
            return super()._sample_action(learning_starts, action_noise, n_envs)  # type: ignore[arg-type]
        actor = self._exploration()[0]
        if actor is None:  # the predict path is the user's: SB3's own
            return super()._sample_action(learning_starts, action_noise, n_envs)  # type: ignore[arg-type]
        prefetched = self.__dict__.pop("_prefetched_action", None)  # pi(s) computed with other seeds' (SeedBatch)
        if prefetched is not None and prefetched.valid_for(self):
            scaled_action = prefetched.actions
        else:
            with th.no_grad():
                obs = th.as_tensor(self._last_obs, device=self.device).reshape(n_envs, *self.observation_space.shape)
                # (n_envs, *action_shape), in [-1, 1]
                scaled_action = actor(obs).cpu().numpy().reshape((n_envs, *self.action_space.shape))
        if action_noise is not None:
            scaled_action = np.clip(scaled_action + action_noise(), -1, 1)
        return self.policy.unscale_action(scaled_action), scaled_action

    def _own_stream_noise(self, noise: ActionNoise | None) -> Callable[[], np.ndarray] | None:
        """SB3's ``NormalActionNoise`` drawn as it draws it, from the model's numpy stream instead of numpy's global
        generator; any other noise, or any noise while the streams are the global generators, as it is."""
        if type(noise) is not NormalActionNoise or self.random_streams.bound:
            return noise
        return lambda: self.random_streams.numpy.normal(noise._mu, noise._sigma).astype(noise._dtype)

    def _exploration(self) -> tuple[Callable[[th.Tensor], th.Tensor] | None, str, str]:
        """How collection computes pi(s), its name and why (chosen again when the actor is replaced): the actor module
        itself (``"actor"``), or ``None`` (``"sb3_predict"``: SB3's ``_sample_action``) where SB3's predict path is
        the user's (:func:`~sb3_td3x.td3x.update_paths.exploration.why_not_direct`)."""
        cached = self.__dict__.get("_exploration_choice")
        if cached is None or cached[0] is not self.actor:
            why = why_not_direct(self)
            choice = (None, "sb3_predict", why) if why else (self.actor, "actor", "the actor module called directly")
            cached = self._exploration_choice = (self.actor, *choice)
            self.exploration_path = cached[2]
        return cached[1], cached[2], cached[3]

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """SB3's ``_store_transition``, without its per-step deep copy of the observation when nothing needs it.

        The copy only protects ``new_obs`` when terminal observations are written into ``next_obs``; the tensor
        buffer copies what it stores, so the copy is made only on steps where an episode ended.
        """
        if (
            isinstance(replay_buffer, TensorReplayBuffer)
            and self._vec_normalize_env is None
            and isinstance(new_obs, np.ndarray)
            and not np.any(dones)
        ):
            replay_buffer.add(self._last_obs, new_obs, buffer_action, reward, dones, infos)  # type: ignore[arg-type]
            self._last_obs = new_obs
            self._last_original_obs = new_obs
            return
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)

    # ------------------------------------------------------------------------------------------------------------
    # Logging, learning-rate schedules, save/load
    # ------------------------------------------------------------------------------------------------------------
    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        """The actor follows ``learning_rate``; the critics follow ``critic_learning_rate`` when it is set."""
        progress = self._current_progress_remaining
        self.logger.record("train/learning_rate", self.lr_schedule(progress))
        # Read at each call, so that a schedule replaced after construction is followed (as SB3 does).
        critic_schedule = self.critic_lr_schedule
        if critic_schedule is not self.lr_schedule:
            self.logger.record("train/critic_learning_rate", critic_schedule(progress))
        if not isinstance(optimizers, list):
            optimizers = [optimizers]
        for optimizer in optimizers:
            schedule = critic_schedule if optimizer is self.critic.optimizer else self.lr_schedule
            value = schedule(progress)
            for group in optimizer.param_groups:
                if isinstance(group["lr"], th.Tensor):  # cuda_graph: the graphs read it from the device
                    group["lr"].fill_(value)
                else:
                    group["lr"] = value

    def _log_train_infos(self, critic_infos: list[dict[str, th.Tensor]], actor_infos: list[dict[str, th.Tensor]]) -> None:
        """Average the detached statistics of the gradient steps, with one stack and one device-to-host copy."""
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/actor_updates", self._n_actor_updates)
        groups = [(list(infos[0].keys()), infos) for infos in (critic_infos, actor_infos) if infos]
        if not groups:
            return
        values = th.stack([info[key].float() for keys, infos in groups for info in infos for key in keys]).tolist()
        start = 0
        for keys, infos in groups:
            block = values[start : start + len(infos) * len(keys)]  # step after step, keys in order
            for j, key in enumerate(keys):
                name = key if key.endswith("loss") else f"{key}_mean"
                self.logger.record(f"train/{name}", sum(block[j :: len(keys)]) / len(infos))
            start += len(block)

    def learn(
        self: SelfTD3X,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "TD3X",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfTD3X:
        with self.random_streams.installed():  # detached streams (a SeedBatch's model) as the global ones
            return super().learn(
                total_timesteps=total_timesteps,
                callback=callback,
                log_interval=log_interval,
                tb_log_name=tb_log_name,
                reset_num_timesteps=reset_num_timesteps,
                progress_bar=progress_bar,
            )

    @classmethod
    def load(
        cls: type[SelfTD3X],
        path: Any,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfTD3X:
        """SB3's ``load``. The saved ``cuda_graph`` request (``cuda_graph_request``) is decided again for this machine;
        ``cuda_graph=...`` among ``kwargs`` replaces it, as the constructor argument would."""
        if "cuda_graph" in kwargs:
            kwargs["cuda_graph_request"] = kwargs.pop("cuda_graph")
        return super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)

    def set_parameters(
        self, load_path_or_dict: str | TensorDict, exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        """SB3's ``set_parameters``. A loaded optimizer state brings the options it was saved with (``capturable``
        and device learning rates from a run in CUDA graphs, floats from an eager one): they are set back to what
        this model runs. The update is chosen again (graphs captured on the old state tensors would step those)."""
        super().set_parameters(load_path_or_dict, exact_match, device)
        self._use_cuda_graph(self.cuda_graph, self.cuda_graph_reason)
        self._step_fn = self._step_fn_for = None

    def load_replay_buffer(self, path: Any, truncate_last_traj: bool = True) -> None:
        """SB3's ``load_replay_buffer``; where the update runs in CUDA graphs (``cuda_graph``) the new buffer samples
        on the device, and the graphs, captured on the old buffer's tensors, are captured again."""
        super().load_replay_buffer(path, truncate_last_traj)
        self._link_replay_buffer_streams()
        if self.cuda_graph and isinstance(self.replay_buffer, TensorReplayBuffer):
            self.replay_buffer.enable_static_sampling()
        self._step_fn = self._step_fn_for = None

    def _excluded_save_params(self) -> list[str]:
        # The networks' aliases and parameter lists (the policy is saved), the chosen update and its reasons (decided
        # again after loading: cuda_graph from cuda_graph_request and this machine, update_compiled at the first
        # train() from compile_update), and what belongs to this process (random streams, prefetched actions).
        return [
            *super()._excluded_save_params(),
            "actor", "critic", "actor_target", "critic_target", "_critic_lr_schedule", "_step_fn", "_step_fn_for",
            "_exploration_choice", "_prefetched_action", "random_streams", "update_path", "update_reason", "cuda_graph",
            "cuda_graph_reason", "update_compiled", "compile_reason", "exploration_path", "_core_waits",
            "_actor_params", "_actor_target_params", "_critic_params", "_critic_target_params", "_actor_batch_norm_stats",
            "_actor_batch_norm_stats_target", "_critic_batch_norm_stats", "_critic_batch_norm_stats_target",
        ]  # fmt: skip

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "actor.optimizer", "critic.optimizer"]
        return state_dicts, []
