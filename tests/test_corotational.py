"""The corotational GENERIC model class on small hex8 and tet4 bars of the beam's material: exact under rotation,
the rest-linearised backward-Euler step from rest, energy never created, a model file round trip."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tignn_jax
from fem import implicit, mesh, meshes, scenes
from fem import solver as sv
from tignn_jax.simulators import LinearGeneric
from tignn_jax.simulators import corotational as C
from tignn_jax.simulators import linear as LG

ENVELOPE = {"z_mean": np.zeros(12), "z_std": np.ones(12), "z_dev_max": np.ones(12), "u_max": np.ones(1),
            "f_max": np.full(1, 1e9)}

LOAD = 300.0   # tip force per node added each frame


def bar(clamped=True, divisions=(4, 1, 1)):
    q0, cells = mesh.box_hex_mesh(size=(8.0, 2.0, 2.0), divisions=divisions)
    material = scenes.beam_scene().material
    clamp = np.where(q0[:, 0] == 0.0)[0] if clamped else ()
    problem = sv.setup(q0, cells, material=material, frame_dt=0.05, n_frames=1, clamped=clamp,
                       cell_type="hexahedron", damping=18.0, n_sub=1)
    node_type = np.zeros(len(q0), np.int8)
    node_type[list(clamp)] = 1
    edges = np.asarray(meshes.mesh_edges(cells))
    mesh_dict = {"q0": q0, "senders": edges[0], "receivers": edges[1], "node_type": node_type}
    return problem, material, mesh_dict


@pytest.fixture(scope="module")
def models():
    problem, material, mesh_dict = bar()
    stored = C.from_fem(problem, material)
    corot = tignn_jax.make_params(C.CorotationalGeneric(), stored, mesh_dict, ENVELOPE, {})
    lin = LG.from_rest_linearization(implicit.rest_linearization(problem, material), 0.05)
    return corot, tignn_jax.make_params(LinearGeneric(), lin, mesh_dict, ENVELOPE, {}), problem, material


def state(q0, u=None, v=None):
    z = np.zeros((len(q0), 12), np.float32)
    z[:, :3] = q0 if u is None else q0 + u
    if v is not None:
        z[:, 3:6] = v
    return jnp.asarray(z)


def rotation(angle, axis):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def test_a_rigidly_turned_body_stores_no_energy_and_feels_no_force():
    problem, material, mesh_dict = bar(clamped=False)
    params = tignn_jax.make_params(C.CorotationalGeneric(), C.from_fem(problem, material), mesh_dict, ENVELOPE, {})
    arrays, q0 = params["arrays"], np.asarray(mesh_dict["q0"])
    turned = (q0 - q0.mean(0)) @ rotation(1.2, (1, 2, 3)).T + q0.mean(0) + [3.0, -1.0, 2.0]
    kin = C.kinematics(arrays, jnp.asarray(turned - q0, jnp.float32))
    rest_scale = float(np.abs(np.asarray(arrays["ke"])).max()) * 2.0
    assert float(C.potential(arrays, kin)) < 1e-6 * rest_scale
    assert float(jnp.abs(C.internal_force(arrays, kin, len(q0))).max()) < 1e-4 * rest_scale
    assert float(jnp.abs(C.stress(arrays, kin, kin.jm1, len(q0))).max()) < 1e-4 * float(arrays["kappa"][0])
    # at rest in the turned pose, with no force, the body stays where it is: exactly (float64), and in float32 to
    # the round-off of its energy there (~1 of a scale of 1e6: a free body's rigid motion costs no potential, so
    # the energy budget lets that round-off become kinetic energy, a drift of ~3e-4 of its size in a frame)
    size = np.abs(q0).max()
    z = tignn_jax.stepper(params)(state(q0, turned - q0), jnp.zeros((len(q0), 3)))
    assert np.abs(np.asarray(z[:, :3]) - turned).max() < 1e-3 * size
    with jax.enable_x64(True):
        p64 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if isinstance(x, (np.ndarray, jax.Array))
                                     and jnp.issubdtype(x.dtype, jnp.floating) else x, params)
        z0 = jnp.zeros((len(q0), 12)).at[:, :3].set(turned)
        z = np.asarray(tignn_jax.stepper(p64)(z0, jnp.zeros((len(q0), 3))))
    assert np.abs(z[:, :3] - turned).max() < 1e-9 * size
    assert np.abs(z[:, 3:6]).max() < 1e-9 * size


def test_from_rest_the_first_frame_is_the_fems_rest_linearised_backward_euler_step(models):
    corot, linear, problem, material = models
    q0 = np.asarray(corot["mesh"]["q0"])
    f = np.zeros((len(q0), 3), np.float32)
    f[q0[:, 0] == 8.0, 1] = -200.0
    a = tignn_jax.stepper(corot)(state(q0), jnp.asarray(f))
    b = tignn_jax.stepper(linear)(state(q0), jnp.asarray(f))
    du = np.abs(np.asarray(b[:, :3]) - q0).max()
    assert du > 1e-3
    np.testing.assert_allclose(np.asarray(a[:, :6]), np.asarray(b[:, :6]), atol=2e-3 * du / 0.05)
    # the deviatoric stress is the FEM's at the new displacement (its pressure, κ(J − 1) of the linear step's
    # positions, carries the step's second-order volume change; the model's is the linearised one)
    _, fem_stress = implicit.force_and_stress(problem, material)
    dev = lambda x: np.concatenate([x[:, :3] - x[:, :3].mean(1, keepdims=True), x[:, 3:]], axis=1)
    s = dev(np.asarray(fem_stress(a[:, :3] - jnp.asarray(q0, jnp.float32))))
    assert np.abs(s).max() > 1.0
    np.testing.assert_allclose(dev(np.asarray(a[:, 6:])), s, atol=2e-2 * np.abs(s).max())


def test_the_energy_never_exceeds_the_work_of_the_forces_through_a_large_load_and_its_release(models):
    corot, _, _, _ = models
    q0 = np.asarray(corot["mesh"]["q0"])
    tip = q0[:, 0] == 8.0
    step = tignn_jax.stepper(corot)
    diag = jax.jit(lambda z, f, z1: corot["model"].diagnostics(corot["arrays"], z, f, z1))
    z = state(q0)
    rng = np.random.default_rng(0)
    peak = 0.0
    for k in range(30):   # ramp to a tip load that bends the bar by a tenth of its length, release, kick
        f = np.zeros((len(q0), 3), np.float32)
        f[tip, 1] = -LOAD * (k + 1) if k < 20 else 0.0
        if k == 25:
            z = z.at[:, 3:6].add(jnp.asarray(rng.normal(0, 50.0, (len(q0), 3)), jnp.float32)
                                 * corot["arrays"]["free"])
        z1 = step(z, jnp.asarray(f))
        d = diag(z, jnp.asarray(f), z1)
        assert np.all(np.isfinite(np.asarray(z1))), k
        assert float(d["dissipation"]) >= -1e-5 * max(float(d["energy"]), 1.0), (k, {a: float(b) for a, b in d.items()})
        peak = max(peak, float(-(np.asarray(z1[:, 1]) - q0[:, 1])[tip].mean()))
        z = z1
    assert peak > 0.5     # a large deflection of the 8-long bar, not a small one


def test_a_step_linearised_about_the_first_solve_is_a_newton_iteration(models):
    # the recovery of a frame whose first step breaks the energy budget: linearised about that step's end, the
    # second solve leaves a smaller residual of the backward-Euler equations c M v' − M v / h² + (f_int − f) / h
    corot, _, _, _ = models
    arrays, model = corot["arrays"], corot["model"]
    config = model.config._replace(cg_iterations=40, cg_max_iterations=40)
    q0 = np.asarray(corot["mesh"]["q0"])
    f = np.zeros((len(q0), 3), np.float32)
    f[q0[:, 0] == 8.0, 1] = -40.0 * LOAD     # sudden: the first solve moves the tip by most of the bar's length
    f = jnp.asarray(f)
    z, h, n = state(q0), arrays["dt"][0], len(q0)
    _, alpha, free, m = LG._constants(arrays, jnp.float32)

    def residual(v1):
        u1 = (z[:, :3] - arrays["q0"]) * free + h * v1
        f_int = C.internal_force(arrays, C.kinematics(arrays, u1), n)
        r = ((1.0 + alpha * h) / h ** 2 * m * v1 - m * z[:, 3:6] / h ** 2 + (f_int - f) / h) * free
        return float(jnp.linalg.norm(r))

    _, _, (first,), e0 = C._step((arrays,), (z,), (f,), config, h, (jnp.zeros_like(f),), False, None)
    _, _, (second,), _ = C._step((arrays,), (z,), (f,), config, h, (first,), True, e0)
    tip = -float(np.asarray(first[q0[:, 0] == 8.0, 1]).mean() * h)
    assert tip > 1.0, tip
    assert residual(second) < 0.2 * residual(first), (residual(first), residual(second))


def test_a_model_file_round_trip_steps_the_same(models, tmp_path):
    corot, _, _, _ = models
    path = tignn_jax.save_model(corot, tmp_path / "corot.npz")
    again = tignn_jax.load_model(path)
    assert again["model"] == corot["model"]
    q0 = np.asarray(corot["mesh"]["q0"])
    f = jnp.full((len(q0), 3), 100.0)
    np.testing.assert_array_equal(np.asarray(tignn_jax.stepper(again)(state(q0), f)),
                                  np.asarray(tignn_jax.stepper(corot)(state(q0), f)))


@pytest.mark.long   # another cell type: the hex tests above make each of these checks on the class
def test_tet_meshes_nodal_volume_rigid_rest_step_and_energy():
    """A tet4 bar (nodal volume change and shared deviatoric energy, as the FEM's nodal tet4): a rigid turn
    stores nothing; from rest the first frame is the FEM's rest-linearised backward-Euler step; a large load
    and its release never create energy."""
    problem, material, mesh_dict = tet_bar()
    q0 = mesh_dict["q0"]
    stored = C.from_fem(problem, material)
    assert float(stored["mu_nodes"][0]) > 0
    corot = tignn_jax.make_params(C.CorotationalGeneric(), stored, mesh_dict, ENVELOPE, {})
    arrays = corot["arrays"]
    turned = (q0 - q0.mean(0)) @ rotation(0.9, (1, -2, 1)).T + q0.mean(0)
    kin = C.kinematics(arrays, jnp.asarray(turned - q0, jnp.float32))
    scale = float(arrays["kappa"][0]) * float(np.asarray(stored["volume"]).sum())
    assert float(C.potential(arrays, kin)) < 1e-7 * scale
    assert float(jnp.abs(C.internal_force(arrays, kin, len(q0))).max()) < 1e-5 * scale
    lin = LG.from_rest_linearization(implicit.rest_linearization(problem, material), 0.05)
    linear = tignn_jax.make_params(LinearGeneric(), lin, mesh_dict, ENVELOPE, {})
    tip = q0[:, 0] == 8.0
    f = np.zeros((len(q0), 3), np.float32)
    f[tip, 1] = -200.0
    a = tignn_jax.stepper(corot)(state(q0), jnp.asarray(f))
    b = tignn_jax.stepper(linear)(state(q0), jnp.asarray(f))
    du = np.abs(np.asarray(b[:, :3]) - q0).max()
    assert du > 1e-3
    np.testing.assert_allclose(np.asarray(a[:, :6]), np.asarray(b[:, :6]), atol=2e-3 * du / 0.05)
    step = tignn_jax.stepper(corot)
    diag = jax.jit(lambda z, f, z1: corot["model"].diagnostics(arrays, z, f, z1))
    z, peak = state(q0), 0.0
    for k in range(24):
        f = np.zeros((len(q0), 3), np.float32)
        f[tip, 1] = -LOAD * (k + 1) if k < 18 else 0.0
        z1 = step(z, jnp.asarray(f))
        d = diag(z, jnp.asarray(f), z1)
        assert np.all(np.isfinite(np.asarray(z1))), k
        assert float(d["dissipation"]) >= -1e-5 * max(float(d["energy"]), 1.0), k
        peak = max(peak, float(-(np.asarray(z1[:, 1]) - q0[:, 1])[tip].mean()))
        z = z1
    assert peak > 0.5


@pytest.mark.parametrize("schur_limit", [0, 4096])
def test_the_preconditioner_inverts_the_rest_operator_on_its_lowest_modes_and_is_positive_definite(schur_limit):
    # P₀ = Φ Λ⁻¹ Φᵀ + (I − ΦΦᵀ) B⁻¹ (I − ΦΦᵀ) on a bar with more free unknowns (216) than modes (8), B⁻¹ the node
    # blocks' inverse or (schur_limit above the bar's 64 elements) the Schur-complement one: symmetric, positive
    # definite on the free unknowns, exactly A₀⁻¹ on A₀'s lowest modes, and all of A₀⁻¹ given all modes
    problem, material, mesh_dict = bar(divisions=(8, 2, 2))
    node_type = mesh_dict["node_type"]
    stored = C.from_fem(problem, material)
    config = C.CorotationalConfig(modes=8, schur_limit=schur_limit)
    params = tignn_jax.make_params(C.CorotationalGeneric(config), stored, mesh_dict, ENVELOPE, {})
    assert ("schur_inv" in params["arrays"]) == (schur_limit > 0)
    A = C.rest_operator(params["arrays"], node_type).toarray()
    free = np.repeat(node_type == 0, 3)
    assert free.sum() == 216 and np.allclose(A, A.T) and np.array_equal(A[~free][:, ~free], np.eye((~free).sum()))
    eye = jnp.eye(A.shape[0], dtype=jnp.float32)
    P = np.asarray(jax.vmap(lambda r: C.apply_rest_preconditioner(params["arrays"], r))(eye), np.float64)
    np.testing.assert_allclose(P, P.T, atol=1e-6 * np.abs(P).max())
    assert np.linalg.eigvalsh(P[free][:, free]).min() > 0
    lam, vec = np.linalg.eigh(A[free][:, free])
    phi = np.zeros((A.shape[0], 8))
    phi[free] = vec[:, :8]
    np.testing.assert_allclose(P @ (A @ phi), phi, atol=1e-4)
    assert np.abs(P[free][:, free] - np.linalg.inv(A[free][:, free])).max() > 1e-2 * np.abs(P).max()
    every = jax.tree_util.tree_map(jnp.asarray, C.rest_preconditioner(A, node_type, modes=216))
    P_all = np.asarray(jax.vmap(lambda r: C.apply_rest_preconditioner(every, r))(eye), np.float64)
    np.testing.assert_allclose(P_all[free][:, free], np.linalg.inv(A[free][:, free]),
                               atol=1e-4 * np.abs(P_all).max())


def tet_bar(divisions=(4, 1, 1)):
    """The hex `bar`'s box cut into tet4s (the FEM's nodal tet4), clamped at x = 0."""
    material = scenes.beam_scene().material
    q0, cells = mesh.box_hex_mesh(size=(8.0, 2.0, 2.0), divisions=divisions)
    tets = mesh.hex_to_tet(cells)
    clamp = np.where(q0[:, 0] == 0.0)[0]
    problem = sv.setup(q0, tets, material=material, frame_dt=0.05, n_frames=1, clamped=clamp, cell_type="tetra",
                       damping=18.0, n_sub=1)
    node_type = np.zeros(len(q0), np.int8)
    node_type[clamp] = 1
    edges = np.asarray(meshes.mesh_edges(tets))
    return problem, material, {"q0": q0, "senders": edges[0], "receivers": edges[1], "node_type": node_type}


@pytest.mark.parametrize("make", ["hex8", "tet4"])
def test_the_models_energy_and_forces_are_the_fems_at_large_strain(make):
    """The model's potential is the FEM's energy (hexes: Mooney–Rivlin's isochoric energy of the one-point F, the
    hourglass control turned with the element, the volume change; tets: the nodal tet4's, the isochoric energy on
    the elements and the nodes' averaged F, the nodes' volume change), and its internal force the FEM's, at a bend,
    twist and stretch of the bar with strains of ~20 %; the hexes' hourglass part is blind to linear fields."""
    problem, material, mesh_dict = bar() if make == "hex8" else tet_bar()
    if make == "hex8":
        stored = C.from_fem(problem, material)
        khg = stored["ke"] - C.one_point_stiffness(stored["b"], stored["volume"],
                                                   2.0 * (float(material.c10) + float(material.c01)))
        xe = mesh_dict["q0"][stored["cells"]]
        linear = np.einsum("ij,eaj->eai", np.random.default_rng(2).normal(size=(3, 3)), xe).reshape(len(xe), -1)
        k_lin = np.abs(np.einsum("eij,ej->ei", stored["ke"], linear)).max()
        assert np.abs(np.einsum("eij,ej->ei", khg, linear)).max() < 1e-4 * k_lin
    q0 = mesh_dict["q0"]
    corot = tignn_jax.make_params(C.CorotationalGeneric(), C.from_fem(problem, material), mesh_dict, ENVELOPE, {})
    s = q0[:, 0] / 8.0
    u = np.stack([0.15 * q0[:, 0] * s - 0.1 * q0[:, 1] * s, 1.5 * s ** 2 + 0.2 * (q0[:, 2] - 1.0) * s,
                  -0.2 * (q0[:, 1] - 1.0) * s], axis=1)
    u += 0.02 * np.random.default_rng(0).normal(size=u.shape)
    u[q0[:, 0] == 0.0] = 0.0
    kin = C.kinematics(corot["arrays"], jnp.asarray(u, jnp.float32))
    e_fem = float(sv.internal_energy(problem, material, jnp.asarray(q0 + u, jnp.float32)))
    assert abs(float(C.potential(corot["arrays"], kin)) - e_fem) < 2e-4 * e_fem
    f_fem = np.asarray(sv.internal_force(problem, material, jnp.asarray(q0 + u, jnp.float32)))
    f = np.asarray(C.internal_force(corot["arrays"], kin, len(q0)))
    assert np.abs(f - f_fem).max() < 2e-4 * np.abs(f_fem).max()
    # a body turned inside out (mirrored: every J = −1) keeps a finite energy, forces and stress (J held at the floor)
    mirrored = C.kinematics(corot["arrays"], jnp.asarray(q0 * [-1.0, 1.0, 1.0] - q0, jnp.float32))
    for x in (C.potential(corot["arrays"], mirrored), C.internal_force(corot["arrays"], mirrored, len(q0)),
              C.stress(corot["arrays"], mirrored, mirrored.jm1, len(q0))):
        assert np.all(np.isfinite(np.asarray(x)))


