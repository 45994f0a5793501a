"""The learned linear GENERIC model (`tignn_jax.linear_generic`): its operators' structure, its backward-Euler
rollout, training with resume, and its packing into the frame_solve model format."""
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fem.mesh import box_hex_mesh, hex_to_tet
from fem.meshes import mesh_edges
from tignn_jax.train import linear as LG


@pytest.fixture(autouse=True)
def x64():
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", False)


def bar(kind="tet"):
    """A clamped 4×1×1 bar of 4 hexes, each split into tets (``kind`` "tet") or not ("hex")."""
    pts, hexes = box_hex_mesh(size=(4.0, 1.0, 1.0), divisions=(4, 1, 1))
    cells = hex_to_tet(hexes) if kind == "tet" else hexes
    edges = mesh_edges(cells)
    edges = np.concatenate([edges, edges[::-1]], axis=1) if not _both_directions(edges) else edges
    node_type = (pts[:, 0] < 1e-9).astype(np.int32)
    return pts, edges, cells, node_type


def _both_directions(edges):
    pairs = set(zip(*map(tuple, edges)))
    return all((b, a) in pairs for a, b in pairs)


def random_params(config, geo, seed=1):
    """Parameters with every head randomised, so the checks hold for any learned state, not just the start."""
    p = LG.init(config, geo, seed)
    keys = jax.random.split(jax.random.PRNGKey(seed), 64)
    leaves, tree = jax.tree_util.tree_flatten(p)
    leaves = [x + 0.3 * jax.random.normal(k, jnp.shape(x)) for x, k in zip(leaves, keys)]
    return jax.tree_util.tree_unflatten(tree, leaves)


def operators(config, geo, params):
    ga = LG.geometry_arrays(geo)
    ops = jax.jit(lambda p, g: LG.operators(p["net"], g, geo.h, config, p))(params, ga)
    K = np.asarray(jax.jit(lambda o, g: LG.stiffness(o, g, geo.h))(ops, ga))
    return ops, ga, K


def rigid_and_uniform(pts):
    """Displacement fields [k, N, 3]: three translations, three infinitesimal rotations, one uniform strain."""
    fields = [np.broadcast_to(e, pts.shape) for e in np.eye(3)]
    fields += [np.cross(w, pts - pts.mean(0)) for w in np.eye(3)]
    return np.stack(fields), pts @ np.array([[1e-3, 2e-4, 0], [2e-4, -5e-4, 1e-4], [0, 1e-4, 3e-4]]).T


def test_gradient_weights_reproduce_linear_fields():
    # a uniform gradient must be read exactly at every node, for the least-squares start and for any learned one
    pts, edges, cells, node_type = bar()
    geo = LG.geometry(pts, edges, cells, node_type)
    config = LG.LinearConfig(hidden=8)
    ops, ga, _ = operators(config, geo, random_params(config, geo))
    A = np.array([[0.3, -0.1, 0.2], [0.05, 0.4, -0.2], [0.1, 0.0, -0.3]])
    u = pts @ A.T
    for g in (np.asarray(ga["g_ls"]) / geo.h, np.asarray(ga["g_avg"]) / geo.h, np.asarray(ops.g), np.asarray(ops.gs)):
        local = np.concatenate([u[:, None], u[geo.nbr]], axis=1)
        grads = np.asarray(jax.vmap(LG._gradient)(jnp.asarray(local), jnp.asarray(g)))
        assert np.abs(grads - A).max() < 1e-10


