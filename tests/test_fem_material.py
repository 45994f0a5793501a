"""Mooney–Rivlin + Prony material: stresses against closed forms written here from principal stretches."""
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fem
from fem import solver

STRETCHES = (0.6, 0.8, 0.95, 1.05, 1.3, 1.8)
MATERIALS = {  # (c10, c01, d1)
    "paper_beam": (1.5e5, 5e3, 1e-7),
    "compressible": (1.0, 0.3, 0.5),
    "neo_hookean_c01_0": (2.0, 0.0, 0.05),
}


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


# --- closed form, independent of fem/: U(λ1, λ2, λ3) and σ_i = (λ_i / J) ∂U/∂λ_i ----------------------------

def principal_cauchy(c10, c01, d1, lam):
    """Principal Cauchy stresses of U = C10(Ī1−3) + C01(Ī2−3) + (J−1)²/D1 written in the principal stretches.

    λ_i ∂Ī1/∂λ_i = J^(−2/3) (2λ_i² − ⅔ I1),  λ_i ∂Ī2/∂λ_i = J^(−4/3) (2λ_i² (I1 − λ_i²) − 4⁄3 I2),
    λ_i ∂[(J−1)²/D1]/∂λ_i = 2 J (J − 1) / D1.
    """
    lam = np.asarray(lam, dtype=float)
    J = np.prod(lam)
    sq = lam ** 2
    I1 = sq.sum()
    I2 = sq[0] * sq[1] + sq[1] * sq[2] + sq[2] * sq[0]
    dI1 = J ** (-2.0 / 3.0) * (2.0 * sq - 2.0 * I1 / 3.0)
    dI2 = J ** (-4.0 / 3.0) * (2.0 * sq * (I1 - sq) - 4.0 * I2 / 3.0)
    return (c10 * dI1 + c01 * dI2 + 2.0 * J * (J - 1.0) / d1) / J


def lateral_stretch(c10, c01, d1, stretch):
    """λ_2 = λ_3 with σ_22 = σ_33 = 0 under axial stretch λ_1, by Newton to machine precision."""
    s2 = lambda l2: principal_cauchy(c10, c01, d1, (stretch, l2, l2))[1]
    l2 = stretch ** -0.5
    for _ in range(100):
        eps = 1e-7 * l2
        step = s2(l2) / ((s2(l2 + eps) - s2(l2 - eps)) / (2 * eps))
        l2 -= step
        if abs(step) < 1e-15 * l2:
            break
    return l2


def uniaxial_F(c10, c01, d1, stretch):
    l2 = lateral_stretch(c10, c01, d1, stretch)
    return np.diag([stretch, l2, l2])


def test_closed_form_lateral_stretch_is_converged():
    """The reference itself: the lateral faces are traction free to round-off."""
    c10, c01, d1 = MATERIALS["paper_beam"]
    for stretch in STRETCHES:
        lam = np.diag(uniaxial_F(c10, c01, d1, stretch))
        s = principal_cauchy(c10, c01, d1, lam)
        assert abs(s[1]) <= 1e-9 * abs(s[0])


@pytest.mark.parametrize("name", list(MATERIALS))
def test_uniaxial_stretch_cauchy_stress_matches_closed_form(name):
    """Homogeneous uniaxial stretch/compression: σ11 as the compressible Mooney–Rivlin closed form, σ22 = σ33 = 0."""
    c10, c01, d1 = MATERIALS[name]
    m = fem.mooney_rivlin(c10, c01, d1)
    Fs = np.stack([uniaxial_F(c10, c01, d1, s) for s in STRETCHES])
    sig = np.asarray(fem.cauchy_stress(m, jnp.asarray(Fs)))
    for k, F in enumerate(Fs):
        ref = principal_cauchy(c10, c01, d1, np.diag(F))
        scale = abs(ref[0])
        np.testing.assert_allclose(sig[k, 0, 0], ref[0], rtol=1e-6)
        np.testing.assert_allclose(np.diag(sig[k])[1:], 0.0, atol=1e-6 * scale)
        np.testing.assert_allclose(sig[k] - np.diag(np.diag(sig[k])), 0.0, atol=1e-12 * scale)


def test_cauchy_stress_rotates_with_the_body():
    """Objectivity: F = Q U gives σ = Q σ(U) Qᵀ (rotation after the stretch changes only the orientation)."""
    c10, c01, d1 = MATERIALS["compressible"]
    m = fem.mooney_rivlin(c10, c01, d1)
    U = uniaxial_F(c10, c01, d1, 1.4)
    Q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    ref = Q @ np.diag(principal_cauchy(c10, c01, d1, np.diag(U))) @ Q.T
    np.testing.assert_allclose(np.asarray(fem.cauchy_stress(m, jnp.asarray(Q @ U))), ref,
                               rtol=0, atol=1e-9 * np.abs(ref).max())