def test_the_isochoric_stress_is_the_gradient_of_the_energy_and_float32_keeps_small_strains():
    """P = ∂Ψ/∂F of `isochoric_energy` against central differences (float64), both against `fem.material` at
    finite strain, and in float32 the energy of a 1e-4 strain to 1e-6 (formed as Ī1 − 3 it would be lost)."""
    from fem import material as M

    c10, c01 = 0.2, 0.06
    rng = np.random.default_rng(1)
    with jax.enable_x64(True):
        H = jnp.asarray(0.2 * rng.normal(size=(3, 3, 8)))
        P = np.asarray(C._isochoric_stress(c10, c01, H))
        eps = 1e-6
        for i in range(3):
            for j in range(3):
                d = jnp.zeros((3, 3, 1)).at[i, j].set(eps)
                fd = (C.isochoric_energy(c10, c01, H + d) - C.isochoric_energy(c10, c01, H - d)) / (2 * eps)
                np.testing.assert_allclose(P[i, j], np.asarray(fd), rtol=1e-6, atol=1e-9)
        m = M.mooney_rivlin(c10, c01, 1e-3)
        F = H + jnp.eye(3)[:, :, None]
        np.testing.assert_allclose(np.asarray(C.isochoric_energy(c10, c01, H)), np.asarray(M.isochoric_energy(m, F)),
                                   rtol=1e-9)
        S, _, _ = M.isochoric_pk2(m, F)
        np.testing.assert_allclose(P, np.asarray(M.matmul3(F, S)), rtol=1e-7, atol=1e-9)
        small = 1e-4 * rng.normal(size=(3, 3, 8))
        exact = np.asarray(C.isochoric_energy(c10, c01, jnp.asarray(small)))
    got = np.asarray(C.isochoric_energy(np.float32(c10), np.float32(c01), jnp.asarray(small, jnp.float32)))
    np.testing.assert_allclose(got, exact, rtol=1e-5)


