"""Element technology for nearly incompressible solids: one-point hex8 with physical hourglass control, and
average-nodal-pressure tet4.

Both paper scenes are nearly incompressible (K/μ ≈ 64 for the beam, ≈ 78 for the bunny). A fully integrated
trilinear hexahedron locks twice there: volumetrically (eight independent J constraints per element) and in
bending (parasitic shear: an element of aspect ratio 1 bent in its plane is ~30 % too stiff at ν ≈ 0.5). A
constant-strain tetrahedron locks volumetrically (one J constraint per element, more elements than nodes).

hex8 — uniform-gradient one-point quadrature with physical (enhanced-strain) hourglass stabilisation:
    * F = Σ_a x_a ⊗ b̄_a with the uniform gradients b̄_a = (1/V) ∫ ∇N_a dV (Flanagan–Belytschko); the full
      hyperelastic–viscoelastic stress is evaluated once per element (one J per element: no volumetric
      locking; passes the patch test on distorted meshes, forces included).
    * The 12 hourglass modes (4 patterns h = ξη, ηζ, ζξ, ξηζ × 3 components) that one point cannot see get a
      stiffness K̂ [12×12] derived, once per element, from the incompatible-modes (Wilson–Taylor QM6) element of
      small-strain elasticity with the instantaneous Lamé constants: the 33-dof element (24 nodal + 9
      incompatible (1−ξ², 1−η², 1−ζ²) dofs) is statically condensed and projected on the hourglass basis
      (Flanagan–Belytschko vectors γ_α = h_α − (h_α·X) b). For rectangular elements this reproduces the
      incompatible-modes element, which is exact in pure bending — the dominant mode of both scenes — and it
      has no volumetric locking in bending because the lateral modes absorb the Poisson contraction.
    * The hourglass energy ½ gᵀK̂g acts on g = G Rᵀx, co-rotated with the element rotation R (polar
      decomposition of F), so rigid rotations stay stress-free. Its viscoelastic part relaxes with the same
      Prony series: K̂ = K̂_eq + ΔK̂ with K̂_eq at the long-term shear modulus g∞μ0.
    This is the element family of Abaqus's C3D8R with enhanced hourglass control; the reported stress is the
    centre-point stress (volume average of the single integration point).

tet4 — average nodal pressure (Bonet & Burton 1998): the volumetric energy Σ_a V_a U(J_a) is evaluated with
nodal Jacobians J_a = v_a / V_a from the lumped nodal volumes, so there is one volume constraint per node
instead of per element; the deviatoric part uses the element's constant F. The element pressure is the mean of
its nodes' pressures.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

# VTK / meshio hexahedron node order and natural coordinates.
HEX_XI = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                   [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)
HEX_FACES = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])
TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
HOURGLASS = np.stack([HEX_XI[:, 0] * HEX_XI[:, 1], HEX_XI[:, 1] * HEX_XI[:, 2],
                      HEX_XI[:, 2] * HEX_XI[:, 0], HEX_XI[:, 0] * HEX_XI[:, 1] * HEX_XI[:, 2]])  # [4, 8]
_GAUSS = np.array([-1.0, 1.0]) / np.sqrt(3.0)


class HexGeometry(NamedTuple):
    """Reference-configuration data of hex8 elements (numpy arrays, K elements)."""

    b: np.ndarray        # [K, 8, 3] centre shape-function gradients ∂N_a/∂X
    volume: np.ndarray   # [K] exact reference volumes (2×2×2 Gauss)
    gamma: np.ndarray    # [K, 4, 8] Flanagan–Belytschko hourglass vectors
    hg_lam: tuple        # (Kuu, Kua, Kaa) projected λ-parts: [K,12,12], [K,12,9], [K,9,9]
    hg_mu: tuple         # the same for the μ-parts


class TetGeometry(NamedTuple):
    b: np.ndarray        # [K, 4, 3]
    volume: np.ndarray   # [K]
    node_volume: np.ndarray  # [N] lumped reference nodal volumes Σ V_e / 4


def element_volumes(points: np.ndarray, cells: np.ndarray, cell_type: str) -> np.ndarray:
    """Signed reference volumes [K] of hex8 (2×2×2 Gauss) or tet4 elements."""
    xe = points[cells]
    if cell_type == "tetra":
        d = xe[:, 1:] - xe[:, :1]
        return np.linalg.det(d) / 6.0
    vol = np.zeros(len(cells))
    for xi, eta, zeta in np.array(np.meshgrid(_GAUSS, _GAUSS, _GAUSS, indexing="ij")).reshape(3, -1).T:
        dN = _hex_dn_dxi(np.array([xi, eta, zeta]))
        vol += np.linalg.det(np.einsum("kai,aj->kij", xe, dN))
    return vol


def _hex_dn_dxi(p):
    """∂N_a/∂ξ_j at natural point p: [8, 3]."""
    s = HEX_XI
    t = 1.0 + s * p  # [8,3]
    return np.stack([s[:, 0] * t[:, 1] * t[:, 2], t[:, 0] * s[:, 1] * t[:, 2], t[:, 0] * t[:, 1] * s[:, 2]], -1) / 8.0


def hex_geometry(points: np.ndarray, cells: np.ndarray) -> HexGeometry:
    xe = points[cells]  # [K,8,3]
    J0 = np.einsum("kai,aj->kij", xe, _hex_dn_dxi(np.zeros(3)))  # dX/dξ at centre
    J0inv = np.linalg.inv(J0)
    # Flanagan–Belytschko uniform gradient b̄_a = (1/V) ∫ ∇N_a dV (exact with 2×2×2 Gauss). Unlike the
    # centre-point gradient it makes a uniform stress self-equilibrated on distorted elements (patch test).
    b = np.zeros_like(xe)
    volume = np.zeros(len(cells))
    for p in np.array(np.meshgrid(_GAUSS, _GAUSS, _GAUSS, indexing="ij")).reshape(3, -1).T:
        dN = _hex_dn_dxi(p)
        J = np.einsum("kai,aj->kij", xe, dN)
        detJ = np.linalg.det(J)
        b += detJ[:, None, None] * np.einsum("aj,kji->kai", dN, np.linalg.inv(J))
        volume += detJ
    b /= volume[:, None, None]
    hX = np.einsum("ma,kai->kmi", HOURGLASS, xe)  # [K,4,3]
    gamma = HOURGLASS[None] - np.einsum("kmi,kai->kma", hX, b)
    lam, mu = _incompatible_mode_parts(xe, J0, J0inv)
    return HexGeometry(b, volume, gamma, lam, mu)


def _incompatible_mode_parts(xe, J0, J0inv):
    """λ- and μ-parts of the 33-dof QM6 stiffness, projected on the hourglass basis H = h/8.

    Returns for each part (Hᵀ K_uu H [K,12,12], Hᵀ K_uα [K,12,9], K_αα [K,9,9]) so that the condensed
    hourglass stiffness for any (λ, μ) is K̂ = Kuu − Kuα Kαα⁻¹ Kαᵤ with each block = λ·part_λ + μ·part_μ.
    """
    K = len(xe)
    detJ0 = np.linalg.det(J0)
    vol_m = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    dev_m = np.diag([2.0, 2.0, 2.0, 1.0, 1.0, 1.0])
    A = np.zeros((K, 33, 33))
    Bm = np.zeros((K, 33, 33))
    for p in np.array(np.meshgrid(_GAUSS, _GAUSS, _GAUSS, indexing="ij")).reshape(3, -1).T:
        dN = _hex_dn_dxi(p)
        J = np.einsum("kai,aj->kij", xe, dN)
        detJ = np.linalg.det(J)
        gN = np.einsum("aj,kji->kai", dN, np.linalg.inv(J))  # [K,8,3]
        dP = np.diag(-2.0 * p)  # ∂(1−ξ_m²)/∂ξ_j, [3 modes, 3]
        gP = (detJ0 / detJ)[:, None, None] * np.einsum("mj,kji->kmi", dP, J0inv)  # Taylor's modification
        grads = np.concatenate([gN, gP], axis=1)  # [K, 11, 3]
        Bk = np.zeros((K, 6, 33))
        for n in range(11):
            gx, gy, gz = grads[:, n, 0], grads[:, n, 1], grads[:, n, 2]
            c = 3 * n
            Bk[:, 0, c], Bk[:, 1, c + 1], Bk[:, 2, c + 2] = gx, gy, gz
            Bk[:, 3, c], Bk[:, 3, c + 1] = gy, gx
            Bk[:, 4, c + 1], Bk[:, 4, c + 2] = gz, gy
            Bk[:, 5, c], Bk[:, 5, c + 2] = gz, gx
        w = detJ[:, None, None]
        Bv = np.einsum("i,kij->kj", vol_m, Bk)
        A += w * np.einsum("ki,kj->kij", Bv, Bv)
        Bm += w * np.einsum("kai,ab,kbj->kij", Bk, dev_m, Bk)
    H = np.zeros((24, 12))
    for m in range(4):
        for i in range(3):
            H[i::3, 3 * m + i] = HOURGLASS[m] / 8.0

    def project(K33):
        Kuu, Kua, Kaa = K33[:, :24, :24], K33[:, :24, 24:], K33[:, 24:, 24:]
        return (np.einsum("ai,kab,bj->kij", H, Kuu, H), np.einsum("ai,kab->kib", H, Kua), Kaa)

    return project(A), project(Bm)


def tet_geometry(points: np.ndarray, cells: np.ndarray) -> TetGeometry:
    xe = points[cells]
    D = np.swapaxes(xe[:, 1:] - xe[:, :1], 1, 2)  # columns x1-x0, x2-x0, x3-x0: [K,3,3]
    Dinv = np.linalg.inv(D)
    dN = np.array([[-1.0, -1.0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    b = np.einsum("aj,kji->kai", dN, Dinv)
    volume = np.linalg.det(D) / 6.0
    node_volume = np.zeros(len(points))
    np.add.at(node_volume, cells.ravel(), np.repeat(volume / 4.0, 4))
    return TetGeometry(b, volume, node_volume)


def characteristic_lengths(points: np.ndarray, cells: np.ndarray, cell_type: str) -> np.ndarray:
    """Element length L_e for the explicit stability limit h ≤ L_e / c_d.

    tet4: the smallest altitude 3V / A_max. hex8: 0.8 · V / A_max — the hourglass stiffness raises the highest
    element frequency above the one-point estimate; on a cube mesh the global limit 2/ω_max measured by power
    iteration is 0.856 · V/A_max / c_d (tests/test_fem_dynamics.py checks the bound)."""
    vol = element_volumes(points, cells, cell_type)
    faces = HEX_FACES if cell_type == "hexahedron" else TET_FACES
    fx = points[cells[:, faces]]  # [K, nf, nv, 3]
    if cell_type == "hexahedron":
        area = 0.5 * np.linalg.norm(np.cross(fx[:, :, 2] - fx[:, :, 0], fx[:, :, 3] - fx[:, :, 1]), axis=-1)
        return 0.8 * vol / area.max(axis=1)
    area = 0.5 * np.linalg.norm(np.cross(fx[:, :, 1] - fx[:, :, 0], fx[:, :, 2] - fx[:, :, 0]), axis=-1)
    return 3.0 * vol / area.max(axis=1)


def incidence_table(cells: np.ndarray, n_nodes: int) -> np.ndarray:
    """[N, max_valence] indices into the node-major flattened element-node array (index a·K + k for local node
    a of element k), padded with K·n_per.

    Assembling nodal sums by gathering through this table is a dense gather instead of a scatter-add, which
    is several times faster on CPU.
    """
    flat = cells.T.ravel()
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=n_nodes)
    width = int(counts.max())
    table = np.full((n_nodes, width), flat.size, dtype=np.int32)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(flat.size) - np.repeat(starts, counts)
    table[flat[order], rank] = order
    return table
