"""Explicit dynamics: energy conservation and balance, viscous and damping dissipation, and the stable step."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse.linalg

import fem
from fem import solver
from fem.meshes import boundary_faces

CELL_TYPES = ["hexahedron", "tetra"]
# A small cantilever 6 × 1 × 1 (unit elements), μ0 = 1e4, K0 = 5e4, ρ = 1: first bending period ≈ 1.3,
# about 450 sub-steps per period, so 10 periods cost a few thousand sub-steps on 6 hexes / 36 tets.
ELASTIC = dict(c10=5e3, c01=0.0, d1=4e-5, density=1.0)
PRONY = dict(g=(0.3, 0.49), tau=(0.2, 0.5))


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def cantilever(cell_type, material, frame_dt, n_frames, **kw):
    pts, cells = fem.box_hex_mesh((6.0, 1.0, 1.0), (6, 1, 1))
    if cell_type == "tetra":
        cells = fem.hex_to_tet(cells)
    clamped = np.where(pts[:, 0] < 1e-9)[0]
    prob = fem.setup(pts, cells, material=material, frame_dt=frame_dt, n_frames=n_frames, clamped=clamped, **kw)
    v0 = np.zeros_like(pts)
    v0[:, 1] = 0.1 * (pts[:, 0] / 6.0) ** 2   # bending-like initial velocity (tip amplitude ≈ L/300)
    return prob, pts, v0


def tip_y(res, pts):
    tip = pts[:, 0] > 6.0 - 1e-9
    return np.asarray(res.q)[:, tip, 1].mean(axis=1) - pts[tip, 1].mean()


def period_from_zero_crossings(t, y):
    s = np.sign(y[1:])
    idx = np.where(s[1:] != s[:-1])[0] + 1
    tc = t[1:][idx - 1] - y[1:][idx - 1] * (t[1:][idx] - t[1:][idx - 1]) / (y[1:][idx] - y[1:][idx - 1])
    return 2.0 * (tc[-1] - tc[0]) / (len(tc) - 1)


@pytest.mark.parametrize("cell_type", CELL_TYPES)
def test_elastic_free_vibration_conserves_energy_over_ten_periods(cell_type):
    """No loads, no damping, no Prony terms: kinetic + strain energy is conserved (symplectic central
    differences: bounded O((ωh)²) fluctuation, no drift) to 0.5 % over ≥ 10 bending periods."""
    m = fem.mooney_rivlin(**ELASTIC)
    prob, pts, v0 = cantilever(cell_type, m, frame_dt=0.05, n_frames=300)
    res = fem.simulate(prob, m, fem.Loads(v0=jnp.asarray(v0)), on_inversion="raise")
    e = res.energies
    total = np.asarray(e.kinetic + e.strain)
    t = np.asarray(res.t)
    period = period_from_zero_crossings(t, tip_y(res, pts))
    assert t[-1] >= 10 * period, f"only {t[-1] / period:.1f} periods"
    assert np.max(np.abs(total / total[0] - 1.0)) <= 5e-3
    assert float(np.max(np.asarray(e.strain))) > 0.3 * total[0]   # energy really exchanges kinetic ↔ strain
    np.testing.assert_allclose(np.asarray(e.external), 0.0, atol=1e-14)


def _balance_error(e, e0):
    bal = np.asarray(e.kinetic + e.strain + e.viscous + e.damping - e.external) - e0
    return np.max(np.abs(bal)) / max(float(np.max(np.abs(np.asarray(e.external)))), e0)


@pytest.mark.parametrize("cell_type", CELL_TYPES)
def test_prony_dissipation_is_non_negative_and_energy_balance_closes(cell_type):
    """Viscoelastic vibration under a tip load switched on at t = 0.5: the viscous dissipation is ≥ 0 and
    non-decreasing every frame, and kinetic + stored + dissipated = initial + external work to 1 %."""
    m = fem.mooney_rivlin(**ELASTIC, **PRONY)
    n_frames = 80
    prob, pts, v0 = cantilever(cell_type, m, frame_dt=0.05, n_frames=n_frames)
    nodal = np.zeros((n_frames, len(pts), 3))
    tip = np.where(pts[:, 0] > 6.0 - 1e-9)[0]
    nodal[10:, tip, 1] = 2.0 / len(tip)        # ≈ quarter of the vibration amplitude statically
    res = fem.simulate(prob, m, fem.Loads(nodal=jnp.asarray(nodal), v0=jnp.asarray(v0)), on_inversion="raise")
    e = res.energies
    visc = np.asarray(e.viscous)
    e0 = float(e.kinetic[0] + e.strain[0])
    assert np.all(visc >= 0.0)
    assert np.all(np.diff(visc) >= 0.0)
    assert visc[-1] > 0.2 * e0                  # it really dissipates
    assert float(e.external[-1]) > 0.05 * e0    # and the load really works
    assert _balance_error(e, e0) <= 0.01


@functools.lru_cache(maxsize=None)
def damped_run(cell_type, alpha):
    """Energies of a damped free vibration (numpy; shared by the damping tests)."""
    with jax.enable_x64(True):
        m = fem.mooney_rivlin(**ELASTIC)
        prob, pts, v0 = cantilever(cell_type, m, frame_dt=0.05, n_frames=60, damping=alpha)
        res = fem.simulate(prob, m, fem.Loads(v0=jnp.asarray(v0)), on_inversion="raise")
        return np.asarray(res.t), jax.tree_util.tree_map(np.asarray, res.energies)


@pytest.mark.parametrize("cell_type", CELL_TYPES)
def test_rayleigh_damping_dissipation_is_non_negative_and_balance_closes(cell_type):
    """Mass-proportional damping α: the damping dissipation is ≥ 0, non-decreasing, and kinetic + strain +
    damping dissipation stays equal to the initial energy to 1 %."""
    _, e = damped_run(cell_type, 0.5)
    e0 = float(e.kinetic[0] + e.strain[0])
    assert np.all(e.damping >= 0.0) and np.all(np.diff(e.damping) >= 0.0)
    assert e.damping[-1] > 0.5 * e0
    assert _balance_error(e, e0) <= 0.01


def test_rayleigh_mass_damping_decays_energy_at_rate_alpha():
    """M ü + α M u̇ + K u = 0 decays every mode's energy as e^(−α t): the fitted slope of log(kinetic + strain)
    over 3 s is −α within 5 % (the O(α/ω) in-period modulation averages out over the fit)."""
    t, e = damped_run("hexahedron", 0.5)
    slope = np.polyfit(t, np.log(e.kinetic + e.strain), 1)[0]
    assert slope == pytest.approx(-0.5, rel=0.05)


# --- stable time step -----------------------------------------------------------------------------------------

def omega_max(prob, m):
    """Largest ω of K φ = ω² M φ (free dofs) by Lanczos on M^(−½) K M^(−½), matrix-free through jax.jvp."""
    X = prob.arrays.points
    free = np.asarray(prob.arrays.free)
    scale = 1.0 / np.sqrt(np.repeat(np.asarray(fem.lumped_mass(prob, m)), 3)) * np.repeat(free[:, 0], 3)
    kv = jax.jit(lambda u: jax.jvp(lambda x: fem.internal_force(prob, m, x), (X,), (u.reshape(-1, 3),))[1].ravel())
    op = scipy.sparse.linalg.LinearOperator((X.size, X.size), dtype=float,
                                            matvec=lambda u: scale * np.asarray(kv(jnp.asarray(scale * np.ravel(u)))))
    lam = scipy.sparse.linalg.eigsh(op, k=1, which="LA", tol=1e-10, return_eigenvectors=False)[0]
    return float(np.sqrt(lam))


def beam_like(cell_type, distorted):
    pts, cells = (fem.box_hex_mesh((40.0, 10.0, 10.0), (20, 5, 5)) if not distorted
                  else fem.box_hex_mesh((4.0, 3.0, 3.0), (4, 3, 3)))
    if distorted:
        pts = pts + np.random.default_rng(3).uniform(-0.25, 0.25, pts.shape)
    if cell_type == "tetra":
        cells = fem.hex_to_tet(cells)
    return pts, cells, np.where(pts[:, 0] < 1e-9 if not distorted else pts[:, 0] < -1.0)[0]


@pytest.mark.parametrize("distorted", [False, True], ids=["beam_20x5x5", "distorted_random"])
@pytest.mark.parametrize("cell_type", CELL_TYPES)
def test_automatic_sub_step_is_below_central_difference_limit(cell_type, distorted):
    """Central differences are stable for h < 2/ω_max: the automatic sub-step (safety 0.9) satisfies it, for
    the paper's beam mesh (clamped) and a randomly distorted free mesh, at the paper's beam material."""
    m = fem.mooney_rivlin(1.5e5, 5e3, 1e-7, density=1.1e-3)
    pts, cells, clamped = beam_like(cell_type, distorted)
    prob = fem.setup(pts, cells, material=m, frame_dt=1e-3, n_frames=1, clamped=clamped)
    h = prob.config.frame_dt / prob.config.n_sub
    w = omega_max(prob, m)
    assert h < 2.0 / w, f"h = {h:.4g} exceeds 2/ω_max = {2.0 / w:.4g}"


def test_power_iteration_max_frequency_agrees_with_lanczos():
    """fem.solver.max_frequency (power iteration) finds the same ω_max as Lanczos, from below."""
    m = fem.mooney_rivlin(1.5e5, 5e3, 1e-7, density=1.1e-3)
    pts, cells, clamped = beam_like("tetra", True)
    prob = fem.setup(pts, cells, material=m, frame_dt=1e-3, n_frames=1, clamped=clamped)
    w = omega_max(prob, m)
    assert 0.95 * w <= solver.max_frequency(prob, m) <= w * (1 + 1e-6)


def _vmapped(prob, material, loads):
    """The straightforward batch: `jax.vmap` of the single-case run (cases first)."""
    return jax.vmap(lambda ld: solver._simulate(prob.arrays, material, ld, prob.config))(loads)


def _assert_results_equal(a, b, rtol=1e-9):
    for name, x, y in zip(a._fields, a, b):
        if name == "energies":
            for en, xe, ye in zip(x._fields, x, y):
                np.testing.assert_allclose(np.asarray(xe), np.asarray(ye), rtol=rtol,
                                           atol=rtol * (np.abs(ye).max() + 1e-300), err_msg=en)
        elif y is not None:
            x, y = np.asarray(x), np.asarray(y)
            assert x.shape == y.shape, (name, x.shape, y.shape)
            if x.dtype.kind == "f":
                scale = np.max(np.abs(y[np.isfinite(y)]), initial=0.0)
                np.testing.assert_allclose(x, y, rtol=rtol, atol=rtol * scale + 1e-300, err_msg=name)
            else:
                np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.parametrize("cell_type", ["hexahedron", pytest.param("tetra", marks=pytest.mark.long)])
def test_simulate_batch_equals_vmap_of_simulate_with_prony_damping_and_pressure(cell_type):
    """The batched run keeps the cases on the trailing axis for speed; it must be the same computation as vmap."""
    mat = fem.mooney_rivlin(**ELASTIC, **PRONY)
    pts, cells = fem.box_hex_mesh((6.0, 1.0, 1.0), (6, 1, 1))
    if cell_type == "tetra":
        cells = fem.hex_to_tet(cells)
    tip_faces = boundary_faces(cells)
    tip_faces = tip_faces[np.all(pts[tip_faces][:, :, 0] > 6.0 - 1e-9, axis=1)]
    prob = fem.setup(pts, cells, material=mat, frame_dt=0.02, n_frames=3, clamped=np.where(pts[:, 0] < 1e-9)[0],
                     damping=0.5, pressure_faces=tip_faces, load_interp="linear")
    rng = np.random.default_rng(0)
    nodal = rng.normal(size=(3, 3, len(pts), 3)) * 50.0
    loads = fem.Loads(nodal=jnp.asarray(nodal), pressure=jnp.asarray(rng.normal(size=(3, 3, len(tip_faces))) * 20.0),
                      v0=jnp.asarray(rng.normal(size=(3, len(pts), 3)) * 0.01))
    new = fem.simulate_batch(prob, mat, loads)
    assert np.asarray(new.q).shape == (3, 4, len(pts), 3)
    assert float(np.abs(np.asarray(new.energies.viscous)).max()) > 0
    _assert_results_equal(new, _vmapped(prob, mat, loads))


@pytest.mark.long
def test_simulate_batch_equals_vmap_of_simulate_with_contact():
    """Contact search and forces are per case in the batched run too (different loads, different pairs)."""
    pts, cells = fem.box_hex_mesh((1.0, 1.0, 1.0), (2, 2, 2))
    points = np.concatenate([pts, pts + np.array([0.0, 0.0, 1.4])])   # gap 0.4 > r0
    allc = np.concatenate([cells, cells + len(pts)])
    mat = fem.mooney_rivlin(10.0, 0.0, 0.01, density=1.0)
    ctc = dict(a=np.arange(len(pts)), b=np.arange(len(pts), 2 * len(pts)), r0=0.3, stiffness=500.0, skin=0.3,
               capacity=512)
    prob = fem.setup(points, allc, material=mat, frame_dt=0.02, n_frames=3, contact=ctc)
    v0 = np.zeros((2, len(points), 3))
    v0[0, :len(pts), 2], v0[0, len(pts):, 2] = 3.0, -3.0      # case 0: the cubes collide
    v0[1, :len(pts), 0] = 1.0                                    # case 1: sliding apart, no contact
    loads = fem.Loads(v0=jnp.asarray(v0))
    new = fem.simulate_batch(prob, mat, loads)
    strain = np.asarray(new.energies.strain)
    assert strain[0, -1] > 1e3 * max(strain[1, -1], 1e-12)    # only case 0 is in contact
    _assert_results_equal(new, _vmapped(prob, mat, loads))


def test_simulate_batch_needs_a_batched_load():
    pts, cells = fem.box_hex_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    mat = fem.mooney_rivlin(**ELASTIC)
    prob = fem.setup(pts, cells, material=mat, frame_dt=0.01, n_frames=1)
    with pytest.raises(ValueError, match="at least one batched entry"):
        fem.simulate_batch(prob, mat, fem.Loads())


@pytest.mark.parametrize("integrator", ["explicit", "implicit"])
def test_an_initial_displacement_held_by_clamps_keeps_its_closed_form_stress(integrator):
    # Loads.u0: a unit hex8 stretched homogeneously (F = diag(1.2, 0.95, 0.9)) at t = 0, every node clamped there:
    # positions stay at X + u0 and the nodal stress is the material's Cauchy stress of F in every frame, with
    # nothing dissipated; a u0 of the wrong shape or with NaN is named
    from fem import implicit
    from fem.mesh import box_hex_mesh

    with jax.enable_x64(True):
        m = fem.mooney_rivlin(1.5e5, 5e3, 1e-4)
        X, cells = box_hex_mesh((1.0, 1.0, 1.0), (1, 1, 1))
        prob = fem.setup(X, cells, material=m, frame_dt=0.01, n_frames=5, clamped=np.arange(len(X)))
        F = np.diag([1.2, 0.95, 0.9])
        u0 = jnp.asarray(X @ F.T - X)
        loads = fem.Loads(u0=u0)
        res = fem.simulate(prob, m, loads) if integrator == "explicit" else implicit.simulate_implicit(
            prob, m, loads)[0]
        np.testing.assert_allclose(np.asarray(res.q), np.broadcast_to(X @ F.T, res.q.shape), atol=1e-12)
        s = np.asarray(fem.cauchy_stress(m, jnp.asarray(F)))
        voigt = np.array([s[0, 0], s[1, 1], s[2, 2], s[0, 1], s[0, 2], s[1, 2]])
        np.testing.assert_allclose(np.asarray(res.sigma), np.broadcast_to(voigt, res.sigma.shape), rtol=1e-9,
                                   atol=1e-9 * np.abs(voigt).max())
        assert np.abs(np.asarray(res.energies.damping)).max() < 1e-9 * float(res.energies.strain[0])
        for bad, said in ((u0[:4], r"loads.u0 must have shape \[8, 3\]"), (u0.at[0, 0].set(jnp.nan), "NaN")):
            with pytest.raises(ValueError, match=said):
                fem.simulate(prob, m, fem.Loads(u0=bad))
