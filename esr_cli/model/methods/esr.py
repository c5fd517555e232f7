"""ESR: Empowerment via Successor Representations (the paper's section 4, Algorithm 1).

Three representations, learned contrastively from (s, aR, aH, g) with g a future state of the
same episode (see replay.py):
    phi(s, aR, aH)    the controlled model   (12 input channels in the gridworld)
    phi'(s, aR)       the uncontrolled model = phi with the human-action planes zeroed
    psi(g)            the future-state representation
At the optimum phi^T psi and phi'^T psi are log density ratios up to constants, so
    r(s, aR, aH, g) = (phi(s, aR, aH) - phi'(s, aR))^T psi(g)
estimates log p(g | s, aR, aH) / p(g | s, aR), whose expectation is the human's conditional
mutual information I(aH; s+ | s, aR): the robot's reward, resampled with a fresh g at every
critic update.

As in the original code (docs/paper-facts.md), phi and phi' are one network (phi' zeroes the human input), logits
are phi . psi / repr_dim, and the reward is the raw dot product (not divided by repr_dim).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from esr_cli.model.gradient import gradient_step
from esr_cli.model.methods.latent_actions import LatentActions, code_action_agreement
from esr_cli.model.networks import conv_net
from esr_cli.model.replay import map_episodes


def _symmetric_infonce(logits: jax.Array) -> jax.Array:
    """-(mean log row-softmax diagonal) - (mean log column-softmax diagonal)."""
    rows = jnp.diagonal(jax.nn.log_softmax(logits, axis=1))
    cols = jnp.diagonal(jax.nn.log_softmax(logits, axis=0))
    return -jnp.mean(rows) - jnp.mean(cols)


def infonce_loss(phi_s: jax.Array, phi_sa: jax.Array, psi: jax.Array, mode: str = "stacked") -> jax.Array:
    """The symmetric InfoNCE loss of ESR, logits = x . y / d.

    stacked (original code): one 2B x 2B problem, [phi'; phi] against [psi; psi]. Each positive
        then appears twice in its row and column, so the loss cannot reach 0.
    separate (the paper's equation): InfoNCE(phi, psi) + InfoNCE(phi', psi), each B x B.
    """
    d = psi.shape[-1]
    if mode == "stacked":
        x = jnp.concatenate([phi_s, phi_sa], axis=0)
        y = jnp.concatenate([psi, psi], axis=0)
        return _symmetric_infonce(x @ y.T / d)
    if mode == "separate":
        return _symmetric_infonce(phi_sa @ psi.T / d) + _symmetric_infonce(phi_s @ psi.T / d)
    raise ValueError(f"unknown InfoNCE mode {mode!r}")


def mutual_information_estimate(phi_s, phi_sa, psi) -> jax.Array:
    """Mean diagonal logit of phi minus that of phi' (the original's logged MI estimate)."""
    d = psi.shape[-1]
    return jnp.mean(jnp.sum((phi_sa - phi_s) * psi, axis=-1)) / d


def same_future(future_obs: jax.Array) -> jax.Array:
    """bool[B, B]: which futures in the batch are the same state (duplicates are common)."""
    flat = future_obs.reshape(future_obs.shape[0], -1)
    if flat.dtype.itemsize == 1:
        # Compare 4 bytes at a time: the same answer for a quarter of the work.
        flat = jnp.pad(flat, ((0, 0), (0, -flat.shape[1] % 4)))
        flat = jax.lax.bitcast_convert_type(flat.reshape(flat.shape[0], -1, 4), jnp.int32)
    return jnp.all(flat[:, None, :] == flat[None, :, :], axis=-1)


def contrastive_accuracy(phi_sa, psi, same=None) -> jax.Array:
    """How often phi(s, aR, aH) picks its own future among the B in the batch.

    With `same` (see `same_future`), picking an identical copy of the true future counts as
    right: the representations cannot tell identical states apart, and in the gridworld many
    futures in a batch are the same state.
    """
    pick = jnp.argmax(phi_sa @ psi.T, axis=1)
    if same is None:
        return jnp.mean(pick == jnp.arange(psi.shape[0]))
    return jnp.mean(same[jnp.arange(psi.shape[0]), pick])


def contrastive_chance(same) -> jax.Array:
    """The accuracy of guessing uniformly among the batch: mean fraction of identical futures."""
    return jnp.mean(same)


def empowerment_reward(phi_s, phi_sa, psi) -> jax.Array:
    """r = (phi(s, aR, aH) - phi'(s, aR))^T psi(g), per example."""
    return jnp.sum((phi_sa - phi_s) * psi, axis=-1)


def simplified_reward(phi_s, phi_sa, normalized: bool = False) -> jax.Array:
    """The reward without a future state, per example: the paper's appendix form
    r = exp(|phi|^2 / 2d) (phi - phi')^T phi, or with normalized=True r = (phi - phi')^T phi.

    If the future representations are standard normal on the logit scale (psi / sqrt(d) ~
    N(0, I), since logits are phi . psi / d), then E_{p(g)}[exp(phi . psi / d) (phi - phi')^T psi]
    is the paper's form, and exp(|phi|^2 / 2d) = E_{p(g)}[exp(phi . psi / d)] is the partition
    function that a density ratio learned only up to a factor of (s, aR, aH) leaves in it.
    Dividing it out gives the normalized form: the main reward's expectation over the model's
    own p(g | s, aR, aH) (docs/estimators.md). The exponent is capped at 80 so that float32
    cannot overflow in the reward itself."""
    gain = jnp.sum((phi_sa - phi_s) * phi_sa, axis=-1)
    if normalized:
        return gain
    d = phi_sa.shape[-1]
    return jnp.exp(jnp.minimum(jnp.sum(phi_sa * phi_sa, axis=-1) / (2 * d), 80.0)) * gain


class RewardTable(NamedTuple):
    """The representations of everything in the replay buffer, for one set of parameters."""

    phi_s: jax.Array  # [E, T, d]   phi'(s_t, aR_t)
    phi_sa: jax.Array  # [E, T, d]  phi(s_t, aR_t, aH_t)
    psi: jax.Array  # [E, T + 1, d] psi(s_t)


class ESRState(NamedTuple):
    params: dict  # {"phi": ..., "psi": ...}
    opt_state: tuple


BASE_METRICS = ("repr_loss", "mi_estimate", "contrastive_accuracy", "contrastive_chance")
# human_action: inferred. Logged for the researcher; the code metrics read the true actions and
# never enter a loss.
INFERRED_METRICS = ("latent_loss", "code_accuracy", "code_action_mi")


class ESR(NamedTuple):
    env: object
    spec: object  # ESRMethodSpec
    network_spec: object

    learns_policy: bool = True
    metric_names: tuple = BASE_METRICS
    all_metric_names = BASE_METRICS + INFERRED_METRICS  # not a field: those of any ESR spec
    acts_by_rule: bool = False
    has_reward_table: bool = True  # reward_table / reward_from_table (model/train.reward_table_pays)

    @classmethod
    def from_spec(cls, spec, env, human):
        inferred = spec.method.human_action == "inferred"
        return cls(env=env, spec=spec.method, network_spec=spec.network,
                   metric_names=BASE_METRICS + (INFERRED_METRICS if inferred else ()))

    @property
    def infers_human_action(self) -> bool:
        return self.spec.human_action == "inferred"

    @property
    def latent(self) -> LatentActions:
        return LatentActions(env=self.env, network_spec=self.network_spec, codes=self.spec.inferred_codes)

    def human_input(self, params, obs, human_action, next_obs):
        """What phi receives for the human: the true action (observed), or the latent code's
        distribution q(z | s, s') (inferred; the true action is never read)."""
        if self.infers_human_action:
            return jax.lax.stop_gradient(self.latent.code_probs(params, obs, next_obs))
        return human_action

    @property
    def updates_per_epoch(self) -> int:
        return self.spec.repr_updates_per_epoch

    @property
    def phi_net(self):
        return conv_net(self.network_spec, self.spec.repr_dim)

    @property
    def psi_net(self):
        return conv_net(self.network_spec, self.spec.repr_dim)

    @property
    def optimizer(self):
        return optax.adam(self.spec.repr_lr)

    def _appended(self, action, n: int):
        """[B, H, W, n]: the action's one-hot in cell (0, 0) only, zeros elsewhere. A network that
        flattens its input first (the MLP) then sees the one-hot once, as if appended to the
        flattened observation (the published Overcooked code); `broadcast` repeats it per cell."""
        vectors = jax.nn.one_hot(action, n) if jnp.issubdtype(action.dtype, jnp.integer) else action
        h, w = self.env.obs_shape[:2]
        return jnp.zeros((action.shape[0], h, w, n), jnp.float32).at[:, 0, 0, :].set(vectors)

    def _human_planes(self, human):
        """Planes for phi's human input: a true action [B] (int), or a code distribution [B, K]."""
        if not self.infers_human_action:
            if self.spec.action_input == "append":
                return self._appended(human, self.env.num_human_actions)
            return jax.vmap(self.env.human_action_planes)(human)
        if self.spec.action_input == "append":
            return self._appended(human, self.spec.inferred_codes)
        h, w = self.env.obs_shape[:2]
        return jnp.broadcast_to(human[:, None, None, :], (human.shape[0], h, w, human.shape[-1])).astype(jnp.float32)

    def _robot_planes(self, robot_action):
        if self.spec.action_input == "append":
            return self._appended(robot_action, self.env.num_robot_actions)
        return jax.vmap(self.env.robot_action_planes)(robot_action)

    def _phi_inputs(self, obs, robot_action, human):
        """[2B, H, W, C]: the phi'(s, aR) inputs stacked on the phi(s, aR, aH) inputs; `human` as
        `_human_planes` takes it."""
        ar = self._robot_planes(robot_action)
        ah = self._human_planes(human)
        if not self.spec.condition_on_robot_action:
            ar = jnp.zeros_like(ar)
        base = jnp.concatenate([obs.astype(jnp.float32), ar], axis=-1)
        with_human = jnp.concatenate([base, ah], axis=-1)
        without_human = jnp.concatenate([base, jnp.zeros_like(ah)], axis=-1)
        return jnp.concatenate([without_human, with_human], axis=0)

    def represent_phi(self, params, obs, robot_action, human):
        """-> (phi'(s, aR), phi(s, aR, aH)), each [B, repr_dim], in one pass of the network.
        `human`: the true actions, or with `human_action: inferred` the codes (`human_input`)."""
        both = self.phi_net.apply(params["phi"], self._phi_inputs(obs, robot_action, human))
        return tuple(jnp.split(both, 2, axis=0))

    def represent_future(self, params, future_obs):
        """psi(g), [B, repr_dim]. With `future: human` psi sees only the human's part of g
        (the environment's `human_view`), so the future cannot be matched by the layout."""
        if self.spec.future == "human":
            future_obs = jax.vmap(self.env.human_view)(future_obs)
        return self.psi_net.apply(params["psi"], future_obs)

    def represent(self, params, obs, robot_action, human, future_obs):
        """-> (phi'(s, aR), phi(s, aR, aH), psi(g)), each [B, repr_dim]."""
        phi_s, phi_sa = self.represent_phi(params, obs, robot_action, human)
        return phi_s, phi_sa, self.represent_future(params, future_obs)

    def represent_batch(self, params, batch):
        """`represent` of a replay batch, the human input chosen by `human_input`."""
        human = self.human_input(params, batch.obs, batch.human_action, batch.next_obs)
        return self.represent(params, batch.obs, batch.robot_action, human, batch.future_obs)

    def init(self, key, obs_example) -> ESRState:
        k_phi, k_psi, k_latent = jax.random.split(key, 3)
        a = jnp.zeros((1,), jnp.int32)
        human = jnp.zeros((1, self.spec.inferred_codes)) if self.infers_human_action else a
        phi_in = self._phi_inputs(obs_example[None], a, human)[:1]
        params = {
            "phi": self.phi_net.init(k_phi, phi_in),
            "psi": self.psi_net.init(k_psi, obs_example[None]),
        }
        if self.infers_human_action:
            params.update(self.latent.init(k_latent, obs_example, self._robot_planes(a)[0]))
        return ESRState(params=params, opt_state=self.optimizer.init(params))

    def update(self, state: ESRState, batch, key):
        def loss_fn(params):
            phi_s, phi_sa, psi = self.represent_batch(params, batch)
            loss = infonce_loss(phi_s, phi_sa, psi, self.spec.infonce)
            if not self.infers_human_action:
                return loss, (loss, phi_s, phi_sa, psi, ())
            latent_loss, logits = self.latent.loss(params, batch.obs, self._robot_planes(batch.robot_action), batch.next_obs, key)
            return loss + latent_loss, (loss, phi_s, phi_sa, psi, (latent_loss, logits))

        (_, (loss, phi_s, phi_sa, psi, latent)), params, opt_state = gradient_step(
            loss_fn, state.params, state.opt_state, self.optimizer)
        same = same_future(batch.future_obs)
        metrics = {
            "repr_loss": loss,
            "mi_estimate": mutual_information_estimate(phi_s, phi_sa, psi),
            "contrastive_accuracy": contrastive_accuracy(phi_sa, psi, same),
            "contrastive_chance": contrastive_chance(same),
        }
        if self.infers_human_action:  # logged only: the true actions reach no parameter
            latent_loss, logits = latent
            agreement = code_action_agreement(jnp.argmax(logits, axis=-1), batch.human_action,
                                              self.spec.inferred_codes, self.env.num_human_actions)
            metrics.update({"latent_loss": latent_loss, **jax.lax.stop_gradient(agreement)})
        return ESRState(params=params, opt_state=opt_state), metrics

    def reward(self, state: ESRState, batch, key):
        if self.spec.reward != "dot":
            human = self.human_input(state.params, batch.obs, batch.human_action, batch.next_obs)
            phi_s, phi_sa = self.represent_phi(state.params, batch.obs, batch.robot_action, human)
            return jax.lax.stop_gradient(simplified_reward(phi_s, phi_sa, self.spec.reward == "simplified_normalized"))
        phi_s, phi_sa, psi = self.represent_batch(state.params, batch)
        return jax.lax.stop_gradient(empowerment_reward(phi_s, phi_sa, psi))

    # The critic phase uses one set of representation parameters, so the runner may represent
    # every stored transition once and look its batches up (Trainer.reward_table_pays).
    def reward_table(self, state: ESRState, buf) -> RewardTable:
        steps = buf.robot_action.shape[1]

        def episode(args):
            obs, robot_action, human_action = args
            human = self.human_input(state.params, obs[:steps], human_action, obs[1 : steps + 1])
            phi_s, phi_sa = self.represent_phi(state.params, obs[:steps], robot_action, human)
            return phi_s, phi_sa, self.represent_future(state.params, obs)

        phi_s, phi_sa, psi = map_episodes(episode, (buf.obs, buf.robot_action, buf.human_action), steps)
        return jax.lax.stop_gradient(RewardTable(phi_s=phi_s, phi_sa=phi_sa, psi=psi))

    def reward_from_table(self, table: RewardTable, idx) -> jax.Array:
        """The reward of the batch at buffer index `idx` (model/replay.Index)."""
        if self.spec.reward != "dot":
            return simplified_reward(table.phi_s[idx.episode, idx.t], table.phi_sa[idx.episode, idx.t],
                                     self.spec.reward == "simplified_normalized")
        return empowerment_reward(
            table.phi_s[idx.episode, idx.t], table.phi_sa[idx.episode, idx.t], table.psi[idx.episode, idx.future]
        )
