"""The GENERIC graph network: structure of L and M, gradients, degeneracy, clamping, the public API."""
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fem.meshes
from tignn_jax import api
from tignn_jax import data as D
from tignn_jax import graph as G
from tignn_jax import model as M

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import skips  # noqa: E402

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "abaqus_beam.npz"
CONFIG = M.ModelConfig(hidden=8, mlp_layers=2, passes=2)


@pytest.fixture(scope="module")
def toy():
    """A tiny untrained model on a 4x2x2 synthetic bar (4 clamped nodes) and a mid-rollout state."""
    data = D.synthetic_beam(nx=4, ny=2, nz=2, cases=3, frames=4)
    norm = D.normalization(data, D.split_rows(data, "train"))
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0))
    z, f = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    nt = jnp.asarray(data.node_type, jnp.int32)
    jnorm = {k: jnp.asarray(v) for k, v in norm.items()}
    weights = M.init_weights(jax.random.PRNGKey(1), CONFIG, jnorm, z, f, nt, topo)
    params = api.make_params(CONFIG, norm, weights, data.q0, data.edges, data.node_type)
    return dict(data=data, params=params, norm=jnorm, topo=topo, z=z, f=f, nt=nt, weights=weights)


def _args(t):
    return t["weights"], CONFIG, t["norm"], t["z"], t["f"], t["nt"], t["topo"]


def test_L_is_skew_symmetric_and_M_symmetric_positive_semidefinite(toy):
    # GENERIC: L conserves energy (skew), M dissipates (symmetric PSD), at every node.
    big_l, big_m = M.operators(*_args(toy))
    scale_l, scale_m = float(jnp.max(jnp.abs(big_l))), float(jnp.max(jnp.abs(big_m)))
    assert scale_l > 0 and scale_m > 0
    assert float(jnp.max(jnp.abs(big_l + jnp.swapaxes(big_l, 1, 2)))) <= 1e-6 * scale_l
    assert float(jnp.max(jnp.abs(big_m - jnp.swapaxes(big_m, 1, 2)))) <= 1e-6 * scale_m
    eig = np.linalg.eigvalsh(np.asarray(big_m, np.float64))
    assert eig.min() >= -1e-6 * scale_m
    assert np.all(np.abs(np.diagonal(np.asarray(big_l), axis1=1, axis2=2)) == 0)


def _assert_skew_and_psd(big_l, big_m):
    """Per-node L skew-symmetric and M positive semi-definite, relative to their largest entries."""
    assert float(jnp.max(jnp.abs(big_l + jnp.swapaxes(big_l, 1, 2)))) <= 1e-6 * float(jnp.max(jnp.abs(big_l)))
    assert np.linalg.eigvalsh(np.asarray(big_m, np.float64)).min() >= -1e-6 * float(jnp.max(jnp.abs(big_m)))


def _assert_gradients_match_finite_differences(weights, config, norm, z, f, nt, topo, directions=3, seed=0):
    """∇E, ∇S of ``rates`` against central differences of ``energy_entropy`` along random directions (float64)."""
    with jax.enable_x64(True):
        w64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), weights)
        n64 = {k: jnp.asarray(v, jnp.float64) for k, v in norm.items()}
        z64, f64 = jnp.asarray(z, jnp.float64), jnp.asarray(f, jnp.float64)
        rt = M.rates(w64, config, n64, z64, f64, nt, topo)
        scale = M.state_scale(n64)
        potentials = lambda z_: M.energy_entropy(w64, config, n64, z_, f64, nt, topo)
        rng = np.random.default_rng(seed)
        for _ in range(directions):
            direction = jnp.asarray(rng.normal(size=z64.shape)) * scale   # a step in w = z / s
            h = 1e-6
            fd = (potentials(z64 + h * direction) - potentials(z64 - h * direction)) / (2 * h)
            unit = direction / scale
            analytic = jnp.stack([jnp.sum(rt.grad_e * unit), jnp.sum(rt.grad_s * unit)])
            np.testing.assert_allclose(np.asarray(analytic), np.asarray(fd), rtol=1e-6, atol=1e-9)


def _assert_generic_structure(args, seed):
    """At the state in ``args`` (the arguments of ``model.rates``): L skew-symmetric, M PSD, and ∇E, ∇S equal to
    central differences along one random direction."""
    _assert_skew_and_psd(*M.operators(*args))
    _assert_gradients_match_finite_differences(*args, directions=1, seed=seed)


def test_energy_gradient_matches_finite_differences(toy):
    # dz/dt uses ∇E, ∇S from autodiff; check them along random directions by central differences in float64.
    _assert_gradients_match_finite_differences(*_args(toy))


def test_degeneracy_residuals_on_a_hand_built_case():
    # L∇S and M∇E with L = l - lᵀ, M = m mᵀ: one node, l with l[1,0] = 2, m with m[0,0] = 1, m[2,0] = 3.
    l_mat = np.zeros((1, 12, 12), np.float32)
    l_mat[0, 1, 0] = 2.0
    m_mat = np.zeros((1, 12, 12), np.float32)
    m_mat[0, 0, 0], m_mat[0, 2, 0] = 1.0, 3.0
    grad_s = np.zeros((1, 12), np.float32)
    grad_s[0, 0], grad_s[0, 1] = 1.0, 5.0
    grad_e = np.zeros((1, 12), np.float32)
    grad_e[0, 2] = 1.0
    # L = [[0,-2],[2,0]] on (0,1): L∇S = (-2*5, 2*1); M = [[1,3],[3,9]] on (0,2): M∇E = (3, 9)
    expected_l = np.zeros(12)
    expected_l[0], expected_l[1] = -10.0, 2.0
    expected_m = np.zeros(12)
    expected_m[0], expected_m[2] = 3.0, 9.0
    np.testing.assert_allclose(np.asarray(M._apply_l(jnp.asarray(l_mat), jnp.asarray(grad_s)))[0], expected_l)
    np.testing.assert_allclose(np.asarray(M._apply_m(jnp.asarray(m_mat), jnp.asarray(grad_e)))[0], expected_m)


def test_rates_residuals_equal_operators_times_gradients(toy):
    # The residuals reported in training are exactly L∇S and M∇E of the assembled per-node operators.
    rt = M.rates(*_args(toy))
    big_l, big_m = M.operators(*_args(toy))
    np.testing.assert_allclose(np.asarray(rt.deg_l), np.asarray(jnp.einsum("nij,nj->ni", big_l, rt.grad_s)),
                               rtol=1e-4, atol=1e-6 * float(jnp.max(jnp.abs(rt.deg_l))))
    np.testing.assert_allclose(np.asarray(rt.deg_m), np.asarray(jnp.einsum("nij,nj->ni", big_m, rt.grad_e)),
                               rtol=1e-4, atol=1e-6 * float(jnp.max(jnp.abs(rt.deg_m))))
    free = np.asarray(toy["nt"]) == 0
    dw = np.asarray(jnp.einsum("nij,nj->ni", big_l, rt.grad_e) + jnp.einsum("nij,nj->ni", big_m, rt.grad_s))
    np.testing.assert_allclose(np.asarray(rt.dw)[free], dw[free], rtol=1e-4, atol=1e-6 * np.abs(dw).max())


def test_exact_degeneracy_projection_meets_generic_to_float_precision(toy):
    # With exact_degeneracy the same weights give L'∇S = M'∇E = 0 to rounding, L' skew and M' PSD, dw equal to
    # the projected operators times the gradients, and per-node entropy production ∇Sᵀ M' ∇S >= 0.
    cfg = CONFIG._replace(exact_degeneracy=True)
    args = (toy["weights"], cfg, toy["norm"], toy["z"], toy["f"], toy["nt"], toy["topo"])
    plain = M.rates(*_args(toy))
    rt = M.rates(*args)
    big_l, big_m = M.operators(*args)
    size_l = float(jnp.max(jnp.abs(big_l))) * float(jnp.max(jnp.abs(rt.grad_s)))
    size_m = float(jnp.max(jnp.abs(big_m))) * float(jnp.max(jnp.abs(rt.grad_e)))
    assert float(jnp.max(jnp.abs(plain.deg_l))) > 1e-3 * size_l       # the unprojected model is not degenerate
    assert float(jnp.max(jnp.abs(rt.deg_l))) <= 1e-5 * size_l
    assert float(jnp.max(jnp.abs(rt.deg_m))) <= 1e-5 * size_m
    assert float(jnp.max(jnp.abs(jnp.einsum("nij,nj->ni", big_l, rt.grad_s)))) <= 1e-5 * size_l
    _assert_skew_and_psd(big_l, big_m)
    free = np.asarray(toy["nt"]) == 0
    dw = np.asarray(jnp.einsum("nij,nj->ni", big_l, rt.grad_e) + jnp.einsum("nij,nj->ni", big_m, rt.grad_s))
    np.testing.assert_allclose(np.asarray(rt.dw)[free], dw[free], rtol=1e-4, atol=1e-5 * np.abs(dw).max())
    production = np.einsum("ni,nij,nj->n", np.asarray(rt.grad_s, np.float64), np.asarray(big_m, np.float64),
                           np.asarray(rt.grad_s, np.float64))
    assert production.min() >= -1e-6 * np.abs(production).max()
    # per node, the increment's entropy change equals that production (the L' part is orthogonal to ∇S)
    per_node = np.sum(np.asarray(rt.grad_s) * dw, axis=1)
    np.testing.assert_allclose(per_node, production, rtol=1e-3, atol=1e-5 * np.abs(production).max())


def test_neighbor_gather_gradient_matches_plain_gather(toy):
    # The slot gather's hand-written transpose (a gather through reverse edges) is its true adjoint.
    topo = toy["topo"]
    x = jax.random.normal(jax.random.PRNGKey(0), (len(toy["nt"]), 5))
    ct = jax.random.normal(jax.random.PRNGKey(1), topo.nbr.shape + (5,))
    plain = lambda x: x[topo.nbr] * topo.mask[..., None]
    _, vjp_fast = jax.vjp(lambda x: M.gather_neighbors(x, topo), x)
    _, vjp_plain = jax.vjp(plain, x)
    np.testing.assert_allclose(np.asarray(vjp_fast(ct)[0]), np.asarray(vjp_plain(ct)[0]), rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(M.gather_neighbors(x, topo)), np.asarray(plain(x)))


def test_topology_rejects_one_directional_edges():
    # The reverse-edge transpose needs every edge in both directions (the data format's contract).
    with pytest.raises(ValueError, match="both directions"):
        M.topology(np.array([0, 1]), np.array([1, 2]), 3)


