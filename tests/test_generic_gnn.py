"""The thermodynamics-informed graph network (`GenericGNN`): the GENERIC structure of its step, its gradients, the
clamped nodes, the graph layout and its configuration."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tignn_jax import data as D
from tignn_jax.simulators import generic_gnn as GG
from tignn_jax.simulators.generic_gnn import GenericGNN, GNNConfig
from tignn_jax.train import gnn as T

CONFIG = GNNConfig(hidden=8, mlp_layers=2, passes=2)
# the model's methods compiled (the model static), as `tignn_jax.api` runs them
step = jax.jit(GenericGNN.step_state, static_argnums=0)
rates = jax.jit(GenericGNN.rates, static_argnums=0)
operators = jax.jit(GenericGNN.operators, static_argnums=0)
energy_entropy = jax.jit(GenericGNN.energy_entropy, static_argnums=0)


@pytest.fixture(scope="module")
def toy():
    """An untrained model on a 4x2x2 synthetic bar (4 clamped nodes), a mid-rollout state and its force."""
    data = D.synthetic_beam(nx=4, ny=2, nz=2, cases=3, frames=4)
    norm = D.normalization(data, D.split_rows(data, "train"))
    mesh = {"q0": data.q0, "senders": data.edges[0], "receivers": data.edges[1], "node_type": data.node_type}
    model = GenericGNN(CONFIG)
    arrays = model.prepare(model.init(jax.random.PRNGKey(1), norm, mesh), mesh)
    return dict(data=data, norm=norm, mesh=mesh, model=model, arrays=arrays,
                z=jnp.asarray(data.z[0, 2]), f=jnp.asarray(data.f[0, 2]))


def _random_state(toy, seed, size=0.3):
    """A mid-rollout state with noise of ``size`` state stds on every entry."""
    noise = np.random.default_rng(seed).normal(size=toy["z"].shape) * toy["norm"]["z_std"] * size
    return toy["z"] + jnp.asarray(noise, jnp.float32)


def _float64(tree):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64) if jnp.issubdtype(jnp.asarray(a).dtype,
                                                                                            jnp.floating) else a, tree)


def test_L_is_skew_symmetric_and_M_symmetric_positive_semidefinite_at_random_states(toy):
    # GENERIC: L conserves energy (skew-symmetric), M dissipates (symmetric positive semi-definite), at every node.
    for seed in range(3):
        big_l, big_m = operators(toy["model"], toy["arrays"], _random_state(toy, seed), toy["f"])
        assert big_l.shape == big_m.shape == (len(toy["data"].q0), 12, 12)
        scale_l, scale_m = float(jnp.max(jnp.abs(big_l))), float(jnp.max(jnp.abs(big_m)))
        assert scale_l > 0 and scale_m > 0
        assert float(jnp.max(jnp.abs(big_l + jnp.swapaxes(big_l, 1, 2)))) <= 1e-6 * scale_l
        assert float(jnp.max(jnp.abs(big_m - jnp.swapaxes(big_m, 1, 2)))) <= 1e-6 * scale_m
        assert np.linalg.eigvalsh(np.asarray(big_m, np.float64)).min() >= -1e-6 * scale_m


def test_gradients_of_E_and_S_match_finite_differences(toy):
    # The step uses ∇E, ∇S from automatic differentiation through the message passing (custom transposes of the
    # gathers included): central differences of E and S along random directions, in float64.
    with jax.enable_x64(True):
        arrays, z, f = _float64(toy["arrays"]), _float64(_random_state(toy, 7)), _float64(toy["f"])
        model = toy["model"]
        rt = rates(model, arrays, z, f)
        scale = GG.state_scale(arrays["norm"])
        rng = np.random.default_rng(0)
        for _ in range(3):
            unit = jnp.asarray(rng.normal(size=z.shape))          # a direction in w = z / s
            h = 1e-6
            fd = (energy_entropy(model, arrays, z + h * unit * scale, f)
                  - energy_entropy(model, arrays, z - h * unit * scale, f)) / (2 * h)
            analytic = jnp.stack([jnp.sum(rt.grad_e * unit), jnp.sum(rt.grad_s * unit)])
            np.testing.assert_allclose(np.asarray(analytic), np.asarray(fd), rtol=1e-6, atol=1e-9)


def test_degeneracy_residuals_on_a_hand_built_case():
    # L∇S and M∇E with L = l − lᵀ, M = m mᵀ: one node, l with l[1,0] = 2, m with m[0,0] = 1, m[2,0] = 3.
    l_mat = np.zeros((1, 12, 12), np.float32)
    l_mat[0, 1, 0] = 2.0
    m_mat = np.zeros((1, 12, 12), np.float32)
    m_mat[0, 0, 0], m_mat[0, 2, 0] = 1.0, 3.0
    grad_s = np.zeros((1, 12), np.float32)
    grad_s[0, 0], grad_s[0, 1] = 1.0, 5.0
    grad_e = np.zeros((1, 12), np.float32)
    grad_e[0, 2] = 1.0
    # L = [[0,-2],[2,0]] on (0,1): L∇S = (-2*5, 2*1); M = [[1,3],[3,9]] on (0,2): M∇E = (3, 9)
    expected_l, expected_m = np.zeros(12), np.zeros(12)
    expected_l[0], expected_l[1] = -10.0, 2.0
    expected_m[0], expected_m[2] = 3.0, 9.0
    np.testing.assert_allclose(np.asarray(GG.apply_l(jnp.asarray(l_mat), jnp.asarray(grad_s)))[0], expected_l)
    np.testing.assert_allclose(np.asarray(GG.apply_m(jnp.asarray(m_mat), jnp.asarray(grad_e)))[0], expected_m)


def test_decoded_entries_fill_strictly_lower_l_and_lower_m_row_major():
    heads = jnp.arange(1.0, 1.0 + GG.N_L + GG.N_M)[None]
    l_mat, m_mat = (np.asarray(a[0]) for a in GG.matrices(heads))
    rows, cols = np.tril_indices(12, -1)
    np.testing.assert_array_equal(l_mat[rows, cols], np.arange(1, 67))
    assert np.count_nonzero(l_mat) == 66 and np.count_nonzero(np.triu(l_mat)) == 0
    rows, cols = np.tril_indices(12)
    np.testing.assert_array_equal(m_mat[rows, cols], np.arange(67, 145))
    assert np.count_nonzero(np.triu(m_mat, 1)) == 0


def test_rates_residuals_and_step_are_the_operators_times_the_gradients(toy):
    # The residuals that training penalises are L∇S and M∇E of the per-node operators, and the step is
    # z + s ⊙ (L∇E + M∇S) with the clamped nodes' q, v rows zeroed.
    model, arrays, z, f = toy["model"], toy["arrays"], _random_state(toy, 1), toy["f"]
    rt = rates(model, arrays, z, f)
    big_l, big_m = operators(model, arrays, z, f)
    apply = lambda op, g: np.asarray(jnp.einsum("nij,nj->ni", op, g))
    for got, want in ((rt.deg_l, apply(big_l, rt.grad_s)), (rt.deg_m, apply(big_m, rt.grad_e))):
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-6 * np.abs(want).max())
    dw = apply(big_l, rt.grad_e) + apply(big_m, rt.grad_s)
    dw[toy["data"].node_type != 0, :6] = 0.0
    np.testing.assert_allclose(np.asarray(rt.dw), dw, rtol=1e-4, atol=1e-6 * np.abs(dw).max())
    euler = z + rt.dw * GG.state_scale(arrays["norm"])
    np.testing.assert_allclose(np.asarray(step(model, arrays, z, f)), np.asarray(euler), rtol=1e-6,
                               atol=1e-6 * float(jnp.max(jnp.abs(z))))


def test_energy_and_entropy_change_only_through_the_degeneracy_residuals(toy):
    # With L skew and M symmetric, at every free node ∇E·Δw = (M∇E)·∇S and ∇S·Δw = ∇SᵀM∇S − (L∇S)·∇E: where the
    # degeneracy L∇S = M∇E = 0 holds, the step conserves energy and produces entropy ∇SᵀM∇S >= 0 (float64).
    with jax.enable_x64(True):
        model, arrays = toy["model"], _float64(toy["arrays"])
        z, f = _float64(_random_state(toy, 2)), _float64(toy["f"])
        rt = rates(model, arrays, z, f)
        _, big_m = operators(model, arrays, z, f)
        g_e, g_s, dw = (np.asarray(a) for a in (rt.grad_e, rt.grad_s, rt.dw))
        free = toy["data"].node_type == 0
        dot = lambda a, b: np.sum(a * b, axis=1)[free]
        size = np.abs(dot(np.abs(g_e), np.abs(dw))).max() + np.abs(dot(np.abs(g_s), np.abs(dw))).max()
        np.testing.assert_allclose(dot(g_e, dw), dot(np.asarray(rt.deg_m), g_s), atol=1e-12 * size)
        production = np.einsum("ni,nij,nj->n", g_s, np.asarray(big_m), g_s)
        assert production.min() >= 0.0
        np.testing.assert_allclose(dot(g_s, dw), production[free] - dot(np.asarray(rt.deg_l), g_e),
                                   atol=1e-12 * size)
        np.testing.assert_allclose(float(rt.dissipation), production.sum(), rtol=1e-12)


def _mlp(params, x, layers):
    for i in range(layers):
        x = x @ params[f"Dense_{i}"]["kernel"] + params[f"Dense_{i}"]["bias"]
        x = jax.nn.silu(x) if i < layers - 1 else x
    return x


def _reference_step(config, arrays, mesh, z, f):
    """The paper's network and step written out on the plain edge list (segment sums, assembled edge features)."""
    w, norm, c = arrays["weights"], arrays["norm"], config
    s, r, n = np.asarray(mesh["senders"]), np.asarray(mesh["receivers"]), len(mesh["q0"])
    node_type = np.asarray(mesh["node_type"])
    f_in = f / norm["f_std"]

    def outputs(z_):
        q, v, sig = z_[:, :3], z_[:, 3:6], z_[:, 6:]
        x_node = jnp.concatenate([(v - norm["z_mean"][3:6]) / norm["z_std"][3:6],
                                  (sig - norm["z_mean"][6:]) / norm["z_std"][6:],
                                  jax.nn.one_hot(node_type, 2, dtype=z_.dtype), f_in], axis=1)
        dq, dv = q[s] - q[r], (v[s] - v[r]) / norm["dv_std"]
        length = jnp.linalg.norm(dq, axis=1, keepdims=True)
        products = (dv[:, :, None] * (dq / norm["dqn_mean"])[:, None, :]).reshape(-1, 9)
        x_edge = jnp.concatenate([dq / norm["dq_std"], (length - norm["dqn_mean"]) / norm["dqn_std"], dv, products],
                                 axis=1)
        h = _mlp(w["MLP_0"], x_node, c.mlp_layers)
        for p in range(c.passes):
            first = w[f"Dense_{3 * p}"]
            a = x_edge @ first["kernel"] + first["bias"] + h[s] @ w[f"Dense_{3 * p + 1}"]["kernel"] \
                + h[r] @ w[f"Dense_{3 * p + 2}"]["kernel"]
            msg = jax.ops.segment_sum(jax.nn.silu(a), r, n) / np.bincount(r).max()
            h = h + _mlp(w[f"MLP_{p + 1}"], jnp.concatenate([h, msg, f_in], axis=1), c.mlp_layers)
        return _mlp(w[f"MLP_{c.passes + 1}"], h, c.mlp_layers)

    scale = jnp.sqrt(norm["dz_std"] * norm["z_std"])
    grad_e = jax.grad(lambda z_: jnp.sum(outputs(z_)[:, 0]))(z) * scale
    grad_s = jax.grad(lambda z_: jnp.sum(outputs(z_)[:, 1]))(z) * scale
    out = outputs(z)
    l_mat = jnp.zeros((n, 12, 12), z.dtype).at[(slice(None),) + np.tril_indices(12, -1)].set(out[:, 2:68])
    m_mat = jnp.zeros((n, 12, 12), z.dtype).at[(slice(None),) + np.tril_indices(12)].set(out[:, 68:])
    big_l, big_m = l_mat - jnp.swapaxes(l_mat, 1, 2), m_mat @ jnp.swapaxes(m_mat, 1, 2)
    dw = jnp.einsum("nij,nj->ni", big_l, grad_e) + jnp.einsum("nij,nj->ni", big_m, grad_s)
    dw = dw.at[node_type != 0, :6].set(0.0)
    return z + dw * scale


