"""The embedded corotational model class: a fine mesh carried by a coarse cage. The embedding reproduces affine
motion and reads its own states back, keeps the forces' total, moment and work, carries the body's mass, never
creates energy, and a mesh that is its own cage steps exactly as the corotational model."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tignn_jax
from fem import mesh, meshes, scenes
from fem import solver as sv
from tignn_jax.simulators import corotational as C
from tignn_jax.simulators import embedded as EM

ENVELOPE = {"z_mean": np.zeros(12), "z_std": np.ones(12), "z_dev_max": np.ones(12), "u_max": np.ones(1),
            "f_max": np.full(1, 1e9)}


def bar(divisions, tets=False, clamped=True):
    """An 8 × 2 × 2 bar of the beam's material, clamped at x = 0: (problem, material, model mesh)."""
    q0, cells = mesh.box_hex_mesh(size=(8.0, 2.0, 2.0), divisions=divisions)
    if tets:
        cells = mesh.hex_to_tet(cells)
    material = scenes.beam_scene().material
    clamp = np.flatnonzero(q0[:, 0] == 0.0) if clamped else ()
    problem = sv.setup(q0, cells, material=material, frame_dt=0.05, n_frames=1, clamped=clamp, damping=18.0,
                       n_sub=1)
    node_type = np.zeros(len(q0), np.int8)
    node_type[list(clamp)] = 1
    edges = np.asarray(meshes.mesh_edges(cells))
    return problem, material, {"q0": q0, "senders": edges[0], "receivers": edges[1], "node_type": node_type}


def embedded(divisions, cell, tets=False, clamped=True):
    problem, material, mesh_dict = bar(divisions, tets, clamped)
    stored = EM.embed(problem, material, cell)
    return tignn_jax.make_params(EM.EmbeddedCorotational(), stored, mesh_dict, ENVELOPE, {}), problem, material


def rest(q0):
    return jnp.asarray(np.concatenate([q0, np.zeros((len(q0), 9))], 1), jnp.float32)


def tip_force(q0, load):
    f = np.zeros((len(q0), 3), np.float32)
    tip = np.flatnonzero(q0[:, 0] == q0[:, 0].max())
    f[tip, 1] = -load / len(tip)
    return jnp.asarray(f)


def test_a_mesh_that_is_its_own_cage_steps_as_the_corotational_model():
    # cage cell = the mesh's cell: W is a permutation, so the model is the corotational one, frame by frame
    params, problem, material = embedded((4, 1, 1), 2.0)
    q0 = np.asarray(params["mesh"]["q0"])
    corot = tignn_jax.make_params(C.CorotationalGeneric(), C.from_fem(problem, material), params["mesh"],
                                  ENVELOPE, {})
    a, b = rest(q0), rest(q0)
    for k in range(5):
        f = tip_force(q0, 1500.0 * (k + 1))
        a, b = tignn_jax.stepper(params)(a, f), tignn_jax.stepper(corot)(b, f)
    assert float(jnp.abs(b[:, :3] - q0).max()) > 0.05
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5 * float(jnp.abs(b).max()))


@pytest.mark.parametrize("divisions", [(8, 2, 2), (7, 3, 3)], ids=["nested", "not nested"])
def test_the_cage_reproduces_affine_motion_and_reads_its_own_states_back(divisions):
    params, _, _ = embedded(divisions, 2.0, clamped=False)
    arrays, q0 = params["arrays"], np.asarray(params["mesh"]["q0"], np.float64)
    y0 = np.asarray(arrays["cage"]["q0"], np.float64)
    rng = np.random.default_rng(0)
    # an affine map of the cage is the same map of every fine node (trilinear weights reproduce linear fields)
    a, t = np.eye(3) + 0.3 * rng.standard_normal((3, 3)), rng.standard_normal(3)
    zc = np.zeros((len(y0), 12), np.float32)
    zc[:, :3] = y0 @ a.T + t
    fine = np.asarray(EM.fine_state(arrays, jnp.asarray(zc)), np.float64)
    np.testing.assert_allclose(fine[:, :3], q0 @ a.T + t, atol=1e-5 * np.abs(q0).max())
    # any cage state comes back from the fine state it makes
    zc[:, :6] = np.concatenate([y0 + rng.standard_normal(y0.shape), rng.standard_normal(y0.shape)], 1)
    back = EM.cage_state(arrays, EM.fine_state(arrays, jnp.asarray(zc)))
    np.testing.assert_allclose(np.asarray(back[:, :6]), zc[:, :6], atol=1e-4)


