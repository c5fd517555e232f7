"""The paper's Overcooked human network: a convolutional actor-critic in the shape of the
Boltzmann-policy-distribution codebase's Overcooked PPO model (Laidlaw and Dragan 2022,
cassidylaidlaw/boltzmann-policy-distribution, bpd/models/overcooked_models.py, with the
defaults of bpd/experiments/train_overcooked.py).

Each tower: Conv(25, 5x5, padded to keep the size), Conv(25, 3x3, padded), Conv(25, 3x3,
unpadded: the grid shrinks by 2 each way), flatten, then three Dense(64), leaky ReLU after
every layer. The policy head is Dense(6) on one tower; the value head Dense(1) on a second,
separate tower (BPD's `vf_share_layers = False`): nothing is shared between the two.

Input: overcooked-ai's lossless encoding layout (W, H, 26). JaxMARL's `get_obs` gives
(H, W, 26), so the human reads `overcooked_ai_view(obs)`, as the paper authors' code did
(vivekmyers/empowerment_successor_representations, networks/human.py, transposes its input
before the first convolution). The urgency channel is kept: this human is trained in
400-step episodes, so the channel means what it says.

Initialisation follows PyTorch's layer defaults (BPD's model is PyTorch): weights and biases
uniform in +-1/sqrt(fan_in). The flatten is channel-major, as PyTorch flattens NCHW maps, so
weights converted from a BPD checkpoint would line up.

Convolutions are im2col + matmul (as esr_cli.model.networks.PatchConv, generalised to 5x5 and
unpadded): the same function and parameters (HWIO kernels) as `nn.Conv`, faster on XLA's CPU
backend inside `lax.scan`.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from esr_cli.model.envs.overcooked import NUM_ACTIONS

FILTERS = 25
HIDDEN = 64
NUM_HIDDEN_LAYERS = 3
# (kernel size, padding per side) of the three convolutions: 5x5 SAME, 3x3 SAME, 3x3 VALID.
CONV_LAYERS = ((5, 2), (3, 1), (3, 0))


def overcooked_ai_view(obs: jax.Array) -> jax.Array:
    """JaxMARL's [..., H, W, 26] observation as overcooked-ai's [..., W, H, 26] (every channel
    kept, urgency included; dtype unchanged)."""
    return jnp.swapaxes(obs, -3, -2)


def torch_uniform(fan_in: int):
    """PyTorch's default for Linear and Conv2d weights and biases: U(-1/sqrt(fan_in), 1/sqrt(fan_in))."""
    bound = 1.0 / fan_in**0.5

    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


def patches(x: jax.Array, size: int, pad: int) -> jax.Array:
    """[..., A, B, C] -> [..., A', B', size*size*C]: each output cell's size x size window
    (zero padded by `pad` on every side), ordered (row, column, channel) like an HWIO kernel."""
    a, b = x.shape[-3] + 2 * pad - size + 1, x.shape[-2] + 2 * pad - size + 1
    xp = jnp.pad(x, [(0, 0)] * (x.ndim - 3) + [(pad, pad), (pad, pad), (0, 0)])
    return jnp.concatenate([xp[..., i : i + a, j : j + b, :] for i in range(size) for j in range(size)], axis=-1)


class Conv(nn.Module):
    """A stride-1 convolution with `pad` zeros on each side, as a matmul (HWIO kernel)."""

    features: int
    size: int
    pad: int

    @nn.compact
    def __call__(self, x):
        c = x.shape[-1]
        fan_in = self.size * self.size * c
        kernel = self.param("kernel", torch_uniform(fan_in), (self.size, self.size, c, self.features))
        bias = self.param("bias", torch_uniform(fan_in), (self.features,))
        return patches(x, self.size, self.pad) @ kernel.reshape(fan_in, self.features) + bias


def dense(features: int, fan_in: int, name: str | None = None) -> nn.Dense:
    return nn.Dense(features, kernel_init=torch_uniform(fan_in), bias_init=torch_uniform(fan_in), name=name)


class Tower(nn.Module):
    """Three convolutions, channel-major flatten, three dense layers; leaky ReLU throughout."""

    filters: int = FILTERS
    hidden: int = HIDDEN
    num_hidden_layers: int = NUM_HIDDEN_LAYERS

    @nn.compact
    def __call__(self, x):
        for size, pad in CONV_LAYERS:
            x = nn.leaky_relu(Conv(self.filters, size, pad)(x))  # slope 0.01, as torch's LeakyReLU
        x = jnp.moveaxis(x, -1, -3)  # [..., F, W', H']: PyTorch's flatten order
        x = x.reshape(x.shape[:-3] + (-1,))
        for _ in range(self.num_hidden_layers):
            x = nn.leaky_relu(dense(self.hidden, x.shape[-1])(x))
        return x


class ConvActorCritic(nn.Module):
    """[..., W, H, 26] (overcooked-ai layout; any dtype) -> (policy logits [..., 6], value [...])."""

    filters: int = FILTERS
    hidden: int = HIDDEN
    num_hidden_layers: int = NUM_HIDDEN_LAYERS
    num_actions: int = NUM_ACTIONS

    @nn.compact
    def __call__(self, x):
        x = x.astype(jnp.float32)
        tower = lambda name: Tower(self.filters, self.hidden, self.num_hidden_layers, name=name)  # noqa: E731
        logits = dense(self.num_actions, self.hidden, "policy_head")(tower("policy_tower")(x))
        value = dense(1, self.hidden, "value_head")(tower("value_tower")(x))[..., 0]
        return logits, value


def init_params(key: jax.Array, height: int, width: int, net: ConvActorCritic | None = None):
    """Parameters for a layout of JaxMARL size (height, width)."""
    net = net or ConvActorCritic()
    return net.init(key, jnp.zeros((width, height, 26), jnp.float32))


def apply_jaxmarl(params, obs: jax.Array, net: ConvActorCritic | None = None):
    """The network on JaxMARL observations [..., H, W, 26] -> (logits [..., 6], value [...])."""
    return (net or ConvActorCritic()).apply(params, overcooked_ai_view(obs))


def policy_logits(params, obs: jax.Array) -> jax.Array:
    """The human's policy logits [..., 6] from its JaxMARL observation [..., H, W, 26]."""
    return apply_jaxmarl(params, obs)[0]


def parameter_count(params) -> int:
    return int(sum(leaf.size for leaf in jax.tree.leaves(params)))