def test_step_keeps_clamped_position_and_velocity_but_evolves_their_stress(toy):
    # Clamped nodes are prescribed (q, v fixed); their stress is predicted, not copied.
    graph = G.from_state(toy["z"], toy["data"].edges, toy["data"].node_type)
    new = api.step(toy["params"], graph, toy["f"])
    clamped = np.asarray(toy["nt"]) == 1
    z0, z1 = np.asarray(toy["z"]), np.asarray(new.nodes["z"])
    np.testing.assert_array_equal(z1[clamped, :6], z0[clamped, :6])
    assert np.abs(z1[clamped, 6:] - z0[clamped, 6:]).max() > 0
    assert np.abs(z1[~clamped, :6] - z0[~clamped, :6]).max() > 0


def test_rollout_equals_repeated_steps(toy):
    # lax.scan rollout is the same map as calling step in a Python loop.
    data = toy["data"]
    graph = G.from_data(data, 0, 0)
    states = api.rollout(toy["params"], graph, data.f[0])
    assert states.shape == (data.f.shape[1] + 1, len(data.q0), 12)
    np.testing.assert_array_equal(np.asarray(states[0]), data.z[0, 0])
    g = graph
    for k in range(data.f.shape[1]):
        g = api.step(toy["params"], g, data.f[0, k])
        np.testing.assert_allclose(np.asarray(states[k + 1]), np.asarray(g.nodes["z"]), rtol=1e-5, atol=1e-5)


def _assert_batched_bodies_step_separately(params, data):
    """Two bodies of the model's mesh in one graph (jraph-style batch) step as each does alone."""
    g1, g2 = G.from_data(data, 0, 1), G.from_data(data, 1, 2)
    both = api.step(params, G.batch([g1, g2]), np.concatenate([data.f[0, 1], data.f[1, 2]]))
    n = len(data.q0)
    np.testing.assert_allclose(np.asarray(both.nodes["z"][:n]),
                               np.asarray(api.step(params, g1, data.f[0, 1]).nodes["z"]), atol=1e-5)
    np.testing.assert_allclose(np.asarray(both.nodes["z"][n:]),
                               np.asarray(api.step(params, g2, data.f[1, 2]).nodes["z"]), atol=1e-5)


def test_batched_copies_step_like_separate_graphs(toy):
    # Two bodies of the model's mesh in one graph (jraph-style batch) evolve independently.
    _assert_batched_bodies_step_separately(toy["params"], toy["data"])


def test_batched_graph_steps_and_rolls_out_alike_as_one_graph_or_body_by_body(toy, monkeypatch):
    # step and rollout of a batched graph: on a CPU body by body (lax.map), elsewhere as one graph; both layouts
    # give the same states, and a rollout equals repeated steps.
    params, data = toy["params"], toy["data"]
    graph = G.batch([G.from_data(data, 0, 1), G.from_data(data, 1, 2)])
    f = np.concatenate([data.f[0, 1:3], data.f[1, 2:4]], axis=1)      # [2, 2N, 3]
    out = {}
    for one_by_one in (True, False):
        monkeypatch.setattr(api, "_one_by_one", lambda k, v=one_by_one: v and k > 1)
        stepped, g = [graph.nodes["z"]], graph
        for k in range(len(f)):
            g = api.step(params, g, f[k])
            stepped.append(g.nodes["z"])
        out[one_by_one] = (np.asarray(jnp.stack(stepped)), np.asarray(api.rollout(params, graph, f)))
    for a, b in (out[True], out[False], (out[True][0], out[False][1])):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)


def test_step_rejects_bad_inputs_naming_them(toy):
    # Validation at the public boundary: shapes, NaN forces, and graphs of another mesh.
    data, params = toy["data"], toy["params"]
    graph = G.from_data(data, 0, 0)
    n = len(data.q0)
    with pytest.raises(ValueError, match="forces"):
        api.step(params, graph, np.zeros((n, 2)))
    bad = np.zeros((n, 3))
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        api.step(params, graph, bad)
    with pytest.raises(ValueError, match="forces_seq"):
        api.rollout(params, graph, np.zeros((n, 3)))
    other = D.synthetic_beam(nx=5, ny=2, nz=2)
    with pytest.raises(ValueError, match="n_node"):
        api.step(params, G.from_data(other), np.zeros((len(other.q0), 3)))
    rewired = G.from_state(data.z[0, 0], data.edges[:, ::-1], data.node_type)
    with pytest.raises(ValueError, match="senders/receivers"):
        api.step(params, rewired, np.zeros((n, 3)))
    retyped = G.from_state(data.z[0, 0], data.edges, np.zeros(n, np.int8))
    with pytest.raises(ValueError, match="node_type"):
        api.step(params, retyped, np.zeros((n, 3)))


def test_saved_model_loads_and_steps_identically(toy, tmp_path):
    # A model file round-trips: same config, normalisation and weights give the same step.
    path = api.save_model(toy["params"], tmp_path / "m" / "model.npz")
    params, rest = api.load_pretrained(str(path.parent))
    np.testing.assert_array_equal(np.asarray(rest.nodes["z"][:, :3]), toy["data"].q0)
    assert np.all(np.asarray(rest.nodes["z"][:, 3:]) == 0)
    graph = G.from_data(toy["data"], 0, 2)
    a = api.step(toy["params"], graph, toy["f"]).nodes["z"]
    b = api.step(params, graph, toy["f"]).nodes["z"]
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_load_pretrained_unknown_name_lists_shipped_models():
    with pytest.raises(ValueError, match="no model named"):
        api.load_pretrained("no-such-model")


def test_loader_reads_the_reference_beam():
    # The Abaqus reference data: 52 sims, 756 nodes, 3960 directed edges, published split 41/5/6.
    if not REFERENCE.exists():
        pytest.skip(f"reference data not found at {REFERENCE}")
    data = D.load(REFERENCE)
    assert data.z.shape == (52, 21, 756, 12) and data.f.shape == (52, 20, 756, 3)
    assert data.edges.shape == (2, 3960) and int(data.node_type.sum()) == 36
    assert sorted(data.splits["test"].tolist()) == [9, 10, 12, 13, 38, 44]
    assert len(D.split_rows(data, "train")) == 41
    topo = M.topology(data.edges[0], data.edges[1], 756)
    assert int(topo.mask.sum()) == 3960
    norm = D.normalization(data, D.split_rows(data, "train"))
    assert all(np.all(v > 0) for k, v in norm.items() if k.endswith("std"))


def _shipped(name):
    """A shipped model and its graph (skipped where this checkout has none): at most 5 MiB, with a model card."""
    path = Path(api.MODELS_DIR) / name / "model.npz"
    if not path.exists():
        pytest.skip(f"no shipped {name} model in this checkout")
    assert path.stat().st_size <= 5 * 2 ** 20 and (path.parent / "MODEL_CARD.md").exists()
    return api.load_pretrained(name)


@pytest.mark.parametrize("name", ["beam-abaqus", "beam-abaqus-64x2", "beam", "beam-fem", "beam-gnn"])
def test_shipped_beam_model_loads_with_its_mesh(name):
    # The shipped models are small and bring the rest-state graph of the beam mesh (the FEM's beam uses the
    # reference mesh and numbering).
    params, graph = _shipped(name)
    assert graph.nodes["z"].shape == (756, 12) and int(np.sum(graph.nodes["node_type"])) == 36
    moved = api.step(params, graph, np.zeros((756, 3), np.float32))
    assert np.all(np.isfinite(np.asarray(moved.nodes["z"])))


@pytest.mark.parametrize("name", ["bunny-128x6", "bunny-dense-128x6"])
def test_shipped_gpu_bunny_models_load_on_the_bunny_mesh(name):
    # The GPU-trained bunny models (not meeting the targets; see their cards) are small, carry their training
    # envelope, and step the 1330-node bunny mesh (the FEM scene's mesh in the scan's scale) to finite states.
    params, graph = _shipped(name)
    assert graph.nodes["z"].shape == (1330, 12) and {"z_dev_max", "u_max"} <= set(params["norm"])
    assert params["info"]["fem_integrator"] == "implicit"
    from fem import scenes
    points = scenes.bunny_scene().points
    q0 = np.asarray(params["mesh"]["q0"], np.float64)
    units = float(np.sum(q0 * points) / np.sum(points ** 2))
    np.testing.assert_allclose(q0, points * units, atol=1e-3 * np.abs(q0).max())
    forces = np.zeros((1330, 3), np.float32)
    forces[int(np.argmax(q0[:, 2]))] = [0.0, 0.0, -0.5]   # half the training loads' unit total force
    moved = api.step(params, graph, forces)
    assert np.all(np.isfinite(np.asarray(moved.nodes["z"])))


@pytest.mark.parametrize("name, nodes, load", [("bunny-linear", 1330, -1.0), ("beam-linear", 756, -1e5)])
def test_shipped_linear_models_are_the_rest_linearised_backward_euler_step(name, nodes, load):
    # The shipped `bunny-linear` and `beam-linear` (frame_solve + linear_prior with the network's weights zero,
    # see their cards): one step from rest under a load equals the backward-Euler frame of the FEM's rest
    # linearisation, A₀ u₁ = f, to float32 precision, with v₁ = u₁ / Δt.
    params, graph = _shipped(name)
    cfg = api._config(params)
    assert cfg.frame_solve and cfg.linear_prior and graph.nodes["z"].shape == (nodes, 12)
    q0 = np.asarray(params["mesh"]["q0"], np.float64)
    forces = np.zeros((nodes, 3), np.float32)
    forces[int(np.argmax(q0[:, 2] + 1e-3 * q0[:, 0]))] = [0.0, 0.0, load]
    z1 = np.asarray(api.step(params, graph, forces).nodes["z"], np.float64)
    u_ref = np.asarray(params["norm"]["fs_ainv"], np.float64) @ forces.reshape(-1).astype(np.float64)
    u1 = (z1[:, :3] - q0).reshape(-1)
    assert np.abs(u1 - u_ref).max() < 1e-4 * np.abs(u_ref).max()
    np.testing.assert_allclose(z1[:, 3:6].reshape(-1), u1 / 0.05, atol=1e-3 * np.abs(u1).max() / 0.05)


