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


def test_the_linear_message_passing_probe_is_linear_in_the_state_and_sees_p_hops():
    import jax
    import jax.numpy as jnp

    import bunny_linear_gnn as lg

    n, layers = 9, 2
    s = np.concatenate([np.arange(n - 1), np.arange(1, n)])        # a chain, both directions
    r = np.concatenate([np.arange(1, n), np.arange(n - 1)])
    g = jnp.asarray(np.random.default_rng(0).standard_normal((len(s), 13)), jnp.float32)
    p = lg.init(jax.random.PRNGKey(0), layers, 8, 13)
    x1, x2 = (jnp.asarray(np.random.default_rng(k).standard_normal((2, n, 9)), jnp.float32) for k in (1, 2))
    f = lambda x: lg.apply(p, x, g, jnp.asarray(s), jnp.asarray(r))
    np.testing.assert_allclose(f(2.0 * x1 - 3.0 * x2), 2.0 * f(x1) - 3.0 * f(x2), rtol=1e-4, atol=1e-6)
    # a disturbance at node 0 reaches nodes 0..layers and no further
    kick = jnp.zeros((1, n, 9)).at[0, 0, 0].set(1.0)
    reached = np.abs(np.asarray(f(kick))[0]).sum(1) > 0
    assert reached[: layers + 1].all() and not reached[layers + 1:].any()