def test_averaged_gradient_of_a_single_tet_is_the_tet_gradient():
    # one tet: every node's volume-averaged gradient is the element's own, ∇N_j
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 1.0, 0.1], [0.1, 0.2, 1.3]])
    cells = np.array([[0, 1, 2, 3]])
    edges = np.array([(a, b) for a in range(4) for b in range(4) if a != b]).T
    geo = LG.geometry(pts, edges, cells, np.zeros(4, np.int32))
    grad_n = np.linalg.inv(np.stack([pts[1] - pts[0], pts[2] - pts[0], pts[3] - pts[0]]))   # columns ∇N_1..3
    grad_n = np.concatenate([-grad_n.sum(axis=1, keepdims=True), grad_n], axis=1).T       # rows ∇N_0..3
    for i in range(4):
        for d, j in enumerate(geo.nbr[i]):
            assert np.allclose(geo.g_avg[i, d] / geo.h, grad_n[j], atol=1e-12)
    assert np.isclose(geo.volume.sum(), abs(np.linalg.det(np.stack([pts[1], pts[2], pts[3]]))) / 6)


@pytest.mark.parametrize("kind,element_channels,cell_pressure",
                         [("tet", False, False), ("tet", True, False), ("hex", False, False), ("hex", True, True)])
def test_stiffness_is_symmetric_psd_and_free_of_rigid_motions(kind, element_channels, cell_pressure):
    # K = Σ B_iᵀB_i (+ the cells' B_tᵀB_t): symmetric PSD; rigid translations and rotations store no energy, a
    # uniform strain does
    pts, edges, cells, node_type = bar(kind)
    geo = LG.geometry(pts, edges, cells, node_type)
    config = LG.LinearConfig(hidden=8, element_channels=element_channels, cell_pressure=cell_pressure)
    _, _, K = operators(config, geo, random_params(config, geo))
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()
    assert np.linalg.eigvalsh(K).min() >= -1e-10 * np.abs(K).max()
    rigid, strain = rigid_and_uniform(pts)
    for u in rigid:
        assert np.abs(K @ u.reshape(-1)).max() <= 1e-10 * np.abs(K).max() * np.abs(u).max()
    assert strain.reshape(-1) @ K @ strain.reshape(-1) > 0


@pytest.mark.parametrize("kind,cells_too", [("tet", False), ("hex", False), ("hex", True)])
def test_stress_is_zero_for_rigid_motions_and_isotropic_for_a_uniform_strain(kind, cells_too):
    # no stress for a rigid motion whatever was learned; with uniform moduli (the start) a uniform strain gives
    # the linear-elastic stress 2μˢ dev ε + κ tr ε I at every node (the smoothing W averages with weights summing
    # to 1; with cell pressures the nodes' and the cells' halves of κ add up)
    pts, edges, cells, node_type = bar(kind)
    geo = LG.geometry(pts, edges, cells, node_type)
    ones = jnp.ones((geo.nbr.shape[0], 1))
    assert np.allclose(LG.smooth(ones, LG.geometry_arrays(geo)), 1.0)
    assert np.isclose(geo.volume.sum(), 4.0) and np.isclose(geo.cell_volume.sum(), 4.0)
    config = LG.LinearConfig(hidden=8, mu=0.7, kappa=20.0, tied_pressure=True, element_channels=cells_too,
                             cell_pressure=cells_too)
    rigid, strain = rigid_and_uniform(pts)
    ops, ga, _ = operators(config, geo, random_params(config, geo))
    for u in rigid:
        assert np.abs(np.asarray(LG.nodal_stress(jnp.asarray(u), ops, ga))).max() < 1e-10
    ops, ga, _ = operators(config, geo, LG.init(config, geo))
    sig = np.asarray(LG.nodal_stress(jnp.asarray(strain), ops, ga))
    eps = np.array([[1e-3, 2e-4, 0], [2e-4, -5e-4, 1e-4], [0, 1e-4, 3e-4]])
    tr = np.trace(eps)
    s = 2 * 0.7 * (eps - tr / 3 * np.eye(3)) + 20.0 * tr * np.eye(3)
    assert np.allclose(sig, [s[a, b] for a, b in LG.VOIGT], rtol=1e-9, atol=1e-14)


