"""Process set-up of the real-time loop: CPU pinning, one CPU device per core, and XLA:CPU options.

All of these act only before JAX's first operation in the process (XLA:CPU sizes its thread pool and creates its
devices when its backend starts), so a program calls them first, in this order::

    real_time_xla_flags()                 # XLA_FLAGS, read when the backend starts
    pinned, devices = real_time_cores(n)  # pinned to n CPUs, one CPU device per core

Comparisons of the loop pinned and unpinned: see benchmarks/pinning.py.
"""
from __future__ import annotations

import os
import warnings

import jax
import numpy as np

from tignn_jax.api import YNN_FUSION_OPTION

REAL_TIME_XLA_FLAG = f"--{YNN_FUSION_OPTION}="   # the option the public step compiles its frame with


def real_time_xla_flags(environ=None) -> bool:
    """Turn off XLA:CPU's YNNPACK fusions for this process, unless the user already chose a fusion type.

    Appends ``REAL_TIME_XLA_FLAG`` to ``XLA_FLAGS``; like `cpu_devices` it acts only before JAX's first operation.
    The option makes the learned models' frame step faster on XLA:CPU and leaves its states the same to float32
    rounding (a later jaxlib may differ).

    Args:
      environ: the environment to change (default: ``os.environ``).

    Returns:
      Whether the option was added.
    """
    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    if REAL_TIME_XLA_FLAG.split("=")[0] in flags:
        return False
    environ["XLA_FLAGS"] = f"{flags} {REAL_TIME_XLA_FLAG}".strip()
    return True


def pin_cores(n: int) -> tuple:
    """Pin this process to ``n`` of the CPUs it may run on (the lowest-numbered ones).

    Every thread the process has now is pinned, and threads start with their creator's CPUs, so call it before
    JAX's first operation: XLA:CPU sizes its thread pool by the CPUs a process may use when its backend starts,
    and a pool made for more cores and then squeezed onto fewer is slower than either. Why pin: a loop on one
    pinned core has steadier frame times (p99 close to p50) than one spread over cores that each wait for the
    slowest (see benchmarks/pinning.py).

    Args:
      n: the number of CPUs, >= 1.

    Returns:
      The pinned CPU ids (sorted), or () where the platform cannot pin (no ``os.sched_setaffinity``: nothing is
      changed there).

    Raises:
      ValueError: ``n`` is not a positive integer, or more than the CPUs the process may use.
      RuntimeError: JAX's backend has already started and ``n`` is fewer than the CPUs the process may use
        (nothing is changed).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    if not hasattr(os, "sched_setaffinity"):
        return ()
    allowed = sorted(os.sched_getaffinity(0))
    if n > len(allowed):
        raise ValueError(f"n = {n} is more than the {len(allowed)} CPUs this process may use ({allowed})")
    cpus = set(allowed[:n])
    if n < len(allowed):
        from jax._src import xla_bridge
        if xla_bridge.backends_are_initialized():
            raise RuntimeError(f"pin_cores({n}) must run before JAX's first operation: the backend has already "
                               f"sized its thread pool for {len(allowed)} CPUs")
    for tid in os.listdir("/proc/self/task") if os.path.isdir("/proc/self/task") else ["0"]:
        try:
            os.sched_setaffinity(int(tid), cpus)
        except (ProcessLookupError, PermissionError):   # a thread that ended meanwhile, or one not ours to move
            pass
    return tuple(sorted(cpus))


def real_time_cores(n: int) -> tuple:
    """Set this process up as ``tignn demo --cores n`` runs: pinned to ``n`` CPUs, one CPU device per core.

    `pin_cores` then `cpu_devices`. Both act only before JAX's first operation, so call it first (after
    `real_time_xla_flags`). Where JAX has already started (a notebook, a test) the process stays unpinned and a
    warning says so.

    Args:
      n: the number of cores.

    Returns:
      (pinned CPU ids, or () where not pinned; the local devices).

    Raises:
      ValueError: a bad ``n`` (as `pin_cores`).
    """
    try:
        pinned = pin_cores(n)
    except RuntimeError as e:
        warnings.warn(f"not pinned: {e}", stacklevel=2)
        pinned = ()
    return pinned, cpu_devices(n)


def cpu_devices(n: int) -> tuple:
    """The local devices after asking JAX for ``n`` CPU devices (``jax_num_cpu_devices``).

    One device per core is what ``Scene.devices`` (`tignn_jax.mr.scene`) wants. The count can only be set before
    JAX's first operation in the process; after it, or on an accelerator, this returns the devices there already
    are (a one-device tuple leaves a scene serial).

    Args:
      n: the number of CPU devices, >= 1.

    Returns:
      ``jax.local_devices()`` as a tuple.

    Raises:
      ValueError: ``n`` is not a positive integer.
    """
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    try:
        jax.config.update("jax_num_cpu_devices", int(n))
    except RuntimeError:   # the backend is already initialised: keep what it has
        pass
    return tuple(jax.local_devices())
