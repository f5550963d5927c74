"""Batches split over devices. Private to the distribution."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec


def sharded_vmap(fn, batch, devices=None):
    """``jax.vmap(fn)(batch)`` with the leading batch axis split over devices (``jax.sharding``).

    The batch (any pytree of arrays with a common leading axis) is padded to a multiple of the
    device count, laid out with a NamedSharding over a 1-D mesh, mapped under jit with the output
    sharded the same way, and un-padded. With one device this is plain jit(vmap).

    Args:
        fn: function of one batch element.
        batch: pytree of arrays with leading axis size N.
        devices: devices to use (default ``jax.devices()``)."""
    devices = list(jax.devices() if devices is None else devices)
    leaves = jax.tree_util.tree_leaves(batch)
    if not leaves or any(np.ndim(x) == 0 for x in leaves):
        raise ValueError("batch: expected a pytree of arrays with a leading batch axis")
    n = np.shape(leaves[0])[0]
    if any(np.shape(x)[0] != n for x in leaves):
        raise ValueError("batch: every leaf needs the same leading axis size")
    pad = (-n) % len(devices)
    if pad:
        batch = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), batch)
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    batch = jax.device_put(batch, sharding)
    out = jax.jit(jax.vmap(fn), out_shardings=sharding)(batch)
    return jax.tree_util.tree_map(lambda x: x[:n], out) if pad else out
