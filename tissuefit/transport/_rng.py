"""Random numbers as a function of (key, photon index, event counter).

Each photon owns a xoshiro128** stream (Blackman & Vigna 2018, "Scrambled linear pseudorandom
number generators") whose 128-bit state is seeded by Threefry-2x32 (Salmon et al. 2011, JAX's own
counter-based hash) of (key, photon index). The n-th number a photon draws is therefore a pure
function of (key, photon index, n): results do not depend on the lane count, the batch size or the
order in which lanes finish. xoshiro128** costs a few integer operations per draw, several times
less than a Threefry-20 hash per draw, which matters at ~4 draws per photon step.

Uniforms are in (0, 1] (never 0, so -ln(xi) is finite), with 24 bits for float32 and 32 bits for
float64 working precision.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.extend.random import threefry2x32_p
from jaxtyping import Array, Float, UInt

RngState = tuple[Array, Array, Array, Array]


def key_words(key: Array) -> tuple[Array, Array]:
    """The two uint32 words of a JAX PRNG key (new-style or raw uint32[2])."""
    data = jax.random.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else key
    data = data.reshape(-1).astype(jnp.uint32)
    return data[0], data[1]


def hash2(words: tuple[Array, Array], a: UInt[Array, " n"], b: UInt[Array, " n"]) -> tuple[Array, Array]:
    """Threefry-2x32 of the counter pair (a, b) under the key `words`."""
    k0 = jnp.broadcast_to(words[0], a.shape)
    k1 = jnp.broadcast_to(words[1], a.shape)
    out = threefry2x32_p.bind(k0, k1, a.astype(jnp.uint32), b.astype(jnp.uint32))
    return out[0], out[1]


def seed_streams(words: tuple[Array, Array], photon: UInt[Array, " lanes"], stream: int = 0) -> RngState:
    """Initial xoshiro128** states for photons `photon` (stream selects an independent family)."""
    s0, s1 = hash2(words, photon, jnp.full_like(photon, 2 * stream))
    s2, s3 = hash2(words, photon, jnp.full_like(photon, 2 * stream + 1))
    # The all-zero state is xoshiro's fixed point; Threefry makes it a 2^-128 event, but be exact.
    s3 = jnp.where((s0 | s1 | s2 | s3) == 0, jnp.uint32(1), s3)
    return s0, s1, s2, s3


def _rotl(x: Array, k: int) -> Array:
    return (x << k) | (x >> (32 - k))


def next_bits(state: RngState) -> tuple[UInt[Array, " lanes"], RngState]:
    """One 32-bit output of xoshiro128** and the advanced state."""
    s0, s1, s2, s3 = state
    out = _rotl(s1 * jnp.uint32(5), 7) * jnp.uint32(9)
    t = s1 << 9
    s2 = s2 ^ s0
    s3 = s3 ^ s1
    s1 = s1 ^ s2
    s0 = s0 ^ s3
    s2 = s2 ^ t
    s3 = _rotl(s3, 11)
    return out, (s0, s1, s2, s3)


def bits_to_uniform(bits: UInt[Array, " n"], dtype) -> Float[Array, " n"]:
    """Map uint32 bits to a uniform in (0, 1] of `dtype`."""
    if jnp.dtype(dtype) == jnp.float32:
        return ((bits >> 8).astype(jnp.float32) + 1.0) * jnp.float32(2.0**-24)
    return (bits.astype(jnp.float64) + 1.0) * (2.0**-32)


def next_uniform(state: RngState, dtype) -> tuple[Float[Array, " lanes"], RngState]:
    bits, state = next_bits(state)
    return bits_to_uniform(bits, dtype), state


def radical_inverse(index: Array, base: int, dtype) -> Array:
    """Van der Corput radical inverse of non-negative integers `index` in `base` (Halton 1960)."""
    digits = {2: 32, 3: 21, 5: 14, 7: 12}.get(base, 32)
    i = index.astype(jnp.int64)
    result = jnp.zeros(index.shape, jnp.float64)
    scale = 1.0 / base
    for _ in range(digits):
        result = result + (i % base).astype(jnp.float64) * scale
        i = i // base
        scale /= base
    return result.astype(dtype)


def halton_uniforms(words: tuple[Array, Array], photon: Array, dtype) -> Float[Array, "lanes 2"]:
    """Two-dimensional Halton points (bases 2, 3) for photon indices, in (0, 1].

    A Cranley–Patterson rotation by a shift drawn from the key randomises the sequence, so independent
    keys give independent estimates while each run keeps Halton's low discrepancy.
    """
    shift0, shift1 = hash2(words, jnp.zeros(1, jnp.uint32), jnp.full((1,), 0xFFFFFFFF, jnp.uint32))
    shift = jnp.stack([bits_to_uniform(shift0, jnp.float64), bits_to_uniform(shift1, jnp.float64)], -1)
    pts = jnp.stack(
        [radical_inverse(photon + 1, 2, jnp.float64), radical_inverse(photon + 1, 3, jnp.float64)], -1
    )
    u = jnp.mod(pts + shift, 1.0)
    return jnp.where(u == 0.0, 1.0, u).astype(dtype)