@pytest.mark.parametrize("name", ["bunny-linear", "beam-linear"])
def test_stepper_skips_a_zero_network_with_the_same_states(name):
    # A rest-linearised model's network has every weight zero, so its rate is exactly zero: `stepper` runs the
    # linearised solve alone (`network_is_zero`). Over ten loaded steps its states equal the full step's (the
    # network traced), to float32 rounding of the stiff solve: 1e-2 of each component's range along the run.
    params, graph = _shipped(name)
    assert api.network_is_zero(params)
    skip, full, forces = skips.zero_network_pair(params)   # the pair benchmarks/skips.py times
    za = zb = graph.nodes["z"]
    runs = []
    for _ in range(10):
        za, zb = skip(za, forces), full(zb, forces)
        runs.append(np.stack([np.asarray(za), np.asarray(zb)]))
    runs = np.stack(runs)                                           # [10, 2, N, 12]
    scale = np.abs(runs[:, 1] - np.asarray(graph.nodes["z"])).max(axis=(0, 1))
    assert np.all(scale > 0)
    assert np.all(np.abs(runs[:, 0] - runs[:, 1]).max(axis=(0, 1)) <= 1e-2 * scale)
    # a trained network, or a zero network with a term that is not zero at zero weights, is run as it is
    assert not api.network_is_zero(_shipped("beam-abaqus")[0])
    ported = {**params, "config": {**params["config"], "force_port": True}}
    assert not api.network_is_zero(ported)


def _irregular_graph(n=40, seed=0):
    """Symmetric random graph with degrees from 1 to ~20 (an irregular mesh's spread of degrees)."""
    rng = np.random.default_rng(seed)
    pairs = {(0, i) for i in range(1, 20)}          # one hub of degree 19
    pairs |= {tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(3 * n)}
    a, b = np.array(sorted(pairs)).T
    return np.concatenate([a, b]), np.concatenate([b, a]), n


def test_row_layout_aggregates_like_a_segment_sum_on_an_irregular_graph():
    # Nodes of high degree own several rows of K slots; the sum of messages over rows must be the plain
    # sum over incoming edges, and the gather's custom transpose must be its adjoint.
    s, r, n = _irregular_graph()
    topo = M.topology(s, r, n)
    assert topo.nbr.shape[0] > n and topo.nbr.shape[1] < np.bincount(r).max()   # extra rows are used
    x = jax.random.normal(jax.random.PRNGKey(0), (n, 4))
    ref = jax.ops.segment_sum(x[s], r, n)
    got = M.reduce_rows(jnp.sum(M.gather_neighbors(x, topo), axis=1), topo)
    np.testing.assert_allclose(got, ref, atol=1e-5)
    y = jax.random.normal(jax.random.PRNGKey(1), topo.nbr.shape + (4,)) * topo.mask[..., None]
    assert abs(float(jnp.vdot(M.gather_neighbors(x, topo), y) - jnp.vdot(x, M.sum_reverse(y, topo)))) < 1e-4
    loss = lambda fn: jax.grad(lambda x_: jnp.sum(jnp.sin(fn(x_))))(x)
    np.testing.assert_allclose(loss(lambda x_: M.reduce_rows(jnp.sum(M.gather_neighbors(x_, topo) ** 2, 1), topo)),
                               loss(lambda x_: jax.ops.segment_sum(x_[s] ** 2, r, n)), atol=1e-4)


def test_tiled_row_layout_equals_separate_copies():
    s, r, n = _irregular_graph(seed=1)
    topo = M.topology(s, r, n, q0=np.random.default_rng(0).normal(size=(n, 3)))
    tiled = M.tile_topology(topo, 3)
    x = jax.random.normal(jax.random.PRNGKey(2), (n, 4))
    xs = jnp.concatenate([x, 2 * x, -x])
    agg = lambda x_, t: M.reduce_rows(jnp.sum(M.gather_neighbors(x_, t), axis=1), t)
    one = agg(x, topo)
    np.testing.assert_allclose(agg(xs, tiled), jnp.concatenate([one, 2 * one, -one]), atol=1e-5)
    dx = lambda t: M.reduce_rows(jnp.sum(t.dx0, axis=1), t)
    np.testing.assert_allclose(dx(tiled), jnp.concatenate([dx(topo)] * 3), atol=1e-5)


def test_edge_strain_features_vanish_at_rest(toy):
    # The displacement-difference features measure deformation against the rest mesh: zero in the rest state.
    data = toy["data"]
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), data.q0)
    z0 = jnp.concatenate([jnp.asarray(data.q0), jnp.zeros((len(data.q0), 9))], axis=1)
    norm = {**toy["norm"], "du_std": jnp.ones(3)}
    _, x_edge = M._features(norm, z0, toy["f"], toy["nt"], topo, edge_velocity=False, edge_strain=True)
    assert float(jnp.max(jnp.abs(x_edge[..., -4:]))) < 1e-6
    _, x_def = M._features(norm, toy["z"], toy["f"], toy["nt"], topo, edge_velocity=False, edge_strain=True)
    assert float(jnp.max(jnp.abs(x_def[..., -4:]))) > 1e-3


def test_stepper_matches_validated_step(toy):
    params, data = toy["params"], toy["data"]
    graph = G.batch([G.from_state(data.z[0, 2], data.edges, data.node_type)] * 2)
    forces = np.concatenate([data.f[0, 2], 2 * data.f[0, 2]])
    want = api.step(params, graph, forces).nodes["z"]
    for one_graph in (None, True, False):   # the backend's default, one graph, one body after another
        fn = api.stepper(params, copies=2, one_graph=one_graph)
        np.testing.assert_allclose(fn(graph.nodes["z"], jnp.asarray(forces)), want, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="copies"):
        api.stepper(params, copies=0)


def test_force_check_flags_loads_beyond_the_training_range(toy):
    params = toy["params"]
    bound = float(params["norm"]["f_max"][0])
    assert bound == pytest.approx(float(np.linalg.norm(toy["data"].f[D.split_rows(toy["data"], "train")],
                                                       axis=-1).max()), rel=1e-6)
    n = len(toy["data"].q0)
    inside = np.zeros((n, 3))
    inside[0, 1] = 0.5 * bound
    beyond = inside * 6.0
    assert not api.force_check(params, inside)["out_of_distribution"]
    flagged = api.force_check(params, beyond)
    assert flagged["out_of_distribution"] and flagged["max_force_ratio"] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="shape"):
        api.force_check(params, np.zeros(3))


def test_state_check_flags_states_far_outside_training_and_non_finite(toy):
    params, data = toy["params"], toy["data"]
    ok = api.state_check(params, data.z[0, 2])
    assert ok["finite"] and not ok["out_of_distribution"] and ok["max_deviation"] < 8.0
    wild = np.array(data.z[0, 2])
    wild[3, 7] = float(params["norm"]["z_mean"][7] + 20 * params["norm"]["z_std"][7])
    assert api.state_check(params, wild)["out_of_distribution"]
    wild[0, 0] = np.nan
    flagged = api.state_check(params, wild)
    assert not flagged["finite"] and flagged["out_of_distribution"]


def test_state_guard_agrees_with_state_check(toy):
    params, data = toy["params"], toy["data"]
    guard = jax.jit(api.state_guard(params))
    wild = np.array(data.z[0, 2])
    wild[3, 7] = float(params["norm"]["z_mean"][7] + 20 * params["norm"]["z_std"][7])
    nan = np.array(data.z[0, 2])
    nan[1, 4] = np.nan
    for z in (data.z[0, 2], wild, nan):
        assert bool(guard(jnp.asarray(z))) == api.state_check(params, z)["out_of_distribution"]


def test_node_position_features_see_displacement_and_keep_force_last(toy):
    # Without position features a rigid shift of every node changes no input (only differences are seen); with
    # them the node sees its displacement q − X, so a shifted state is a different state. The force stays the
    # last three node features (the processor reads it there).
    data = toy["data"]
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), data.q0)
    shift = jnp.zeros(12).at[:3].set(jnp.array([0.3, -0.2, 0.1]))
    for position in (False, True):
        x, _ = M._features(toy["norm"], toy["z"], toy["f"], toy["nt"], topo, node_position=position)
        x_s, _ = M._features(toy["norm"], toy["z"] + shift, toy["f"], toy["nt"], topo, node_position=position)
        np.testing.assert_allclose(np.asarray(x[:, -3:]), np.asarray(toy["f"] / toy["norm"]["f_std"]), rtol=1e-6)
        moved = float(jnp.max(jnp.abs(x_s - x)))
        assert (moved > 1e-3) if position else (moved < 1e-5)
    assert x.shape[1] == 6 + 6 + 2 + 3 + 3
    tiled = M.tile_topology(topo, 2)
    np.testing.assert_array_equal(np.asarray(tiled.x0), np.concatenate([data.q0, data.q0]).astype(np.float32))
    with pytest.raises(ValueError, match="rest positions"):
        M._features(toy["norm"], toy["z"], toy["f"], toy["nt"], toy["topo"], node_position=True)


def test_node_position_model_saves_loads_and_steps(toy, tmp_path):
    # A model with position features round-trips through save/load and steps like before saving.
    data = toy["data"]
    cfg = CONFIG._replace(node_position=True)
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), data.q0)
    w = M.init_weights(jax.random.PRNGKey(2), cfg, toy["norm"], toy["z"], toy["f"], toy["nt"], topo)
    params = api.make_params(cfg, toy["norm"], w, data.q0, data.edges, data.node_type)
    path = api.save_model(params, tmp_path / "m.npz")
    loaded = api.load_model(path)
    g = G.from_data(data, 0, 2)
    np.testing.assert_allclose(np.asarray(api.step(loaded, g, data.f[0, 2]).nodes["z"]),
                               np.asarray(api.step(params, g, data.f[0, 2]).nodes["z"]), atol=1e-6)


@pytest.mark.parametrize("name", ["beam-abaqus", "beam-abaqus-64x2"])
def test_shipped_beam_model_beats_the_published_test_errors(name):
    # The target: on the published test split, every mean rollout error (q, v, sigma with clamped
    # stress predicted, u) below the published network's (which copied the clamped nodes' true state).
    # beam-abaqus-64x2 is the two-pass network (session 46) that the real-time beam row runs.
    from tignn_jax import evaluate as EV

    path = D.reference_path()
    if not path.exists():
        pytest.skip(f"reference data not found at {path}")
    params, _ = api.load_pretrained(name)
    data = D.load(path)
    errs = EV.summarize(EV.split_errors(params, data, D.split_rows(data, "test")))["all"]
    for name, published in EV.PUBLISHED_TEST.items():
        assert errs[name]["mean"] < published, (name, errs[name]["mean"], published)