def test_rollout_solves_backward_euler_and_keeps_clamps():
    # each frame satisfies M (v' − v)/Δt = f − K u' − αM v', u' = u + Δt v' on the free nodes; clamps stay put
    pts, edges, cells, node_type = bar()
    geo = LG.geometry(pts, edges, cells, node_type)
    config = LG.LinearConfig(hidden=8, mu=1.0, kappa=20.0, density=1.0, alpha=2.0)
    params = random_params(config, geo)
    ops, ga, K = operators(config, geo, params)
    forces = np.zeros((1, 6, len(pts), 3))
    forces[0, :, pts[:, 0] > 3.9, 2] = -0.1
    u, v, _ = LG.rollout(ops, ga, geo.h, jnp.asarray(forces), 0.05)
    u, v = np.asarray(u)[0], np.asarray(v)[0]
    free = np.repeat(node_type == 0, 3)
    m3, dt, a = np.repeat(np.asarray(ops.mass), 3), 0.05, float(ops.alpha)
    u_prev, v_prev = np.zeros(3 * len(pts)), np.zeros(3 * len(pts))
    for k in range(6):
        uk, vk = u[k].reshape(-1), v[k].reshape(-1)
        res = m3 * (vk - v_prev) / dt - forces[0, k].reshape(-1) + K @ uk + a * m3 * vk
        assert np.abs(res[free]).max() < 1e-9 * np.abs(forces).max()
        assert np.allclose(uk, u_prev + dt * vk, atol=1e-12)
        u_prev, v_prev = uk, vk
    assert np.abs(u[:, node_type != 0]).max() == 0.0
    assert np.abs(u).max() > 1e-4


def test_relative_errors_over_the_snapshot_or_the_case_peak():
    # a case that comes back to rest: the snapshot measure divides by its vanishing last norm, the peak one does not
    t = jnp.array([[1.0, 2.0, 1e-6]])[..., None, None] * jnp.ones((1, 3, 2, 3))
    p = t + 0.01
    snap = np.asarray(LG.relative_errors(p, p, p, (t, t, t)))
    peak = np.asarray(LG.relative_errors(p, p, p, (t, t, t), "peak"))
    assert np.allclose(snap[0, :2, 0], [0.01, 0.005], rtol=1e-6) and snap[0, 2, 0] > 1e3
    assert np.allclose(peak[0, :, 0], 0.005, rtol=1e-6)
    with pytest.raises(ValueError, match="'max'"):
        LG.relative_errors(p, p, p, (t, t, t), "max")


def synthetic(tmp_path, pts, edges, cells, node_type, cases=4, frames=5, splits=None):
    """A data file made by a hidden linear GENERIC model (other moduli than the fit's start) under tip loads;
    ``splits`` {name: sim ids} are stored as the file's split keys."""
    geo = LG.geometry(pts, edges, cells, node_type)
    truth = LG.LinearConfig(hidden=8, mu=2.0, kappa=30.0, density=1.5, alpha=3.0)
    tp = LG.init(truth, geo, seed=7)
    ops = LG.operators(tp["net"], LG.geometry_arrays(geo), geo.h, truth, tp)
    rng = np.random.default_rng(0)
    forces = np.zeros((cases, frames, len(pts), 3))
    tip = np.where(pts[:, 0] > 3.9)[0]
    for c in range(cases):
        forces[c, :, tip] = rng.normal(size=3) * 0.2 * np.linspace(0.2, 1.0, frames)[None, :, None]
    u, v, s = LG.rollout(ops, LG.geometry_arrays(geo), geo.h, jnp.asarray(forces), 0.05)
    z = np.concatenate([pts + np.asarray(u), np.asarray(v), np.asarray(s)], -1)
    z = np.concatenate([np.concatenate([np.broadcast_to(pts, (cases, 1) + pts.shape),
                                        np.zeros((cases, 1, len(pts), 9))], -1), z], axis=1)
    path = tmp_path / "lin.npz"
    cell_type = "tetra" if np.shape(cells)[1] == 4 else "hexahedron"
    np.savez(path, z=z.astype(np.float32), f=forces.astype(np.float32), q0=pts, edges=edges,
             node_type=node_type.astype(np.int8), dt=np.array(0.05), cells=cells, cell_type=np.array(cell_type),
             sim_id=np.arange(1, cases + 1), metadata=np.array(json.dumps({"scene": "synthetic"})),
             **{f"split_{k}": np.asarray(v) for k, v in (splits or {}).items()})
    return path


