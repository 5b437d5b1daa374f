"""Data-parallel learners: one seed's work split over several devices of this host.

``split_batch(grad_fn, devices, batch_argnum)`` wraps ``grad_fn(*args) -> (loss, grads)`` so that each
of ``devices`` devices takes an equal share of the batch argument (its leading axis), computes the
loss and gradient of its share, and the shares are averaged (``pmean``). For a loss that is a mean
over equally weighted batch rows this is the whole batch's loss and gradient, equal to one device's
up to float rounding. ``split_rows(fn, devices, batch_argnum)`` does the same for a row-wise ``fn``
(each output row depends on its input row only): the shares' outputs are concatenated. Everything
else in the jitted program stays replicated on every device (``whole_on(devices)`` lays a learner's initial
state out so). ``rows_over(devices)`` lays arrays' rows over the devices and lets XLA split whatever
computes with them (PPO: the envs of the rollout and the samples of each minibatch). ``over_devices(fn,
xs)`` splits whole independent runs instead: ``jax.vmap(fn)(xs)`` with the rows of ``xs`` (one per seed)
spread over the process's devices, each device vmapping its own rows.

On a CPU, JAX sees one device unless it is told otherwise before it first runs:
``use_cpu_devices(n)`` (what ``marbler-jax train`` calls for ``--hp learner_devices=n`` and, with one
device per core, for ``--seed-batching devices``) splits the host into ``n`` CPU devices, each running
its share on its own thread: a single-device step of small matmuls leaves most of a second core idle,
which a second device puts to work (BENCHMARKS.md).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "batch"
SEEDS_AXIS = "seeds"


def use_cpu_devices(n: int) -> None:
    """Ask JAX for ``n`` CPU devices; must run before JAX first computes anything (else a no-op that
    :func:`split_batch` then reports)."""
    if n > 1 and jax.config.jax_num_cpu_devices < n:
        try:
            jax.config.update("jax_num_cpu_devices", n)
        except RuntimeError:        # the backend already started: split_batch says what to do
            pass


def _mesh(devices: int, axis: str = AXIS) -> Mesh:
    available = jax.local_devices()        # this process's own, also under jax.distributed
    if len(available) < devices:
        raise ValueError(
            f"learner_devices={devices} needs {devices} devices but JAX has {len(available)} "
            f"({available[0].platform}); on a CPU call marbler_jax_rl.data_parallel.use_cpu_devices({devices}) "
            f"(or set jax.config 'jax_num_cpu_devices') before JAX first runs -- marbler-jax train does this")
    return Mesh(np.array(available[:devices]), (axis,))


def _laid_out(devices: int, spec: PartitionSpec):
    """``tree -> tree`` with every leaf constrained to ``spec`` over ``devices`` devices inside a jitted
    program; the identity for one device."""
    if devices == 1:
        return lambda tree: tree
    sharding = NamedSharding(_mesh(devices), spec)
    return lambda tree: jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, sharding), tree)


def whole_on(devices: int):
    """``place(tree)``: every leaf whole on each of ``devices`` devices inside a jitted program (the
    identity for one device). A program split by :func:`split_batch` / :func:`split_rows` returns its
    state laid out so; its initial state laid out the same way enters it as every later call's does, so
    the program compiles once."""
    return _laid_out(devices, PartitionSpec())


def rows_over(devices: int):
    """``spread(tree)``: every leaf's leading axis (its rows: envs, samples) laid over ``devices``
    devices inside a jitted program, the rest of the program left to XLA's partitioner; the identity for
    one device. What is computed is unchanged, so a program spread this way gives one device's results up
    to float rounding (its random draws too: JAX's random bits do not depend on the layout)."""
    return _laid_out(devices, PartitionSpec(AXIS))


def _specs(args, batch_argnum: int):
    return tuple(PartitionSpec(AXIS) if i == batch_argnum else PartitionSpec() for i in range(len(args)))


def split_batch(grad_fn, devices: int, batch_argnum: int):
    """``grad_fn`` with its ``batch_argnum``-th argument (a pytree of ``[B, ...]`` arrays, ``B``
    divisible by ``devices``) split over the first ``devices`` devices; returns ``grad_fn`` unchanged
    for ``devices == 1``."""
    if devices == 1:
        return grad_fn
    mesh = _mesh(devices)

    def share(*args):
        return jax.lax.pmean(grad_fn(*args), AXIS)

    def wrapped(*args):
        return jax.shard_map(share, mesh=mesh, in_specs=_specs(args, batch_argnum), out_specs=PartitionSpec(),
                             check_vma=False)(*args)

    return wrapped


def split_rows(fn, devices: int, batch_argnum: int):
    """Row-wise ``fn`` (output rows ``[B, ...]`` from input rows) with its ``batch_argnum``-th argument
    split over ``devices`` devices and the outputs concatenated; ``fn`` itself where ``devices == 1`` or
    ``B`` is not divisible by ``devices``."""
    if devices == 1:
        return fn
    mesh = _mesh(devices)

    def wrapped(*args):
        rows = jax.tree_util.tree_leaves(args[batch_argnum])[0].shape[0]
        if rows % devices:
            return fn(*args)
        return jax.shard_map(fn, mesh=mesh, in_specs=_specs(args, batch_argnum), out_specs=PartitionSpec(AXIS),
                             check_vma=False)(*args)

    return wrapped


def over_devices(fn, xs):
    """``jax.vmap(fn)(xs)`` with the leading axis of ``xs`` (``[S, ...]`` leaves: one row per seed) split
    over ``min(S, local devices)`` devices, each vmapping its share; the outputs are ``[S, ...]`` like
    vmap's, equal to them up to float rounding. ``S`` not divisible by the device count is padded by
    repeating the last row, whose duplicate results are dropped. ``fn`` must not itself split over
    devices (:func:`split_batch`)."""
    rows = jax.tree_util.tree_leaves(xs)[0].shape[0]
    count = min(rows, jax.local_device_count())
    if count == 1:
        return jax.vmap(fn)(xs)
    pad = -rows % count
    if pad:
        xs = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), xs)
    out = jax.shard_map(jax.vmap(fn), mesh=_mesh(count, SEEDS_AXIS), in_specs=PartitionSpec(SEEDS_AXIS),
                        out_specs=PartitionSpec(SEEDS_AXIS), check_vma=False)(xs)
    return jax.tree_util.tree_map(lambda x: x[:rows], out) if pad else out


__all__ = ["split_batch", "split_rows", "over_devices", "rows_over", "whole_on", "use_cpu_devices"]