def test_shipped_beam_linear_test_errors():
    # The rest-linearised FEM on the reference mesh (the fallback of api.fallback_stepper), on the published
    # test split: the errors its card reports (u 0.051, v 0.091, σ 0.063).
    from tignn_jax import evaluate as EV

    path = D.reference_path()
    if not path.exists():
        pytest.skip(f"reference data not found at {path}")
    params, _ = _shipped("beam-linear")
    data = D.load(path)
    errs = EV.summarize(EV.split_errors(params, data, D.split_rows(data, "test")))["all"]
    for name, card in (("u", 0.0508), ("v", 0.0912), ("sigma", 0.0630), ("q", 0.0050)):
        assert errs[name]["mean"] == pytest.approx(card, rel=0.02), (name, errs[name]["mean"])


def _far_response(config, norm, z, f, nt, topo, q0, seed=3) -> float:
    """How much the rate of the node farthest from node 0 changes when node 0 is pushed (an untrained model of
    ``config``): zero when the push cannot reach it."""
    far = int(np.argmax(np.linalg.norm(q0 - q0[0], axis=1)))
    push = jnp.zeros_like(f).at[0].set(jnp.array([1.0, -2.0, 0.5]))
    w = M.init_weights(jax.random.PRNGKey(seed), config, norm, z, f, nt, topo)
    rate = lambda f_: M.rates(w, config, norm, z, f_, nt, topo).dw[far]
    return float(jnp.max(jnp.abs(rate(f + push) - rate(f))))


@pytest.fixture(scope="module")
def pooled(toy):
    """The toy model with global pooling (one virtual node per body)."""
    config = CONFIG._replace(global_pool=True)
    weights = M.init_weights(jax.random.PRNGKey(2), config, toy["norm"], toy["z"], toy["f"], toy["nt"], toy["topo"])
    data = toy["data"]
    params = api.make_params(config, {k: np.asarray(v) for k, v in toy["norm"].items()}, weights, data.q0,
                             data.edges, data.node_type)
    return dict(toy, config=config, weights=weights, params=params)


def test_global_pool_reaches_every_node_in_one_pass(pooled):
    # Without pooling a force reaches only nodes within `passes` hops; with it, every node's rate depends on it.
    t = pooled
    one_pass = {"pool": t["config"]._replace(passes=1), "plain": CONFIG._replace(passes=1)}
    seen = {name: _far_response(config, t["norm"], t["z"], t["f"], t["nt"], t["topo"], t["data"].q0)
            for name, config in one_pass.items()}
    assert seen["plain"] == 0.0          # node 0 is more than one pass (plus the ∇ reverse pass) away
    assert seen["pool"] > 1e-6


def test_global_pool_keeps_generic_structure_and_exact_gradients(pooled):
    t = pooled
    _assert_generic_structure((t["weights"], t["config"], t["norm"], t["z"], t["f"], t["nt"], t["topo"]), seed=1)


def test_global_pool_pools_each_body_of_a_batch_separately(pooled):
    # Two bodies in one graph: each body's summary comes from its own nodes only.
    t = pooled
    _assert_batched_bodies_step_separately(t["params"], t["data"])
    with pytest.raises(ValueError, match="already tiled"):
        M.tile_topology(M.tile_topology(t["topo"], 2), 2)


@pytest.fixture(scope="module")
def kinematic(toy):
    """The toy model with the canonical q–v coupling and kinetic energy built in."""
    data = toy["data"]
    norm = D.normalization(data, D.split_rows(data, "train"))
    jnorm = {k: jnp.asarray(v) for k, v in norm.items()}
    config = CONFIG._replace(kinematic_prior=True)
    weights = M.init_weights(jax.random.PRNGKey(4), config, jnorm, toy["z"], toy["f"], toy["nt"], toy["topo"])
    return dict(toy, config=config, weights=weights, norm=jnorm, dt=data.dt)