def test_step_is_the_papers_generic_step_of_the_network_on_the_plain_edge_list(toy):
    # The model's factored, slot-layout network with hand-written transposes computes, with the same parameter
    # tree, the network and forward-Euler GENERIC step written out on the edge list (float64).
    with jax.enable_x64(True):
        arrays, z, f = _float64(toy["arrays"]), _float64(_random_state(toy, 3)), _float64(toy["f"])
        want = jax.jit(lambda a, z_, f_: _reference_step(CONFIG, a, toy["mesh"], z_, f_))(arrays, z, f)
        got = step(toy["model"], arrays, z, f)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-10, atol=1e-10)
        assert float(jnp.max(jnp.abs(want - z))) > 1e-6   # the step moves the state


def test_step_keeps_clamped_position_and_velocity_but_evolves_their_stress(toy):
    # Clamped nodes are prescribed (q, v fixed); their stress is predicted, not copied.
    z0 = toy["z"]
    z1 = np.asarray(step(toy["model"], toy["arrays"], z0, toy["f"]))
    clamped = toy["data"].node_type == 1
    assert clamped.sum() == 4
    np.testing.assert_array_equal(z1[clamped, :6], np.asarray(z0)[clamped, :6])
    assert np.abs(z1[clamped, 6:] - np.asarray(z0)[clamped, 6:]).max() > 0
    assert np.abs(z1[~clamped, :6] - np.asarray(z0)[~clamped, :6]).max() > 0


