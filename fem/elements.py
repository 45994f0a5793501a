"""Element technology for nearly incompressible solids: one-point hex8 with physical hourglass control, and
tet4 with nodal pressure and a stabilised nodally averaged deformation gradient.

Both paper scenes are nearly incompressible (K/μ ≈ 64 for the beam, ≈ 78 for the bunny). A fully integrated
trilinear hexahedron locks twice there: volumetrically (eight independent J constraints per element) and in
bending (parasitic shear: an element of aspect ratio 1 bent in its plane is ~30 % too stiff at ν ≈ 0.5). A
constant-strain tetrahedron locks twice as well: volumetrically (one J constraint per element, more elements
than nodes) and in bending (a constant strain per element cannot represent the linear strain of bending).

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

tet4 — two formulations, chosen with ``fem.setup(tet_formulation=...)``. Both evaluate the volumetric energy at
the nodes, Σ_a V_a U(J_a) with J_a = Σ_{e∋a} (V_e/4) J_e / V_a the nodal Jacobian from the lumped nodal volumes
V_a = Σ_{e∋a} V_e/4 (average nodal pressure, Bonet & Burton 1998): one volume constraint per node instead of
per element, which removes volumetric locking. They differ in the isochoric (deviatoric) part:

"anp": the element's constant F_e. A constant-strain tetrahedron still locks in bending on coarse meshes
    (parasitic shear: a linear field cannot bend an element): the 40 × 2 × 2 cantilever of
    tests/test_fem_elements.py, six tets per hex of an 80 × 2 × 2 grid, is 31.8 % too stiff at the tip (first
    frequency +14.7 %); at ν = 0.36 it is still −34 % on the 40 × 2 × 2 grid, so this is not volumetric locking.

"nodal" (default): stabilised averaged-nodal deformation gradient, the finite-strain form of the αFEM of Liu,
    Nguyen-Thoi & Lam (CMAME 197, 2008, 3883) with a selective (nodal) volumetric part::

        Π = Σ_a V_a U(J_a) + α Σ_e V_e Ψ_iso(F_e) + (1 − α) Σ_a V_a Ψ_iso(F_a),
        F_a = Σ_{e∋a} (V_e/4) F_e / V_a.

    * The nodal term alone is the averaged nodal deformation gradient tetrahedron of Bonet, Marriott & Hassan
      (2001), i.e. the node-based smoothed FEM (NS-FEM) of Liu, Nguyen-Thoi, Nguyen-Xuan & Lam (2009): strains
      are smoothed over the cell around each node, so bending no longer has to be carried by constant-strain
      elements. NS-FEM is too
      soft (it is an upper bound of the compliance where FEM is a lower bound) and has spurious low-energy
      modes — patterns whose element strains cancel in every nodal average — which in explicit dynamics are
      excited and grow into hourglass-like noise (Puso & Solberg, IJNME 67, 2006).
    * The element term with weight α gives every such mode the stiffness α K_FEM > 0 and brings the stiffness
      between the two bounds. The energy is a convex combination of two objective energies of the same
      deformation, so: a linear field (every F_e = F_a = A) is reproduced exactly (patch test, uniform
      stress); rigid rotations are stress-free; the forces are the exact gradient of Π. At small strain each
      nodal quadratic form is bounded by the element ones (Jensen: V_a ψ(ε_a) ≤ Σ_{e∋a} (V_e/4) ψ(ε_e) for
      convex ψ), so the stiffness is bounded by that of the constant-strain element and the element-size
      stable time step below still holds (measured on the paper's beam mesh split into tets: h ω_max / 2 =
      0.776 with "nodal", 0.777 with "anp"; tests/test_fem_dynamics.py checks h < 2/ω_max).
    * α = 0.3: the cantilever's tip deflection against Timoshenko's is linear in α, and the α that makes it exact
      depends on the mesh (0.25–0.33 on three grids); 0.3 roughly minimises the largest error. It was chosen for
      a bending-dominated solid a few elements thick, not taken from the αFEM literature (whose values target
      general elasticity with their own definition of α). On the bunny scene "nodal" is the closer of the two to
      the refined meshes' response. The measurements: docs/research_log.md ("The nodal tet4's α").
    * Viscoelasticity: each term keeps its own Prony history (elements: [n_prony, 3, 3, K], nodes:
      [n_prony, 3, 3, N]), weighted α and 1 − α in the stress, the stored energy and the dissipation.
    * Reported stress: the element Cauchy stress is α σ_iso(F_e) + (1 − α) × the mean of σ_iso(F_a) over the
      element's four nodes + the mean nodal pressure (the same averaging that carries the nodal stresses into
      the element forces); the solver's nodal output is, as for every element, the volume average of the
      adjacent elements' stresses.
    Cost: one more isochoric stress evaluation per node (N ≈ K/4 … K/6), one gather of F to the nodes and one
    of the nodal stresses back to the elements (and nodal Prony histories).
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
TET_DEFAULT = "nodal"   # tet4 formulation of fem.setup
TET_BLEND = 0.3         # α of the "nodal" tet4 (module docstring)


class HexGeometry(NamedTuple):
    """Reference-configuration data of hex8 elements (numpy arrays, K elements)."""

    b: np.ndarray        # [K, 8, 3] centre shape-function gradients ∂N_a/∂X
    volume: np.ndarray   # [K] exact reference volumes (2×2×2 Gauss)
    gamma: np.ndarray    # [K, 4, 8] Flanagan–Belytschko hourglass vectors
    hg_lam: tuple        # (Kuu, Kua, Kaa) projected λ-parts: [K,12,12], [K,12,9], [K,9,9]
    hg_mu: tuple         # the same for the μ-parts


class TetGeometry(NamedTuple):
    """Reference-configuration data of tet4 elements (numpy arrays, K elements, N nodes)."""

    b: np.ndarray              # [K, 4, 3] shape-function gradients ∂N_a/∂X
    volume: np.ndarray         # [K] reference volumes
    node_volume: np.ndarray    # [N] lumped reference nodal volumes V_a = Σ_{e∋a} V_e / 4
    node_elements: np.ndarray  # [N, w] elements around each node, padded with K


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
        Bm += w * (Bk.transpose(0, 2, 1) @ (np.diag(dev_m)[:, None] * Bk))      # Bᵀ D B, D diagonal
    H = np.zeros((24, 12))
    for m in range(4):
        for i in range(3):
            H[i::3, 3 * m + i] = HOURGLASS[m] / 8.0

    def project(K33):
        Kuu, Kua, Kaa = K33[:, :24, :24], K33[:, :24, 24:], K33[:, 24:, 24:]
        return H.T @ Kuu @ H, H.T @ Kua, Kaa

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
    table = incidence_table(cells, len(points))
    node_elements = np.where(table < cells.size, table % len(cells), len(cells)).astype(np.int32)
    return TetGeometry(b, volume, node_volume, node_elements)


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