def test_kinematic_prior_moves_positions_by_dt_v_before_training(kinematic):
    # With every weight zero the network contributes nothing: L = L0, E = ½|w_v|², M = 0, so the step is
    # exactly q' = q + Δt v (free nodes), v' = v, σ' = σ.
    t = kinematic
    zero = jax.tree_util.tree_map(jnp.zeros_like, t["weights"])
    z_next = M.step_state(zero, t["config"], t["norm"], t["z"], t["f"], t["nt"], t["topo"])
    free = np.asarray(t["nt"]) == 0
    z, zn = np.asarray(t["z"], np.float64), np.asarray(z_next, np.float64)
    np.testing.assert_allclose(zn[free, :3], z[free, :3] + t["dt"] * z[free, 3:6], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(zn[:, 3:], z[:, 3:], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(zn[~free, :3], z[~free, :3])


def test_kinematic_prior_keeps_generic_structure_and_exact_gradients(kinematic):
    t = kinematic
    args = (t["weights"], t["config"], t["norm"], t["z"], t["f"], t["nt"], t["topo"])
    big_l, big_m = M.operators(*args)
    scale_l = float(jnp.max(jnp.abs(big_l)))
    assert float(jnp.max(jnp.abs(big_l + jnp.swapaxes(big_l, 1, 2)))) <= 1e-6 * scale_l
    # the operator applied to ∇E, ∇S is what the step uses
    rt = M.rates(*args)
    dw = jnp.einsum("nij,nj->ni", big_l, rt.grad_e) + jnp.einsum("nij,nj->ni", big_m, rt.grad_s)
    clamped = (np.asarray(t["nt"]) != 0)[:, None] & (np.arange(12) < 6)[None, :]
    np.testing.assert_allclose(np.where(clamped, 0.0, np.asarray(dw)), np.asarray(rt.dw), rtol=1e-4, atol=1e-6)
    _assert_gradients_match_finite_differences(*args, directions=1, seed=2)   # ∇E includes the kinetic term


def test_kinematic_prior_needs_the_time_step_in_the_normalisation(kinematic):
    t = kinematic
    old = {k: v for k, v in t["norm"].items() if k != "dt"}
    with pytest.raises(ValueError, match="dt"):
        M.step_state(t["weights"], t["config"], old, t["z"], t["f"], t["nt"], t["topo"])


@pytest.mark.parametrize("options", [dict(), dict(edge_velocity=False), dict(edge_strain=True),
                                     dict(edge_strain=True, global_pool=True, passes=3),
                                     dict(edge_velocity=False, edge_traction=True)])
def test_factored_edge_inputs_compute_the_straightforward_network(toy, options):
    # The model computes the edge MLP's first layer in parts (node-level for the features linear in q, v):
    # outputs and their gradients with respect to the state equal those of the assembled x_edge, same weights.
    data = toy["data"]
    s, r, n = _irregular_graph(seed=3)   # an irregular graph: several rows per node, padding slots
    q0 = np.random.default_rng(4).normal(size=(n, 3))
    topo = M.topology(s, r, n, q0=q0, slots=3)
    assert topo.nbr.shape[0] > n and float(jnp.min(topo.mask)) == 0.0
    config = CONFIG._replace(**options)
    norm = {**toy["norm"], "du_std": jnp.asarray([0.3, 0.2, 0.25])}
    key = jax.random.split(jax.random.PRNGKey(5), 3)
    z = jnp.concatenate([jnp.asarray(q0) + 0.1 * jax.random.normal(key[0], (n, 3)),
                         jax.random.normal(key[1], (n, 9))], axis=1).astype(jnp.float32)
    f = 0.1 * jax.random.normal(key[2], (n, 3))
    nt = jnp.asarray(np.arange(n) % 5 == 0, jnp.int32)
    weights = M.init_weights(jax.random.PRNGKey(6), config, norm, z, f, nt, topo)
    assert weights["Dense_0"]["kernel"].shape[0] == M.edge_columns(config.edge_velocity, config.edge_strain,
                                                                   edge_traction=config.edge_traction)[0]

    def dense(z_):
        x_node, x_edge = M._features(norm, z_, f, nt, topo, config.edge_velocity, config.edge_strain,
                                     config.node_position, edge_traction=config.edge_traction)
        return jnp.concatenate(M.Network(config).apply({"params": weights}, x_node, x_edge, topo), axis=1)

    factored = lambda z_: M._network_out(weights, config, norm, z_, f, nt, topo)
    out = dense(z)   # float32: agreement to rounding of the output's scale
    np.testing.assert_allclose(factored(z), out, rtol=1e-5, atol=1e-6 * float(jnp.max(jnp.abs(out))))
    energy = lambda fn: jax.grad(lambda z_: jnp.sum(fn(z_)[:, :2] * jnp.asarray([1.0, -0.5])))(z)
    g = energy(dense)
    np.testing.assert_allclose(energy(factored), g, rtol=1e-4, atol=1e-5 * float(jnp.max(jnp.abs(g))))


def test_traction_features_turn_with_the_body_and_read_the_stress_tensor(toy):
    # σ·n with σ from its Voigt vector (11, 22, 33, 12, 13, 23): rotating positions and stress by R rotates each
    # traction by R (a wrong Voigt order would not); a uniaxial σ11 on an edge along x gives (σ11 |dq|, 0, 0).
    s, r, n = _irregular_graph(seed=7)
    rng = np.random.default_rng(8)
    q = rng.normal(size=(n, 3))
    topo = M.topology(s, r, n, q0=q)
    sig = rng.normal(size=(n, 6))
    norm = {**toy["norm"], "dqn_mean": jnp.ones(1), "z_std": jnp.ones(12)}
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    idx = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    tensor = np.zeros((n, 3, 3))
    for a, (i, j) in enumerate(idx):
        tensor[:, i, j] = tensor[:, j, i] = sig[:, a]
    turned = np.einsum("ab,nbc,dc->nad", rot, tensor, rot)
    sig_rot = np.stack([turned[:, i, j] for i, j in idx], axis=1)
    dq = lambda x: M.gather_neighbors(jnp.asarray(x), topo) - M.expand_rows(jnp.asarray(x), topo)[:, None, :]
    t = M._tractions(norm, jnp.asarray(sig), dq(q), topo)
    t_rot = M._tractions(norm, jnp.asarray(sig_rot), dq(q @ rot.T), topo)
    expected = np.concatenate([np.asarray(t[..., :3]) @ rot.T, np.asarray(t[..., 3:]) @ rot.T], axis=-1)
    np.testing.assert_allclose(np.asarray(t_rot), expected, atol=1e-4)
    line = M.topology(np.array([0, 1]), np.array([1, 0]), 2, q0=np.array([[0.0, 0, 0], [2.0, 0, 0]]))
    uni = jnp.asarray([[3.0, 0, 0, 0, 0, 0]] * 2)
    np.testing.assert_allclose(M._tractions(norm, uni, M.gather_neighbors(line.x0, line) - line.x0[:, None, :], line)[1, 0],
                               [-6.0, 0, 0, -6.0, 0, 0], atol=1e-6)


def test_network_output_does_not_depend_on_the_slot_layout():
    # The same graph in rows of K = 2, 3 and the maximum degree: one function (message sums are scaled by the
    # maximum degree, not by K), so a model trained in one layout runs in any other.
    s, r, n = _irregular_graph(seed=9)
    q0 = np.random.default_rng(10).normal(size=(n, 3))
    config = CONFIG._replace(edge_strain=True)
    norm = {k: jnp.ones(d) for k, d in (("z_mean", 12), ("z_std", 12), ("dz_std", 12), ("f_std", 3), ("dq_std", 3),
                                        ("dv_std", 3), ("du_std", 3), ("dqn_mean", 1), ("dqn_std", 1))}
    z = jnp.concatenate([jnp.asarray(q0, jnp.float32), 0.1 * jax.random.normal(jax.random.PRNGKey(11), (n, 9))], 1)
    f, nt = jnp.zeros((n, 3)), jnp.zeros(n, jnp.int32)
    layouts = [M.topology(s, r, n, q0, slots=k) for k in (2, 3, int(np.bincount(r).max()))]
    assert len({t.nbr.shape for t in layouts}) == 3
    weights = M.init_weights(jax.random.PRNGKey(12), config, norm, z, f, nt, layouts[0])
    outs = [M.step_state(weights, config, norm, z, f, nt, t) for t in layouts]
    for out in outs[1:]:
        np.testing.assert_allclose(out, outs[0], rtol=1e-5, atol=1e-6)
    assert float(M.max_degree(layouts[0])) == np.bincount(r).max()


def _port_part(config, norm, z, f, nt, topo):
    """An untrained force-port model's step minus its operators' part L∇E + M∇S (the port term B f), with its
    rates and L; the weights' seed is fixed."""
    weights = M.init_weights(jax.random.PRNGKey(14), config, norm, z, f, nt, topo)
    rt = M.rates(weights, config, norm, z, f, nt, topo)
    l_op, m_op = M.operators(weights, config, norm, z, f, nt, topo)
    return rt.dw - (jnp.einsum("nij,nj->ni", l_op, rt.grad_e) + jnp.einsum("nij,nj->ni", m_op, rt.grad_s)), rt, l_op


def test_force_port_adds_a_positive_gain_times_the_force_to_the_velocities_only(toy):
    # dz/dt = L∇E + M∇S + B f: the step minus the operators' part is g_i f_i / f_std in the v rows of free
    # nodes (g_i > 0), nothing in q and σ, nothing at clamped nodes; L and M keep their structure. (The form of
    # models whose statistics have no port_gain; the toy's data start at rest under a load, so it is dropped.)
    config = CONFIG._replace(force_port=True)
    z, nt, topo = toy["z"], toy["nt"], toy["topo"]
    norm = {k: v for k, v in toy["norm"].items() if k != "port_gain"}
    f = jnp.asarray(toy["f"]) + 0.3 * jax.random.normal(jax.random.PRNGKey(13), toy["f"].shape)
    port, rt, l_op = _port_part(config, norm, z, f, nt, topo)
    free = np.asarray(nt) == 0
    port = np.asarray(port)[free]
    np.testing.assert_allclose(port[:, :3], 0.0, atol=1e-6)
    np.testing.assert_allclose(port[:, 6:], 0.0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(rt.dw)[~free, :6], 0.0)   # clamped: no port either
    gain = port[:, 3:6] / (np.asarray(f)[free] / np.asarray(norm["f_std"]))
    assert np.all(gain > 0)
    np.testing.assert_allclose(gain, np.repeat(gain[:, :1], 3, axis=1), rtol=1e-3)   # one gain per node
    np.testing.assert_allclose(l_op, -jnp.swapaxes(l_op, 1, 2), atol=1e-6)


def test_load_context_points_every_node_of_a_body_at_its_own_load(toy):
    # Two bodies in one graph: body A has a point load at node 5, body B none. Every node of A reads A's total
    # force and the vector from itself to node 5's rest position; every node of B reads zeros.
    data, norm = toy["data"], toy["norm"]
    n = len(data.q0)
    topo = M.tile_topology(M.topology(data.edges[0], data.edges[1], n, data.q0), 2)
    load = np.array([0.4, -1.0, 0.2], np.float32)
    f = jnp.zeros((2 * n, 3)).at[5].set(load)
    ctx = np.asarray(M.load_context(norm, f, topo))
    assert ctx.shape == (2 * n, M.LOAD_CONTEXT_DIM)
    np.testing.assert_allclose(ctx[:n, :3], np.broadcast_to(load / np.asarray(norm["f_std"]), (n, 3)), rtol=1e-6)
    d = (data.q0[5] - data.q0) / np.asarray(norm["x0_std"])
    np.testing.assert_allclose(ctx[:n, 3:6], d, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ctx[:n, 6], np.linalg.norm(d, axis=1), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(ctx[n:], 0.0)
    # Two equal loads: the centre is their midpoint; the context does not depend on the state at all.
    f2 = f.at[9].set(jnp.asarray(load))
    mid = (data.q0[5] + data.q0[9]) / 2
    np.testing.assert_allclose(np.asarray(M.load_context(norm, f2, topo))[:n, 3:6],
                               (mid - data.q0) / np.asarray(norm["x0_std"]), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="rest positions"):
        M.load_context(norm, f, toy["topo"])


def test_load_context_reaches_every_node_in_one_pass_and_keeps_the_structure(toy):
    # A one-pass model cannot see a load beyond its reach; with the context every node's rate depends on it.
    # L stays skew-symmetric, M PSD, and ∇E, ∇S match finite differences (the context is not a state function).
    data, norm, z, nt = toy["data"], toy["norm"], toy["z"], toy["nt"]
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), data.q0)
    seen = {context: _far_response(CONFIG._replace(passes=1, load_context=context), norm, z, toy["f"], nt, topo,
                                   data.q0) for context in (False, True)}
    assert seen[False] == 0.0 and seen[True] > 1e-6
    config = CONFIG._replace(load_context=True)
    f = toy["f"].at[0].add(jnp.array([1.0, -2.0, 0.5]))
    w = M.init_weights(jax.random.PRNGKey(4), config, norm, z, f, nt, topo)
    _assert_generic_structure((w, config, norm, z, f, nt, topo), seed=2)
    params = api.make_params(config, {k: np.asarray(v) for k, v in norm.items()}, w, data.q0, data.edges,
                             data.node_type)
    _assert_batched_bodies_step_separately(params, data)


def test_load_context_has_finite_force_gradients(toy):
    # The context holds norms of the forces and of the node-to-centre vectors, which vanish at unloaded nodes
    # and at the loaded node itself: the step's sensitivity to the forces must still be finite there.
    data, norm, z, nt = toy["data"], toy["norm"], toy["z"], toy["nt"]
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), data.q0)
    config = CONFIG._replace(load_context=True)
    f = jnp.zeros_like(toy["f"]).at[3].set(jnp.array([0.0, -1.0, 0.0]))
    w = M.init_weights(jax.random.PRNGKey(5), config, norm, z, f, nt, topo)
    grad = jax.grad(lambda f_: jnp.sum(M.step_state(w, config, norm, z, f_, nt, topo) ** 2))
    for load in (f, jnp.zeros_like(f)):
        assert np.all(np.isfinite(np.asarray(grad(load))))


def test_coarse_clusters_cover_the_mesh_in_connected_pieces_and_seed_every_component():
    # Every node in exactly one cluster, each cluster connected through mesh edges; two disjoint copies of a
    # mesh (no edge between them) each get clusters of their own even when placed on top of each other.
    data = D.synthetic_beam(nx=6, ny=2, nz=2, cases=1, frames=1)
    s, r = data.edges
    n = len(data.q0)
    cluster = M.coarse_clusters(s, r, data.q0, 5)
    assert cluster.shape == (n,) and set(cluster.tolist()) == set(range(5))
    for c in range(5):
        nodes = set(np.flatnonzero(cluster == c).tolist())
        seen, todo = set(), [min(nodes)]
        while todo:
            a = todo.pop()
            if a in seen:
                continue
            seen.add(a)
            todo += [int(b) for b in s[r == a] if int(b) in nodes]
        assert seen == nodes, f"cluster {c} is not connected"
    np.testing.assert_array_equal(M.coarse_clusters(s, r, data.q0, 5), cluster)   # deterministic
    two = M.coarse_clusters(np.concatenate([s, s + n]), np.concatenate([r, r + n]), np.concatenate([data.q0] * 2), 2)
    assert len(set(two[:n].tolist())) == 1 and len(set(two[n:].tolist())) == 1 and two[0] != two[n]
    cg = M.coarse_graph(s, r, data.q0, 5)
    np.testing.assert_allclose(np.asarray(cg.pool @ cg.assign), np.eye(5), atol=1e-6)   # means of indicators
    adj = np.asarray(cg.adj)
    assert np.all(adj == adj.T) and np.all(np.diag(adj) == 0) and adj.sum() > 0
    with pytest.raises(ValueError, match="coarse_nodes"):
        M.coarse_clusters(s, r, data.q0, n + 1)


@pytest.fixture(scope="module")
def coarse(toy):
    """The toy model with a coarse level of 4 clusters (2 coarse passes per pass)."""
    data = toy["data"]
    config = CONFIG._replace(coarse_nodes=4)
    topo = M.model_topology(config, data.edges[0], data.edges[1], len(data.q0), data.q0)
    weights = M.init_weights(jax.random.PRNGKey(6), config, toy["norm"], toy["z"], toy["f"], toy["nt"], topo)
    params = api.make_params(config, {k: np.asarray(v) for k, v in toy["norm"].items()}, weights, data.q0,
                             data.edges, data.node_type)
    return dict(toy, config=config, weights=weights, params=params, topo=topo)


def test_coarse_level_carries_a_load_beyond_the_fine_reach(coarse):
    # One fine pass sees a load only one hop (and the ∇ reverse pass) away; with the coarse level the farthest
    # node's rate depends on a load at node 0 (the clusters pass it on).
    t = coarse
    seen = {name: _far_response(config, t["norm"], t["z"], t["f"], t["nt"], t["topo"], t["data"].q0)
            for name, config in {"coarse": t["config"]._replace(passes=1), "plain": CONFIG._replace(passes=1)}.items()}
    assert seen["plain"] == 0.0 and seen["coarse"] > 1e-6


def test_coarse_level_keeps_generic_structure_exact_gradients_and_translation_invariance(coarse):
    # L skew, M PSD, ∇E and ∇S equal finite differences, and (without node_position) the energy depends on
    # positions only through differences: the internal force −∇_q E sums to zero over the body.
    t = coarse
    args = (t["weights"], t["config"], t["norm"], t["z"], t["f"], t["nt"], t["topo"])
    _assert_generic_structure(args, seed=3)
    g_e = M.rates(*args).grad_e
    assert float(jnp.max(jnp.abs(jnp.sum(g_e[:, :3], axis=0)))) <= 1e-4 * float(jnp.sum(jnp.abs(g_e[:, :3])))