def test_strain_energy_density_is_mooney_rivlin_in_principal_stretches():
    """U(F) equals the Abaqus Mooney–Rivlin potential evaluated from the principal stretches."""
    c10, c01, d1 = MATERIALS["compressible"]
    m = fem.mooney_rivlin(c10, c01, d1)
    lam = np.array([1.3, 0.9, 0.8])
    J, sq = np.prod(lam), lam ** 2
    ref = (c10 * (J ** (-2 / 3) * sq.sum() - 3)
           + c01 * (J ** (-4 / 3) * (sq[0] * sq[1] + sq[1] * sq[2] + sq[2] * sq[0]) - 3)
           + (J - 1) ** 2 / d1)
    np.testing.assert_allclose(float(fem.strain_energy_density(m, jnp.diag(jnp.asarray(lam)))), ref, rtol=1e-12)


def _single_element(cell_type, m):
    pts, cells = fem.box_hex_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    if cell_type == "tetra":
        cells = fem.hex_to_tet(cells)
    return fem.setup(pts, cells, material=m, frame_dt=1.0, n_frames=1, n_sub=1)


@pytest.mark.parametrize("cell_type", ["hexahedron", "tetra"])
def test_uniaxial_stretch_element_stress_and_forces_match_closed_form(cell_type):
    """The element routines see the same homogeneous state: element σ equals the closed form, and the nodal
    forces are the discrete divergence V (J σ F⁻ᵀ) ∇N (no hourglass/ANP artefacts for a homogeneous field)."""
    c10, c01, d1 = MATERIALS["paper_beam"]
    m = fem.mooney_rivlin(c10, c01, d1)
    prob = _single_element(cell_type, m)
    X = np.asarray(prob.arrays.points)
    for stretch in (0.8, 1.3):
        F = uniaxial_F(c10, c01, d1, stretch)
        ref = principal_cauchy(c10, c01, d1, np.diag(F))
        x = jnp.asarray(X @ F.T)
        sig_e = np.asarray(solver._element_stress(prob.arrays, m, x - prob.arrays.points,
                                                  solver._zero_visco(prob.arrays, prob.config), prob.config))
        np.testing.assert_allclose(sig_e[:, 0], ref[0], rtol=1e-6)
        np.testing.assert_allclose(sig_e[:, 1:], 0.0, atol=1e-6 * abs(ref[0]))
        # nodal forces of a homogeneous stress: the face tractions P·n lumped equally on each boundary face's nodes
        P = np.linalg.det(F) * np.diag(ref) @ np.linalg.inv(F).T
        f = np.asarray(fem.internal_force(prob, m, x))
        np.testing.assert_allclose(f, _lumped_face_tractions(X, np.asarray(prob.arrays.cells), P), rtol=0,
                                   atol=1e-6 * abs(ref[0]))


def _lumped_face_tractions(X, cells, P):
    """Σ over boundary faces of the unit box of P·n·A / n_face_nodes at each face node (exact for linear
    triangles; for the rectangular bilinear quad the four shares are equal too)."""
    f = np.zeros_like(X)
    n_face = 4 if cells.shape[1] == 8 else 3
    seen = set()
    for cell in cells:
        for face in itertools.combinations(cell.tolist(), n_face):
            for i in range(3):
                side = X[list(face), i]
                if np.all(side == side[0]) and side[0] in (0.0, 1.0) and frozenset(face) not in seen:
                    seen.add(frozenset(face))
                    n = np.zeros(3)
                    n[i] = 1.0 if side[0] == 1.0 else -1.0
                    area = 1.0 if n_face == 4 else 0.5
                    f[list(face)] += P @ n * area / n_face
    return f


# --- Prony relaxation -----------------------------------------------------------------------------------------

PAPER_G, PAPER_TAU = (0.3, 0.49), (0.2, 0.5)


def test_relaxation_modulus_is_prony_series():
    """g_R(t) = 1 − Σ ḡ_i (1 − e^(−t/τ_i)): 1 at t = 0, 1 − Σḡ as t → ∞."""
    m = fem.mooney_rivlin(1.0, 0.0, 0.1, g=PAPER_G, tau=PAPER_TAU)
    t = np.array([0.0, 0.1, 0.7, 100.0])
    ref = 1.0 - sum(g * (1.0 - np.exp(-t / tau)) for g, tau in zip(PAPER_G, PAPER_TAU))
    np.testing.assert_allclose(np.asarray(fem.relaxation_modulus(m, t)), ref, rtol=1e-14)
    assert ref[-1] == pytest.approx(1.0 - sum(PAPER_G))


