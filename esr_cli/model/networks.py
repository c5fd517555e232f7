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


# The original's dense layers (Haiku's `hk.Linear`) draw weights from a normal of standard
# deviation 1/sqrt(fan_in) truncated at 2 deviations, *without* rescaling for the truncation,
# so their spread is 0.88/sqrt(fan_in); flax's default (lecun_normal) rescales to 1/sqrt(fan_in).
# Matching it matters early in training: a wider initial spread of Q and of the reward
# makes the dual step sharpen the robot's policy sooner. Convolutions already match (Haiku's
# Conv2D default is the rescaled one, as flax's).
TRUNCATED_NORMAL_STD = 0.87962566103423978  # std of a standard normal truncated to [-2, 2]
haiku_linear_init = nn.initializers.variance_scaling(TRUNCATED_NORMAL_STD**2, "fan_in", "truncated_normal")


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
        x = nn.silu(nn.Dense(self.hidden, kernel_init=haiku_linear_init)(x))
        return nn.Dense(self.out, kernel_init=haiku_linear_init)(x)


def orthogonal(scale: float = 1.0):
    """Orthogonal initializer (as flax's `nn.initializers.orthogonal` for 2-D kernels) by
    Gram-Schmidt in plain XLA ops. flax's uses a QR decomposition (a LAPACK call on CPU), and
    several of those in one program vmapped over seeds deadlock XLA's CPU runtime on 2 cores
    (jax 0.10.2); this one compiles to matmuls. Q has the distribution of flax's: the Q
    factor of a Gaussian matrix with R's diagonal made positive, which Gram-Schmidt gives."""

    def init(key, shape, dtype=jnp.float32):
        if len(shape) != 2:
            raise ValueError(f"orthogonal init here is for 2-D kernels, got shape {shape}")
        rows, cols = shape
        tall = (rows, cols) if rows >= cols else (cols, rows)
        a = jax.random.normal(key, tall, jnp.float32)

        def column(j, q):
            v = a[:, j]
            for _ in range(2):  # orthogonalise twice: numerically orthogonal to float precision
                v = v - q @ (q.T @ v)  # columns not yet filled are zero and subtract nothing
            return q.at[:, j].set(v / jnp.linalg.norm(v))

        q = jax.lax.fori_loop(0, tall[1], column, jnp.zeros(tall, jnp.float32))
        q = q if rows >= cols else q.T
        return (scale * q).astype(dtype)

    return init


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
            x = nn.tanh(nn.Dense(h, kernel_init=orthogonal(2**0.5), bias_init=nn.initializers.zeros_init())(x))
        return nn.Dense(self.out, kernel_init=orthogonal(self.out_scale), bias_init=nn.initializers.zeros_init())(x)


def conv_net(network_spec, out: int) -> nn.Module:
    """The network a spec's `network` section asks for: the conv net (kind conv, the default)
    or the MLP (kind mlp). Every method and the learner build their networks here."""
    if getattr(network_spec, "kind", "conv") == "mlp":
        return MLP(hidden=tuple(network_spec.mlp_layers), out=out)
    return ConvNet(conv_channels=tuple(network_spec.conv_channels), hidden=network_spec.hidden, out=out)