def test_coarse_level_steps_each_body_of_a_batch_separately_and_saves(coarse, tmp_path):
    t = coarse
    _assert_batched_bodies_step_separately(t["params"], t["data"])
    path = api.save_model(t["params"], tmp_path / "model.npz")
    loaded = api.load_model(path)
    graph = G.from_data(t["data"], 0, 2)
    np.testing.assert_array_equal(np.asarray(api.step(loaded, graph, t["f"]).nodes["z"]),
                                  np.asarray(api.step(t["params"], graph, t["f"]).nodes["z"]))
    plain = M.topology(t["data"].edges[0], t["data"].edges[1], len(t["data"].q0), t["data"].q0)
    with pytest.raises(ValueError, match="coarse_nodes=4"):   # a Topology built without the clusters
        M.step_state(t["weights"], t["config"], t["norm"], t["z"], t["f"], t["nt"], plain)


def test_coarse_mixing_couples_clusters_that_share_no_edge(coarse):
    # With no coarse message passing a cluster's latent reaches only its own nodes; the mixing layer couples
    # every cluster of a body to every other, and keeps the structure and the per-body separation.
    t = coarse
    data = t["data"]
    seen = {mixing: _far_response(t["config"]._replace(passes=1, coarse_passes=0, coarse_mixing=mixing), t["norm"],
                                  t["z"], t["f"], t["nt"], t["topo"], data.q0) for mixing in (False, True)}
    assert seen[False] == 0.0 and seen[True] > 1e-9   # exactly zero without the path; small at initialisation
    config = t["config"]._replace(coarse_mixing=True)
    w = M.init_weights(jax.random.PRNGKey(7), config, t["norm"], t["z"], t["f"], t["nt"], t["topo"])
    args = (w, config, t["norm"], t["z"], t["f"], t["nt"], t["topo"])
    _assert_generic_structure(args, seed=4)
    params = api.make_params(config, {k: np.asarray(v) for k, v in t["norm"].items()}, w, data.q0, data.edges,
                             data.node_type)
    _assert_batched_bodies_step_separately(params, data)


def test_rest_equilibrium_keeps_the_unloaded_body_at_rest_and_the_structure(toy):
    # The same weights with and without the shift: without it an untrained network drifts from rest under zero
    # force; with it the rest state is a fixed point (∇E = ∇S = 0 there) while a load still moves the body.
    # L skew, M PSD, and ∇E, ∇S equal finite differences of the shifted E, S.
    data, norm, nt = toy["data"], toy["norm"], toy["nt"]
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), data.q0)
    config = CONFIG._replace(rest_equilibrium=True)
    rest = jnp.concatenate([jnp.asarray(data.q0, jnp.float32), jnp.zeros((len(data.q0), 9))], axis=1)
    zero = jnp.zeros((len(data.q0), 3))
    w = M.init_weights(jax.random.PRNGKey(8), config, norm, rest, zero, nt, topo)
    drift = {}
    for flag in (False, True):
        c = config._replace(rest_equilibrium=flag)
        z = rest
        for _ in range(5):
            z = M.step_state(w, c, norm, z, zero, nt, topo)
        drift[flag] = float(jnp.max(jnp.abs(z - rest)))
    assert drift[False] > 1e-4 and drift[True] <= 1e-6 * float(jnp.max(jnp.abs(rest)))
    load = zero.at[-1].set(jnp.array([0.0, 0.0, -10.0]) * norm["f_std"])   # ten training force scales
    pushed = M.step_state(w, config, norm, rest, load, nt, topo)
    assert float(jnp.max(jnp.abs(pushed - rest))) > 100 * max(drift[True], 1e-9)
    args = (w, config, norm, toy["z"], toy["f"], nt, topo)
    _assert_generic_structure(args, seed=5)


def test_rest_equilibrium_precomputed_rest_gradients_give_the_same_steps(toy):
    # stepper and rollout compute the rest gradients once (model.with_rest); the validated step recomputes them.
    data = toy["data"]
    config = CONFIG._replace(rest_equilibrium=True)
    params = api.make_params(config, {k: np.asarray(v) for k, v in toy["norm"].items()}, toy["weights"], data.q0,
                             data.edges, data.node_type)
    graph = G.from_data(data, 0, 1)
    forces = jnp.asarray(data.f[0, 1:3])
    stepped = api.step(params, api.step(params, graph, forces[0]), forces[1]).nodes["z"]
    np.testing.assert_allclose(np.asarray(api.rollout(params, graph, forces)[-1]), np.asarray(stepped), atol=1e-5)
    fn = api.stepper(params)
    np.testing.assert_allclose(np.asarray(fn(fn(graph.nodes["z"], forces[0]), forces[1])), np.asarray(stepped),
                               atol=1e-5)


def test_force_port_with_the_datas_port_gain_starts_at_the_physical_size(toy):
    # With norm["port_gain"] (velocity per unit force per frame, ≈ Δt / nodal mass) the port adds
    # g_i · port_gain · f in physical velocity with the learned factor g_i = softplus(·)/softplus(0) ≈ 1 at
    # initialisation: the bunny needs ~160× the old f/f_std scale, which training could not reach.
    config = CONFIG._replace(force_port=True)
    z, nt, topo = toy["z"], toy["nt"], toy["topo"]
    norm = dict(toy["norm"], port_gain=jnp.array([37.0]))
    f = jnp.asarray(toy["f"]) + 0.3 * jax.random.normal(jax.random.PRNGKey(13), toy["f"].shape)
    port, _, _ = _port_part(config, norm, z, f, nt, topo)
    free = np.asarray(nt) == 0
    dv = np.asarray(port[:, 3:6] * M.state_scale(norm)[3:6])[free]   # physical velocity added in one step
    factor = dv / (37.0 * np.asarray(f)[free])
    assert np.all((factor > 0.7) & (factor < 1.4)), factor.min()
    np.testing.assert_allclose(factor, np.repeat(factor[:, :1], 3, axis=1), rtol=1e-3)
    big = float(np.abs(np.asarray(port)).max())
    np.testing.assert_allclose(np.asarray(port)[:, :3], 0.0, atol=1e-6 * big)   # float32 round-off of dw only


def test_node_embedding_gives_each_mesh_node_its_own_learned_vector(toy, tmp_path):
    # A zero-initialised table [nodes, D]; filled with random numbers the model keeps the GENERIC structure,
    # changing one node's vector changes that node's rate, two bodies of the mesh in one batch each read the
    # table (not one long table), and the weights survive save/load.
    data, norm, z, f, nt, topo = toy["data"], toy["norm"], toy["z"], toy["f"], toy["nt"], toy["topo"]
    config = CONFIG._replace(node_embedding=3)
    w = M.init_weights(jax.random.PRNGKey(5), config, norm, z, f, nt, topo)
    table = w["node_embedding"]
    assert table.shape == (len(data.q0), 3) and not np.any(np.asarray(table))
    w = {**w, "node_embedding": jax.random.normal(jax.random.PRNGKey(6), table.shape)}
    _assert_generic_structure((w, config, norm, z, f, nt, topo), seed=3)
    free = int(np.where(np.asarray(data.node_type) == 0)[0][-1])
    moved = {**w, "node_embedding": w["node_embedding"].at[free].add(1.0)}
    rate = lambda weights: np.asarray(M.rates(weights, config, norm, z, f, nt, topo).dw)
    assert np.abs(rate(moved)[free] - rate(w)[free]).max() > 1e-6
    params = api.make_params(config, {k: np.asarray(v) for k, v in norm.items()}, w, data.q0, data.edges,
                             data.node_type)
    _assert_batched_bodies_step_separately(params, data)
    loaded = api.load_model(api.save_model(params, tmp_path / "m.npz"))
    g = G.from_data(data, 0, 2)
    np.testing.assert_allclose(np.asarray(api.step(loaded, g, data.f[0, 2]).nodes["z"]),
                               np.asarray(api.step(params, g, data.f[0, 2]).nodes["z"]), atol=1e-6)


def test_elastic_port_is_a_spring_potential_through_the_port(toy):
    # elastic_port adds B(−∇_q U) in the velocity rows: the spring force equals minus the gradient of
    # U = ½ Σ over undirected edges of k (ℓ − ℓ⁰)², computed here from the edge list (so k must be the same on both
    # directions of an edge); it vanishes at the rest positions; the rate differs from the model without the
    # spring term by exactly the port applied to that force; it needs force_port and the statistics' spring_k.
    data, z, f, nt = toy["data"], toy["z"], toy["f"], toy["nt"]
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), q0=data.q0)
    k0 = 1e6   # the toy bar's strains are ~1e-6: a stiffness that makes the term count
    norm = {**toy["norm"], "port_gain": jnp.asarray([0.3]), "spring_k": jnp.asarray([k0])}
    config = CONFIG._replace(force_port=True, elastic_port=True)
    w = M.init_weights(jax.random.PRNGKey(7), config, norm, z, f, nt, topo)
    np.testing.assert_allclose(np.asarray(M.spring_stiffness(w, norm, topo))[np.asarray(topo.mask) > 0], k0,
                               rtol=1e-6)   # ψ ≡ 0 at initialisation: k = k₀
    w = {**w, "spring": jax.random.normal(jax.random.PRNGKey(8), w["spring"].shape) * 0.5}
    k_slot = np.asarray(M.spring_stiffness(w, norm, topo))
    nbr, mask, row = np.asarray(topo.nbr), np.asarray(topo.mask), np.asarray(topo.row_node)
    k_edge = {(int(nbr[r_, s_]), int(row[r_])): k_slot[r_, s_] for r_, s_ in zip(*np.nonzero(mask))}
    send, recv = data.edges
    assert len(k_edge) == len(send)
    k = np.array([k_edge[(int(a), int(b))] for a, b in zip(send, recv)])
    np.testing.assert_allclose(k, [k_edge[(int(b), int(a))] for a, b in zip(send, recv)], rtol=1e-6)
    rest = np.linalg.norm(data.q0[send] - data.q0[recv], axis=1)

    def energy(q):
        return 0.25 * jnp.sum(k * (jnp.linalg.norm(q[send] - q[recv], axis=1) - rest) ** 2)   # both directions

    q = jnp.asarray(z[:, :3])
    force = np.asarray(M.spring_force(w, norm, z, topo))
    np.testing.assert_allclose(force, -np.asarray(jax.grad(energy)(q)), rtol=1e-4, atol=1e-6 * np.abs(force).max())
    assert np.abs(force).max() > 0
    z_rest = jnp.asarray(z).at[:, :3].set(jnp.asarray(data.q0, z.dtype))
    assert np.abs(np.asarray(M.spring_force(w, norm, z_rest, topo))).max() < 1e-5 * np.abs(force).max()
    plain = config._replace(elastic_port=False)
    w_plain = {key: v for key, v in w.items() if key != "spring"}
    port = M._network_out(w_plain, plain, norm, z, f, nt, topo)[:, -1:]
    dw = np.asarray(M.rates(w, config, norm, z, f, nt, topo).dw)
    diff = dw - np.asarray(M.rates(w_plain, plain, norm, z, f, nt, topo).dw)
    expected = np.array(M.force_term(port, force, norm))
    expected[np.asarray(nt) != 0, :6] = 0.0   # clamped nodes keep q and v
    assert np.abs(expected).max() > 1e-3 * np.abs(dw).max()
    np.testing.assert_allclose(diff, expected, rtol=1e-4, atol=1e-5 * np.abs(dw).max())   # float32 round-off
    with pytest.raises(ValueError, match="elastic_port=True needs force_port=True"):
        M.init_weights(jax.random.PRNGKey(7), config._replace(force_port=False), norm, z, f, nt, topo)
    with pytest.raises(ValueError, match="spring_k"):
        M.rates(w, config, {key: v for key, v in norm.items() if key != "spring_k"}, z, f, nt, topo)


