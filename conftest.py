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


# The files whose tests take longest (measured on a cold cache), heaviest first: pytest-xdist hands out whole files
# (``--dist loadfile``) in collection order (``--no-loadscope-reorder``), so the two workers start on these and
# finish together on the short files, instead of one worker ending alone on a notebook or an end-to-end check.
HEAVIEST_FIRST = ("tests/test_render.py", "tests/test_benchmarks_mr.py", "tests/test_view.py",
                  "tests/test_train_linear.py", "tests/test_user_mesh.py", "tests/test_fem_dynamics.py",
                  "tests/test_shipped_models.py", "tests/test_corotational.py", "tests/test_fem_elements.py",
                  "tests/test_generic_gnn.py", "tests/test_cli.py", "tests/test_fem_scenes.py",
                  "notebooks/02_reference_beam.ipynb", "tests/test_fem_gradients.py",
                  "notebooks/01_fem_verification.ipynb", "tests/test_stability.py", "tests/test_fem_implicit.py",
                  "tests/test_cli_demo.py", "tests/test_pinning.py", "notebooks/03_train_small_model.ipynb",
                  "notebooks/04_mixed_reality.ipynb")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVIEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))   # stable: file order kept
    if os.environ.get("TIGNN_LONG_TESTS") == "1":
        return
    import pytest

    skip = pytest.mark.skip(reason="a long variant: set TIGNN_LONG_TESTS=1 to run it")
    for item in items:
        if item.get_closest_marker("long") is not None:
            item.add_marker(skip)