def test_training_fits_a_hidden_linear_model_and_resumes_to_the_same_result(tmp_path):
    # the fit moves from the wrong moduli towards the hidden model's, and a run cut in two ends where one run does
    pts, edges, cells, node_type = bar()
    path = synthetic(tmp_path, pts, edges, cells, node_type)
    config = LG.LinearConfig(hidden=8, mu=1.0, kappa=10.0, density=1.0, alpha=1.0)
    one = LG.train(path, [0, 1, 2], [3], tmp_path / "one", config, steps=20, lr=3e-2, val_every=5, progress=False)
    records = [json.loads(x) for x in (tmp_path / "one" / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["train_loss"] < 0.5 * records[0]["train_loss"]
    LG.train(path, [0, 1, 2], [3], tmp_path / "two", config, steps=20, lr=3e-2, val_every=5, progress=False,
             until=10)
    LG.train(path, [0, 1, 2], [3], tmp_path / "two", config, steps=20, lr=3e-2, val_every=5, progress=False)
    again = [json.loads(x) for x in (tmp_path / "two" / "metrics.jsonl").read_text().splitlines()]
    assert again[-1]["step"] == 20
    assert np.isclose(again[-1]["train_loss"], records[-1]["train_loss"], rtol=1e-6)
    assert one["val_loss"] < records[0]["val_loss"]


@pytest.mark.parametrize("kind", [pytest.param("tet", marks=pytest.mark.long), "hex"])
def test_packed_model_steps_like_the_learned_operators(tmp_path, kind):
    # the linear model class carries the learned K, S, masses and α: the public rollout of the saved and loaded
    # model reproduces the training rollout (on hexes with the cells' pressures, whose stress reaches the nodes
    # two cells away)
    from tignn_jax import api
    from tignn_jax import data as D
    from tignn_jax.simulators import LinearGeneric
    from tignn_jax.simulators.linear import from_rest_linearization

    pts, edges, cells, node_type = bar(kind)
    geo = LG.geometry(pts, edges, cells, node_type)
    config = LG.LinearConfig(hidden=8, mu=1.0, kappa=20.0, density=1.0, alpha=2.0, element_channels=True,
                             tied_pressure=True, cell_pressure=kind == "hex")
    params = random_params(config, geo)
    stored = from_rest_linearization(LG.to_rest_linearization(params, geo, config), 0.05)
    envelope = D.normalization(D.load(synthetic(tmp_path, pts, edges, cells, node_type)), np.arange(4))
    mesh = {"q0": pts, "senders": edges[0], "receivers": edges[1], "node_type": node_type}
    model = api.make_params(LinearGeneric(config), stored, mesh, envelope)
    forces = np.zeros((5, len(pts), 3), np.float32)
    forces[:, pts[:, 0] > 3.9, 1] = 0.05
    loaded, graph = api.load_pretrained(str(api.save_model(model, tmp_path / "m" / "model.npz")))
    assert loaded["model"] == LinearGeneric(config)
    states = np.asarray(api.rollout(loaded, graph, forces))
    ops, ga, _ = operators(config, geo, params)
    u, v, s = (np.asarray(x)[0] for x in LG.rollout(ops, ga, geo.h, jnp.asarray(forces[None], jnp.float64), 0.05))
    scale = np.abs(u).max()
    assert scale > 1e-4
    assert np.abs(states[1:, :, :3] - pts - u).max() < 2e-3 * scale
    assert np.abs(states[1:, :, 3:6] - v).max() < 2e-3 * np.abs(v).max()
    assert np.abs(states[1:, :, 6:] - s).max() < 2e-3 * np.abs(s).max()


def assert_same_linearisation(mine, lin, free, tol):
    """Two `RestLinearization`s agree: K on the free nodes and S to ``tol`` of their largest entry, masses, α."""
    n = len(free)

    def dense(rows, cols, blocks, r):
        out = np.zeros((n, n, r, 3))
        out[rows, cols] = blocks
        return out

    K0, K = dense(lin.k_rows, lin.k_cols, lin.k_blocks, 3), dense(mine.k_rows, mine.k_cols, mine.k_blocks, 3)
    assert np.abs(K - K0)[free][:, free].max() < tol * np.abs(K0).max()
    S0, S = dense(lin.s_rows, lin.s_cols, lin.s_blocks, 6), dense(mine.s_rows, mine.s_cols, mine.s_blocks, 6)
    assert np.abs(S - S0).max() < tol * np.abs(S0).max()
    assert np.allclose(mine.mass, lin.mass, rtol=1e-9) and np.isclose(mine.alpha, lin.alpha)


def test_model_class_holds_the_fem_rest_linearisation():
    # at nodal / cell shear shares 0.7 / 0.3, smoothing share 0.7 and the material's moduli, the learned operators
    # are the FEM's linearisation about rest (the stabilised nodal tet with blend 0.3): what training can reach
    from fem import implicit
    from fem.material import mooney_rivlin
    from fem.solver import setup

    pts, edges, cells, node_type = bar()
    c10, d1 = 0.26, 0.049
    material = mooney_rivlin(c10, 0.0, d1, 1e-3)
    problem = setup(pts, cells, material=material, frame_dt=0.05, n_frames=1, clamped=np.where(node_type)[0],
                    cell_type="tetra", damping=2.0, n_sub=1)
    lin = implicit.rest_linearization(problem, material)
    geo = LG.geometry(pts, edges, cells, node_type)
    config = LG.LinearConfig(hidden=8, mu=2 * c10, kappa=2 / d1, density=1e-3, alpha=2.0, stabilisation=1e-12,
                             element_channels=True, tied_pressure=True)
    params = LG.init(config, geo)
    params["net"]["params"]["log_scales"] = jnp.zeros(8).at[0].set(np.log(0.7 / 0.5)).at[6].set(
        np.log(0.3 / 0.5)).at[7].set(np.log(0.7 / 0.3))
    mine = LG.to_rest_linearization(params, geo, config)
    assert_same_linearisation(mine, lin, node_type == 0, 1e-6)


@pytest.mark.long   # CI time: test_model_class_holds_the_fem_rest_linearisation covers the prior
def test_prior_starts_the_model_at_the_fem_rest_linearisation_of_a_hex_bar():
    # with a prior (the FEM's rest linearisation) and learned channels started a millionth as stiff, the operators
    # are the prior's: K, S, masses and α; training then learns a correction (its scales, a PSD K throughout)
    from fem import implicit
    from fem.material import mooney_rivlin
    from fem.solver import setup

    pts, edges, cells, node_type = bar("hex")
    material = mooney_rivlin(1.5, 0.05, 0.01, 1e-3)
    problem = setup(pts, cells, material=material, frame_dt=0.05, n_frames=1, clamped=np.where(node_type)[0],
                    cell_type="hexahedron", damping=3.0, n_sub=1)
    lin = implicit.rest_linearization(problem, material)
    geo = LG.with_prior(LG.geometry(pts, edges, cells, node_type), lin)
    config = LG.LinearConfig(hidden=8, mu=3.1e-6, kappa=2e-4, density=1e-3, alpha=3.0, element_channels=True,
                             cell_pressure=True, tied_pressure=True, prior=True)
    mine = LG.to_rest_linearization(LG.init(config, geo), geo, config)
    assert_same_linearisation(mine, lin, node_type == 0, 1e-5)
    with pytest.raises(ValueError, match="prior"):
        LG.operators(LG.init(config, geo)["net"], LG.geometry_arrays(LG.geometry(pts, edges, cells, node_type)),
                     geo.h, config, LG.init(config, geo))
