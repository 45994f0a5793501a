"""Implicit (backward-Euler) dynamics: the linear limit against the discrete recurrence, static equilibrium,
low-mode dynamics against the explicit solver and backward Euler's amplification factor, dissipation, scope."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fem
from fem import implicit, scenes
from fem.generate import run_cases

CELL_TYPES = ["hexahedron", "tetra"]
ELASTIC = dict(c10=5e3, c01=0.0, d1=4e-5, density=1.0)   # as in test_fem_dynamics: bending period ≈ 1.3


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def cantilever(cell_type, frame_dt, n_frames, damping=0.0, load_interp="step"):
    pts, cells = fem.box_hex_mesh((6.0, 1.0, 1.0), (6, 1, 1))
    if cell_type == "tetra":
        cells = fem.hex_to_tet(cells)
    m = fem.mooney_rivlin(**ELASTIC)
    prob = fem.setup(pts, cells, material=m, frame_dt=frame_dt, n_frames=n_frames,
                     clamped=np.where(pts[:, 0] < 1e-9)[0], damping=damping, load_interp=load_interp)
    return prob, m, pts


def tip_load(pts, n_frames, total):
    f = np.zeros((n_frames, len(pts), 3))
    tip = pts[:, 0] > 6.0 - 1e-9
    f[:, tip, 1] = total / tip.sum()
    return f


@pytest.mark.parametrize("cell_type", ["hexahedron", pytest.param("tetra", marks=pytest.mark.long)])
def test_small_loads_follow_the_linear_backward_euler_recurrence(cell_type):
    """With loads small enough for the linear regime, every frame equals the recurrence
    (c M + K₀) uₙ₊₁ = fₙ₊₁ + c M uₙ + M vₙ / h, c = (1 + αh)/h², built from the dense rest operator."""
    h, T, alpha = 0.05, 12, 0.7
    prob, m, pts = cantilever(cell_type, h, T, damping=alpha)
    f = tip_load(pts, T, 1e-3) * np.linspace(0.2, 1.0, T)[:, None, None]
    res, diag = implicit.simulate_implicit(prob, m, fem.Loads(nodal=jnp.asarray(f)), tol=1e-6)
    A = implicit.rest_operator(prob, m)
    mass = np.repeat(np.asarray(fem.lumped_mass(prob, m)), 3)
    free = np.repeat(np.asarray(prob.arrays.free[:, 0]) > 0, 3)
    c = (1.0 + alpha * h) / h ** 2
    u, v, ref = np.zeros(3 * len(pts)), np.zeros(3 * len(pts)), [np.zeros(3 * len(pts))]
    for k in range(T):
        rhs = np.where(free, f[k].reshape(-1) + c * mass * u + mass * v / h, 0.0)
        u_new = np.linalg.solve(A, rhs)
        u, v = u_new, (u_new - u) / h
        ref.append(u)
    got = (np.asarray(res.q) - pts).reshape(T + 1, -1)
    ref = np.stack(ref)
    assert np.abs(got - ref).max() < 1e-4 * np.abs(ref).max()
    assert np.all(np.asarray(diag.residual) <= 1e-6)   # float64 floor ~1e-8 here: J − 1 ~ 1e-7 loses digits


@pytest.mark.optimized   # 60 frames of ~10 Newton iterations each: the run takes longer than its compilation
@pytest.mark.parametrize("cell_type", ["hexahedron", pytest.param("tetra", marks=pytest.mark.long)])
def test_held_load_settles_to_static_equilibrium(cell_type):
    """A held tip load with damping: the run comes to rest at f_int(u) = f_ext (a finite-strain static
    solution), and the non-viscous dissipation (Rayleigh + numerical) is never negative."""
    T = 60
    prob, m, pts = cantilever(cell_type, 0.1, T, damping=3.0)
    f = tip_load(pts, T, 2e2)   # tip deflection ≈ 3 % of the length: geometrically non-linear
    res, diag = implicit.simulate_implicit(prob, m, fem.Loads(nodal=jnp.asarray(f)), tol=1e-10, max_newton=30)
    x = np.asarray(res.q[-1])
    r = (np.asarray(fem.internal_force(prob, m, jnp.asarray(x))) - f[-1]) * np.asarray(prob.arrays.free)
    assert np.linalg.norm(r) < 1e-6 * np.linalg.norm(f[-1])
    assert np.abs(np.asarray(res.v[-1])).max() < 1e-6 * np.abs(x - pts).max() / 0.1
    d = np.asarray(res.energies.damping)
    # (hex8: the co-rotational hourglass force is not exactly the gradient of the stored energy, so allow 1e-6)
    assert d.min() >= -1e-6 * float(res.energies.external[-1]) and np.diff(d).min() >= -1e-6 * d[-1], np.diff(d).min()
    assert np.asarray(diag.residual).max() <= 1e-10 and int(res.inverted) == -1


@pytest.mark.long   # CI time: the recurrence and static-equilibrium tests verify the implicit step
def test_low_modes_match_explicit_dynamics_and_backward_euler_decay():
    """Free bending vibration with ωh ≈ 0.05: the period is the explicit solver's to 0.5 %, and the amplitude
    decays per period as backward Euler's amplification |1 + iωh|⁻¹ per step predicts (to 5 %)."""
    h, T = 0.01, 300
    prob, m, pts = cantilever("hexahedron", h, T)
    v0 = np.zeros_like(pts)
    v0[:, 1] = 0.1 * (pts[:, 0] / 6.0) ** 2
    loads = fem.Loads(v0=jnp.asarray(v0))
    res, _ = implicit.simulate_implicit(prob, m, loads, tol=1e-10, max_newton=30)
    ref = fem.simulate(prob, m, loads)
    tip = pts[:, 0] > 6.0 - 1e-9
    t = np.asarray(res.t)
    y_imp = np.asarray(res.q)[:, tip, 1].mean(1) - pts[tip, 1].mean()
    y_exp = np.asarray(ref.q)[:, tip, 1].mean(1) - pts[tip, 1].mean()

    def crossings(y):
        i = np.where(np.sign(y[2:]) != np.sign(y[1:-1]))[0] + 1
        return t[i] - y[i] * (t[i + 1] - t[i]) / (y[i + 1] - y[i])

    ci, ce = crossings(y_imp), crossings(y_exp)
    period_i = 2 * (ci[-1] - ci[0]) / (len(ci) - 1)
    period_e = 2 * (ce[-1] - ce[0]) / (len(ce) - 1)
    assert abs(period_i / period_e - 1) < 5e-3
    # Peaks of |y| between crossings: decay over the run against (1 + (ωh)²)^(-n/2).
    peaks = [(np.abs(y_imp[a:b]).max(), t[a + np.abs(y_imp[a:b]).argmax()])
             for a, b in zip(np.searchsorted(t, ci[:-1]), np.searchsorted(t, ci[1:]))]
    (a0, t0), (a1, t1) = peaks[0], peaks[-1]
    omega = 2 * np.pi / period_e
    predicted = (1 + (omega * h) ** 2) ** (-(t1 - t0) / h / 2)
    assert abs((a1 / a0) / predicted - 1) < 0.05


