"""The pieces of benchmarks/ainv_product.py that decide its findings: the scaled smaller storages of A₀⁻¹, their
numerics on a shipped model, and the verdict on positive definiteness."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import ainv_product  # noqa: E402

from tignn_jax import api  # noqa: E402


@pytest.mark.parametrize("storage, tol", [("float16", 5e-4), ("bfloat16", 4e-3), ("int16", 2e-5)])
def test_stored_round_trip_is_within_the_storage_precision(storage, tol):
    a = np.random.default_rng(0).normal(size=(40, 40)) * 1e-7   # tiny entries: the scale must carry them
    s, scale = ainv_product.stored(a, storage)
    back = np.asarray(s.astype(np.float32), np.float64) * scale
    assert np.abs(back - a).max() <= tol * np.abs(a).max()


def test_numerics_of_the_shipped_beam_flag_what_the_storage_breaks():
    if not (Path(api.MODELS_DIR) / "beam" / "model.npz").exists():
        pytest.skip("no shipped beam model in this checkout")
    params, _ = api.load_pretrained("beam")
    r, a = ainv_product.numerics(params)
    free = int((np.asarray(params["mesh"]["node_type"]) == 0).sum())
    assert r["dofs"] == 3 * free and a.shape == (3 * free, 3 * free)
    assert r["eig_float32"][0] > 0   # the shipped operator is positive definite
    for storage, x in r["storages"].items():
        assert x["positive_definite"] == (x["eig"][0] > 0), storage
        assert x["step_difference"] < 1e-3, storage   # one step barely moves
    # the beam's A₀⁻¹ has a condition number near 1e6: 11 bits (float16) cannot keep it definite, 16 (int16) can
    assert not r["storages"]["float16"]["positive_definite"] and r["storages"]["int16"]["positive_definite"]
    text = "\n".join(ainv_product.findings({"numerics": {"beam": r}, "times": {}}))
    assert "beam, float16: A₀⁻¹ is no longer positive definite" in text