@pytest.mark.parametrize("make", [bar, tet_bar], ids=["hex8", "tet4"])
def test_the_schur_complement_inverts_the_volumetric_stiffness_and_conditions_the_solve(make):
    # the constraints carry the rest operator's whole volumetric stiffness, A₀ − A₀(κ = 0) = κ Gᵀ W G, and
    # `schur_preconditioner`'s Woodbury form is (D + κ Gᵀ W G)⁻¹ with D the node blocks of A₀(κ = 0); with the same
    # 8 modes, P₀ A₀'s condition number is a fifth or less of the node-blocks variant's (nearly incompressible)
    problem, material, mesh_dict = make(divisions=(8, 2, 2))
    node_type = mesh_dict["node_type"]
    free = np.repeat(node_type == 0, 3)
    stored = C.from_fem(problem, material)
    cond = {}
    for limit in (0, 4096):
        params = tignn_jax.make_params(C.CorotationalGeneric(C.CorotationalConfig(modes=8, schur_limit=limit)),
                                       stored, mesh_dict, ENVELOPE, {})
        arrays = params["arrays"]
        A = C.rest_operator(arrays, node_type)
        eye = jnp.eye(A.shape[0], dtype=jnp.float32)
        P = np.asarray(jax.vmap(lambda r: C.apply_rest_preconditioner(arrays, r))(eye), np.float64)[free][:, free]
        lam = np.sort(np.linalg.eigvals(P @ A.toarray()[free][:, free]).real)
        assert lam[0] > 0
        cond[limit] = lam[-1] / lam[0]
    deviatoric = C.rest_operator({**arrays, "kappa": np.zeros(1)}, node_type)
    G, W = C.constraint_operator(arrays, node_type)
    kappa = float(arrays["kappa"][0])
    volumetric = (kappa * G.T @ np.diag(W) @ G)
    np.testing.assert_allclose((A - deviatoric).toarray(), volumetric, atol=1e-9 * np.abs(volumetric).max())
    D = np.zeros_like(volumetric)
    d = deviatoric.toarray()
    for a in np.flatnonzero(node_type == 0):
        D[3 * a:3 * a + 3, 3 * a:3 * a + 3] = d[3 * a:3 * a + 3, 3 * a:3 * a + 3]
    local = {**arrays, "modes": jnp.zeros_like(arrays["modes"])}   # the preconditioner without its modes
    P_local = np.asarray(jax.vmap(lambda r: C.apply_rest_preconditioner(local, r))(eye), np.float64)
    expect = np.linalg.inv((D + volumetric)[free][:, free])
    np.testing.assert_allclose(P_local[free][:, free], expect, atol=2e-4 * np.abs(expect).max())
    assert cond[4096] < 0.2 * cond[0], cond