def test_scope_is_checked():
    prob, m, pts = cantilever("tetra", 0.05, 2)
    visco = fem.mooney_rivlin(**ELASTIC, g=(0.3,), tau=(0.2,))
    with pytest.raises(ValueError, match="Prony"):
        implicit.simulate_implicit(prob, visco, fem.Loads(nodal=jnp.zeros((2, len(pts), 3))))
    with pytest.raises(ValueError, match="pressure"):
        implicit.simulate_implicit(prob, m, fem.Loads(pressure=jnp.zeros((2, 3))))
    with pytest.raises(ValueError, match="loads.nodal"):
        implicit.simulate_implicit(prob, m, fem.Loads(nodal=jnp.zeros((3, len(pts), 3))))


@pytest.mark.long
def test_batch_matches_single_runs_and_generation_keeps_residuals(tmp_path):
    """The vmapped batch equals one-case runs; `run_cases(integrator='implicit')` writes them with each case's
    Newton residuals and iterations."""
    prob, m, pts = cantilever("tetra", 0.05, 4, damping=1.0, load_interp="linear")
    forces = np.stack([tip_load(pts, 4, s) for s in (10.0, 40.0)])
    res, diag = implicit.simulate_implicit_batch(prob, m, fem.Loads(nodal=jnp.asarray(forces)))
    one, _ = implicit.simulate_implicit(prob, m, fem.Loads(nodal=jnp.asarray(forces[1])))
    np.testing.assert_allclose(np.asarray(res.q[1]), np.asarray(one.q), atol=1e-9)
    sc = scenes.Scene("bar", pts, np.asarray(prob.arrays.cells), "tetra",
                      fem.meshes.mesh_edges(np.asarray(prob.arrays.cells)),
                      (pts[:, 0] < 1e-9).astype(np.int8), m, 0.05, 4, 1.0, "linear")
    out = run_cases(sc, prob, forces, tmp_path / "d.npz", batch_size=2, progress=False, velocity="solver",
                    integrator="implicit")
    d = np.load(out)
    np.testing.assert_allclose(d["z"][1, :, :, :3], np.asarray(one.q), atol=1e-5)
    assert d["newton_residual"].shape == (2, 4) and d["newton_residual"].max() <= 1e-3
    assert "backward Euler" in str(d["metadata"])
    with pytest.raises(ValueError, match="integrator"):
        run_cases(sc, prob, forces, tmp_path / "e.npz", integrator="rk4")