def test_jitted_step_equals_the_step_without_jit(toy):
    model, arrays, z, f = toy["model"], toy["arrays"], _random_state(toy, 4), toy["f"]
    jitted = step(model, arrays, z, f)
    with jax.disable_jit():
        eager = model.step_state(arrays, z, f)
    # float32: XLA fuses and reorders the compiled program's sums, so the two agree to round-off amplified by the
    # message passes (a few 1e-6 of the state's scale), not bit for bit
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=1e-5,
                               atol=1e-5 * float(jnp.max(jnp.abs(z))))


def test_loss_gradient_matches_finite_differences_on_weights(toy):
    # The training gradient (second order through the network: the loss reads ∇E, ∇S) against central differences
    # of the loss in three weights: the encoder's, the first edge layer's and the decoder's l block (float64).
    data = toy["data"]
    cfg = T.TrainConfig(model=CONFIG, noise=0.0, deg_weight=1.0)
    with jax.enable_x64(True):
        arrays = _float64(toy["arrays"])
        batch = _float64(T.Batch(jnp.asarray(data.z[:2, 1]), jnp.asarray(data.f[:2, 1]), jnp.asarray(data.z[:2, 2])))
        value_and_grad = jax.jit(jax.value_and_grad(lambda w: T.loss_fn(w, batch, jax.random.PRNGKey(0), arrays,
                                                                          cfg)[0]))
        loss = lambda w: value_and_grad(w)[0]   # one compilation for the values and the gradient
        grads = value_and_grad(arrays["weights"])[1]
        decoder = f"MLP_{CONFIG.passes + 1}"
        for path in (("MLP_0", "Dense_0", "kernel", (1, 2)), ("Dense_0", "kernel", (4, 3)),
                     (decoder, "Dense_1", "kernel", (5, 10))):
            *keys, index = path

            def moved(h, keys=keys, index=index):
                w = jax.tree_util.tree_map(lambda a: a, arrays["weights"])
                leaf = w
                for k in keys[:-1]:
                    leaf = leaf[k]
                leaf[keys[-1]] = leaf[keys[-1]].at[index].add(h)
                return loss(w)

            analytic = grads
            for k in keys:
                analytic = analytic[k]
            h = 1e-4
            fd = (moved(h) - moved(-h)) / (2 * h)
            np.testing.assert_allclose(float(analytic[index]), float(fd), rtol=1e-6, atol=1e-11)
            assert abs(float(fd)) > 1e-8


