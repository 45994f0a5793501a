"""Test-session set-up: one persistent XLA compilation cache for every process of a test run.

The suite's time is mostly XLA compilation, and its processes (two pytest-xdist workers, the notebooks' kernels,
the CLI and benchmark subprocesses) compile many of the same programs (a shipped model's step, the demo's scene).
The cache lives in the checkout (``.jax_cache/``, ignored by git); set ``TIGNN_NO_JAX_CACHE=1`` to run without it.
"""
import os
from pathlib import Path

if not os.environ.get("TIGNN_NO_JAX_CACHE"):
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parent / ".jax_cache"))
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")


def pytest_configure(config):
    config.addinivalue_line("markers", "long: a heavier variant of a check the default run already makes (another "
                                       "cell type, a batched or multi-device form, a benchmark's smoke run whose "
                                       "functions other tests call); runs with TIGNN_LONG_TESTS=1")


def pytest_collection_modifyitems(config, items):
    if os.environ.get("TIGNN_LONG_TESTS") == "1":
        return
    import pytest

    skip = pytest.mark.skip(reason="a long variant: set TIGNN_LONG_TESTS=1 to run it")
    for item in items:
        if item.get_closest_marker("long") is not None:
            item.add_marker(skip)