def _columns(problem, m, reach=None):
    """(rows, cols, (K₀, S₀) blocks) of `implicit.coloured_jacobian`, 32 products per call (one compiled program
    for every reach); by default every node its own colour: one jvp per degree of freedom."""
    force, stress = implicit.force_and_stress(problem, m)
    n = problem.arrays.points.shape[0]
    return implicit.coloured_jacobian(lambda u: (force(u), stress(u)), np.asarray(problem.arrays.cells), n,
                                      n if reach is None else reach, problem.arrays.points.dtype, chunk=32)


@pytest.mark.parametrize("cell_type, formulation", [("hexahedron", "anp"), ("tetra", "nodal"),
                                                    pytest.param("tetra", "anp", marks=pytest.mark.long)])
def test_rest_linearization_is_the_uncoloured_jacobian_in_node_blocks(cell_type, formulation):
    # the coloured products (many nodes' columns per jvp) give the blocks of one jvp per degree of freedom
    pts, cells = fem.box_hex_mesh((4.0, 1.0, 1.0), (6, 2, 1))
    cells = fem.hex_to_tet(cells) if cell_type == "tetra" else cells
    m = fem.mooney_rivlin(**ELASTIC)
    prob = fem.setup(pts, cells, material=m, frame_dt=0.05, n_frames=1, clamped=np.where(pts[:, 0] < 1e-9)[0],
                     tet_formulation=formulation)
    lin = implicit.rest_linearization(prob, m, chunk=32)
    n = len(pts)
    rows, cols, (k, s) = _columns(prob, m)
    assert len(rows) == n ** 2 and len(lin.k_rows) < n ** 2 / 2    # sparse: the pairs that interact
    k = k.reshape(n, n, 3, 3)                                        # every pair, sorted by (a, b)
    for rows, cols, blocks, ref in ((lin.k_rows, lin.k_cols, lin.k_blocks, 0.5 * (k + k.transpose(1, 0, 3, 2))),
                                    (lin.s_rows, lin.s_cols, lin.s_blocks, s.reshape(n, n, 6, 3))):
        got = np.zeros_like(ref)
        got[rows, cols] = blocks
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    # the tets' nodal averages reach two rings: coloured as if one, the random-direction check catches it
    if formulation == "nodal":
        with pytest.raises(RuntimeError, match="reach = 1"):
            _columns(prob, m, reach=1)