@pytest.mark.parametrize("field, value", [("hidden", 0), ("mlp_layers", -1), ("passes", 1.5), ("hidden", True),
                                          ("activation", "relu")])
def test_bad_config_values_raise_naming_the_value(field, value):
    with pytest.raises(ValueError) as err:
        GenericGNN(GNNConfig(**{field: value}))
    assert field in str(err.value) and repr(value) in str(err.value)


def test_config_from_a_model_files_flat_record_accepts_only_this_model():
    record = {"hidden": 64, "mlp_layers": 2, "passes": 3, "activation": "silu", "edge_velocity": True,
              "edge_strain": False, "coarse_nodes": 0, "coarse_passes": 2, "integrator": "euler", "substeps": 1}
    assert GNNConfig.from_dict(record) == GNNConfig(64, 2, 3, "silu")
    assert GNNConfig.from_dict({"passes": 2}) == GNNConfig(passes=2)
    with pytest.raises(ValueError, match="edge_strain"):
        GNNConfig.from_dict({**record, "edge_strain": True})
    with pytest.raises(ValueError, match="integrator"):
        GNNConfig.from_dict({**record, "integrator": "rk4"})
    with pytest.raises(ValueError, match="unknown.*bogus"):
        GNNConfig.from_dict({**record, "bogus": 1})
    with pytest.raises(ValueError, match="hidden"):
        GNNConfig.from_dict({**record, "hidden": 0})


