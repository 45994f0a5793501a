"""Test-session set-up: one persistent XLA compilation cache for every process of a test run.

The suite's time is mostly XLA compilation, and its processes (two pytest-xdist workers, the notebooks' kernels,
the CLI and benchmark subprocesses) compile many of the same programs (a shipped model's step, the demo's scene).
The cache lives in the checkout (``.jax_cache/``, ignored by git); set ``TIGNN_NO_JAX_CACHE=1`` to run without it.
The tests' programs are compiled with JAX's ``jax_disable_most_optimizations`` (LLVM's expensive passes off; XLA's
graph optimisations, fusion included, stay on): they run once or a few times each, so compiling costs more than
running (`docs/research_log.md`), except in the tests marked ``optimized``, whose programs run long; set
``TIGNN_OPTIMIZE_TESTS=1`` to compile every test's programs as a user's programs are.
"""
import contextlib
import os
from pathlib import Path

import pytest

if not os.environ.get("TIGNN_NO_JAX_CACHE"):
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parent / ".jax_cache"))
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
if not os.environ.get("TIGNN_OPTIMIZE_TESTS"):
    os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")


def pytest_configure(config):
    config.addinivalue_line("markers", "optimized: a test whose programs run longer than they compile: compiled with "
                                       "LLVM's optimisations on")
    config.addinivalue_line("markers", "long: a heavier variant of a check the default run already makes (another "
                                       "cell type, a batched or multi-device form, a benchmark's smoke run whose "
                                       "functions other tests call); runs with TIGNN_LONG_TESTS=1")


def pytest_collection_modifyitems(config, items):
    if os.environ.get("TIGNN_LONG_TESTS") == "1":
        return
    skip = pytest.mark.skip(reason="a long variant: set TIGNN_LONG_TESTS=1 to run it")
    for item in items:
        if item.get_closest_marker("long") is not None:
            item.add_marker(skip)


@contextlib.contextmanager
def _llvm_optimisations():
    """Programs compiled inside are compiled with all of LLVM's optimisations (see the module docstring)."""
    import jax

    was = jax.config.values["jax_disable_most_optimizations"]
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", was)


@pytest.fixture(autouse=True)
def _optimized_compilation(request):
    """Compile an ``optimized`` test's programs with all of LLVM's optimisations (see the module docstring)."""
    if request.node.get_closest_marker("optimized") is None:
        yield
        return
    with _llvm_optimisations():
        yield


@pytest.fixture(scope="session")
def optimized():
    """A context manager: the programs compiled inside it are compiled with LLVM's optimisations, for a part of a
    test (a reference computed over many steps) whose programs run longer than they compile."""
    return _llvm_optimisations
