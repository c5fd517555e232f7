"""PPO for the Overcooked human: one jitted `lax.scan` over updates, in the manner of
PureJaxRL's PPO and JaxMARL's IPPO (baselines/IPPO/ippo_ff_overcooked.py): vmapped
environments, GAE, the clipped surrogate, a clipped value loss, an entropy bonus, Adam with a
global-norm clip and a linearly annealed learning rate, minibatch epochs. The defaults are
JaxMARL's Overcooked IPPO recipe (baselines/IPPO/config/ippo_ff_overcooked.yaml).

Every player of the environment is the one network (self-play with shared parameters), each
acting and learning from its own view: a batch holds num_envs x players actor-steps a step.
The episode's time limit counts as terminal for GAE, as in IPPO (in Overcooked the urgency
channel tells the network that the end is near).
Two optional terms make the three training modes (`mode_config`):

- `selfplay`: the sparse reward only.
- `shaped`: the sparse reward plus each player's own shaped reward (JaxMARL's
  `info["shaped_reward"]`: 3 per onion in a pot, 3 per plate picked up, 5 per soup picked
  up) times a coefficient annealed linearly from 1 to 0 over `shaping_fraction` of training
  (the recipe's REW_SHAPING_HORIZON, 2.5e6 of 5e6 steps).
- `bc_kl`: `kl_coef * KL(pi_clone || pi)` added to the loss on the visited states, towards a
  fixed behaviour-cloned policy given as a function of the observation: the human learns
  to play but stays near the humans' own behaviour.

With `random_partner` = p > 0, in every step of every environment the partner's seat
(player 0: the robot's seat, so the human learns in its own) acts uniformly at random with
probability p instead of by the network, and those random actions are left out of the loss
(masked means). p = 1 trains the human beside a uniform random partner, the paper's Random
robot; p = 0 is plain self-play (and computes exactly what it did before the option).

The core sees the environment only through `SelfPlayEnv` (reset, step with automatic reset,
observe) and the network only through `Agent` (init, apply), so the tests run it on toy
environments; `overcooked_env` and `overcooked_agent` are the Overcooked side.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from esr_cli.model.envs.overcooked import NUM_ACTIONS, Overcooked
from esr_cli.model.gradient import gradient_step
from esr_cli.model.humans import conv_actor_critic as cac


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    total_steps: int = 5_000_000  # environment steps (each counts once, whatever the players)
    num_envs: int = 16
    rollout_steps: int = 128
    lr: float = 2.5e-4
    anneal_lr: bool = True  # linearly to 0 over total_steps
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2  # the surrogate's and the value's clip
    update_epochs: int = 4
    num_minibatches: int = 4
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    shaping_fraction: float = 0.0  # shaped reward annealed 1 -> 0 over this fraction; 0: sparse only
    kl_coef: float = 0.0  # weight of KL(pi_clone || pi); > 0 needs a clone
    random_partner: float = 0.0  # probability that player 0 acts uniformly at random in a step

    def __post_init__(self):
        if self.num_updates < 1:
            raise ValueError(f"total_steps {self.total_steps} is less than one rollout ({self.num_envs} x {self.rollout_steps})")
        if not 0.0 <= self.shaping_fraction <= 1.0:
            raise ValueError(f"shaping_fraction must be in [0, 1], got {self.shaping_fraction}")
        if self.kl_coef < 0:
            raise ValueError(f"kl_coef must be >= 0, got {self.kl_coef}")
        if not 0.0 <= self.random_partner <= 1.0:
            raise ValueError(f"random_partner must be in [0, 1], got {self.random_partner}")

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.rollout_steps

    @property
    def num_updates(self) -> int:
        return self.total_steps // self.steps_per_update

    @property
    def mode(self) -> str:
        """The training mode these fields make (see the module docstring)."""
        if self.kl_coef > 0:
            return "bc_kl" if self.shaping_fraction == 0 else "bc_kl+shaped"
        return "shaped" if self.shaping_fraction > 0 else "selfplay"


MODES = ("selfplay", "shaped", "bc_kl")


def mode_config(mode: str, **fields) -> PPOConfig:
    """The config of a named training mode: `selfplay` (sparse reward), `shaped` (the shaped
    reward annealed over the first half, the recipe's 2.5e6 of 5e6 steps) or `bc_kl`
    (sparse reward, KL to the clone with weight 1 unless given); `fields` override."""
    presets = {"selfplay": {}, "shaped": {"shaping_fraction": 0.5}, "bc_kl": {"kl_coef": 1.0}}
    if mode not in presets:
        raise ValueError(f"unknown PPO mode {mode!r}; known: {', '.join(MODES)}")
    return PPOConfig(**{**presets[mode], **fields})


# ---------------------------------------------------------------- the interfaces
class SelfPlayEnv(NamedTuple):
    """What PPO needs of an environment with `players` seats all played by the network.

    reset(key) -> state; observe(state) -> obs [players, ...];
    step(key, state, actions int[players]) -> (state, sparse_reward f32[], shaped_reward
    f32[players], done bool[]), resetting by itself when the episode ends (the returned
    state is then a fresh one; `done` marks the step that ended the old episode)."""

    reset: Callable
    step: Callable
    observe: Callable
    players: int
    num_actions: int


class Agent(NamedTuple):
    """init(key) -> params; apply(params, obs [..., *obs_shape]) -> (logits [..., A], value [...])."""

    init: Callable
    apply: Callable


class RunnerState(NamedTuple):
    params: Any
    opt_state: Any
    env_state: Any  # [num_envs, ...]
    obs: jax.Array  # [num_envs, players, ...]
    episode_return: jax.Array  # [num_envs]: sparse return so far of each running episode
    update: jax.Array  # int32: updates done
    key: jax.Array


class Transition(NamedTuple):
    obs: jax.Array
    action: jax.Array
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array
    done: jax.Array
    clone_log_probs: jax.Array  # [..., A] (zeros-size placeholder when there is no KL term)
    learnt: jax.Array  # 1.0 where the network chose the action, 0.0 where the random partner did


METRICS = (
    "episode_return",  # mean sparse return of the episodes that ended in this rollout (NaN if none)
    "episodes_finished",
    "sparse_per_step",  # mean sparse reward per environment step of the rollout
    "shaping_coef",
    "loss",
    "actor_loss",
    "value_loss",
    "entropy",
    "kl_to_clone",  # KL(pi_clone || pi) on the minibatches (0 without a clone)
    "approx_kl",  # KL(pi_old || pi) estimate: how far an update moved the policy
    "clip_fraction",
    "lr",
)


# ---------------------------------------------------------------- PPO
class PPO(NamedTuple):
    env: SelfPlayEnv
    agent: Agent
    config: PPOConfig
    clone_logits: Callable | None = None  # obs [..., *obs_shape] -> logits [..., A]

    @property
    def optimizer(self):
        c = self.config
        steps_per_update = c.update_epochs * c.num_minibatches

        def schedule(count):
            return c.lr * (1.0 - (count // steps_per_update) / c.num_updates)

        return optax.chain(optax.clip_by_global_norm(c.max_grad_norm), optax.adam(schedule if c.anneal_lr else c.lr, eps=1e-5))

    def check(self):
        c = self.config
        if c.kl_coef > 0 and self.clone_logits is None:
            raise ValueError("kl_coef > 0 needs the cloned policy (clone_logits)")
        batch = c.rollout_steps * c.num_envs * self.env.players
        if batch % c.num_minibatches:
            raise ValueError(f"a batch of {batch} actor-steps does not split into {c.num_minibatches} minibatches")

    def init(self, key) -> RunnerState:
        self.check()
        return self._init(key)

    @functools.partial(jax.jit, static_argnums=0)
    def _init(self, key) -> RunnerState:
        k_params, k_reset, key = jax.random.split(key, 3)
        params = self.agent.init(k_params)
        env_state = jax.vmap(self.env.reset)(jax.random.split(k_reset, self.config.num_envs))
        obs = jax.vmap(self.env.observe)(env_state)
        return RunnerState(
            params=params,
            opt_state=self.optimizer.init(params),
            env_state=env_state,
            obs=obs,
            episode_return=jnp.zeros((self.config.num_envs,), jnp.float32),
            update=jnp.int32(0),
            key=key,
        )

    def shaping_coef(self, update):
        """1 -> 0 linearly over shaping_fraction of training, by environment steps done."""
        c = self.config
        if c.shaping_fraction == 0:
            return jnp.float32(0.0)
        horizon = c.shaping_fraction * c.num_updates * c.steps_per_update
        return jnp.clip(1.0 - update * c.steps_per_update / horizon, 0.0, 1.0).astype(jnp.float32)

    # ---- rollout
    def rollout(self, runner: RunnerState):
        c, env = self.config, self.env
        coef = self.shaping_coef(runner.update)

        def step(carry, key):
            params, env_state, obs, ep_ret = carry
            k_act, k_env = jax.random.split(key)
            logits, value = self.agent.apply(params, obs)  # [E, P, A], [E, P]
            action, learnt = self.act(k_act, logits)
            log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]
            env_state, sparse, shaped, done = jax.vmap(env.step)(jax.random.split(k_env, c.num_envs), env_state, action)
            reward = sparse[:, None] + coef * shaped
            clone = jax.nn.log_softmax(self.clone_logits(obs)) if c.kl_coef > 0 else jnp.zeros(action.shape + (0,))
            ep_ret = ep_ret + sparse
            ended = jnp.where(done, ep_ret, 0.0)
            ep_ret = jnp.where(done, 0.0, ep_ret)
            done_p = jnp.broadcast_to(done[:, None], action.shape)
            t = Transition(obs, action, log_prob, value, reward.astype(jnp.float32), done_p, clone, learnt)
            next_obs = jax.vmap(env.observe)(env_state)
            return (params, env_state, next_obs, ep_ret), (t, sparse, done, ended)

        key, k_steps = jax.random.split(runner.key)
        carry = (runner.params, runner.env_state, runner.obs, runner.episode_return)
        (_, env_state, obs, ep_ret), (traj, sparse, done, ended) = jax.lax.scan(step, carry, jax.random.split(k_steps, c.rollout_steps))
        finished = done.sum()
        stats = {
            "episode_return": jnp.where(finished > 0, ended.sum() / jnp.maximum(finished, 1), jnp.nan),
            "episodes_finished": finished.astype(jnp.float32),
            "sparse_per_step": sparse.mean(),
            "shaping_coef": coef,
        }
        return runner._replace(env_state=env_state, obs=obs, episode_return=ep_ret, key=key), traj, stats

    def act(self, key, logits):
        """Sampled actions [E, P] and where the network chose them (1.0) rather than the random
        partner (0.0). Without a random partner, exactly `categorical(key, logits)`."""
        p = self.config.random_partner
        if p == 0:
            action = jax.random.categorical(key, logits)
            return action, jnp.ones(action.shape, jnp.float32)
        k_net, k_uniform, k_coin = jax.random.split(key, 3)
        action = jax.random.categorical(k_net, logits)
        partner = (jnp.arange(action.shape[-1]) == 0) & jax.random.bernoulli(k_coin, p, action.shape[:-1] + (1,))
        action = jnp.where(partner, jax.random.randint(k_uniform, action.shape, 0, logits.shape[-1]), action)
        return action, (~partner).astype(jnp.float32)

    def gae(self, traj: Transition, last_value):
        """-> (advantages, value targets), [T, E, P]."""
        c = self.config

        def back(carry, t):
            gae, next_value = carry
            live = 1.0 - t.done.astype(jnp.float32)
            delta = t.reward + c.gamma * next_value * live - t.value
            gae = delta + c.gamma * c.gae_lambda * live * gae
            return (gae, t.value), gae

        _, adv = jax.lax.scan(back, (jnp.zeros_like(last_value), last_value), traj, reverse=True)
        return adv, adv + traj.value

    # ---- loss
    def loss(self, params, t: Transition, adv, target):
        c = self.config
        if c.random_partner > 0:  # over the network's own actions only
            weight = t.learnt / jnp.maximum(t.learnt.sum(), 1.0)
            mean = lambda x: (weight * x).sum()  # noqa: E731
            adv_mean = mean(adv)
            adv_std = jnp.sqrt(mean(jnp.square(adv - adv_mean)))
        else:  # plain means, as before the option (bit for bit)
            mean = jnp.mean
            adv_mean, adv_std = adv.mean(), adv.std()
        logits, value = self.agent.apply(params, t.obs)
        logp_all = jax.nn.log_softmax(logits)
        logp = jnp.take_along_axis(logp_all, t.action[..., None], -1)[..., 0]
        v_clipped = t.value + jnp.clip(value - t.value, -c.clip_eps, c.clip_eps)
        value_loss = 0.5 * mean(jnp.maximum(jnp.square(value - target), jnp.square(v_clipped - target)))
        log_ratio = logp - t.log_prob
        ratio = jnp.exp(log_ratio)
        adv = (adv - adv_mean) / (adv_std + 1e-8)
        actor_loss = -mean(jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - c.clip_eps, 1 + c.clip_eps) * adv))
        probs = jnp.exp(logp_all)
        entropy = mean(-(probs * logp_all).sum(-1))
        if c.kl_coef > 0:
            kl = mean((jnp.exp(t.clone_log_probs) * (t.clone_log_probs - logp_all)).sum(-1))
        else:
            kl = jnp.float32(0.0)
        total = actor_loss + c.vf_coef * value_loss - c.ent_coef * entropy + c.kl_coef * kl
        aux = {
            "loss": total,
            "actor_loss": actor_loss,
            "value_loss": value_loss,
            "entropy": entropy,
            "kl_to_clone": kl,
            "approx_kl": mean((ratio - 1) - log_ratio),
            "clip_fraction": mean((jnp.abs(ratio - 1) > c.clip_eps).astype(jnp.float32)),
        }
        return total, aux

    # ---- one update
    def update(self, runner: RunnerState):
        """One PPO update: a rollout of rollout_steps x num_envs, then the minibatch epochs.
        -> (runner, metrics {name: scalar}, see METRICS)."""
        c = self.config
        runner, traj, stats = self.rollout(runner)
        _, last_value = self.agent.apply(runner.params, runner.obs)
        adv, target = self.gae(traj, last_value)
        batch = adv.size  # T x E x P actor-steps
        flat = jax.tree.map(lambda x: x.reshape((batch,) + x.shape[3:]), (traj, adv, target))
        opt = self.optimizer

        def epoch(carry, key):
            def minibatch(carry, idx):
                params, opt_state = carry
                t, a, g = jax.tree.map(lambda x: x[idx], flat)
                (_, aux), params, opt_state = gradient_step(lambda p: self.loss(p, t, a, g), params, opt_state, opt)
                return (params, opt_state), aux

            order = jax.random.permutation(key, batch).reshape(c.num_minibatches, -1)
            return jax.lax.scan(minibatch, carry, order)

        key, k_epochs = jax.random.split(runner.key)
        (params, opt_state), aux = jax.lax.scan(epoch, (runner.params, runner.opt_state), jax.random.split(k_epochs, c.update_epochs))
        lr = c.lr * (1.0 - runner.update / c.num_updates) if c.anneal_lr else jnp.float32(c.lr)
        metrics = {**stats, **jax.tree.map(jnp.mean, aux), "lr": jnp.asarray(lr, jnp.float32)}
        runner = runner._replace(params=params, opt_state=opt_state, update=runner.update + 1, key=key)
        return runner, metrics

    @functools.partial(jax.jit, static_argnums=(0, 2))
    def run(self, runner: RunnerState, updates: int):
        """`updates` updates in one jitted scan -> (runner, metrics {name: [updates]})."""
        return jax.lax.scan(lambda r, _: self.update(r), runner, None, length=updates)

    def train(self, key, updates: int | None = None):
        """From scratch: config.num_updates updates (or `updates`) -> (runner, metrics)."""
        return self.run(self.init(key), self.config.num_updates if updates is None else updates)


# ---------------------------------------------------------------- Overcooked
def overcooked_env(env: Overcooked) -> SelfPlayEnv:
    """JaxMARL's Overcooked, both seats played by the network from their own (H, W, 26)
    views, with the shaped reward of each and an automatic reset after episode_steps."""
    base = env.base

    def observe(state):
        obs = base.get_obs(state)
        return jnp.stack([obs["agent_0"], obs["agent_1"]]).astype(jnp.uint8)

    def step(key, state, actions):
        k_step, k_reset = jax.random.split(key)
        _, nxt, rewards, dones, info = base.step_env(k_step, state, {"agent_0": actions[0], "agent_1": actions[1]})
        done = dones["__all__"]
        nxt = jax.tree.map(lambda fresh, old: jnp.where(done, fresh, old), env.reset(k_reset), nxt)
        shaped = jnp.stack([info["shaped_reward"]["agent_0"], info["shaped_reward"]["agent_1"]]).astype(jnp.float32)
        return nxt, rewards["agent_0"].astype(jnp.float32), shaped, done

    return SelfPlayEnv(reset=env.reset, step=step, observe=observe, players=2, num_actions=NUM_ACTIONS)


def overcooked_agent(env: Overcooked, net: cac.ConvActorCritic | None = None) -> Agent:
    """The convolutional actor-critic on JaxMARL observations (read in overcooked-ai's layout)."""
    net = net or cac.ConvActorCritic()
    return Agent(
        init=lambda key: cac.init_params(key, env.height, env.width, net),
        apply=lambda params, obs: cac.apply_jaxmarl(params, obs, net),
    )


def overcooked_ppo(env: Overcooked, config: PPOConfig, clone_logits: Callable | None = None) -> PPO:
    """PPO for the human in `env`'s layout. clone_logits: obs [..., H, W, 26] -> logits
    [..., 6], the cloned policy (`bc_kl`), e.g. `lambda o: bc.cloned_policy(spec).logits(bc_params, o)`."""
    ppo = PPO(env=overcooked_env(env), agent=overcooked_agent(env), config=config, clone_logits=clone_logits)
    ppo.check()
    return ppo