def test_the_forces_keep_their_total_moment_and_work_on_the_cage():
    params, _, _ = embedded((7, 3, 3), 2.0, clamped=False)
    arrays, q0 = params["arrays"], np.asarray(params["mesh"]["q0"], np.float64)
    y0 = np.asarray(arrays["cage"]["q0"], np.float64)
    rng = np.random.default_rng(1)
    f = rng.standard_normal(q0.shape)
    fc = np.asarray(EM.restrict(arrays, jnp.asarray(f, jnp.float32)), np.float64)
    np.testing.assert_allclose(fc.sum(0), f.sum(0), atol=1e-4)
    np.testing.assert_allclose(np.cross(y0, fc).sum(0), np.cross(q0, f).sum(0), atol=1e-3)
    du = rng.standard_normal(y0.shape)                   # f · W Δu_c = (Wᵀ f) · Δu_c
    fine = np.asarray(EM.interpolate(arrays, jnp.asarray(du, jnp.float32)), np.float64)
    np.testing.assert_allclose(np.sum(f * fine), np.sum(fc * du), rtol=1e-4)


@pytest.mark.parametrize("tets", [False, True], ids=["hex8", "tet4"])
def test_the_cage_carries_the_bodys_mass_and_its_clamped_nodes_never_move(tets):
    params, problem, material = embedded((7, 3, 3), 3.0, tets=tets)
    arrays, q0 = params["arrays"], np.asarray(params["mesh"]["q0"])
    body = float(material.density) * float(np.sum(np.asarray(problem.arrays.geo.volume)))
    np.testing.assert_allclose(float(jnp.sum(arrays["cage"]["mass"])), body, rtol=1e-5)
    z = rest(q0)
    for k in range(4):
        z = tignn_jax.stepper(params)(z, tip_force(q0, 3000.0 * (k + 1)))
    clamped = params["mesh"]["node_type"] != 0
    assert float(jnp.abs(z[:, :3] - q0).max()) > 0.05
    assert float(jnp.abs(z[clamped, :6] - rest(q0)[clamped, :6]).max()) == 0.0


def test_a_curved_body_gets_a_cage_it_can_be_read_back_from_and_keeps_its_mass():
    # the bunny fills few of its bounding box's cells whole: cells with a corner no node weighs are left out
    # (else that corner could not be read back from the state), their nodes follow the nearest cell, extrapolated
    scene = scenes.bunny_scene()
    problem = scenes.setup_scene(scene._replace(n_frames=1))
    q0 = np.asarray(problem.arrays.points, np.float64)
    stored = EM.embed(problem, scene.material, 10.0)
    mesh_dict = {"q0": q0, "senders": scene.edges[0], "receivers": scene.edges[1], "node_type": scene.node_type}
    params = tignn_jax.make_params(EM.EmbeddedCorotational(), stored, mesh_dict, ENVELOPE, {})
    arrays = params["arrays"]
    weights = np.asarray(stored["weights"], np.float64)
    assert weights.min() < 0.0          # some nodes follow a cell they are not in
    y0 = np.asarray(stored["cage"]["q0"], np.float64)
    a = np.eye(3) + 0.2 * np.random.default_rng(3).standard_normal((3, 3))
    zc = np.zeros((len(y0), 12), np.float32)
    zc[:, :3] = y0 @ a.T
    fine = np.asarray(EM.fine_state(arrays, jnp.asarray(zc)), np.float64)
    np.testing.assert_allclose(fine[:, :3], q0 @ a.T, atol=1e-4 * np.abs(q0).max())
    body = float(scene.material.density) * float(np.sum(np.asarray(problem.arrays.geo.volume)))
    mass = float(jnp.sum(arrays["cage"]["mass"]))
    assert body <= mass * (1 + 1e-5) and mass < body * (1 + EM.FILL_FLOOR), (mass, body)
    z, f = rest(q0), np.zeros((len(q0), 3), np.float32)
    f[np.argmax(q0[:, 2]), 2] = -50.0
    z1 = tignn_jax.stepper(params)(z, jnp.asarray(f))
    d = {k: float(v) for k, v in params["model"].diagnostics(arrays, z, jnp.asarray(f), z1).items()}
    assert np.all(np.isfinite(np.asarray(z1))) and d["work"] > 0.0
    assert d["dissipation"] >= -C.ROUNDOFF * (abs(d["energy"]) + abs(d["work"])), d


