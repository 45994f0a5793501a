"""`RestStartGNN`: the paper's network started from rest at the quasi-static rate of its load."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tignn_jax as T
from tignn_jax import data as D
from tignn_jax import graph as G
from tignn_jax.simulators.generic_gnn import GenericGNN, GNNConfig
from tignn_jax.simulators.rest_start import RestStartGNN, rest_rate, start_from_rest, with_rest_start


def _laplacian_blocks(senders, receivers, n):
    """K₀ = (graph Laplacian of the mesh's edges + I) ⊗ I₃ as 3 × 3 node blocks: symmetric positive definite."""
    pairs = {(int(a), int(b)) for a, b in zip(senders, receivers) if a != b}
    degree = np.bincount([a for a, _ in pairs], minlength=n)
    rows = list(range(n)) + [a for a, _ in pairs]
    cols = list(range(n)) + [b for _, b in pairs]
    k = [(d + 1.0) * np.eye(3) for d in degree] + [-np.eye(3)] * len(pairs)
    return {"k_rows": np.array(rows), "k_cols": np.array(cols), "k": np.array(k, np.float32)}


@pytest.fixture(scope="module")
def toy():
    data = D.synthetic_beam(nx=4, ny=2, nz=2, cases=3, frames=4)
    norm = D.normalization(data, D.split_rows(data, "train"))
    mesh = {"q0": data.q0, "senders": data.edges[0], "receivers": data.edges[1], "node_type": data.node_type}
    gnn = GenericGNN(GNNConfig(hidden=16, mlp_layers=1, passes=1))
    stored = gnn.init(jax.random.PRNGKey(1), norm, mesh)
    blocks = _laplacian_blocks(*data.edges, len(data.q0))
    model = RestStartGNN(gnn.config)
    arrays = model.prepare({**stored, "rest_stiffness": blocks}, mesh)
    return dict(data=data, mesh=mesh, gnn=gnn, stored=stored, blocks=blocks, model=model, arrays=arrays,
                plain=gnn.prepare(stored, mesh), dt=float(np.asarray(norm["dt"]).reshape(-1)[0]))


def test_a_body_at_rest_starts_at_the_quasi_static_rate_of_its_load(toy):
    # K₀ (v₀ Δt) = f on the free nodes, v₀ = 0 on the clamped ones; q and σ are kept
    data, free = toy["data"], toy["data"].node_type == 0
    z = jnp.asarray(G.rest_state(data.q0), jnp.float32)
    f = np.random.default_rng(0).normal(size=(len(data.q0), 3)).astype(np.float32)
    started = np.asarray(start_from_rest(toy["arrays"], z, jnp.asarray(f)), np.float64)
    np.testing.assert_array_equal(started[:, :3], np.asarray(z[:, :3]))
    np.testing.assert_array_equal(started[:, 6:], 0.0)
    assert np.all(started[~free, 3:6] == 0.0)
    n = len(data.q0)
    K = np.zeros((n, 3, n, 3))
    for r, c, k in zip(toy["blocks"]["k_rows"], toy["blocks"]["k_cols"], toy["blocks"]["k"]):
        K[r, :, c, :] += k
    force = np.einsum("iajb,jb->ia", K, started[:, 3:6] * toy["dt"])
    np.testing.assert_allclose(force[free], f[free], atol=1e-4 * np.abs(f).max())


def test_a_moving_body_steps_as_the_papers_network(toy):
    data = toy["data"]
    z, f = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    assert float(jnp.abs(z[:, 3:6]).max()) > 0
    np.testing.assert_array_equal(np.asarray(toy["model"].step_state(toy["arrays"], z, f)),
                                  np.asarray(toy["gnn"].step_state(toy["plain"], z, f)))
    # at rest the first frame is the network's from (q₀, K₀⁻¹f/Δt, 0)
    rest = z.at[:, 3:].set(0.0)
    np.testing.assert_allclose(np.asarray(toy["model"].step_state(toy["arrays"], rest, f)),
                               np.asarray(toy["gnn"].step_state(toy["plain"], start_from_rest(toy["arrays"], rest, f),
                                                                f)), rtol=1e-6, atol=1e-6)


def test_saved_and_loaded_it_steps_the_same_and_loads_as_its_class(toy, tmp_path):
    params = T.make_params(toy["model"], toy["model"].stored(toy["arrays"]), toy["mesh"],
                           {"z_mean": np.zeros(12), "z_std": np.ones(12), "z_dev_max": np.ones(12),
                            "u_max": np.ones(1), "f_max": np.ones(1)})
    path = T.save_model(params, tmp_path / "m.npz")
    loaded = T.load_model(path)
    assert isinstance(loaded["model"], RestStartGNN)
    graph = T.rest_graph(loaded)
    f = np.zeros((len(toy["data"].q0), 3), np.float32)
    f[toy["data"].node_type == 0, 2] = -1.0
    a = T.step(loaded, graph, f).nodes["z"]
    b = T.step(params, T.rest_graph(params), f).nodes["z"]
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert float(jnp.abs(a[:, :3] - graph.nodes["z"][:, :3]).max()) > 0   # it moves from rest


def test_bad_rest_stiffness_is_named(toy):
    with pytest.raises(ValueError, match="rest_stiffness"):
        toy["model"].prepare(toy["stored"], toy["mesh"])
    far = dict(toy["blocks"], k_rows=toy["blocks"]["k_rows"] + 1000)
    with pytest.raises(ValueError, match="names node"):
        rest_rate(far, toy["data"].node_type, 0.05)
    with pytest.raises(ValueError, match="frame step"):
        rest_rate(toy["blocks"], toy["data"].node_type, 0.0)
    with pytest.raises(ValueError, match="must be a GenericGNN"):
        with_rest_start({"model": toy["model"]}, {})
