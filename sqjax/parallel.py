"""Batches split over the local CPU devices.

XLA runs a small kernel on one core. Given several CPU devices (JAX's `jax_num_cpu_devices`, or
`XLA_FLAGS=--xla_force_host_platform_device_count=N`, set before JAX starts; the command line and the
benchmarks give one per core), a batch of independent problems or pairs is split between them with
`shard_map`, one block per device, and every problem runs the same code as on one device. The results
are the same bit for bit where a device's block is fitted in chunks of the same width as the whole
batch would be; otherwise (`solver.map_problems` fits min(K, chunk) problems at a time, and a block
holds fewer than the whole batch) they agree to rounding, and a segmentation's thresholded decisions
can then go the other way: the iCub cylinder (`robotology_find_superquadric/cylinder.txt`) keeps a
1.6 m rod for 0.23 m of points in a one-device process and a 0.25 m one with two devices (2026-12-05),
one of the benchmark's scenes where the spread shows (`benchmarks/segment.py --perturb`). The meshes
suite of `benchmarks/segment.py` gives 51 of 77 parts correct with two devices and 45 with one
(2026-12-06): compare runs at one device count. On an accelerator, or with one CPU device, nothing is
split.
"""

from __future__ import annotations

import functools

import jax
import numpy as np


def cpu_devices() -> int:
    """The number of local CPU devices a batch can be split over (1 on an accelerator)."""
    devices = jax.local_devices()
    return len(devices) if devices[0].platform == "cpu" else 1


def splits(n: int, at_least: int = 0) -> bool:
    """Whether a batch of n problems is split: several CPU devices, they divide n, and n >= `at_least`
    (a pair kernel's smaller calls run faster whole: `padding.PAIRS`)."""
    d = cpu_devices()
    return d > 1 and n % d == 0 and n >= at_least


def device_mesh() -> jax.sharding.Mesh:
    """The local devices in one axis, "k": what `shard` splits a batch over."""
    return jax.sharding.Mesh(np.array(jax.local_devices()), ("k",))


def shard(fn, sharded: tuple[bool, ...]):
    """`fn` (a function of arrays) over the CPU devices: the arguments marked in `sharded` split along
    their first axis, the others replicated; the outputs joined along their first axis."""
    mesh = device_mesh()
    spec = jax.sharding.PartitionSpec
    in_specs = tuple(spec("k") if s else spec() for s in sharded)
    return jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=spec("k"), check_vma=False)


@functools.cache
def sharded_kernel(fn, sharded: tuple[bool, ...]):
    """`jax.jit(shard(fn, sharded))` with sqjax's compiler options (`cache.kernel_jit`), made once per
    function and pattern, and kept on disk with the compilation cache (`cache.persistent_kernel`)."""
    from .cache import kernel_jit, persistent_kernel

    name = f"{fn.__module__}.{fn.__qualname__}.split{''.join('s' if s else 'r' for s in sharded)}"
    return persistent_kernel(kernel_jit(shard(fn, sharded)), name=name)


def use_cpu_cores(n: int | None = None) -> int:
    """Give JAX one CPU device per core (or `n`), so that batches are split over them.

    Call it before JAX runs anything (the command line and the benchmarks do); afterwards, or when a
    device count was chosen already (`XLA_FLAGS=--xla_force_host_platform_device_count`,
    `JAX_NUM_CPU_DEVICES`), it changes nothing. Returns the number of CPU devices in effect."""
    import os

    chosen = "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", "")
    if not chosen and not os.environ.get("JAX_NUM_CPU_DEVICES"):
        try:
            jax.config.update("jax_num_cpu_devices", int(n or os.cpu_count() or 1))
        except RuntimeError:  # JAX has started: its devices stay as they are
            pass
    return cpu_devices()