def test_the_energy_never_exceeds_the_work_of_the_forces_through_a_load_its_release_and_a_kick():
    params, _, _ = embedded((8, 2, 2), 2.0)
    q0 = np.asarray(params["mesh"]["q0"])
    step = tignn_jax.stepper(params)
    diag = jax.jit(lambda z, f, z1: params["model"].diagnostics(params["arrays"], z, f, z1))
    z, peak = rest(q0), 0.0
    rng = np.random.default_rng(2)
    for k in range(30):
        f = tip_force(q0, 1500.0 * (k + 1) if k < 20 else 0.0)
        if k == 25:
            z = z.at[:, 3:6].add(jnp.asarray(rng.normal(0, 50.0, q0.shape), jnp.float32) * params["arrays"]["free"])
        z1 = step(z, f)
        d = {key: float(v) for key, v in diag(z, f, z1).items()}
        assert np.all(np.isfinite(np.asarray(z1))), k
        assert d["dissipation"] >= -C.ROUNDOFF * (abs(d["energy"]) + abs(d["work"]) + 1.0), (k, d)
        peak = max(peak, float(-(z1[:, 1] - q0[:, 1]).min()))
        z = z1
    assert peak > 0.5      # a large deflection of the 8-long bar


@pytest.mark.long   # CI time; in the default run tests/test_user_mesh.py checks a cage against the FEM
def test_a_finer_mesh_follows_its_own_corotational_model_under_a_tip_load():
    # the cage is 4 × 1 × 1 elements of the 16 × 4 × 4 mesh's 256: the bending a tip load makes is smooth, so the
    # cage follows the fine model closely in displacement (a dent finer than a cell it cannot: benchmarks/embedded.py)
    params, problem, material = embedded((16, 4, 4), 2.0)
    q0 = np.asarray(params["mesh"]["q0"])
    fine = tignn_jax.make_params(C.CorotationalGeneric(), C.from_fem(problem, material), params["mesh"],
                                 ENVELOPE, {})
    a, b = rest(q0), rest(q0)
    for k in range(10):
        f = tip_force(q0, 1500.0 * min(k + 1, 5))
        a, b = tignn_jax.stepper(params)(a, f), tignn_jax.stepper(fine)(b, f)
    u_a, u_b = np.asarray(a[:, :3]) - q0, np.asarray(b[:, :3]) - q0
    assert np.abs(u_b).max() > 0.1
    assert np.linalg.norm(u_a - u_b) < 0.1 * np.linalg.norm(u_b), np.linalg.norm(u_a - u_b) / np.linalg.norm(u_b)


def test_a_model_file_round_trip_steps_the_same_through_the_public_step(tmp_path):
    params, _, _ = embedded((8, 2, 2), 2.0)
    again = tignn_jax.load_model(tignn_jax.save_model(params, tmp_path / "embedded.npz"))
    assert again["model"] == params["model"]
    q0 = np.asarray(params["mesh"]["q0"])
    f = tip_force(q0, 2000.0)
    a = tignn_jax.step(again, tignn_jax.rest_graph(again), f).nodes["z"]
    np.testing.assert_array_equal(np.asarray(a), np.asarray(tignn_jax.stepper(params)(rest(q0), f)))


def test_bad_input_is_refused_naming_the_value(monkeypatch):
    problem, material, mesh_dict = bar((4, 1, 1))
    for cell in (0.0, -1.0, float("nan"), "2"):
        with pytest.raises(ValueError, match="cell"):
            EM.embed(problem, material, cell)
    with pytest.raises(ValueError, match="no cage cell of size 0.01"):    # the bar's 20 nodes see no cell whole
        EM.embed(problem, material, 0.01)
    monkeypatch.setattr(EM, "MAX_CAGE_NODES", 12)
    with pytest.raises(ValueError, match="cell=1.0 gives a cage of 81 nodes, more than 12"):
        EM.embed(bar((8, 2, 2))[0], material, 1.0)
    monkeypatch.undo()
    stored = EM.embed(problem, material, 2.0)
    model = EM.EmbeddedCorotational()
    with pytest.raises(ValueError, match="sum to 1"):
        model.prepare({**stored, "weights": 2.0 * stored["weights"]}, mesh_dict)
    with pytest.raises(ValueError, match=r"\[20, 8\]"):
        model.prepare({**stored, "parents": stored["parents"][:-1]}, mesh_dict)
    loose = {**stored["cage"], "node_type": np.zeros_like(stored["cage"]["node_type"])}
    with pytest.raises(ValueError, match="clamped fine nodes"):
        model.prepare({**stored, "cage": loose}, mesh_dict)
    with pytest.raises(ValueError, match="missing|needs"):
        model.prepare({"cage": stored["cage"]}, mesh_dict)
