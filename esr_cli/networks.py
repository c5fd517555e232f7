"""Flax modules shared by the learner and the methods.

The gridworld networks of the original work: Conv(16, 3x3) SiLU, Conv(32, 3x3) SiLU, flatten,
Dense(hidden) SiLU, Dense(out). Inputs are channel-last grids; integer observations are cast
to float32 here so that buffers can hold compact uint8 grids.

Convolutions are computed as im2col + matmul (`PatchConv`): the same parameters and the same
function as a SAME-padded `nn.Conv`, but XLA's CPU backend runs the matmul form about 8x
faster inside `lax.scan` loops, where the whole training core lives (docs/performance.md).
"""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


def patches3x3(x: jax.Array) -> jax.Array:
    """[..., H, W, C] -> [..., H, W, 9C]: each cell's 3x3 neighbourhood (zero padded), row-major."""
    h, w = x.shape[-3], x.shape[-2]
    pad = [(0, 0)] * (x.ndim - 3) + [(1, 1), (1, 1), (0, 0)]
    xp = jnp.pad(x, pad)
    return jnp.concatenate([xp[..., i : i + h, j : j + w, :] for i in range(3) for j in range(3)], axis=-1)


class PatchConv(nn.Module):
    """A 3x3, stride-1, SAME-padded convolution (HWIO kernel, like nn.Conv) as a matmul."""

    features: int

    @nn.compact
    def __call__(self, x):
        c = x.shape[-1]
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (3, 3, c, self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        return patches3x3(x) @ kernel.reshape(9 * c, self.features) + bias


class ConvNet(nn.Module):
    conv_channels: Sequence[int]
    hidden: int
    out: int

    @nn.compact
    def __call__(self, x):
        x = x.astype(jnp.float32)
        for c in self.conv_channels:
            x = nn.silu(PatchConv(c)(x))
        x = x.reshape(x.shape[:-3] + (-1,))
        x = nn.silu(nn.Dense(self.hidden)(x))
        return nn.Dense(self.out)(x)


class MLP(nn.Module):
    """Flatten the [..., H, W, C] input, then tanh Dense layers with orthogonal init (the
    original Overcooked networks: 64-64)."""

    hidden: Sequence[int]
    out: int
    out_scale: float = 1.0

    @nn.compact
    def __call__(self, x):
        x = x.astype(jnp.float32)
        x = x.reshape(x.shape[:-3] + (-1,))
        for h in self.hidden:
            x = nn.tanh(nn.Dense(h, kernel_init=nn.initializers.orthogonal(2**0.5), bias_init=nn.initializers.zeros_init())(x))
        return nn.Dense(self.out, kernel_init=nn.initializers.orthogonal(self.out_scale), bias_init=nn.initializers.zeros_init())(x)


def conv_net(network_spec, out: int) -> nn.Module:
    """The network a spec's `network` section asks for: the conv net (kind conv, the default)
    or the MLP (kind mlp). Every method and the learner build their networks here."""
    if getattr(network_spec, "kind", "conv") == "mlp":
        return MLP(hidden=tuple(network_spec.mlp_layers), out=out)
    return ConvNet(conv_channels=tuple(network_spec.conv_channels), hidden=network_spec.hidden, out=out)