def test_bad_options_are_refused_naming_the_value(models):
    corot = models[0]
    for bad, said in (({"cg_max_iterations": 2}, "cg_max_iterations.*>= cg_iterations"),
                      ({"cg_tolerance": 0.0}, "cg_tolerance.*0.0"), ({"modes": 0}, "modes.*0"),
                      ({"schur_limit": -1}, "schur_limit.*-1")):
        with pytest.raises(ValueError, match=said):
            C.CorotationalGeneric(C.CorotationalConfig(**bad)).prepare(corot["model"].stored(corot["arrays"]),
                                                                       corot["mesh"])
    with pytest.raises(ValueError, match="cg_iterations.*0"):
        C.CorotationalGeneric(C.CorotationalConfig(cg_iterations=0)).prepare(corot["model"].stored(corot["arrays"]),
                                                                            corot["mesh"])
    old_file = {k: v for k, v in corot["model"].stored(corot["arrays"]).items() if k != "mooney_rivlin"}
    with pytest.raises(ValueError, match=r"mooney_rivlin.*got mooney_rivlin \[0.0, 0.0\]"):
        C.CorotationalGeneric().prepare(old_file, corot["mesh"])


def test_a_noisy_state_is_damped_not_pumped(models):
    # noise added to the input state every frame (as benchmarks/stability.py's noise run): the frame goes on
    # iterating while its residual is large, so the stiff volumetric modes the noise excites are damped as backward
    # Euler damps them; the energy stays near the noiseless run's and no frame creates energy from its input
    corot = models[0]
    q0 = corot["mesh"]["q0"]
    tip = np.where(q0[:, 0] == q0[:, 0].max())[0]
    f = np.zeros_like(q0)
    f[tip, 1] = -LOAD * 10
    free = (corot["mesh"]["node_type"] == 0)[:, None]
    rng = np.random.default_rng(0)
    step = jax.jit(lambda z: corot["model"].step_state(corot["arrays"], z, jnp.asarray(f, jnp.float32)))
    diag = jax.jit(lambda z, z1: corot["model"].diagnostics(corot["arrays"], z, jnp.asarray(f, jnp.float32), z1))
    z = z_quiet = tignn_jax.rest_graph(corot).nodes["z"]
    energies, quiet = [], []
    for k in range(120):
        noise = np.zeros(z.shape, np.float32)
        noise[:, :3] = 0.02 * rng.standard_normal((len(q0), 3)) * free     # 1 % of the bar's thickness
        z_in = z + noise
        z = step(z_in)
        d = diag(z_in, z)
        assert float(d["dissipation"]) >= -1e-4 * float(d["energy"]), k
        energies.append(float(d["energy"]))
        z_quiet = step(z_quiet)
        quiet.append(float(diag(z_quiet, z_quiet)["energy"]))
    assert np.all(np.isfinite(np.asarray(z)))
    assert max(energies[20:]) < 3.0 * max(quiet), (max(energies), max(quiet))