@pytest.mark.parametrize("cell_type", ["hexahedron", "tetra"])
def test_held_step_strain_relaxes_deviatoric_stress_as_g_R(cell_type):
    """A stretch applied at t = 0 and held: the deviatoric Cauchy stress decays as g_R(t) (volumetric part is
    elastic, k̄ = 0). Exercises fem.solver._internal, the same per-sub-step viscous update the solver uses,
    called repeatedly at the held positions (the solver itself has no prescribed displacements)."""
    m = fem.mooney_rivlin(1.5e5, 5e3, 1e-7, g=PAPER_G, tau=PAPER_TAU)
    prob = _single_element(cell_type, m)
    arr, cfg = prob.arrays, prob.config
    F = uniaxial_F(1.5e5, 5e3, 1e-7, 1.2)
    x = jnp.asarray(np.asarray(arr.points) @ F.T)
    u = x - arr.points   # the element routines take displacements
    h, n_steps, every = 2e-4, 10000, 500  # t up to 2 s = 4 τ_2
    hg = solver._hourglass_for(arr, m, cfg)

    def advance(visco, _):
        _, visco, *_ = solver._internal(arr, m, hg, u, visco, cfg, h)
        return visco, None

    def chunk(visco):
        visco, _ = jax.lax.scan(advance, visco, None, length=every)
        return visco, solver._element_stress(arr, m, u, visco, cfg)

    chunk = jax.jit(chunk)
    # the step itself: one sub-step from the undeformed state (linear ramp over [0, h])
    visco = advance(solver._zero_visco(arr, cfg), None)[0]
    dev = lambda s: np.asarray(s[0, :3]) - np.mean(np.asarray(s[0, :3]))
    dev0 = dev(solver._element_stress(arr, m, u, visco, cfg))
    ratios, times = [], []
    for k in range(1, n_steps // every + 1):
        visco, s = chunk(visco)
        ratios.append(dev(s)[0] / dev0[0])
        times.append(h + k * every * h)
    # the instantaneous response is the elastic one (the ramp over one tiny sub-step barely relaxes)
    sig_inst = principal_cauchy(1.5e5, 5e3, 1e-7, np.diag(F))
    np.testing.assert_allclose(dev0[0], sig_inst[0] - sig_inst.mean(), rtol=1e-3)
    g_R = np.asarray(fem.relaxation_modulus(m, np.asarray(times) - h / 2))
    np.testing.assert_allclose(ratios, g_R, atol=1e-3)
    assert ratios[-1] < 0.3  # it really relaxed towards g∞ = 0.21


@pytest.mark.parametrize("cell_type", ["hexahedron", "tetra"])
def test_float32_stress_of_a_small_strain_far_from_the_origin(cell_type):
    """F is built from displacements, so float32 keeps a small strain accurate however large the coordinates:
    a 1e-4 stretch of a unit element placed 1000 units from the origin (positions would lose F − I entirely to
    cancellation: eps32 · 1000 ≈ 1e-4) gives the closed-form Cauchy stress to 5e-3 in float32 (what is left is
    J − 1 ≈ 1e-6 formed from F ≈ I: ~1e-7 absolute, times K = 2e7)."""
    c10, c01, d1 = MATERIALS["paper_beam"]
    m = fem.mooney_rivlin(c10, c01, d1)
    pts, cells = fem.box_hex_mesh((1.0, 1.0, 1.0), (1, 1, 1), origin=(1000.0, 1000.0, 1000.0))
    if cell_type == "tetra":
        cells = fem.hex_to_tet(cells)
    prob = fem.setup(pts, cells, material=m, frame_dt=1.0, n_frames=1, n_sub=1)
    F = uniaxial_F(c10, c01, d1, 1.0 + 1e-4)
    ref = principal_cauchy(c10, c01, d1, np.diag(F))
    u = jnp.asarray((pts - pts.mean(0)) @ (F - np.eye(3)).T, jnp.float32)
    arr = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a,
                                 prob.arrays)
    m32 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), m)
    sig = np.asarray(solver._element_stress(arr, m32, u, solver._zero_visco(arr, prob.config), prob.config))
    assert sig.dtype == np.float32
    np.testing.assert_allclose(sig[:, 0], ref[0], rtol=5e-3)
    np.testing.assert_allclose(sig[:, 1:3], 0.0, atol=5e-3 * abs(ref[0]))
