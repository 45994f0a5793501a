"""The per-node P-hop regression of benchmarks/bunny_local_fit.py, on a chain whose true map is known."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bunny_local_fit as blf  # noqa: E402


def _chain_world(n):
    idx = np.arange(n)
    return {"dist": np.abs(idx[:, None] - idx[None, :]).astype(float)}


def _true_map(n, hops, rng):
    """W [3n, 3n*3] on features ordered (dof, kind), non-zero only between nodes within ``hops``."""
    dist = _chain_world(n)["dist"]
    mask = np.repeat(np.repeat(dist <= hops, 3, 0), 9, 1)
    return 0.1 * rng.standard_normal((3 * n, 9 * n)) * mask


def test_one_hop_fit_recovers_a_one_hop_map_and_its_spectral_radius():
    rng = np.random.default_rng(0)
    n, h = 8, 0.05
    W = _true_map(n, 1, rng)
    x = rng.standard_normal((400, 3 * n, 3))
    y = x.reshape(len(x), -1) @ W.T
    fit = blf.LocalMap(_chain_world(n), 1, blf.LocalMap.moments(x, y), ridge=1e-12)
    x_new = rng.standard_normal((50, 3 * n, 3))
    pred = fit(*np.moveaxis(x_new, -1, 0))
    np.testing.assert_allclose(pred, x_new.reshape(50, -1) @ W.T, atol=1e-8)
    # the unforced map (u, v) -> (u', (u' - u)/h) of the true W, dense
    wu, wv = W[:, 0::3], W[:, 1::3]
    T = np.block([[wu, wv], [(wu - np.eye(3 * n)) / h, wv / h]])
    np.testing.assert_allclose(fit.radius(h), np.abs(np.linalg.eigvals(T)).max(), rtol=1e-6)
    assert fit.mean_support == (2 * 2 + 6 * 3) / 8     # the 2 end nodes see 2 nodes, the 6 inner ones 3


def test_a_fit_with_too_few_hops_cannot_reproduce_a_wider_map():
    rng = np.random.default_rng(1)
    n = 8
    W = _true_map(n, 2, rng)
    x = rng.standard_normal((400, 3 * n, 3))
    y = x.reshape(len(x), -1) @ W.T
    wide = blf.LocalMap(_chain_world(n), 2, blf.LocalMap.moments(x, y), ridge=1e-12)
    narrow = blf.LocalMap(_chain_world(n), 1, blf.LocalMap.moments(x, y), ridge=1e-12)
    err = lambda f: np.linalg.norm(f(*np.moveaxis(x, -1, 0)) - y) / np.linalg.norm(y)
    assert err(wide) < 1e-8
    assert err(narrow) > 0.3