def test_step_from_rest_under_zero_force_is_finite_and_small(toy):
    # A data-free start: the rest state of the mesh (q = X, v = σ = 0) and no force, stepped by an untrained model.
    model, arrays = toy["model"], toy["arrays"]
    rest = GG.rest_state(arrays["topo"])
    out = np.asarray(step(model, arrays, rest, jnp.zeros((16, 3))))
    assert np.all(np.isfinite(out))
    moved = np.abs(out - np.asarray(rest)) / np.asarray(toy["norm"]["dz_std"])
    assert moved.max() < 10.0   # within ten increment stds of rest


def test_step_is_translation_invariant_in_q(toy):
    # The network sees positions only through q − X differences between neighbours: shifting a body shifts its step.
    model, arrays, z, f = toy["model"], toy["arrays"], _random_state(toy, 5), toy["f"]
    shift = jnp.concatenate([jnp.asarray([0.25, -0.5, 0.125]), jnp.zeros(9)])
    a = step(model, arrays, z, f)
    b = step(model, arrays, z + shift, f)
    np.testing.assert_allclose(np.asarray(b - shift), np.asarray(a), rtol=1e-5, atol=1e-5)


def test_stored_arrays_round_trip_and_prepare_checks_them(toy):
    model, arrays, mesh = toy["model"], toy["arrays"], toy["mesh"]
    stored = model.stored(arrays)
    assert set(stored) == {"weights", "norm"}
    again = model.prepare(stored, mesh)
    np.testing.assert_array_equal(np.asarray(step(model, again, toy["z"], toy["f"])),
                                  np.asarray(step(model, arrays, toy["z"], toy["f"])))
    with pytest.raises(ValueError, match="dv_std"):
        model.prepare({**stored, "norm": {k: v for k, v in stored["norm"].items() if k != "dv_std"}}, mesh)
    with pytest.raises(ValueError, match="weights do not fit"):
        GenericGNN(CONFIG._replace(hidden=12)).prepare(stored, mesh)
    with pytest.raises(ValueError, match="weights do not fit"):
        GenericGNN(CONFIG._replace(passes=3)).prepare(stored, mesh)
    with pytest.raises(ValueError, match="node_type"):
        model.prepare(stored, {k: v for k, v in mesh.items() if k != "node_type"})


def test_parameter_tree_has_the_model_files_names(toy):
    names = set(toy["arrays"]["weights"])
    passes = CONFIG.passes
    assert names == {f"Dense_{i}" for i in range(3 * passes)} | {f"MLP_{i}" for i in range(passes + 2)}
    assert toy["arrays"]["weights"]["Dense_0"]["kernel"].shape == (GG.EDGE_FEATURES, CONFIG.hidden)
    assert set(toy["arrays"]["weights"]["Dense_1"]) == {"kernel"}
    assert toy["arrays"]["weights"][f"MLP_{passes + 1}"]["Dense_1"]["kernel"].shape == (8, 2 + 66 + 78)