def test_port_hops_spread_a_force_linearly_over_h_edges(toy):
    # port_hops = H: the port's input map F → F + P₁F + P₂P₁F is the identity at initialisation, linear in F,
    # and a force on one node reaches exactly the nodes within H edges of it; the model keeps its structure.
    data, z, f, nt = toy["data"], toy["z"], toy["f"], toy["nt"]
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), q0=data.q0)
    config = CONFIG._replace(force_port=True, port_hops=2)
    w = M.init_weights(jax.random.PRNGKey(9), config, toy["norm"], z, f, nt, topo)
    np.testing.assert_array_equal(np.asarray(M.spread_forces(w, f, topo, 2)), np.asarray(f))
    w = {**w, "port_spread": jax.random.normal(jax.random.PRNGKey(10), w["port_spread"].shape) * 0.5}
    rng = np.random.default_rng(0)
    a, b = (jnp.asarray(rng.normal(size=f.shape), jnp.float32) for _ in range(2))
    spread = lambda x: np.asarray(M.spread_forces(w, x, topo, 2))
    np.testing.assert_allclose(spread(2.0 * a - b), 2.0 * spread(a) - spread(b), rtol=1e-4, atol=1e-4)
    hops = fem.meshes.hop_distances(data.edges, len(data.q0))
    node = int(np.where(np.asarray(data.node_type) == 0)[0][0])
    reached = np.abs(spread(jnp.zeros_like(f).at[node].set(jnp.asarray([1.0, -2.0, 0.5])))).sum(1) > 0
    np.testing.assert_array_equal(reached, hops[node] <= 2)
    _assert_generic_structure((w, config, toy["norm"], z, f, nt, topo), seed=4)
    with pytest.raises(ValueError, match="port_hops=2 needs force_port=True"):
        M.init_weights(jax.random.PRNGKey(9), config._replace(force_port=False), toy["norm"], z, f, nt, topo)


def test_with_rest_caches_the_rest_mesh_constants_without_changing_the_step(toy):
    # with_rest adds the weight-and-rest-mesh constants (rest gradients, elastic_port's edge stiffnesses,
    # port_hops' edge coefficients) to the statistics once; a step with them equals a step that recomputes them.
    data, z, f, nt = toy["data"], toy["z"], toy["f"], toy["nt"]
    topo = M.topology(data.edges[0], data.edges[1], len(data.q0), q0=data.q0)
    norm = {**toy["norm"], "port_gain": jnp.asarray([0.3]), "spring_k": jnp.asarray([1e6])}
    config = CONFIG._replace(force_port=True, elastic_port=True, port_hops=2, rest_equilibrium=True)
    w = M.init_weights(jax.random.PRNGKey(11), config, norm, z, f, nt, topo)
    keys = jax.random.split(jax.random.PRNGKey(12), 2)
    w = {**w, "spring": jax.random.normal(keys[0], w["spring"].shape) * 0.5,
         "port_spread": jax.random.normal(keys[1], w["port_spread"].shape) * 0.5}
    cached = M.with_rest(w, config, norm, nt, topo)
    assert {"rest_grads", "spring_edges", "spread_edges"} <= set(cached)
    assert cached["spread_edges"].shape[:1] == (2,)
    step = jax.jit(M.step_state, static_argnames="config")
    fresh, fast = (np.asarray(step(w, config, n, z, f, nt, topo)) for n in (norm, cached))
    assert np.abs(fresh - np.asarray(z)).max() > 0
    np.testing.assert_allclose(fast, fresh, rtol=1e-6, atol=1e-6 * np.abs(fresh).max())
    plain = CONFIG
    assert M.with_rest(M.init_weights(jax.random.PRNGKey(1), plain, norm, z, f, nt, topo), plain, norm, nt,
                       topo) is norm


def test_state_check_measures_against_the_training_envelope(toy):
    # With the envelope in the statistics (data.envelope: the largest deviation of each feature in training, the
    # largest displacement) no training state is flagged, whatever its size in standard deviations; a state
    # 2x beyond the envelope in one stress component, or with 2x the largest training displacement, is; a model
    # without the envelope falls back to the fixed bound in standard deviations.
    params, data = toy["params"], toy["data"]
    norm = params["norm"]
    assert {"z_dev_max", "u_max"} <= set(norm)
    guard = jax.jit(api.state_guard(params))
    for z in data.z.reshape(-1, *data.z.shape[-2:]):
        check = api.state_check(params, z)
        assert not check["out_of_distribution"] and check["envelope_ratio"] <= 1.0 + 1e-5
        assert not bool(guard(jnp.asarray(z)))
    wild = np.array(data.z[0, 2], np.float64)
    k = 3 + int(np.argmax(np.asarray(norm["z_dev_max"])[3:]))   # the heaviest-tailed v/σ feature
    wild[1, k] = float(norm["z_mean"][k] + 2.0 * norm["z_dev_max"][k] * norm["z_std"][k])
    check = api.state_check(params, wild)
    assert check["out_of_distribution"] and check["envelope_ratio"] == pytest.approx(2.0, rel=1e-3)
    assert bool(guard(jnp.asarray(wild, jnp.float32)))
    far = np.array(data.z[0, 2], np.float64)
    far[2, :3] = data.q0[2] + np.array([2.0 * float(norm["u_max"][0]), 0.0, 0.0])
    assert api.state_check(params, far)["out_of_distribution"]
    assert api.state_check(params, far, tolerance=2.5)["envelope_ratio"] == pytest.approx(2.0, rel=1e-3)
    two = np.concatenate([data.z[0, 2], wild])   # two stacked copies of the mesh
    assert api.state_check(params, two)["out_of_distribution"] and bool(guard(jnp.asarray(two, jnp.float32)))
    old = {**params, "norm": {k_: v for k_, v in norm.items() if k_ not in ("z_dev_max", "u_max")}}
    fallback = api.state_check(old, wild)
    assert fallback["envelope_ratio"] is None
    assert fallback["out_of_distribution"] == (fallback["max_deviation"] > 8.0)
    with pytest.raises(ValueError, match="tolerance"):
        api.state_check(params, wild, tolerance=0.0)


def test_guarded_stepper_never_returns_non_finite_or_out_of_envelope_states(toy):
    # In distribution the guarded step is the plain step; a state the plain step would carry outside the
    # training envelope (or to NaN) is flagged and replaced: clipped into the envelope ("clip") or the rest
    # state ("reset"); the clipped state passes state_check at the same tolerance.
    params, data = toy["params"], toy["data"]
    plain = api.stepper(params)
    clip = api.guarded_stepper(params, policy="clip")
    reset = api.guarded_stepper(params)   # the default policy
    z, f = jnp.asarray(data.z[0, 2]), jnp.asarray(data.f[0, 2])
    ref = np.asarray(plain(z, f))
    loose = api.guarded_stepper(params, tolerance=1e6)   # nothing this untrained step gives is flagged
    out, flagged = loose(z, f)
    assert not bool(flagged)
    np.testing.assert_array_equal(np.asarray(out), ref)
    norm = params["norm"]
    wild = np.array(data.z[0, 2], np.float32)
    wild[:, 3:] = norm["z_mean"][3:] + 50.0 * np.asarray(norm["z_dev_max"])[3:] * norm["z_std"][3:]
    wild[5, :3] = data.q0[5] + np.array([20.0 * float(norm["u_max"][0]), 0.0, 0.0], np.float32)
    wild[6, 7] = np.nan
    for z_in in (wild, np.full_like(wild, np.inf)):
        out, flagged = clip(jnp.asarray(z_in), f)
        out = np.asarray(out)
        assert bool(flagged) and np.all(np.isfinite(out))
        check = api.state_check(params, out, tolerance=1.5 * (1 + 1e-4))
        assert not check["out_of_distribution"], check
        back, flagged = reset(jnp.asarray(z_in), f)
        assert bool(flagged)
        np.testing.assert_array_equal(np.asarray(back)[:, :3], np.asarray(data.q0, np.float32))
        assert not np.asarray(back)[:, 3:].any()
    # only the body that fails is reset (a non-finite one; the loose tolerance lets the other through)
    pair = api.guarded_stepper(params, copies=2, policy="reset", tolerance=1e6)
    zz = jnp.asarray(np.concatenate([np.asarray(data.z[0, 2]), np.full_like(wild, np.inf)]))
    both, flags = pair(zz, jnp.concatenate([f, f]))
    n = len(data.q0)
    assert flags.shape == (2,) and not bool(flags[0]) and bool(flags[1])
    np.testing.assert_allclose(np.asarray(both)[:n], np.asarray(api.stepper(params, 2)(zz, jnp.concatenate([f, f])))[:n])
    assert not np.asarray(both)[n:, 3:].any()
    with pytest.raises(ValueError, match="policy"):
        api.guarded_stepper(params, policy="freeze")
    with pytest.raises(ValueError, match="tolerance"):
        api.guarded_stepper(params, tolerance=-1.0)


