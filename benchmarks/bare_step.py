"""How fast TD3X's gradient step could be with nothing around its kernels: a floor, measured, not a product path.

    python benchmarks/bare_step.py --env Hopper-v5 --batch-size 100 --mode learn    # SBX, TD3X, TD3X with a bare step
    python benchmarks/bare_step.py --mode learn --variants 0 4     # the bare step, and with TD3X's promises kept
    python benchmarks/bare_step.py --env Hopper-v5 --batch-size 100 --mode train    # what each part of TD3X costs

The *bare step* runs steps 4 to 15 of TD3 on the model's own networks with the kernels ``MlpUpdate`` runs (oneDNN's
fused linear for one network's hidden layers, one batched product per layer for both critics, fused Adam, one
``lerp_`` per network stack), written straight through: no hooks, no checks, no seed axis, no statistics but the
critic loss, indices and noise from torch's global generator, Adam's state its own. It learns (it is TD3), but it
is not what TD3X runs, and it skips what TD3X promises (``p.grad`` set, SB3's random streams, the model's
optimizers, the logged statistics): it says how much of a step those promises and the framework cost. With the
promises that change the numbers kept (v3, v4 below) it gives the weights TD3X's update gives
(``tests/unit/test_bare_step.py``): the floor is the same computation.

``--mode learn``: SBX's TD3, TD3X, and TD3X whose gradient step is a bare one (``--variants``, v0 by default), in
one process, chunks of ``learn()`` alternated (collection as TD3X runs it for every TD3X side). ``--mode train``: gradient steps only, the
bare step (v0) and then one promise added at a time: v1 each parameter's ``.grad`` set, v2 the model's own optimizers
(``optimizer.step()``'s kernel), v3 the batch sampled with SB3's random streams (``model.sample_batch``) and the
smoothing noise from the model's stream, v4 the statistics TD3X logs; then TD3X's own update.
Settings are ``benchmarks/throughput.py``'s (400-300, lr 1e-3, 1000 random steps, N(0, 0.1) exploration).
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time

import torch as th
from throughput import make_model, sbx_td3

from sb3_td3x import TD3X
from sb3_td3x.common.torch_internals import fused_adam_kernel
from sb3_td3x.td3x.update_paths.mlp import MlpUpdate, _relu_backward, _tanh_backward, relu_mlp, step_optimizers


class BareStep:
    """Steps 4 to 15 of TD3 on ``model``'s networks (SB3's 2-critic ReLU MLPs, one env), with ``variant`` of the
    promises above (0 to 4)."""

    def __init__(self, model: TD3X, variant: int):
        self.model, self.variant = model, variant
        update = MlpUpdate(model)  # its stacks: the model's parameters as views of one tensor per role
        self.actor, self.actor_target, self.critic, self.critic_target = update._stacks()
        self.critic_params = [t for pair in zip(self.critic.weights, self.critic.biases) for t in pair]
        self.actor_params = [t for net in self.actor.layers for lin in net for t in (lin.weight, lin.bias)]
        self.adam = {
            id(params): ([th.zeros_like(p) for p in params], [th.zeros_like(p) for p in params], th.zeros(len(params)))
            for params in (self.critic_params, self.actor_params)
        }

    def _adam(self, optimizer: th.optim.Optimizer, params: list[th.Tensor], grads: list[th.Tensor]) -> None:
        """The fused Adam kernel with the optimizer's options, on this step's own state (v0, v1)."""
        exp_avgs, exp_avg_sqs, counters = self.adam[id(params)]
        group = optimizer.param_groups[0]
        beta1, beta2 = group["betas"]
        counters.add_(1)
        fused_adam_kernel(False)(params, grads, exp_avgs, exp_avg_sqs, [], list(counters.unbind(0)), lr=group["lr"],
                                 beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"],
                                 amsgrad=False, maximize=False, grad_scale=None, found_inf=None)

    @staticmethod
    def _mlp(layers: list, x: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """MlpUpdate's forward of one network (its kernels): the output and both hidden activations."""
        out, (_, h1, h2) = relu_mlp([lin.weight for lin in layers], [lin.bias for lin in layers], x)
        return out, h1, h2

    @staticmethod
    def _stacked(weights: list[th.Tensor], biases: list[th.Tensor], x: th.Tensor) -> list[th.Tensor]:
        h1 = th.baddbmm(biases[0].unsqueeze(1), x, weights[0].mT).relu_()
        h2 = th.baddbmm(biases[1].unsqueeze(1), h1, weights[1].mT).relu_()
        return [th.baddbmm(biases[2].unsqueeze(1), h2, weights[2].mT), h1, h2]

    def _batch(self, batch_size: int) -> tuple[th.Tensor, ...]:
        if self.variant >= 3:
            b = self.model.sample_batch(batch_size)
            return b.observations, b.actions, b.next_observations, b.rewards, b.dones
        buffer = self.model.replay_buffer
        rows = th.randint(0, buffer.size(), (batch_size,))
        # One env: a row per step; dones as stored (time-outs not told apart: a floor's shortcut)
        take = lambda x: x.view(x.shape[0], -1).index_select(0, rows)
        return take(buffer.observations), take(buffer.actions), take(buffer.next_observations), take(buffer.rewards), take(buffer.dones)

    @th.no_grad()
    def __call__(self, batch_size: int, update_actor: bool) -> tuple[dict, dict]:
        m, variant = self.model, self.variant
        obs, actions, next_obs, rewards, dones = self._batch(batch_size)
        next_actions = self._mlp(self.actor_target.layers[0], next_obs)[0].tanh_()  # step 5
        if variant >= 3:
            noise = th.randn(next_actions.shape, generator=m.random_streams.torch(next_actions.device))
        else:
            noise = th.randn_like(next_actions)
        noise = (noise * m.target_policy_noise).clamp_(-m.target_noise_clip, m.target_noise_clip)  # step 6
        next_actions = (next_actions + noise).clamp_(-1, 1)
        next_in = th.cat([next_obs, next_actions], 1).expand(2, -1, -1)
        next_q = self._stacked(self.critic_target.weights, self.critic_target.biases, next_in)[0]  # step 7
        target_q = rewards + (1 - dones) * m.gamma * next_q.min(0).values  # steps 8, 9
        x = th.cat([obs, actions], 1).expand(2, -1, -1)
        q, h1, h2 = self._stacked(self.critic.weights, self.critic.biases, x)  # step 10
        td = q - target_q
        critic_loss = td.square().mean() * 2  # step 11: the sum of both critics' MSE
        g = td * (2.0 / batch_size)
        w3 = self.critic.weights[2]
        g2 = _relu_backward(g * w3, h2, 0)
        g1 = _relu_backward(th.bmm(g2, self.critic.weights[1]), h1, 0)
        grads = [th.bmm(g1.mT, x), g1.sum(1), th.bmm(g2.mT, h1), g2.sum(1), th.bmm(g.mT, h2), g.sum(1)]
        self._step(self.critic, m.critic.optimizer, self.critic_params, grads)  # step 12
        infos: tuple[dict, dict] = ({"critic_loss": critic_loss}, {})
        if variant >= 4:
            infos[0]["target_q"] = target_q.mean()
            infos[0]["q1"], infos[0]["q2"] = q.mean(dim=(1, 2)).unbind(0)
        if not update_actor:
            return infos
        critic1 = self.critic.layers[0]
        pre, a1, a2 = self._mlp(self.actor.layers[0], obs)
        pi = pre.tanh_()
        q1, c1, c2 = self._mlp(critic1, th.cat([obs, pi], 1))  # step 13
        g = th.full_like(q1, -1.0 / batch_size)
        g = _relu_backward(g @ critic1[2].weight, c2, 0)
        g = _relu_backward(g @ critic1[1].weight, c1, 0)
        g = _tanh_backward(g @ critic1[0].weight[:, obs.shape[1]:], pi)
        actor_grads = [g.t() @ a2, g.sum(0)]
        g = _relu_backward(g @ self.actor.layers[0][2].weight, a2, 0)
        actor_grads[:0] = [g.t() @ a1, g.sum(0)]
        g = _relu_backward(g @ self.actor.layers[0][1].weight, a1, 0)
        actor_grads[:0] = [g.t() @ obs, g.sum(0)]
        self._step(self.actor, m.actor.optimizer, self.actor_params, actor_grads)
        self.critic_target.store.flat.lerp_(self.critic.store.flat, m.tau)  # step 15
        self.actor_target.store.flat.lerp_(self.actor.store.flat, m.tau)  # step 14
        if variant >= 4:
            infos[1]["actor_loss"] = -q1.mean()
        return infos

    def _step(self, stack, optimizer: th.optim.Optimizer, params: list[th.Tensor], grads: list[th.Tensor]) -> None:
        if self.variant >= 1:  # each parameter's .grad: its network's view of the (stacked) gradient
            per_network = (lambda g: g.unbind(0)) if stack is self.critic else (lambda g: [g])
            for depth in range(len(grads) // 2):
                for net, w, b in zip(stack.layers, per_network(grads[2 * depth]), per_network(grads[2 * depth + 1])):
                    net[depth].weight.grad, net[depth].bias.grad = w, b
        if self.variant >= 2:
            step_optimizers([optimizer])
        else:
            self._adam(optimizer, params, grads)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--mode", choices=("learn", "train"), default="learn")
    parser.add_argument("--chunks", type=int, default=10)
    parser.add_argument("--chunk-steps", type=int, default=400)
    parser.add_argument("--variants", type=int, nargs="+", default=[0], choices=range(5),
                        help="--mode learn: the bare steps to run beside TD3X and SBX (0: bare, 4: TD3X's promises kept)")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    settings = {"batch_size": args.batch_size, "buffer_size": 200_000}
    if args.mode == "learn":
        peer = sbx_td3(args.threads)
        models = {"TD3X": make_model(TD3X, args.env, 0, settings)}
        if peer is not None:
            models = {"SBX TD3": make_model(peer, args.env, 0, settings), **models}
        for variant in args.variants:
            model = models[f"TD3X, bare v{variant}"] = make_model(TD3X, args.env, 0, settings)
            model._step_fn = BareStep(model, variant)
        runs = {name: functools.partial(model.learn, reset_num_timesteps=False) for name, model in models.items()}
        for model in models.values():
            model.learn(1_300)
    else:
        model = make_model(TD3X, args.env, 0, settings)
        model.learn(1_300)
        steps = {f"v{v}": BareStep(model, v) for v in range(5)}
        steps["TD3X"] = model._gradient_step_fn()

        def train(step, n: int) -> None:
            model._step_fn = step
            model.train(n, args.batch_size)

        runs = {name: functools.partial(train, step) for name, step in steps.items()}
    for run in runs.values():
        run(50)
    seconds: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(args.chunks):
        for name, run in runs.items():
            start = time.perf_counter()
            run(args.chunk_steps)
            seconds[name].append((time.perf_counter() - start) / args.chunk_steps)
    first = next(iter(seconds))
    print(f"{args.env}, batch {args.batch_size}, {args.threads} threads, {args.mode}, {args.chunks} chunks of {args.chunk_steps}")
    for name, times in seconds.items():
        ratios = [a / b for a, b in zip(seconds[first], times)]
        print(f"  {name:16s} {statistics.median(times) * 1e3:6.3f} ms/step   speed relative to {first}: "
              f"median {statistics.median(ratios):.3f} (per chunk {min(ratios):.2f} to {max(ratios):.2f})")


if __name__ == "__main__":
    main()