def _irregular_graph(n=30, seed=0):
    """A random symmetric graph with a hub of degree 19 (several rows per node in small slot layouts)."""
    rng = np.random.default_rng(seed)
    pairs = {(0, i) for i in range(1, 20)}
    pairs |= {tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(3 * n)}
    a, b = np.array(sorted(pairs)).T
    return np.concatenate([a, b]), np.concatenate([b, a]), n


def test_row_layout_aggregates_like_a_segment_sum_on_an_irregular_graph():
    # Nodes of high degree own several rows of K slots; the sum of messages over rows is the plain sum over
    # incoming edges, and the gather's hand-written transpose is its adjoint.
    s, r, n = _irregular_graph()
    topo = GG.topology(s, r, n, np.zeros((n, 3)))
    assert topo.nbr.shape[0] > n and topo.nbr.shape[1] < np.bincount(r).max()   # extra rows are used
    x = jax.random.normal(jax.random.PRNGKey(0), (n, 4))
    ref = jax.ops.segment_sum(x[s], r, n)
    got = jax.jit(lambda x_: GG.reduce_rows(jnp.sum(GG.gather_neighbors(x_, topo), axis=1), topo))(x)
    np.testing.assert_allclose(got, ref, atol=1e-5)
    y = jax.random.normal(jax.random.PRNGKey(1), topo.nbr.shape + (4,)) * topo.mask[..., None]
    assert abs(float(jnp.vdot(GG.gather_neighbors(x, topo), y) - jnp.vdot(x, GG.sum_reverse(y, topo)))) < 1e-4
    grad = lambda fn: jax.jit(jax.grad(lambda x_: jnp.sum(jnp.sin(fn(x_)))))(x)
    np.testing.assert_allclose(grad(lambda x_: GG.reduce_rows(jnp.sum(GG.gather_neighbors(x_, topo) ** 2, 1), topo)),
                               grad(lambda x_: jax.ops.segment_sum(x_[s] ** 2, r, n)), atol=1e-4)


def test_topology_rejects_one_directional_and_duplicate_edges():
    # The reverse-edge transpose needs every edge in both directions (the data format's contract).
    with pytest.raises(ValueError, match="both directions"):
        GG.topology(np.array([0, 1]), np.array([1, 2]), 3, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="duplicate"):
        GG.topology(np.array([0, 1, 0]), np.array([1, 0, 1]), 2, np.zeros((2, 3)))


def test_step_does_not_depend_on_the_slot_layout(toy):
    # The same graph in rows of K = 3 and of the maximum degree gives one function (messages are scaled by the
    # maximum degree, not by K), so a model trained in one layout runs in any other.
    s, r, n = _irregular_graph(seed=9)
    q0 = np.random.default_rng(10).normal(size=(n, 3)).astype(np.float32)
    mesh = {"q0": q0, "senders": s, "receivers": r, "node_type": (np.arange(n) % 7 == 0).astype(np.int32)}
    model = toy["model"]
    arrays = model.prepare(model.stored(toy["arrays"]), mesh)   # the weights do not depend on the mesh
    z = jnp.concatenate([jnp.asarray(q0), 0.1 * jax.random.normal(jax.random.PRNGKey(11), (n, 9))], 1)
    f = 0.1 * jax.random.normal(jax.random.PRNGKey(13), (n, 3))
    layouts = [GG.topology(s, r, n, q0, slots=k) for k in (3, int(np.bincount(r).max()))]
    assert layouts[0].nbr.shape[0] > n and layouts[1].nbr.shape[0] == n
    outs = [step(model, {**arrays, "topo": t}, z, f) for t in layouts]
    # the layouts sum the messages in different orders: float32 round-off of the O(1) sums, a few ulps of the
    # largest entry (a layout-dependent scaling would differ by O(1))
    scale = float(jnp.max(jnp.abs(outs[0])))
    for out in outs[1:]:
        np.testing.assert_allclose(out, outs[0], rtol=1e-5, atol=1e-5 * scale)
    assert float(layouts[0].degree_max) == np.bincount(r).max()