def test_nested_dissection_orders_every_node_once_and_its_factor_gives_the_same_modes():
    # a cube's node graph: the order is a permutation whose LU factor fills less than the grid's own order, and the
    # shift-invert modes through that factor are the ones through SuperLU's own ordering
    import scipy.sparse as sparse
    from scipy.sparse.linalg import splu

    points, cells = mesh.box_hex_mesh((8.0, 8.0, 8.0), (8, 8, 8))
    n = len(points)
    pairs = (np.repeat(cells, 8, axis=1).ravel(), np.tile(cells, (1, 8)).ravel())
    graph = sparse.csr_matrix((np.ones(pairs[0].size), pairs), shape=(n, n))
    order = C.nested_dissection(points, graph, leaf=16)
    assert sorted(order.tolist()) == list(range(n))
    shift = np.random.default_rng(0).uniform(0.1, 0.2, n)      # no symmetry: no repeated eigenvalue
    laplacian = sparse.diags(np.asarray(graph.sum(axis=1)).ravel() + shift) - 0.9 * graph   # SPD, the graph's pattern
    fill = lambda p: splu(sparse.csc_matrix(laplacian[p][:, p]), permc_spec="NATURAL").L.nnz  # noqa: E731
    assert fill(order) < 0.7 * fill(np.arange(n)), (fill(order), fill(np.arange(n)))
    A = sparse.kron(laplacian, sparse.diags([1.0, 1.3, 1.7])).tocsr()
    node_type = np.where(points[:, 0] == 0.0, 1, 0)
    ours, scipys = (C.rest_preconditioner(A, node_type, 8, p) for p in (points, None))
    np.testing.assert_allclose(ours["mode_inv"], scipys["mode_inv"], rtol=1e-5)
