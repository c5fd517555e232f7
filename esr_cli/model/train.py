"""The one runner for every method: pure, jitted training chunks.

`make_trainer(spec)` returns a `Trainer` whose functions are pure over pytrees:

    init(seed) -> TrainState
    epoch(state) -> (state, metrics)   one episode in each of num_envs environments, then
                                       U_repr method updates, U_critic critic updates and
                                       U_dual dual updates (docs/choices.md)
    chunk(n)     jit(over seeds(scan of n epochs)), the state donated; seeds are vmapped
                 on an accelerator and run one after another on the CPU

The host (core/loop.py) only touches the state between chunks.
"""

from __future__ import annotations

import json
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from esr_cli.model import replay
from esr_cli.model.envs import make_env
from esr_cli.model.humans.registry import make_human
from esr_cli.model.learner import LearnerState, SoftQLearner, entropy
from esr_cli.model.methods.registry import make_method

BASE_METRICS = (
    "return",
    "success",
    "policy_entropy",
    "beta",
    "critic_loss",
    "q_mean",
    "reward_mean",
    "dual_loss",
)


class TrainState(NamedTuple):
    epoch: jax.Array  # int32[]
    key: jax.Array
    learner: LearnerState
    method: Any
    buffer: replay.Buffer
    human: Any = ()  # a learning human's state (humans/registry.py); () for a fixed human


class Rollout(NamedTuple):
    episodes: replay.Episodes  # [n, T(+1), ...]
    states: Any  # env states, [T+1, n, ...] (for pictures)
    log_probs: jax.Array  # robot policy log-probs at each step [T, n, A] (zeros for random)
    rule_metrics: dict  # per-environment end-of-episode metrics of a rule-based robot