@pytest.mark.parametrize("integrator,terms", [("euler", 1), ("heun", 2), ("rk4", 4)])
def test_runge_kutta_on_a_linear_rate_is_the_truncated_exponential(integrator, terms):
    """For a linear rate Δw = A w, an explicit Runge-Kutta method of order p ≤ 4 with p stages steps by the
    Taylor polynomial of exp(A) of degree p: Σ_{k=1..p} A^k / k! w (the known stability function)."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6)) * 0.4
    w = rng.normal(size=6)
    got, stages = M.runge_kutta(integrator, lambda x: (a @ x,), w, 1.0)
    want, term = np.zeros(6), w.copy()
    for k in range(1, terms + 1):
        term = a @ term / k
        want += term
    assert len(stages) == terms
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("integrator,terms", [("euler", 1), ("rk4", 4)])
def test_runge_kutta_substeps_compose_the_stability_function_of_the_shorter_step(integrator, terms):
    """n sub-steps of a linear rate A w (A per whole step) give P(A/n)^n w, with P the method's Taylor
    polynomial of degree p; on a decay at λΔt = −4, beyond RK4's real stability limit (−2.78), one RK4 step
    grows by R(−4) = 5 and two sub-steps contract by R(−2)² = 1/9; bad sub-step counts are clear errors."""
    rng = np.random.default_rng(1)
    a = rng.normal(size=(5, 5)) * 0.6
    w = rng.normal(size=5)
    got, stages = M.runge_kutta(integrator, lambda x: (a @ x,), w, 1.0, substeps=3)
    x = w.copy()
    for _ in range(3):
        term, inc = x.copy(), np.zeros(5)
        for k in range(1, terms + 1):
            term = a @ term / (3 * k)
            inc += term
        x = x + inc
    assert len(stages) == 3 * terms
    np.testing.assert_allclose(got, x - w, rtol=1e-10, atol=1e-12)
    growth = lambda n: abs(1 + float(M.runge_kutta("rk4", lambda v: (-4.0 * v,), np.ones(1), 1.0, substeps=n)[0][0]))
    np.testing.assert_allclose([growth(1), growth(2)], [5.0, 1 / 9], rtol=1e-12)   # R(−4) = 5, R(−2)² = 1/9
    for bad in (0, 2.5):
        with pytest.raises(ValueError, match="substeps must be"):
            M.check_integrator(M.ModelConfig(substeps=bad))
    with pytest.raises(ValueError, match="substeps=2 with frame_solve"):
        M.check_integrator(M.ModelConfig(substeps=2, frame_solve=True))
    with pytest.raises(ValueError, match="relaxation=True needs"):
        M.check_integrator(M.ModelConfig(relaxation=True, integrator="rk4"))


def test_rk4_step_composes_four_network_rates_and_keeps_clamps(toy):
    """The rk4 step is z + (k1 + 2k2 + 2k3 + k4)/6 in state units with k_i the network's increments at the
    classical stages; clamped nodes keep their position and velocity; the stability function at a large
    dissipative eigenvalue (λΔt = −2.2, where forward Euler grows by 1.2) is below 1."""
    w, _, norm, z, f, nt, topo = _args(toy)
    rk4 = CONFIG._replace(integrator="rk4")
    s = M.state_scale(norm)
    k = lambda x: M._generic(w, CONFIG, norm, x, f, nt, topo)[0]
    k1 = k(z)
    k2 = k(z + 0.5 * k1 * s)
    k3 = k(z + 0.5 * k2 * s)
    k4 = k(z + k3 * s)
    want = z + (k1 + 2 * k2 + 2 * k3 + k4) / 6 * s
    z_r = M.step_state(w, rk4, norm, z, f, nt, topo)
    np.testing.assert_allclose(np.asarray(z_r), np.asarray(want), rtol=1e-5, atol=1e-6)
    clamped = np.asarray(toy["nt"]) != 0
    np.testing.assert_array_equal(np.asarray(z_r)[clamped, :6], np.asarray(z)[clamped, :6])
    growth = {name: abs(1 + float(M.runge_kutta(name, lambda x: (-2.2 * x,), np.ones(1), 1.0)[0][0]))
              for name in ("euler", "rk4")}
    assert growth["rk4"] < 0.5 and growth["euler"] > 1.19


def test_heun_step_is_the_mean_of_the_state_and_two_euler_steps(toy):
    """The explicit trapezoidal rule z + ½(Δw(z) + Δw(z + Δw(z))) equals ½(z + Euler(Euler(z))); clamped nodes
    keep their position and velocity; the option saves, loads and steps; bad combinations are clear errors."""
    w, _, norm, z, f, nt, topo = _args(toy)
    heun = CONFIG._replace(integrator="heun")
    euler = lambda x: M.step_state(w, CONFIG, norm, x, f, nt, topo)
    z_h = M.step_state(w, heun, norm, z, f, nt, topo)
    np.testing.assert_allclose(np.asarray(z_h), np.asarray(0.5 * (z + euler(euler(z)))), rtol=1e-5, atol=1e-6)
    assert float(jnp.abs(z_h - euler(z)).max()) > 1e-4 * float(jnp.abs(euler(z) - z).max())   # not Euler
    clamped = np.asarray(toy["nt"]) != 0
    np.testing.assert_array_equal(np.asarray(z_h)[clamped, :6], np.asarray(z)[clamped, :6])
    data = toy["data"]
    params = api.make_params(heun, {k: np.asarray(v) for k, v in toy["norm"].items()}, w, data.q0, data.edges,
                             data.node_type)
    with pytest.raises(ValueError, match="integrator must be one of"):
        api.make_params(CONFIG._replace(integrator="rk5"), toy["norm"], w, data.q0, data.edges, data.node_type)
    with pytest.raises(ValueError, match="the W-method is the step's integrator"):
        M.check_integrator(CONFIG._replace(integrator="heun", frame_solve=True))
    graph = G.rest_graph(data.q0, data.edges, data.node_type)
    graph = graph._replace(nodes={**graph.nodes, "z": z})
    np.testing.assert_allclose(np.asarray(api.step(params, graph, f).nodes["z"]), np.asarray(z_h), rtol=1e-6,
                               atol=1e-6)


def test_step_growth_is_the_spectral_radius_of_the_step_jacobian(toy):
    # The finite-difference power iteration of api.step_growth against the eigenvalues of the dense Jacobian of
    # the step (reverse mode) in state-std units, at a mid-rollout state; and its input checks.
    params, data = toy["params"], toy["data"]
    z, f = np.asarray(data.z[0, 2]), np.asarray(data.f[0, 2])
    out = api.step_growth(params, z, f, iterations=300, eps=1e-3)
    fn, std = api.stepper(params), params["norm"]["z_std"]
    step = lambda x: (fn(jnp.asarray(z) + x * std, jnp.asarray(f)) / std).ravel()
    jac = np.asarray(jax.jacrev(step)(jnp.zeros(z.shape)), np.float64).reshape(z.size, z.size)
    free = np.ravel(~((np.asarray(data.node_type) != 0)[:, None] & (np.arange(12) < 6)[None, :]))
    jac = jac[np.ix_(free, free)]   # clamped q, v are prescribed: not part of the dynamics
    rho = np.max(np.abs(np.linalg.eigvals(jac)))
    assert abs(out["growth"] / rho - 1) < 0.03, (out["growth"], rho)
    assert out["mode"].shape == z.shape and abs(out["feature_share"].sum() - 1) < 1e-6
    with pytest.raises(ValueError, match=r"z and forces must be \[16, 12\] and \[16, 3\]"):
        api.step_growth(params, z[:-1], f)
    with pytest.raises(ValueError, match="iterations must be an integer >= 3, got 2"):
        api.step_growth(params, z, f, iterations=2)
    with pytest.raises(ValueError, match="must be finite"):
        api.step_growth(params, np.full_like(z, np.nan), f)


def test_growth_terms_split_the_step_jacobian_and_static_l_removes_the_change_of_l(toy):
    # api.growth_terms' four terms (L∇²E, (∂L)∇E, M∇²S, (∂M)∇S) against xᵀ(J − I)x of the dense Jacobian of the
    # step (reverse mode) in state-std units, for a random direction x at a mid-rollout state; with static_l
    # (L decoded at the rest state) L is the same at every state and its change term is exactly zero.
    params, data = toy["params"], toy["data"]
    z, f = np.asarray(data.z[0, 2]), np.asarray(data.f[0, 2])
    free = ~((np.asarray(data.node_type) != 0)[:, None] & (np.arange(12) < 6)[None, :])
    x = np.random.default_rng(0).normal(size=z.shape) * free
    x = x / np.linalg.norm(x)

    def dense_quadratic(p):
        fn, std = api.stepper(p), p["norm"]["z_std"]
        step = lambda d: (fn(jnp.asarray(z) + d * std, jnp.asarray(f)) / std).ravel()
        jac = np.asarray(jax.jacrev(step)(jnp.zeros(z.shape)), np.float64).reshape(z.size, z.size)
        return float(x.ravel() @ jac @ x.ravel()) - 1.0

    terms = api.growth_terms(params, z, f, x)
    parts = sum(terms[k] for k in api.GROWTH_TERMS)
    exact = dense_quadratic(params)
    assert abs(terms["L_change"]) > 1e-4 and abs(terms["L_hessian"]) > 1e-4   # both terms present untrained
    assert abs(parts - exact) <= 1e-3 * max(abs(exact), 1e-2), (terms, exact)
    assert abs(terms["total"] - exact) <= 1e-3 * max(abs(exact), 1e-2)

    static = dict(params, config={**params["config"], "static_l": True})
    l_a, _ = M.operators(toy["weights"], M.ModelConfig(**static["config"]), toy["norm"], jnp.asarray(z),
                         jnp.asarray(f), toy["nt"], params["topo"])
    l_b, _ = M.operators(toy["weights"], M.ModelConfig(**static["config"]), toy["norm"],
                         jnp.asarray(data.z[1, 3]), jnp.asarray(data.f[1, 3]), toy["nt"], params["topo"])
    assert float(jnp.max(jnp.abs(l_a - l_b))) == 0.0 and float(jnp.max(jnp.abs(l_a))) > 0
    s_terms = api.growth_terms(static, z, f, x)
    assert s_terms["L_change"] == 0.0
    assert abs(sum(s_terms[k] for k in api.GROWTH_TERMS) - dense_quadratic(static)) <= 1e-3 * max(
        abs(dense_quadratic(static)), 1e-2)
    with pytest.raises(ValueError, match=r"mode must be \[16, 12\]"):
        api.growth_terms(params, z, f, x[:-1])
    with pytest.raises(ValueError, match="mode must have a non-zero entry"):
        api.growth_terms(params, z, f, x * 0)