class Trainer(NamedTuple):
    spec: Any
    env: Any
    human: Any
    method: Any
    learner: SoftQLearner

    # How the replay buffer is sampled is the method's to say (model/spec.py, `_MethodModel`).
    @property
    def future_gamma(self) -> float:
        return float(self.spec.method.replay_future_gamma(self.spec.learner.gamma))

    @property
    def repr_episode_group(self) -> int:
        """Transitions per sampled episode in a representation batch."""
        return int(self.spec.method.replay_episode_group())

    @property
    def repr_sampler(self) -> replay.Sampler:
        """The representation updates' batches (the method's grouping)."""
        return replay.Sampler(self.spec.learner.batch_size, self.future_gamma, self.repr_episode_group)

    @property
    def critic_sampler(self) -> replay.Sampler:
        """The critic's and the temperature's batches (one transition per sampled episode)."""
        return replay.Sampler(self.spec.learner.batch_size, self.future_gamma)

    @property
    def post_step_pairing(self) -> bool:
        """Every update reads the buffer as `replay.post_step_view` (ESR's `pairing: original`)."""
        return bool(self.spec.method.reads_post_step_view())

    @property
    def metric_names(self) -> tuple[str, ...]:
        return BASE_METRICS + tuple(self.method.metric_names) + tuple(self.human.metric_names)

    @property
    def human_learns(self) -> bool:
        return bool(self.human.learns)

    def obs_example(self):
        return self.env.observe(self.env.reset(jax.random.PRNGKey(0)))

    # ------------------------------------------------------------ state
    def init(self, seed) -> TrainState:
        key = jax.random.PRNGKey(seed)
        key, k_learner, k_method = jax.random.split(key, 3)
        obs = self.obs_example()
        steps = self.env.episode_steps
        capacity = self.spec.learner.buffer_size // steps
        return TrainState(
            epoch=jnp.zeros((), jnp.int32),
            key=key,
            learner=self.learner.init(k_learner, obs),
            method=self.method.init(k_method, obs),
            buffer=replay.init(capacity, steps, obs.shape, obs.dtype),
            # fold_in: the other keys stay as they were for humans without a state
            human=self.human.init(jax.random.fold_in(key, 1), seed) if self.human.has_state else (),
        )

    # ------------------------------------------------------------ acting
    def robot_action(self, lstate: LearnerState, obs, key, mode: str, uniform=False):
        """mode: sample (Boltzmann policy), greedy (argmax Q) or random (uniform).

        `uniform` (a traced bool) overrides a sampled action with a uniform one: the warm-up
        epochs (learner.warmup_epochs) act uniformly while the policy's log-probs are still
        reported.
        """
        n = obs.shape[0]
        k_policy, k_uniform = jax.random.split(key)
        uniform_action = jax.random.randint(k_uniform, (n,), 0, self.env.num_robot_actions, dtype=jnp.int32)
        if mode == "random" or not self.method.learns_policy:
            return jnp.zeros((n, self.env.num_robot_actions)), uniform_action
        log_probs = self.learner.log_probs(lstate, obs)
        if mode == "greedy":
            return log_probs, jnp.argmax(log_probs, axis=-1).astype(jnp.int32)
        action = jax.random.categorical(k_policy, log_probs).astype(jnp.int32)
        return log_probs, jnp.where(uniform, uniform_action, action)

    @property
    def acts_by_rule(self) -> bool:
        return bool(self.method.acts_by_rule)

    def rollout(self, lstate: LearnerState, key, num_envs: int, mode: str = "sample", uniform=False, hstate=()) -> Rollout:
        """One episode in each of `num_envs` environments.

        A method that acts by a fixed rule (Goal Inference) keeps a per-environment memory
        across the steps and decides from the observation and the human's previous action;
        every other robot acts from its learned (or uniform) policy.
        """
        env, human, method = self.env, self.human, self.method
        k_reset, k_steps = jax.random.split(key)
        states = jax.vmap(env.reset)(jax.random.split(k_reset, num_envs))
        obs0 = jax.vmap(env.observe)(states)
        memory = jax.vmap(method.memory_init)(obs0) if self.acts_by_rule else ()
        prev_ah = jnp.zeros((num_envs,), jnp.int32)

        def step(carry, key):
            states, memory, prev_ah = carry
            k_robot, k_human = jax.random.split(key)
            obs = jax.vmap(env.observe)(states)
            if self.acts_by_rule:
                a_r, memory = jax.vmap(method.rule_step)(memory, obs, prev_ah, jax.random.split(k_robot, num_envs))
                log_probs = jnp.zeros((num_envs, env.num_robot_actions))
            else:
                log_probs, a_r = self.robot_action(lstate, obs, k_robot, mode, uniform)
            k_each = jax.random.split(k_human, num_envs)
            if self.human.has_state:
                a_h = jax.vmap(human.act_with, in_axes=(None, 0, 0))(hstate, k_each, states)
            else:
                a_h = jax.vmap(human.act)(k_each, states)
            next_states, reward = jax.vmap(env.step)(states, a_r, a_h)
            return (next_states, memory, a_h), (states, obs, a_r, a_h, reward, log_probs)

        (final, memory, _), (traj, obs, a_r, a_h, reward, log_probs) = jax.lax.scan(
            step, (states, memory, prev_ah), jax.random.split(k_steps, env.episode_steps)
        )
        obs = jnp.concatenate([obs, jax.vmap(env.observe)(final)[None]], axis=0)
        all_states = jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]], axis=0), traj, final)
        swap = lambda x: jnp.swapaxes(x, 0, 1)  # noqa: E731 - [T, n] -> [n, T]
        episodes = replay.Episodes(obs=swap(obs), robot_action=swap(a_r), human_action=swap(a_h), reward=swap(reward))
        rule_metrics = jax.vmap(method.rule_metrics)(memory, final) if self.acts_by_rule else {}
        return Rollout(episodes=episodes, states=all_states, log_probs=log_probs, rule_metrics=rule_metrics)

    # ------------------------------------------------------------ learning
    @property
    def stored_transitions(self) -> int:
        """The replay buffer's capacity in transitions (whole episodes)."""
        steps = self.env.episode_steps
        return (self.spec.learner.buffer_size // steps) * steps

    @property
    def reward_table_pays(self) -> bool:
        """Representing every stored transition once costs less than representing each critic
        batch: the buffer holds fewer transitions than the critic phase samples (the gridworld:
        15,000 against 100 x 256; not Overcooked's 200,000)."""
        learner = self.spec.learner
        return self.method.has_reward_table and self.stored_transitions <= learner.updates_per_epoch * learner.batch_size

    @property
    def q_table_pays(self) -> bool:
        """Likewise for Q of every stored state in the dual phase."""
        learner = self.spec.learner
        return self.stored_transitions <= learner.dual_updates_per_epoch * learner.batch_size

    def _scan_updates(self, step_fn, carry, key, count: int):
        """Run `count` update steps, each on a fresh batch; -> (carry, mean metrics)."""
        if count == 0:
            return carry, {}

        def body(carry, key):
            return step_fn(carry, key)

        carry, metrics = jax.lax.scan(body, carry, jax.random.split(key, count))
        return carry, jax.tree.map(jnp.mean, metrics)

    def epoch(self, state: TrainState):
        spec = self.spec
        key, k_roll, k_repr, k_critic, k_dual = jax.random.split(state.key, 5)
        warming_up = state.epoch < spec.learner.warmup_epochs
        roll = self.rollout(state.learner, k_roll, spec.train.num_envs, "sample", warming_up, state.human)
        buf = replay.add(state.buffer, roll.episodes)
        hstate, h_metrics = state.human, {}
        if self.human_learns:  # the human learns from the episodes it just played
            ep = roll.episodes
            hstate, h_metrics = self.human.update(state.human, roll.states, ep.human_action, ep.reward, jax.random.fold_in(key, 2))
        repr_sampler, critic_sampler = self.repr_sampler, self.critic_sampler
        stored = buf
        if self.post_step_pairing:  # the updates read the published code's pairing; the buffer is unchanged
            buf = replay.post_step_view(buf)

        def repr_step(mstate, key):
            k_sample, k_update = jax.random.split(key)
            batch = repr_sampler.batch(buf, k_sample)
            return self.method.update(mstate, batch, k_update)

        mstate, m_metrics = self._scan_updates(repr_step, state.method, k_repr, self.method.updates_per_epoch)

        # Within a phase the representations (critic phase) or the critic (dual phase) are
        # fixed, so when it pays (see `reward_table_pays`) their values on every stored
        # transition are computed once and the batches looked up: the same numbers, less work.
        reward_table = self.method.reward_table(mstate, buf) if self.reward_table_pays else None

        def critic_step(lstate, key):
            k_sample, k_reward = jax.random.split(key)
            idx = critic_sampler.index(buf, k_sample)
            batch = replay.gather(buf, idx)
            if reward_table is None:
                reward = self.method.reward(mstate, batch, k_reward)
            else:
                reward = self.method.reward_from_table(reward_table, idx)
            lstate, metrics = self.learner.critic_step(
                lstate, batch.obs, batch.robot_action, reward, batch.next_obs, batch.done
            )
            return lstate, {**metrics, "reward_mean": jnp.mean(reward)}

        def dual_step(lstate, key, q_table):
            idx = critic_sampler.index(buf, key)
            if q_table is None:
                return self.learner.dual_step(lstate, buf.obs[idx.episode, idx.t])
            return self.learner.dual_step_q(lstate, q_table[idx.episode, idx.t])

        lstate = state.learner
        c_metrics, d_metrics = {}, {}
        if self.method.learns_policy:
            lstate, c_metrics = self._scan_updates(critic_step, lstate, k_critic, spec.learner.updates_per_epoch)
            q_table = self.learner.q_table(lstate, buf.obs[:, :-1]) if self.q_table_pays else None
            lstate, d_metrics = self._scan_updates(
                partial(dual_step, q_table=q_table), lstate, k_dual, spec.learner.dual_updates_per_epoch
            )

        returns = roll.episodes.reward.sum(axis=1)
        nan = jnp.full((), jnp.nan, jnp.float32)
        metrics = {name: nan for name in self.metric_names}
        metrics.update(
            {
                "return": returns.mean(),
                "success": (returns > 0).mean(),
                "policy_entropy": entropy(roll.log_probs).mean() if self.method.learns_policy else nan,
                "beta": lstate.beta,
            }
        )
        metrics.update(c_metrics)
        metrics.update(d_metrics)
        metrics.update(m_metrics)
        metrics.update(jax.tree.map(jnp.mean, roll.rule_metrics))
        metrics.update(h_metrics)
        new_state = TrainState(epoch=state.epoch + 1, key=key, learner=lstate, method=mstate, buffer=stored, human=hstate)
        return new_state, {k: metrics[k].astype(jnp.float32) for k in self.metric_names}

    def run_epochs(self, state: TrainState, n: int):
        return jax.lax.scan(lambda s, _: self.epoch(s), state, None, length=n)


def make_trainer(spec, human_params=None) -> Trainer:
    """`human_params`: the parameters of a stored human (a BC human), which the caller loads
    (runs.build_trainer); the core never reads the store."""
    env = make_env(spec.env)
    human = make_human(spec.human, env, human_params, spec.train.seeds)
    return Trainer(
        spec=spec,
        env=env,
        human=human,
        method=make_method(spec, env, human),
        learner=SoftQLearner(num_actions=env.num_robot_actions, network_spec=spec.network, spec=spec.learner),
    )


# Jitted programs by (spec, what, n): equal specs compute the same thing, so a process that
# trains, resumes and evaluates one spec compiles each program once.
_COMPILED: dict[tuple[str, str, int], Any] = {}


def _cached(trainer: Trainer, what: str, n: int, build):
    key = (json.dumps(trainer.spec.training_part(), sort_keys=True), what, n)
    if key not in _COMPILED:
        _COMPILED[key] = build()
    return _COMPILED[key]


def release_compiled() -> None:
    """Forget every compiled program. A process that trains many specs one after another (a
    sweep, an ablation, the paper suite) calls this between them: each XLA executable holds
    memory mappings, and hundreds of them exhaust the process's mapping limit."""
    _COMPILED.clear()
    jax.clear_caches()


def compiled_init(trainer: Trainer):
    return _cached(trainer, "init", 0, lambda: jax.jit(jax.vmap(trainer.init)))


def default_seed_batch() -> int | None:
    """How many seeds one program runs side by side (vmap); the rest follow one another in
    the same program (lax.map). On an accelerator every seed at once (None) fills the device.
    On the CPU one at a time: XLA's CPU batched matmuls over per-seed weights, and the larger
    working set, made 5 vmapped seeds 6.3x slower than one (docs/performance.md), while
    one after another costs exactly 5x."""
    return 1 if jax.default_backend() == "cpu" else None


def over_seeds(fn, seed_batch: int | None):
    """fn over the leading (seed) axis: vmapped in groups of `seed_batch` (None: all)."""
    if seed_batch is None:
        return jax.vmap(fn)
    if seed_batch == 1:
        return lambda xs: jax.lax.map(fn, xs)
    return lambda xs: jax.lax.map(fn, xs, batch_size=seed_batch)


def compiled_chunk(trainer: Trainer, n: int, seed_batch: int | None = -1):
    """jit(over seeds(scan of n epochs)); metrics come back as [seeds, n]. seed_batch: see
    `default_seed_batch` (-1: that default)."""
    if seed_batch == -1:
        seed_batch = default_seed_batch()
    return _cached(
        trainer,
        f"chunk/{seed_batch}",
        n,
        lambda: jax.jit(over_seeds(partial(trainer.run_epochs, n=n), seed_batch), donate_argnums=0),
    )
