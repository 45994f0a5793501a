"""The corotational GENERIC model: the FEM's hyperelastic energy, exact under rotation, stepped by backward Euler.

A body of hex8 or tet4 elements e with rest nodal coordinates X_e (centred on the element, [n_e, 3]), volume V_e,
uniform shape-function gradients b_e [n_e, 3] and the stiffness K_e of its deviatoric response at rest. At the
state z = (q, v, σ) with u = q − X::

    F_e = I + Σ_a u_a ⊗ b_a,   F_e = R_e U_e (polar),   J_e = det F_e,   ũ_e = R_eᵀ x̄_e − X_e
    E(z) = ½ vᵀ M v + E_dev + E_vol,   dissipation α vᵀ M v ≥ 0,
    E_dev = Σ_e [V_e Ψ(F_e) + ½ ũ_eᵀ K̂_e ũ_e]  (hex8),   E_dev = β Σ_e V_e Ψ(F_e) + (1 − β) Σ_i V_i Ψ(F̄_i)  (tet4),
    E_vol = Σ_e ½ κ V_e (J_e − 1)²  (hex8),     E_vol = Σ_i ½ κ V_i (J̄_i − 1)²  (tet4),

the FEM's own energy (`fem.elements`): Ψ = C10 (Ī1 − 3) + C01 (Ī2 − 3) Mooney–Rivlin's isochoric energy
(`isochoric_energy`) and (J − 1)²/D1 its volumetric one (κ = 2/D1), exact at any strain, so a nearly incompressible
body keeps its volume and a deep press stiffens as the material does. A hex8 is the FEM's one-point element: Ψ of
its centre's F_e, and its hourglass control K̂_e = K_e − K_e¹ (`one_point_stiffness`: the part of the rest stiffness
beyond the one-point response, which no linear field excites) acting on its displacement in its own rotated frame,
x̄_e the element's current nodal coordinates centred on it (the corotational formulation: a rigidly turned body
stores no energy and feels no force, however far it turns). A tet4 is the FEM's nodal tet4: Ψ shared between the
elements (weight β) and the nodes' averaged deformation gradients F̄_i = Σ_{e∋i} (V_e / 4V_i) F_e, and the volume
change averaged to the nodes, J̄_i − 1 = Σ_{e∋i} (V_e / 4V_i)(J_e − 1) with V_i = Σ_{e∋i} V_e / 4 (a linear tet holds
one volume constraint per element, more than a nearly incompressible mesh has degrees of freedom to meet: it
locks). M = diag(m_i) are lumped masses and α the mass damping. At a fixed temperature GENERIC's L∇E + M∇S reduces
to M v̇ = f − ∂E/∂q − α M v (L the canonical coupling of q and v, M ≥ 0 the mass damping).

One frame Δt = h is one linearised backward-Euler step for v', whose operator K_R is the deviatoric stiffness at
rest turned with the body (R_e K_e R_eᵀ per element, on tets β K_e and the nodes' 2 (1 − β) μ V_i dev sym turned
by R̄_i, μ = 2 (C10 + C01)) and the volumetric term's Gauss–Newton tangent K_J (κ V g gᵀ with g = ∂J/∂x = cof(F) b
per element, or per node κ V_i ḡ_i ḡ_iᵀ with ḡ_i the average of g_e like J̄_i): a quasi-Newton step whose forces
f_int are exact, so a held load settles where the FEM's does::

    [(1 + αh)/h² M + K_R + K_J] v' = M v / h² + (f − f_int(q)) / h,   q' = q + h v',

solved by at least ``cg_iterations`` conjugate-gradient iterations from v' = v (up to ``cg_max_iterations`` while
the residual is large: `CorotationalConfig`), preconditioned with an approximate inverse of the rest operator
turned with the body, R P₀ Rᵀ (R each node's rotation: for hexes the polar factor of the mean of its elements' R_e,
for tets R̄_i, the polar factor of F̄_i, which the tangent's nodal part reads too). With
A₀ = (1 + αh)/h² M + K₀ the FEM's rest operator (sparse) and Φ [3N, m] its m lowest eigenvectors (A₀ Φ = Φ Λ,
ΦᵀΦ = I, computed once when the model is prepared)::

    P₀ = Φ Λ⁻¹ Φᵀ + (I − ΦΦᵀ) B⁻¹ (I − ΦΦᵀ),   B = D + κ Gᵀ W G,

exact on the slow, global modes a fingertip excites (bending, twisting), and on the rest B, A₀'s local part: D the
3 × 3 node blocks of A₀ without its volumetric stiffness and κ Gᵀ W G that stiffness whole (G [C, 3N] the volume
constraints' gradients, one per hex or per tet node), inverted by Woodbury through the dense Schur complement
S = (κW)⁻¹ + G D⁻¹ Gᵀ [C, C] (`schur_preconditioner`; a two-level preconditioner, symmetric positive definite).
A nearly incompressible body's volumetric stiffness is far larger than the rest of A₀: block-Jacobi alone (B = the
node blocks of A₀) is then slow on every mode it dwarfs, and a few modes cannot cover them under a patch press;
with B⁻¹ exact on it, a few iterations are enough (docs/research_log.md). S⁻¹ holds C² numbers: past
``schur_limit`` constraints B is A₀'s node blocks (3N(m + 3) numbers, no N × N operator, O(Nm) a product).

The stress observable σ' = σ_iso(F_e) + κ (J_e − 1 + g_e · Δu_e) I, averaged to the nodes by volume (σ_iso the
isochoric Cauchy stress of Ψ, the centre's as the FEM reports it; for tets the FEM's nodal tet4 blend, the average
J̄'s): the pressure is the step's own linearised one. Taken from J_e(q') it would carry the O(Δθ²) volume change
a linearised step makes when the body turns by Δθ, which times the bulk modulus of a nearly incompressible solid is
of the size of the stress itself (see docs/research_log.md).

Energy never created, by construction: with W = f · (q' − q) the work of the frame's forces, the step keeps E(z') ≤ E(z)
+ W (up to the float32 round-off of the energies, ``ROUNDOFF`` of |E(z)| + |W|). The frame's displacement is taken as θ
h v' with θ the longest of 1, ½, …, 1/32, 0 whose potential energy fits that budget (θ = 1 unless the body turns fast,
e.g. released from a large deformation: a linearised step moves nodes along straight lines, which stretches turning
elements); v' is then scaled down to the budget left (an extra dissipation: M ≥ 0 still). θ = 0 always fits. A frame
whose step had to be shortened is stepped again from its start with the step linearised about the first one's end
(a Newton iteration of the backward-Euler equations: rotations and volume gradients taken there), and if that one
falls short too, as four steps of Δt/4, each kept within its own budget (`frame`). Clamped nodes (node_type ≠ 0)
keep q and v.

Bodies in contact are stepped together (`joint_frame`): one frame of all of them, a penalty energy E_c of their
surfaces' node pairs added to the potential (`tignn_jax.simulators.contact`), its Gauss–Newton stiffness H_c in
the one CG solve of all the bodies' velocities, and one energy budget, E(z') + E_c(q') ≤ E(z) + E_c(q) + W, for all
of them. Each body is preconditioned by its own turned rest operator, except on the slow modes: those of all the
bodies are solved together, with the contact coupling them, E = diag(Λ_b) + Vᵀ H_c V (V = R Φ, each body's
modes turned with it; `tignn_jax.simulators.contact.coarse_stiffness`), for B pressed onto A bends both at
once, a mode neither body's own has.

Made from the FEM's own element operators (`from_fem`): not learned. Accuracy against the FEM at loads past the
training range: ``benchmarks/large_deformation.py``; in contact: ``benchmarks/contact_beams.py``.
"""
from __future__ import annotations

import dataclasses
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fem.material import cofactor3, cofactor3_rows, det3, matmul3, trace3, transpose3
from fem.solver import _polar_rotation as polar
from fem.solver import _sum_over as _sum
from tignn_jax.simulators import contact as C
from tignn_jax.simulators import linear as LG

STORED = ("cells", "ke", "b", "volume", "kappa", "mass", "alpha", "dt", "mu_nodes", "mooney_rivlin")
BACKTRACK = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125, 0.0)   # the step lengths of the frame's line search
SPLIT = 4   # steps a frame is split into where one step would have to be shortened (`frame`)
ROUNDOFF = 2.0 ** -17   # relative round-off allowed in the energy budget E(z') ≤ E(z) + W (about 16 float32 ulps)
RETRIES = 2   # steps taken again with new contact candidates before a step is held (`joint_frame`)
J_FLOOR = 0.5   # the isochoric energy's J is held at this floor below it (`isochoric_energy`)
POLAR_ITERATIONS = 5   # Higham's iteration R ← (R + R⁻ᵀ)/2: quadratic, exact at once for a rigid motion
_VOIGT = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))   # the data's stress order S11 S22 S33 S12 S13 S23


class CorotationalConfig(NamedTuple):
    """How the corotational step solves its frame.

    Attributes:
      cg_iterations: conjugate-gradient iterations every frame's linear solve makes (preconditioned by the turned
        rest operator's approximate inverse, module docstring).
      cg_max_iterations: the most iterations a frame may make: past ``cg_iterations`` the solve goes on while the
        preconditioned residual rᵀP r is above ``cg_tolerance``² times the right-hand side's bᵀA⁻¹b (a state far
        from the rest operator's, e.g. a noisy or fast-turning one, needs more than the few iterations a smooth
        frame does).
      cg_tolerance: that relative residual.
      schur_limit: the most volume constraints C (hex elements, or tet nodes) for which the preconditioner
        eliminates the volumetric stiffness through its dense Schur complement, S⁻¹ [C, C] (`schur_preconditioner`:
        C² numbers, and C² products an iteration); a larger mesh gets A₀'s node blocks there (`rest_preconditioner`).
        Past it the dense products outweigh the rest of the frame (docs/research_log.md).
      modes: m, the rest operator's lowest eigenmodes the two-level preconditioner inverts exactly (all of them on a
        mesh with at most m free degrees of freedom, where it is A₀⁻¹).
    """
    cg_iterations: int = 3
    cg_max_iterations: int = 12
    cg_tolerance: float = 1e-2
    schur_limit: int = 2048
    modes: int = 32


@dataclasses.dataclass(frozen=True)
class CorotationalGeneric:
    """The corotational GENERIC model class (module docstring).

    Stored arrays (``stored``), n_e = 8 (hex8) or 4 (tet4): ``cells`` [K, n_e] int32; ``ke`` [K, 3n_e, 3n_e]
    (deviatoric element stiffness at rest, force per length, rows and columns 3a + i for node a, component i);
    ``b`` [K, n_e, 3] (uniform shape-function gradients, 1/length); ``volume`` [K]; ``mu_nodes`` [1] (μ̄ = (1 − β) μ,
    the nodes' share of the shear modulus: 0 for hexes; a model file without it has none); ``mooney_rivlin`` [2]
    (C10, C01, stress: the isochoric energy); ``kappa`` [1] (bulk modulus, stress); ``mass`` [N]; ``alpha`` [1]
    (1/time); ``dt`` [1] (the frame step).
    """
    config: CorotationalConfig = CorotationalConfig()
    name: ClassVar[str] = "corotational"
    stable_by_construction: ClassVar[bool] = True   # no step creates energy: guard for finiteness only

    def prepare(self, stored: dict, mesh: dict) -> dict:
        """The arrays the step reads: the stored ones; the centred rest element coordinates ``x0e`` [K, n_e, 3]
        and the averaging weights ``wnode`` [K, n_e] (V_e over the volume of the node's elements); for hexes the
        hourglass control ``khg`` [K, 24, 24] (``ke`` less `one_point_stiffness`); all element arrays again in the
        step's element-last layout (`element_last`); for tets the nodes' star stencils ``star``, ``star_c``,
        ``star_ct`` and volumes ``vnode`` (`node_stars`); the preconditioner's ``modes``, ``mode_inv`` and
        ``block_inv`` (`rest_preconditioner`), with ``block_inv`` replaced and ``schur_inv`` added by
        `schur_preconditioner` up to ``schur_limit`` volume constraints; ``q0`` and the free-node mask ``free``
        [N, 1].

        Raises:
          ValueError: an array is missing or sized for another mesh, ``mooney_rivlin`` is missing or not positive
            (a model file made before the model took Mooney–Rivlin's energy), or the CG options are out of
            range.
        """
        c = self.config
        if not (isinstance(c.cg_iterations, (int, np.integer)) and c.cg_iterations >= 1):
            raise ValueError(f"cg_iterations must be a positive integer, got {c.cg_iterations!r}")
        if not (isinstance(c.cg_max_iterations, (int, np.integer)) and c.cg_max_iterations >= c.cg_iterations):
            raise ValueError(f"cg_max_iterations must be an integer >= cg_iterations ({c.cg_iterations}), "
                             f"got {c.cg_max_iterations!r}")
        if not (isinstance(c.cg_tolerance, (int, float, np.floating)) and 0.0 < c.cg_tolerance < 1.0):
            raise ValueError(f"cg_tolerance must be a number in (0, 1), got {c.cg_tolerance!r}")
        if not (isinstance(c.modes, (int, np.integer)) and c.modes >= 1):
            raise ValueError(f"modes must be a positive integer, got {c.modes!r}")
        if not (isinstance(c.schur_limit, (int, np.integer)) and c.schur_limit >= 0):
            raise ValueError(f"schur_limit must be a non-negative integer, got {c.schur_limit!r}")
        stored = {"mu_nodes": np.zeros(1, np.float32), "mooney_rivlin": np.zeros(2, np.float32), **stored}
        missing = [k for k in STORED if k not in stored]
        if missing:
            raise ValueError(f"a corotational model needs the arrays {list(STORED)}, missing {missing}")
        out = {k: np.asarray(stored[k]) for k in STORED}
        out["cells"] = out["cells"].astype(np.int32)
        node_type = np.asarray(mesh["node_type"])
        q0 = np.asarray(mesh["q0"], np.float64)
        n, (k, per) = len(node_type), out["cells"].shape
        if out["mass"].shape != (n,):
            raise ValueError(f"the operators are for {out['mass'].shape[0]} nodes, the mesh has {n}")
        if out["cells"].max() >= n or out["ke"].shape != (k, 3 * per, 3 * per) or out["b"].shape != (k, per, 3):
            raise ValueError(f"cells, ke and b do not describe {k} elements of {per} nodes on {n} nodes")
        mr = np.asarray(out["mooney_rivlin"], np.float64).reshape(-1)
        if not (mr.shape == (2,) and mr.sum() > 0.0 and 0.0 <= out["mu_nodes"].reshape(-1)[0] <= 2.0 * mr.sum()):
            raise ValueError(f"a corotational model needs mooney_rivlin = (C10, C01) with C10 + C01 > 0 and mu_nodes "
                             f"at most 2 (C10 + C01), got mooney_rivlin {mr.tolist()} and mu_nodes "
                             f"{out['mu_nodes'].reshape(-1).tolist()} (a model file made before the model took "
                             f"Mooney–Rivlin's energy: make it again with from_fem)")
        xe = q0[out["cells"]]
        out["x0e"] = (xe - xe.mean(axis=1, keepdims=True)).astype(np.float32)
        share = np.repeat(out["volume"], per)
        total = np.bincount(out["cells"].reshape(-1), share, minlength=n)
        out["wnode"] = (share / total[out["cells"].reshape(-1)]).reshape(k, per).astype(np.float32)
        if per == 8:   # the hexes' stiffness beyond their one-point isochoric response: the hourglass control
            out["khg"] = np.asarray(out["ke"], np.float64) - one_point_stiffness(out["b"], out["volume"],
                                                                                 2.0 * mr.sum())
        out.update(element_last(out))
        out.update(node_stars(out["cells"], out["wnode"], out["b"], out["volume"], n))
        out["q0"] = q0.astype(np.float32)
        out.update(rest_preconditioner(rest_operator(out, node_type), node_type, int(c.modes), q0))
        if (n if per == 4 else k) <= c.schur_limit:
            out.update(schur_preconditioner(out, node_type))
        out["free"] = (node_type == 0)[:, None].astype(np.float32)
        for key in ("ke", "b", "volume", "kappa", "mass", "alpha", "dt", "mu_nodes", "mooney_rivlin"):
            out[key] = out[key].astype(np.float32)
        return jax.tree_util.tree_map(jnp.asarray, out)

    def stored(self, arrays: dict) -> dict:
        """The arrays a model file keeps (``STORED``); the preconditioner is derived when loading."""
        return {k: np.asarray(arrays[k]) for k in STORED}

    def step_state(self, arrays: dict, z, f):
        """One frame of one body: z [N, 12], f [N, 3] (force, constant over the frame) → z' [N, 12]."""
        return frame(arrays, z, f.astype(z.dtype), self.config)

    def step_together(self, arrays: tuple, zs: tuple, fs: tuple, contact) -> tuple:
        """One frame of several bodies of this class solved together, with their penalty contact inside the
        frame (`joint_frame`; ``contact`` a `tignn_jax.simulators.contact.Contact`): tuples of z [N_b, 12] and
        f [N_b, 3], one arrays dict per body, → the bodies' z'."""
        return joint_frame(tuple(arrays), tuple(zs), tuple(fs), self.config, contact)

    def diagnostics(self, arrays: dict, z, f, z_next) -> dict:
        """The energy balance of one frame z → z_next under f: {"energy": E(z_next), "work": W = f · Δq over the
        free nodes, "dissipation": D = W − (E(z_next) − E(z))}, work units; D ≥ 0 by construction."""
        return LG.energy_balance(energy, arrays, z, f, z_next)


def from_fem(problem, material, frame_dt: float | None = None) -> dict:
    """Stored arrays (`CorotationalGeneric.stored`) of an elastic hex8 or tet4 FEM scene: each element's deviatoric
    stiffness at rest (the FEM's own, hourglass control included, by forward differentiation of its internal force,
    all elements at once), shape-function gradients and volumes, the bulk modulus
    2/D1, the Mooney–Rivlin constants (C10, C01), the lumped masses and mass damping of ``problem``.

    Args:
      problem: a `fem.solver.Problem` (hex8 or tet4; its clamps, masses and damping are the model's). A tet4
        element's stiffness is the linear tet's (the FEM's nodal tet4 on a lone element).
      material: its `fem.material.Material` (elastic: no Prony terms).
      frame_dt: the frame step Δt (default: the problem's frame).

    Raises:
      ValueError: the material is viscoelastic.
    """
    from fem import elements as el
    from fem import implicit
    from fem import solver as sv

    cfg = problem.config
    if material.n_prony:
        raise ValueError("the corotational model is elastic: the material has Prony terms")
    points = np.asarray(problem.arrays.points, np.float64)
    cells = np.asarray(problem.arrays.cells)
    k, per = cells.shape
    # every element on its own nodes: one forward derivative per element degree of freedom gives that column of
    # every element's stiffness at once
    alone = sv.setup(points[cells].reshape(-1, 3), np.arange(k * per).reshape(k, per), material=material,
                     frame_dt=cfg.frame_dt, n_frames=1, cell_type=cfg.cell_type)
    force, _ = implicit.force_and_stress(alone, material)
    u0 = jnp.zeros((k * per, 3), alone.arrays.points.dtype)
    column = jax.jit(lambda d: jax.jvp(force, (u0,), (d,))[1])
    kc = []
    for a in range(per):
        for i in range(3):
            d = np.zeros((k, per, 3))
            d[:, a, i] = 1.0
            fk = column(jnp.asarray(d.reshape(-1, 3), u0.dtype))
            kc.append(np.asarray(fk, np.float64).reshape(k, 3 * per))
    ke = np.stack(kc, -1)
    ke = 0.5 * (ke + ke.transpose(0, 2, 1))
    geo = el.hex_geometry(points, cells) if per == 8 else el.tet_geometry(points, cells)
    kappa = 2.0 / float(material.d1)
    bf = geo.b.reshape(k, -1)
    ke -= (kappa * geo.volume)[:, None, None] * bf[:, :, None] * bf[:, None, :]   # the volumetric part is in J
    # a nodal tet4 shares its isochoric energy: weight β per element, 1 − β on the nodes' averaged F
    beta = cfg.tet_blend if (per == 4 and cfg.tet_formulation == "nodal") else 1.0
    mu_nodes = (1.0 - beta) * 2.0 * (float(material.c10) + float(material.c01))
    mass = np.asarray(sv.lumped_mass(problem, material), np.float64)
    h = float(cfg.frame_dt if frame_dt is None else frame_dt)
    return {"cells": cells.astype(np.int32), "ke": (beta * ke).astype(np.float32),
            "b": geo.b.astype(np.float32),
            "volume": geo.volume.astype(np.float32), "kappa": np.array([kappa], np.float32),
            "mass": mass.astype(np.float32), "alpha": np.array([float(problem.arrays.damping_alpha)], np.float32),
            "dt": np.array([h], np.float32), "mu_nodes": np.array([mu_nodes], np.float32),
            "mooney_rivlin": np.array([float(material.c10), float(material.c01)], np.float32)}


def element_last(stored: dict) -> dict:
    """The step's layouts of the element arrays, components first and elements last: ``cells_t`` [n_e, K],
    ``b_t`` and ``x0e_t`` [3, n_e, K], the stiffness as ``ke_f`` [K, 24, 24] for hexes (elements first: applied by
    one batched product, faster on a CPU than element-last multiply-adds) or ``ke_t`` [12, 12, K] for
    tets (element-last multiply-adds, faster than the batched product at that size), with rows and columns n_e i + a
    (component i of node a), the hexes' hourglass part ``khg`` as ``khg_f`` [K, 24, 24] likewise, and ``wnode_t``
    [n_e, K]."""
    cells = np.asarray(stored["cells"]).astype(np.int32)
    k, per = cells.shape

    def layout(x):
        return np.asarray(x, np.float32).reshape(k, per, 3, per, 3).transpose(0, 2, 1, 4, 3).reshape(k, 3 * per, -1)

    ke = layout(stored["ke"])
    stiffness = ({"ke_f": np.ascontiguousarray(ke)} if per == 8
                 else {"ke_t": np.ascontiguousarray(ke.transpose(1, 2, 0))})
    if "khg" in stored:
        stiffness["khg_f"] = np.ascontiguousarray(layout(stored["khg"]))
    return {**stiffness, "cells_t": np.ascontiguousarray(cells.T),
            "b_t": np.ascontiguousarray(np.asarray(stored["b"], np.float32).transpose(2, 1, 0)),
            "x0e_t": np.ascontiguousarray(np.asarray(stored["x0e"], np.float32).transpose(2, 1, 0)),
            "wnode_t": np.ascontiguousarray(np.asarray(stored["wnode"], np.float32).T)}


def one_point_stiffness(b, volume, mu):
    """[K, 3n_e, 3n_e] float64: the stiffness at rest of the isochoric energy V_e Ψ(F_e) of each element's one-point
    deformation gradient, V_e μ [δ_ik (b_a · b_c) + b_ak b_ci − ⅔ b_ai b_ck] for rows 3a + i and columns 3c + k
    (Ψ ≈ μ |dev sym(F − I)|² at small strain, μ = 2 (C10 + C01) the shear modulus)."""
    b = np.asarray(b, np.float64)
    k, per, _ = b.shape
    eye = np.eye(3)
    K = (np.einsum("ik,eaj,ecj->eaick", eye, b, b) + np.einsum("eak,eci->eaick", b, b)
         - 2.0 / 3.0 * np.einsum("eai,eck->eaick", b, b))
    return (float(mu) * np.asarray(volume, np.float64)[:, None, None, None, None] * K).reshape(k, 3 * per, 3 * per)


def node_stars(cells, wnode, b, volume, n: int) -> dict:
    """The nodes' averaged displacement gradient as a stencil over each node's star (the nodes it shares an
    element with, itself included): F̄_i − I = Σ_{e∋i} w_ei Σ_a u_{e,a} ⊗ b_ea = Σ_s u_{star[i, s]} ⊗ c_is, with
    c_ij = Σ_{e∋i,j} w_ei b_e(j) (tets; w = ``wnode``). The star relation is symmetric, so the transposed product
    Σ_i s_i c_ij (`constraints_transpose`: Gᵀ s for nodal constraint values s_i) reads the same lists with
    ``star_ct``: ct_js = c_{star[j, s], j}. Lists are padded to the longest with the node itself and zero coefficients.

    Returns:
      {"star": [N, S] int32, "star_c" and "star_ct": [3, N, S] float32, "vnode": V_i = Σ_{e∋i} V_e / 4 [N]
      float32}; {} for hexes (no nodal terms).
    """
    cells = np.asarray(cells).astype(np.int64)
    k, per = cells.shape
    if per != 4:
        return {}
    i = np.repeat(cells, per, axis=1).ravel()
    j = np.tile(cells, (1, per)).ravel()
    coef = (np.asarray(wnode, np.float64)[:, :, None, None] * np.asarray(b, np.float64)[:, None]).reshape(-1, 3)
    keys, inverse = np.unique(i * n + j, return_inverse=True)
    c = np.zeros((len(keys), 3))
    np.add.at(c, inverse, coef)
    ii, jj = keys // n, keys % n
    degree = np.bincount(ii, minlength=n)
    slot = np.arange(len(keys)) - np.concatenate([[0], np.cumsum(degree)])[ii]
    star = np.tile(np.arange(n)[:, None], (1, degree.max()))
    star[ii, slot] = jj
    cs, cts = np.zeros(star.shape + (3,)), np.zeros(star.shape + (3,))
    cs[ii, slot] = c
    # ct_{j, s} = c_{star[j, s], j}: the pair (i, j) sits in i's list at slot, and (j, i) in j's list at slot_t
    slot_t = slot[np.searchsorted(keys, jj * n + ii)]
    cts[jj, slot_t] = c
    vnode = np.bincount(cells.ravel(), np.repeat(np.asarray(volume, np.float64) / per, per), minlength=n)
    return {"star": star.astype(np.int32), "star_c": np.ascontiguousarray(cs.transpose(2, 0, 1), np.float32),
            "star_ct": np.ascontiguousarray(cts.transpose(2, 0, 1), np.float32), "vnode": vnode.astype(np.float32)}


def rest_operator(stored: dict, node_type):
    """A₀ = (1 + αΔt)/Δt² M + K₀, a `scipy.sparse.csr_matrix` [3N, 3N] float64, K₀ = Σ_e K_e + the volumetric
    stiffness at rest (κ V_e b_e b_eᵀ per hex; per node of a tet mesh κ V_i ḡ_i ḡ_iᵀ and the nodes' deviatoric
    share), identity on the clamped nodes' rows and columns; row 3a + i is component i of node a. For tets
    ``stored`` needs the star stencils of `node_stars` (`CorotationalGeneric.prepare`). Assembled sparse."""
    import scipy.sparse as sparse

    cells = np.asarray(stored["cells"]).astype(np.int64)
    n = len(np.asarray(node_type))
    k, per = cells.shape
    b = np.asarray(stored["b"], np.float64).reshape(k, -1)
    kappa = float(np.asarray(stored["kappa"]).reshape(-1)[0])
    volume = np.asarray(stored["volume"], np.float64)
    dof = (3 * cells[:, :, None] + np.arange(3)).reshape(k, -1)
    ke = np.asarray(stored["ke"], np.float64)
    if per == 8:
        ke = ke + (kappa * volume)[:, None, None] * b[:, :, None] * b[:, None, :]
    rows, cols = np.broadcast_arrays(dof[:, :, None], dof[:, None, :])
    K = sparse.coo_matrix((ke.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n)).tocsr()
    if per == 4:      # the nodes' volumetric and deviatoric stiffness at rest
        K = K + _nodal_rest_stiffness(stored, n)
    h = float(np.asarray(stored["dt"]).reshape(-1)[0])
    alpha = float(np.asarray(stored["alpha"]).reshape(-1)[0])
    mass = np.repeat(np.asarray(stored["mass"], np.float64), 3)
    free = np.repeat(np.asarray(node_type) == 0, 3).astype(np.float64)
    keep = sparse.diags(free)
    return (keep @ (K + sparse.diags((1.0 + alpha * h) / h ** 2 * mass)) @ keep + sparse.diags(1.0 - free)).tocsr()


def rest_preconditioner(A, node_type, modes: int, points=None) -> dict:
    """The arrays of P₀ = Φ Λ⁻¹ Φᵀ + (I − ΦΦᵀ) B⁻¹ (I − ΦΦᵀ) (module docstring) for the rest operator A
    (`rest_operator`): its ``modes`` lowest eigenpairs on the free degrees of freedom, by shift-invert Lanczos
    (`scipy.sparse.linalg.eigsh` about 0, with a sparse LU factor of A ordered by `nested_dissection` where the
    node positions are given; dense on small meshes), and the inverses of its 3 × 3 node blocks.

    Args:
      A: the rest operator [3N, 3N] (sparse or dense, symmetric positive definite on the free nodes).
      node_type: [N] (0 free; the clamped nodes' rows of every array are 0).
      modes: m, at most the number of free degrees of freedom used.
      points: [N, 3] the nodes' rest positions, for the factor's ordering (None: SuperLU's column ordering, whose
        factor of a large mesh fills more: docs/research_log.md, "Building the corotational model of a large mesh").

    Returns:
      {"modes": Φ [3N, m], "mode_inv": 1/λ [m], "block_inv": B⁻¹ [N, 3, 3]}, float32.
    """
    import scipy.sparse as sparse
    from scipy.sparse.linalg import LinearOperator, eigsh, splu

    A = sparse.csr_matrix(A)
    n = len(np.asarray(node_type))
    free_nodes = np.flatnonzero(np.asarray(node_type) == 0)
    free = np.repeat(np.asarray(node_type) == 0, 3)
    af = A[free][:, free]
    m = min(int(modes), af.shape[0])
    if af.shape[0] <= max(4 * m, 600):
        lam, vec = np.linalg.eigh(af.toarray())
        lam, vec = lam[:m], vec[:, :m]
    else:
        inverse = None
        if points is not None:     # A⁻¹ by an LU factor in nested-dissection order, for the shift-invert
            coo = af.tocoo()
            graph = sparse.csr_matrix((np.ones(coo.nnz), (coo.row // 3, coo.col // 3)), shape=(len(free_nodes),) * 2)
            nodes = nested_dissection(np.asarray(points, np.float64)[free_nodes], graph)
            perm = (3 * nodes[:, None] + np.arange(3)).ravel()
            back = np.argsort(perm)
            lu = splu(sparse.csc_matrix(af[perm][:, perm]), permc_spec="NATURAL", options={"SymmetricMode": True})
            inverse = LinearOperator(af.shape, matvec=lambda b: lu.solve(np.ascontiguousarray(b[perm]))[back],
                                     dtype=af.dtype)
        lam, vec = eigsh(af.tocsc(), k=m, sigma=0.0, which="LM", v0=np.ones(af.shape[0]), OPinv=inverse)
        order = np.argsort(lam)
        lam, vec = lam[order], vec[:, order]
    phi = np.zeros((3 * n, m))
    phi[free] = vec
    return {"modes": phi.astype(np.float32), "mode_inv": (1.0 / lam).astype(np.float32),
            "block_inv": block_inverse(A, node_type).astype(np.float32)}


def nested_dissection(points, graph, leaf: int = 64) -> np.ndarray:
    """A fill-reducing elimination order of a mesh's nodes: the nodes split at the median of their longest extent,
    each half ordered the same way, recursively, and the separator (the nodes of the upper half joined by an edge
    to the lower half) last, so a sparse factor's fill stays within the separators' dense blocks.

    Args:
      points: [N, 3] node positions.
      graph: [N, N] sparse matrix whose non-zeros are the node pairs that share an entry (the operator's pattern).
      leaf: parts of at most this many nodes are kept in their order.

    Returns:
      [N] int, a permutation of the nodes.
    """
    import scipy.sparse as sparse

    graph = sparse.csr_matrix(graph)
    points = np.asarray(points, np.float64)
    parts = []

    def split(nodes):
        lower = None
        if len(nodes) > leaf:
            x = points[nodes]
            axis = int(np.argmax(x.max(axis=0) - x.min(axis=0)))
            lower = x[:, axis] < np.median(x[:, axis])
        if lower is None or lower.all() or not lower.any():   # a leaf, or no split along the longest extent
            parts.append(nodes)
            return
        below = np.zeros(graph.shape[0], bool)
        below[nodes[lower]] = True
        upper = nodes[~lower]
        rows = graph[upper]
        touches = np.zeros(len(upper), bool)
        np.logical_or.at(touches, np.repeat(np.arange(len(upper)), np.diff(rows.indptr)), below[rows.indices])
        split(nodes[lower])
        split(upper[~touches])
        parts.append(upper[touches])

    split(np.arange(graph.shape[0]))
    return np.concatenate(parts).astype(np.int64)


def block_inverse(A, node_type):
    """[N, 3, 3] float64: the inverses of the 3 × 3 node blocks of A [3N, 3N] (sparse), 0 on the clamped nodes."""
    import scipy.sparse as sparse

    coo = sparse.coo_matrix(A)
    same = coo.row // 3 == coo.col // 3
    blocks = np.zeros((len(np.asarray(node_type)), 3, 3))
    np.add.at(blocks, (coo.row[same] // 3, coo.row[same] % 3, coo.col[same] % 3), coo.data[same])
    return np.linalg.inv(blocks) * (np.asarray(node_type) == 0)[:, None, None]


def apply_rest_preconditioner(arrays: dict, r, modal=None):
    """P₀ r (`rest_preconditioner`) for a flat [3N] r, in the rest frame, with B⁻¹ replaced by
    `schur_preconditioner`'s (D + κ Gᵀ W G)⁻¹ where the arrays hold ``schur_inv``; ``modal``, where given, is
    (Φᵀ r [m], the coefficients [m] that replace the slow modes' Λ⁻¹ Φᵀ r), computed by the caller (bodies in
    contact: `_step`'s coarse solve of all of them)."""
    phi = arrays["modes"].astype(r.dtype)
    c, c_coarse = (r @ phi, None) if modal is None else modal
    c_coarse = c * arrays["mode_inv"].astype(r.dtype) if c_coarse is None else c_coarse
    binv = arrays["block_inv"].astype(r.dtype)
    n = binv.shape[0]
    y = jnp.einsum("nij,nj->ni", binv, (r - phi @ c).reshape(n, 3))
    if "schur_inv" in arrays:     # B⁻¹ → (D + κ Gᵀ W G)⁻¹ by Woodbury
        s = arrays["schur_inv"].astype(r.dtype) @ constraints(arrays, y)
        y = y - jnp.einsum("nij,nj->ni", binv, constraints_transpose(arrays, s, n))
    y = y.reshape(-1)
    return phi @ c_coarse + y - phi @ (y @ phi)


def constraint_operator(stored: dict, node_type):
    """(G, W): the volume constraints' rest gradients G [C, 3N] (`scipy.sparse.csr_matrix`, float64; zero columns
    on the clamped nodes) and weights W [C], with which the rest operator's volumetric stiffness is κ Gᵀ diag(W) G:
    per hex row e = b_e (J_e − 1 ≈ Σ_a b_ea · u_a) and W_e = V_e; per tet node row i = the star stencil c_i
    (J̄_i − 1 ≈ Σ_s c_is · u_star[i, s], `node_stars`) and W_i = V_i. Row 3a + i of u is component i of node a."""
    import scipy.sparse as sparse

    n = len(np.asarray(node_type))
    free = np.repeat(np.asarray(node_type) == 0, 3).astype(np.float64)
    cells = np.asarray(stored["cells"]).astype(np.int64)
    if cells.shape[1] == 4:
        nodes, weight = np.asarray(stored["star"]).astype(np.int64), np.asarray(stored["vnode"], np.float64)
        coef = np.asarray(stored["star_c"], np.float64).transpose(1, 2, 0)            # [N, S, 3]
    else:
        nodes, weight = cells, np.asarray(stored["volume"], np.float64)
        coef = np.asarray(stored["b"], np.float64)                                     # [K, 8, 3]
    rows = np.broadcast_to(np.arange(len(nodes))[:, None, None], coef.shape)
    cols = 3 * nodes[:, :, None] + np.arange(3)
    G = sparse.csr_matrix((coef.ravel(), (rows.ravel(), cols.ravel())), shape=(len(nodes), 3 * n))
    return (G @ sparse.diags(free)).tocsr(), weight


def schur_preconditioner(stored: dict, node_type) -> dict:
    """The arrays of P₀ = (D + κ Gᵀ W G)⁻¹ = D⁻¹ − D⁻¹ Gᵀ S⁻¹ G D⁻¹, S = (κ W)⁻¹ + G D⁻¹ Gᵀ (Woodbury), with D
    the 3 × 3 node blocks of the rest operator without its volumetric stiffness (`rest_operator` at κ = 0) and
    κ Gᵀ W G that stiffness (`constraint_operator`).

    The volumetric stiffness of a nearly incompressible body is far larger than the rest of A₀ and of rank C (one
    per constraint): block-Jacobi on A₀ then converges only as slowly as the deviatoric modes it dwarfs, and a few
    eigenmodes do not cover them (a patch press excites local ones). P₀ inverts that stiffness exactly, with the
    deviatoric and inertial part by its node blocks, so the CG needs a few iterations whatever κ / μ
    (docs/research_log.md). S is dense [C, C]: C² numbers, C = elements (hex8) or nodes (tet4).

    Args:
      stored: the model's arrays, with `node_stars`'s for tets (`CorotationalGeneric.prepare`).
      node_type: [N] (0 free; the clamped nodes' blocks are 0).

    Returns:
      {"block_inv": D⁻¹ [N, 3, 3], "schur_inv": S⁻¹ [C, C]}, float32.
    """
    import scipy.sparse as sparse

    block_inv = block_inverse(rest_operator({**stored, "kappa": np.zeros(1)}, node_type), node_type)
    G, weight = constraint_operator(stored, node_type)
    kappa = float(np.asarray(stored["kappa"]).reshape(-1)[0])
    S = (G @ sparse.block_diag(list(block_inv), format="csr") @ G.T).toarray() + np.diag(1.0 / (kappa * weight))
    return {"block_inv": block_inv.astype(np.float32), "schur_inv": np.linalg.inv(S).astype(np.float32)}


def constraints(arrays: dict, y):
    """G y [C] for nodal vectors y [N, 3] (`constraint_operator`, at rest)."""
    if _nodal(arrays):
        ys = y.T[:, arrays["star"]]                                              # [3, N, S]
        return jnp.sum(ys * arrays["star_c"].astype(y.dtype), axis=(0, 2))
    return jnp.sum(_gather(arrays, y) * arrays["b_t"].astype(y.dtype), axis=(0, 1))


def constraints_transpose(arrays: dict, s, n: int):
    """Gᵀ s [N, 3] for constraint values s [C] (`constraint_operator`, at rest)."""
    if _nodal(arrays):
        return jnp.sum(s[arrays["star"]][None] * arrays["star_ct"].astype(s.dtype), axis=-1).T
    return _assemble(arrays, arrays["b_t"].astype(s.dtype) * s[None, None], n)


def _nodal_rest_stiffness(stored: dict, n: int):
    """[3N, 3N] `scipy.sparse.csr_matrix`: the tangent at rest of the tet nodes' energies, Ḡᵀ D Ḡ with Ḡ the
    stencil of `node_stars` (dF̄_i = Ḡ_i u) and D_i = 2 μ̄ V_i (dev sym) + κ V_i vec(I) vec(I)ᵀ (at rest R̄ = I and
    J̄_i − 1 = tr dF̄_i to first order)."""
    import scipy.sparse as sparse

    star = np.asarray(stored["star"]).astype(np.int64)
    c = np.asarray(stored["star_c"], np.float64)                       # [3, N, S]
    stars = star.shape[1]
    node, s, a, b = np.meshgrid(np.arange(n), np.arange(stars), np.arange(3), np.arange(3), indexing="ij")
    rows = 9 * node + 3 * a + b
    cols = 3 * star[node, s] + a
    G = sparse.csr_matrix((c[b, node, s].ravel(), (rows.ravel(), cols.ravel())), shape=(9 * n, 3 * n))
    eye = np.eye(3).reshape(9)
    swap = np.eye(9).reshape(3, 3, 9).transpose(1, 0, 2).reshape(9, 9)     # vec(H) → vec(Hᵀ)
    dev_sym = 0.5 * (np.eye(9) + swap) - np.outer(eye, eye) / 3.0
    mu = float(np.asarray(stored["mu_nodes"]).reshape(-1)[0])
    kappa = float(np.asarray(stored["kappa"]).reshape(-1)[0])
    vnode = np.asarray(stored["vnode"], np.float64)
    D = sparse.kron(sparse.diags(vnode), 2.0 * mu * dev_sym + kappa * np.outer(eye, eye), format="csr")
    return (G.T @ D @ G).tocsr()


class _Kinematics(NamedTuple):
    """Per element, components first and elements last (XLA on CPU vectorises the last axis)."""
    R: jax.Array      # [3, 3, K]
    jm1: jax.Array    # [K]: J − 1 from ∇u's invariants (1 + tiny − 1 in float32 would lose it)
    g: jax.Array      # [3, n_e, K]: ∂J/∂x_a = cof(F) b_a
    local: jax.Array  # [3 n_e, K] (hexes; [3 n_e, 0] for tets): ũ = Rᵀ x̄ − X, row n_e i + a for component i of a
    H: jax.Array      # [3, 3, K]: F − I, the elements' displacement gradient
    Rn: jax.Array     # [3, 3, N] (tets; [3, 3, 0] for hexes): the polar factor R̄_i of the nodes' averaged F̄_i
    Hn: jax.Array     # [3, 3, N] (tets): F̄_i − I, the nodes' averaged displacement gradient


def _gather(arrays, u):
    """[3, n_e, K] element nodal values of u [N, 3]."""
    return u.T[:, arrays["cells_t"]]


def _assemble(arrays, fe, n: int):
    """Nodal sums [N, C] of element nodal values fe [C, n_e, K], by a scatter-add over the element nodes (on a CPU
    faster than gathering each node's elements through an incidence table: docs/research_log.md)."""
    return jax.ops.segment_sum(fe.reshape(fe.shape[0], -1).T, arrays["cells_t"].reshape(-1), num_segments=n)


def _rotate(R, x, transpose: bool = False):
    """R x (or Rᵀ x) for R [3, 3, K] and x [3, n_e, K]."""
    if transpose:
        return jnp.stack([_sum(lambda j: R[j, i][None] * x[j], 3) for i in range(3)])
    return jnp.stack([_sum(lambda j: R[i, j][None] * x[j], 3) for i in range(3)])


def _apply_ke(arrays, x, key: str = "ke_f"):
    """K_e x for x [3n_e, K] (the elements' deviatoric stiffness, element-last; ``key`` "khg_f": the hexes'
    hourglass part of it)."""
    if "ke_t" in arrays:
        ke = arrays["ke_t"].astype(x.dtype)
        return jnp.stack([_sum(lambda j: ke[i, j] * x[j], ke.shape[1]) for i in range(ke.shape[0])])
    return jnp.einsum("kij,jk->ik", arrays[key].astype(x.dtype), x)


def kinematics(arrays: dict, u) -> _Kinematics:
    """Each element's rotation, volume change, ∂J/∂x and corotated displacement (hexes) or the nodes' averaged
    displacement gradient and its rotation (tets) at the displacements u [N, 3]."""
    ue = _gather(arrays, u)
    b = arrays["b_t"].astype(u.dtype)                                  # [3, n_e, K]
    H = _keep(_sum(lambda a: ue[:, None, a] * b[None, :, a], b.shape[1]))     # [3, 3, K]
    eye = jnp.eye(3, dtype=u.dtype)[:, :, None]
    R = _keep(polar(H + eye, POLAR_ITERATIONS))
    jm1 = _volume_change(H)
    cof = cofactor3(H + eye)
    g = jnp.stack([_sum(lambda j: cof[i, j][None] * b[j], 3) for i in range(3)])
    if not _nodal(arrays):
        x0e = arrays["x0e_t"].astype(u.dtype)
        xe = x0e + ue - ue.mean(axis=1, keepdims=True)
        local = (_rotate(R, xe, transpose=True) - x0e).reshape(3 * b.shape[1], -1)
        empty = jnp.zeros((3, 3, 0), u.dtype)
        return _kept(_Kinematics(R, jm1, g, local, H, empty, empty))
    Hn = _keep(_nodal_gradient(arrays, u))
    Rn = _keep(polar(Hn + eye, POLAR_ITERATIONS))
    return _kept(_Kinematics(R, jm1, g, jnp.zeros((3 * b.shape[1], 0), u.dtype), H, Rn, Hn))


def _volume_change(H):
    """J − 1 = det(I + H) − 1 [M] from the invariants of H [3, 3, M], without forming 1 + tiny − 1."""
    tr = trace3(H)
    return tr + 0.5 * (tr * tr - _sum(lambda i: _sum(lambda j: H[i, j] * H[j, i], 3), 3)) + det3(H)


def isochoric_energy(c10, c01, H):
    """Mooney–Rivlin's isochoric energy density C10 (Ī1 − 3) + C01 (Ī2 − 3) [M] at F = I + H, H [3, 3, M].

    With J = det F, C = FᵀF, Ī1 = J^(−2/3) tr C and Ī2 = J^(−4/3) ½ (tr²C − tr C²) (`fem.material.isochoric_energy`),
    written so that float32 keeps its small-strain value: Ī1 − 3 and Ī2 − 3 are of second order in H, and formed
    as 1 − 3 + O(H) they would lose it. With E = C − I = H + Hᵀ + HᵀH, t = tr E, J − 1 = x (`_volume_change`) and
    m = J^(2/3) − 1,

        a₁ = J^(2/3) (Ī1 − 3) = t − 3m = (tr H² − tr²H − 2 det H) + |H|² + (2x − 3m),
        a₂ = J^(4/3) (Ī2 − 3) = 2a₁ + ½ (t² − E : E) − 3m²,

    the first bracket exact (it is 2 tr H − 2x), and 2x − 3m = ⅓x² − (4/27)x³ + (7/81)x⁴ − … by its series where
    |x| < 0.05. Below ``J_FLOOR`` J is held there (m and 2x − 3m at the floor, a₁ = t − 3m still), so an element
    squashed or turned inside out (noise, a blow) keeps a finite, smooth energy whose gradient P is exact, and the
    volumetric energy, exact at any J, pulls it back."""
    return _isochoric(c10, c01, H)[0]


def _isochoric(c10, c01, H, stress: bool = False):
    """(`isochoric_energy` [M], and with ``stress`` its first Piola–Kirchhoff stress P = ∂Ψ/∂F [3, 3, M]), from the
    derivatives of the terms of a₁ and a₂: ∂t = 2F, ∂(E : E) = 4FE, ∂x = cof F, ∂(det H) = cof H, ∂m = m' cof F
    with m' = ⅔ (1 + x)^(−1/3), and d(2x − 3m)/dx = 2 − 3m' by its series where |x| < 0.05 (each of first order
    in H where P is, so that float32 keeps it too).

    Written on the nine components as separate [M] arrays, P stacked once at the end, with its four per-element
    factors computed once (`_keep`): XLA:CPU evaluates the [3, 3, M] tensor form slower (docs/research_log.md)."""
    r3 = range(3)
    h = [[H[i, j] for j in r3] for i in r3]
    tr = h[0][0] + h[1][1] + h[2][2]
    trhh = sum(h[i][j] * h[j][i] for i in r3 for j in r3)
    frob = sum(h[i][j] * h[i][j] for i in r3 for j in r3)
    cof_h = cofactor3_rows(h)
    det_h = h[0][0] * cof_h[0][0] + h[0][1] * cof_h[0][1] + h[0][2] * cof_h[0][2]
    x_true = tr + 0.5 * (tr * tr - trhh) + det_h                      # J − 1, as `_volume_change`
    x = jnp.maximum(x_true, J_FLOOR - 1.0)
    active = (x_true > J_FLOOR - 1.0).astype(H.dtype)
    small = jnp.abs(x) < 0.05
    xs = jnp.where(small, x, 0.0)
    series = xs * xs * (1.0 / 3.0 + xs * (-4.0 / 27.0 + xs * (7.0 / 81.0 + xs * (-14.0 / 243.0 + xs * 91.0 / 2187.0))))
    log_j = jnp.log1p(x)
    m = jnp.expm1((2.0 / 3.0) * log_j)
    a1 = ((trhh - tr * tr - 2.0 * det_h) + frob + jnp.where(small, series, 2.0 * x - 3.0 * m)
          + 2.0 * (x_true - x))
    E = [[h[i][j] + h[j][i] + sum(h[k][i] * h[k][j] for k in r3) for j in r3] for i in r3]   # FᵀF − I
    t = E[0][0] + E[1][1] + E[2][2]
    a2 = 2.0 * a1 + 0.5 * (t * t - sum(E[i][j] * E[i][j] for i in r3 for j in r3)) - 3.0 * m * m
    j23 = 1.0 + m
    psi = c10 * a1 / j23 + c01 * a2 / (j23 * j23)
    if not stress:
        return psi, None
    F = [[h[i][j] + (1.0 if i == j else 0.0) for j in r3] for i in r3]
    cof_f = cofactor3_rows(F)
    dseries = xs * (2.0 / 3.0 + xs * (-4.0 / 9.0 + xs * (28.0 / 81.0 + xs * (-70.0 / 243.0 + xs * 182.0 / 729.0))))
    dm = (2.0 / 3.0) * jnp.exp(-log_j / 3.0) * active   # below the floor J is held: of ∂x only 2 (x − x_floor)'s
    dg = jnp.where(small, dseries, 2.0 - 3.0 * dm) * active + 2.0 * (1.0 - active)
    # P = c₀ (H + Hᵀ − tr H I − cof H) + c₁ cof F + c₂ F − c₃ F E, the factors c computed once per element
    a = 2.0 * (c10 / j23 + 2.0 * c01 / j23 ** 2)
    c0, c1, c2, c3 = _keep(jnp.stack([a, a * dg / 2.0 - (c10 * a1 / j23 ** 2 + 2.0 * c01 * a2 / j23 ** 3) * dm
                                      - c01 * 6.0 * m * dm / j23 ** 2, 2.0 * c01 / j23 ** 2 * t,
                                      2.0 * c01 / j23 ** 2]))
    P = [[c0 * (h[i][j] + h[j][i] - (tr if i == j else 0.0) - cof_h[i][j]) + c1 * cof_f[i][j] + c2 * F[i][j]
          - c3 * sum(F[i][k] * E[k][j] for k in r3) for j in r3] for i in r3]
    return psi, _keep(jnp.stack([jnp.stack(row) for row in P]))


def _isochoric_constants(arrays, dtype):
    """(C10, C01, β) of the isochoric energy: β the elements' share of it on tets, 1 − β = μ̄ / μ the nodes', with
    μ = 2 (C10 + C01) the shear modulus (1 on hexes; module docstring)."""
    c10, c01 = arrays["mooney_rivlin"].astype(dtype)[0], arrays["mooney_rivlin"].astype(dtype)[1]
    return c10, c01, 1.0 - arrays["mu_nodes"].reshape(-1)[0].astype(dtype) / (2.0 * (c10 + c01))


def _isochoric_stress(c10, c01, H):
    """P = ∂Ψ/∂F [3, 3, M], the first Piola–Kirchhoff stress of `isochoric_energy` at F = I + H."""
    return _isochoric(c10, c01, H, stress=True)[1]


def _kept(kin: _Kinematics) -> _Kinematics:
    """The same kinematics, each tensor computed once (`_keep`; the rotations and gradients are kept where they
    are made)."""
    return kin._replace(g=_keep(kin.g), local=_keep(kin.local.reshape(3, -1)).reshape(kin.local.shape))


def _keep(x):
    """x [C, ...] passed through a product with the identity (one batched XLA dot): computed once.

    XLA:CPU fuses an elementwise producer into every consumer, and the consumers here are gathers, products and
    the polar iteration, which read each element's entries many times: the producer would be recomputed in each of
    them. A dot is never fused into its consumer, so what goes through one is computed once: ∇u and the rotations
    before the polar iteration and the corotated displacements read them, each tensor of the kinematics, and the
    elements' stress at rest (docs/research_log.md). ``jax.lax.optimization_barrier`` does not survive XLA:CPU's
    passes."""
    return jnp.einsum("ij,j...->i...", jnp.eye(x.shape[0], dtype=x.dtype), x)


def _nodal(arrays) -> bool:
    """Whether the volume change is averaged to the nodes (tet4) rather than kept per element (hex8)."""
    return arrays["cells_t"].shape[0] == 4


def _node_average(arrays, x, n: int):
    """x̄_i = Σ_{e∋i} w_ei x_e of element values x [K] → [N], or x [C, K] → [N, C] (the volume-weighted
    average at each node)."""
    w = arrays["wnode_t"].astype(x.dtype)
    if x.ndim == 1:
        return _assemble(arrays, (x[None, :] * w)[None], n)[:, 0]
    return _assemble(arrays, x[:, None, :] * w[None], n)


def _nodal_gradient(arrays, u):
    """F̄_i − I [3, 3, N], the nodes' averaged displacement gradient of u [N, 3] (`node_stars`)."""
    us = u.T[:, arrays["star"]]                                     # [3, N, S]
    c = arrays["star_c"].astype(u.dtype)
    return jnp.stack([jnp.stack([jnp.sum(us[i] * c[j], axis=-1) for j in range(3)]) for i in range(3)])


def _dev_sym(H):
    """dev sym H for H [3, 3, M]."""
    S = 0.5 * (H + transpose3(H))
    return S - (trace3(S) / 3.0)[None, None] * jnp.eye(3, dtype=H.dtype)[:, :, None]


def _gather_tensor(arrays, P):
    """[3, 3, n_e, K] element nodal values of nodal tensors P [3, 3, N] (gathered as [9, N]: a gather along the
    last axis of a three-dimensional array is many times slower on a CPU)."""
    per, k = arrays["cells_t"].shape
    return P.reshape(9, -1)[:, arrays["cells_t"]].reshape(3, 3, per, k)


def _node_tensor_force(arrays, P):
    """Element nodal forces [3, n_e, K] of nodal stresses P [3, 3, N] acting on the nodes' averaged gradients,
    to be assembled with the elements' own: the nodes' forces Σ_i P_i c_ij (`node_stars`) are, c being
    Σ_{e∋i,j} w_ei b_e(j), Σ_{e∋j} P̄_e b_e(j) with P̄_e = Σ_{i∈e} w_ei P_i (a gather of P over the elements' n_e
    nodes rather than over each node's star)."""
    Pe = _gather_tensor(arrays, P)                                            # [3, 3, n_e, K]
    w = arrays["wnode_t"].astype(P.dtype)
    return _tensor_force(arrays, _sum(lambda a: Pe[:, :, a] * w[a][None, None], w.shape[0]))


def _tensor_force(arrays, P):
    """Element nodal forces P b_a [3, n_e, K] of element stresses P [3, 3, K]."""
    b = arrays["b_t"].astype(P.dtype)
    return jnp.stack([_sum(lambda j: P[i, j][None] * b[j], 3) for i in range(3)])


def _dot3(A, B):
    """A B for A, B [3, 3, M] as one batched XLA dot. Used where the product is then gathered (over stars or
    elements): XLA:CPU would fuse the elementwise form into the gather and recompute it for every read, ~26 times
    per node over the stars; a dot is not fused into its consumer (`_kept`)."""
    return jnp.einsum("ijm,jkm->ikm", A, B)


def _volumetric(arrays, x, n: int):
    """The per-element factors s [K] with which g_e carries the volumetric force of the volume changes x [K]:
    κ V_e x_e per hex, κ (V_e / 4) Σ_{i∈e} x̄_i for tets (∂/∂q of Σ_i ½ κ V_i x̄_i² = Σ_e s_e g_e)."""
    kappa = arrays["kappa"].reshape(-1)[0].astype(x.dtype)
    volume = arrays["volume"].astype(x.dtype)
    if not _nodal(arrays):
        return kappa * volume * x
    xn = _node_average(arrays, x, n)
    return kappa * 0.25 * volume * jnp.sum(xn[arrays["cells_t"]], axis=0)


def potential(arrays: dict, kin: _Kinematics):
    """The isochoric energy (hexes Σ_e V_e Ψ(F_e) + ½ ũ_eᵀ K̂_e ũ_e, tets β Σ_e V_e Ψ(F_e) + (1 − β) Σ_i V_i Ψ(F̄_i))
    + the volumetric energy (module docstring; work units)."""
    dt = kin.H.dtype
    kappa = arrays["kappa"].reshape(-1)[0].astype(dt)
    if not _nodal(arrays):
        c10, c01, _ = _isochoric_constants(arrays, dt)
        dev = (jnp.sum(arrays["volume"].astype(dt) * isochoric_energy(c10, c01, kin.H))
               + 0.5 * jnp.sum(kin.local * _apply_ke(arrays, kin.local, "khg_f")))
        return dev + 0.5 * kappa * jnp.sum(arrays["volume"].astype(dt) * kin.jm1 ** 2)
    n = arrays["q0"].shape[0]
    jn = _node_average(arrays, kin.jm1, n)
    c10, c01, beta = _isochoric_constants(arrays, dt)
    dev = (beta * jnp.sum(arrays["volume"].astype(dt) * isochoric_energy(c10, c01, kin.H))
           + (1.0 - beta) * jnp.sum(arrays["vnode"].astype(dt) * isochoric_energy(c10, c01, kin.Hn)))
    return dev + 0.5 * kappa * jnp.sum(arrays["vnode"].astype(dt) * jn ** 2)


def energy(arrays: dict, z):
    """E(z) = ½ vᵀ M v + the potential (module docstring), z [N, 12] → [] (work units)."""
    free = arrays["free"].astype(z.dtype)
    u, v = (z[:, :3] - arrays["q0"].astype(z.dtype)) * free, z[:, 3:6] * free
    m = arrays["mass"].astype(z.dtype)[:, None]
    return 0.5 * jnp.sum(m * v * v) + potential(arrays, kinematics(arrays, u))


def internal_force(arrays: dict, kin: _Kinematics, n: int):
    """∂(potential)/∂q [N, 3]: hexes Σ_e V_e P(F_e) b_e + R_e K̂_e ũ_e + s_e g_e (the hourglass term at fixed
    rotations; `_volumetric`: s_e = κ V_e (J_e − 1)), tets Σ_e (β V_e P(F_e) + Σ_{i∈e} w_ei (1 − β) V_i P(F̄_i)) b_e
    + s_e g_e (P Mooney–Rivlin's isochoric stress, `_isochoric_stress`)."""
    fe = kin.g * _volumetric(arrays, kin.jm1, n)[None, None]
    if _nodal(arrays):
        dt = kin.H.dtype
        c10, c01, beta = _isochoric_constants(arrays, dt)
        we, wn = beta * arrays["volume"].astype(dt), (1.0 - beta) * arrays["vnode"].astype(dt)
        fe = fe + _tensor_force(arrays, _isochoric_stress(c10, c01, kin.H) * we[None, None])
        fe = fe + _node_tensor_force(arrays, _keep(_isochoric_stress(c10, c01, kin.Hn) * wn[None, None]))
        return _assemble(arrays, fe, n)
    dt = kin.H.dtype
    c10, c01, _ = _isochoric_constants(arrays, dt)
    fe = fe + _tensor_force(arrays, _isochoric_stress(c10, c01, kin.H) * arrays["volume"].astype(dt)[None, None])
    fl = _apply_ke(arrays, kin.local, "khg_f").reshape(3, kin.g.shape[1], -1)
    return _assemble(arrays, fe + _rotate(kin.R, fl), n)


def tangent(arrays: dict, kin: _Kinematics, w):
    """(K_R + K_J) w [N, 3]: Σ_e R_e K_e R_eᵀ w_e + the volumetric Gauss–Newton term (κ V_e g_e (g_e · w_e) per
    hex, Σ_i κ V_i ḡ_i (ḡ_i · w) for tets), the frame's stiffness."""
    n, per = w.shape[0], kin.g.shape[1]
    we = _gather(arrays, w)
    fl = _apply_ke(arrays, _rotate(kin.R, we, transpose=True).reshape(3 * per, -1)).reshape(3, per, -1)
    gw = _volumetric(arrays, jnp.sum(kin.g * we, axis=(0, 1)), n)
    fe = _rotate(kin.R, fl) + kin.g * gw[None, None]
    if _nodal(arrays):   # the nodes' share at rest, turned: P_i = 2 μ̄ V_i R̄_i dev sym(R̄_iᵀ dF̄_i)
        dt = w.dtype
        mu = arrays["mu_nodes"].reshape(-1)[0].astype(dt)
        H = matmul3(transpose3(kin.Rn), _nodal_gradient(arrays, w))
        fe = fe + _node_tensor_force(arrays, _dot3(kin.Rn, _dev_sym(H) * (2.0 * mu * arrays["vnode"].astype(dt))))
    return _assemble(arrays, fe, n)


def node_rotations(arrays: dict, kin: _Kinematics, n: int):
    """Each node's rotation [3, 3, N]: on tets R̄_i, the polar factor of the node's averaged deformation gradient
    (already in ``kin``); on hexes the polar factor of the mean of the node's elements' rotations."""
    if _nodal(arrays):
        return kin.Rn
    R = kin.R
    k, per = R.shape[-1], arrays["cells_t"].shape[0]
    total = _assemble(arrays, jnp.broadcast_to(R.reshape(9, 1, k), (9, per, k)), n)     # [N, 9]
    count = _assemble(arrays, jnp.ones((1, per, k), R.dtype), n)                         # [N, 1]
    lonely = (count == 0) * jnp.eye(3, dtype=R.dtype).reshape(1, 9)   # a node of no element: no turn
    return polar((total / jnp.maximum(count, 1.0) + lonely).T.reshape(3, 3, n), POLAR_ITERATIONS)


def stress(arrays: dict, kin: _Kinematics, volume_change, n: int):
    """Nodal Cauchy stress [N, 6]: the deviatoric stress (hexes σ_iso(F_e), tets β σ_iso(F_e); σ_iso = P Fᵀ / J of
    Mooney–Rivlin's isochoric P) + κ (J_e − 1) I with J_e − 1 given as ``volume_change`` [K], averaged
    over each node's elements by volume. For tets, as the FEM's nodal tet4 reports it: each element's deviatoric
    part plus the mean over its nodes of the nodes' pressure κ (J̄_i − 1) and deviatoric share (1 − β) σ_iso(F̄_i),
    then averaged to the nodes."""
    dt = kin.H.dtype
    p = arrays["kappa"].reshape(-1)[0].astype(dt) * volume_change
    c10, c01, beta = _isochoric_constants(arrays, dt)
    eye = jnp.eye(3, dtype=dt)[:, :, None]

    def cauchy(H):   # J held at the energy's floor, as Ψ holds it: finite for a squashed or inverted element
        J = jnp.maximum(1.0 + _volume_change(H), J_FLOOR)
        return _dot3(_isochoric_stress(c10, c01, H), transpose3(H + eye)) / J

    S = cauchy(kin.H)
    if _nodal(arrays):    # as the FEM's nodal tet4: each element adds the mean of its nodes' pressure and share
        Sn = _keep((1.0 - beta) * cauchy(kin.Hn) + _node_average(arrays, p, n)[None, None] * eye)
        S = beta * S + jnp.mean(_gather_tensor(arrays, Sn), axis=2)
        p = jnp.zeros_like(p)
    sig = jnp.stack([S[a, c] + (p if a == c else 0.0) for a, c in _VOIGT])           # [6, K]
    return _assemble(arrays, sig[:, None, :] * arrays["wnode_t"].astype(dt)[None], n)


def frame(arrays: dict, z, f, config: CorotationalConfig):
    """z' [N, 12] of one frame of one body (module docstring), its CG iterations as ``config`` says
    (`joint_frame` of one body)."""
    return joint_frame((arrays,), (z,), (f,), config)[0]


def joint_frame(arrays: tuple, zs: tuple, fs: tuple, config: CorotationalConfig, contact=None) -> tuple:
    """One frame of bodies solved together: their states z_b' [N_b, 12] (module docstring), with ``contact``
    (`tignn_jax.simulators.contact.Contact`, or None) the bodies' penalty contact inside the frame: its energy
    joins the potential, its Gauss–Newton stiffness the solve's operator, coupling the bodies in one CG solve.

    Where the frame's step would have to be shortened to keep the energy budget (θ < 1), the frame is stepped
    again from its start with the step linearised about the end of the first (one Newton iteration of the
    backward-Euler equations, `_step`'s ``x_lin``); where that one falls short as well, as ``SPLIT`` steps of
    Δt / ``SPLIT`` (each with its own budget), so a fast turn is followed rather than damped. One loop runs all
    three (a single copy of the step in the compiled program). The bodies share the frame step Δt of the first.

    The contact's candidate pairs are chosen where a step starts (`tignn_jax.simulators.contact.candidate_pairs`)
    and checked where it ends: where they may have missed a pair there (a surface node moved farther than
    (reach − r) / 2 since they were chosen, or a list is full: `tignn_jax.simulators.contact.still_exact`), those
    of the end are found, and a step that ends with a pair in contact that was not a candidate is taken again
    with the candidates of its end, and after ``RETRIES``
    such steps as θ = 0, so the contact energy the budget counts is the whole contact energy at every step's
    end. Every pair's energy is ≥ 0, so the candidates' energy at a step's start is at most the whole one there,
    and the budget E(z') ≤ E(z) + W holds for the whole energy.
    """
    dtype = zs[0].dtype
    h = arrays[0]["dt"].reshape(-1)[0].astype(dtype)
    zero = tuple(jnp.zeros_like(z[:, :3]) for z in zs)
    fs = tuple(f.astype(dtype) for f in fs)
    pick = lambda c, a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(c, x, y), a, b)  # noqa: E731
    pairs = () if contact is None else C.candidate_pairs(contact, zs)
    no = jnp.zeros((), jnp.int32)

    def missed(z1, pairs, q_ref):
        """(the candidates for the end of a step, the positions they were chosen at, True where the step's own
        missed a pair in contact there): new ones only where the step moved too far for its own to be exact."""
        if contact is None:
            return pairs, q_ref, jnp.asarray(False)
        q1 = tuple(z[:, :3] for z in z1)

        def check(_):
            ends = C.candidate_pairs(contact, z1)
            e_end, e_step = C.energy(contact, ends, q1), C.energy(contact, pairs, q1)
            return ends, q1, e_end > e_step + ROUNDOFF * e_end

        return jax.lax.cond(C.still_exact(contact, pairs, q_ref, q1), lambda _: (pairs, q_ref, jnp.asarray(False)),
                            check, None)

    def body(carry):
        zk, k, mode, x_lin, e_start, pairs, q_ref, tries = carry   # mode 0: one step, 1: that refined, 2: split
        split = mode == 2
        z1, theta, v_full, e0 = _step(arrays, pick(split, zk, zs), fs, config, jnp.where(split, h / SPLIT, h),
                                      x_lin, mode == 1, e_start, contact, pairs, tries >= RETRIES)
        ends, q_ref, miss = missed(z1, pairs, q_ref)
        retry = miss & (tries < RETRIES)         # again from the same start, with the candidates of this end
        short = ~retry & (mode < 2) & (theta < 1.0)          # fell short: refine the step, or split the frame
        advance = ~retry & ~short
        return (pick(advance, z1, pick(split, zk, zs)), jnp.where(advance, k + 1, jnp.where(short, 0, k)),
                jnp.where(short, mode + 1, mode),
                pick(retry, x_lin, pick(short & (mode == 0), v_full, zero)),
                jnp.where((mode == 0) & ~retry, e0, e_start), ends, q_ref, jnp.where(retry, tries + 1, 0))

    def more(carry):
        _, k, mode = carry[:3]
        return k < jnp.where(mode == 2, SPLIT, 1)

    start = (tuple(zs), no, no, zero, jnp.zeros((), dtype), pairs, tuple(z[:, :3] for z in zs), no)
    return jax.lax.while_loop(more, body, start)[0]


class _Body(NamedTuple):
    """One body's frame linearisation (`_step`)."""
    u: jax.Array
    v: jax.Array
    x_lin: jax.Array
    kin: _Kinematics
    rn: jax.Array
    free: jax.Array
    m: jax.Array
    c: jax.Array
    rhs: jax.Array


def _linearise(arrays: dict, z, f, h, x_lin) -> _Body:
    _, alpha, free, m = LG._constants(arrays, z.dtype)
    n = z.shape[0]
    u, v = (z[:, :3] - arrays["q0"].astype(z.dtype)) * free, z[:, 3:6] * free
    x_lin = x_lin * free
    kin = kinematics(arrays, u + h * x_lin)
    rn = jnp.moveaxis(node_rotations(arrays, kin, n), -1, 0)       # [N, 3, 3]: the products below stay in
                                                                    # the [N, 3] layout the dense one reads
    rhs = (m * v / h ** 2 + (f - internal_force(arrays, kin, n)) / h) * free
    return _Body(u, v, x_lin, kin, rn, free, m, (1.0 + alpha * h) / h ** 2, rhs)


def _step(arrays: tuple, zs: tuple, fs: tuple, config: CorotationalConfig, h, x_lin, refine, e_start,
          contact=None, pairs=(), hold=False):
    """(z' of each body after a step h, the step length θ the energy budget allowed, the solve's v' before θ,
    E(z)), all bodies in one solve and one budget.

    The frame's equations M(v' − v)/h + αMv' + f_int(u + hv') + ∂E_c/∂q = f are linearised about u + h x_lin
    (x_lin = 0: about the start; ``refine``: about the end of a previous solve x_lin, whose start energy
    ``e_start`` is E(z)), [(1 + αh)/h² M + K + H_c] v' = M v / h² + (f − f_int − ∂E_c/∂q) / h + (K + H_c) x_lin,
    K the bodies' stiffness there and H_c the contact's Gauss–Newton stiffness (zero without ``contact``), over the
    candidate ``pairs``. ``hold``: the step length θ = 0 (the bodies stay where they are)."""
    dtype = zs[0].dtype
    bodies = tuple(_linearise(a, z, f, h, x) for a, z, f, x in zip(arrays, zs, fs, x_lin))
    q0 = tuple(a["q0"].astype(dtype) for a in arrays)
    if contact is not None:
        lin = C.linearise(contact, pairs, tuple(q + b.u + h * b.x_lin for q, b in zip(q0, bodies)))
        bodies = tuple(b._replace(rhs=b.rhs - g * b.free / h) for b, g in zip(bodies, lin.gradient))

    def apply_a(w):
        w = tuple(x * b.free for x, b in zip(w, bodies))
        out = tuple(b.c * b.m * x + tangent(a, b.kin, x) for a, b, x in zip(arrays, bodies, w))
        if contact is not None:
            out = tuple(o + hc for o, hc in zip(out, C.apply_stiffness(contact, pairs, lin, w)))
        return tuple(o * b.free for o, b in zip(out, bodies))

    coarse = None
    if contact is not None:   # the slow modes of all the bodies solved together, with the contact coupling them
        turned = tuple(jnp.einsum("nij,njm->nim", b.rn, a["modes"].astype(dtype).reshape(b.rn.shape[0], 3, -1))
                       * b.free[:, :, None] for a, b in zip(arrays, bodies))
        coupling = C.coarse_stiffness(contact, lin, turned)
        sizes = [a["modes"].shape[1] for a in arrays]
        eigen = jnp.concatenate([1.0 / a["mode_inv"].astype(dtype) for a in arrays])
        factor = jax.scipy.linalg.cho_factor(jnp.diag(eigen) + coupling, lower=True)
        coarse = lambda c: jnp.split(jax.scipy.linalg.cho_solve(factor, jnp.concatenate(c)),  # noqa: E731
                                     np.cumsum(sizes)[:-1])

    def precondition(r):
        backs = [jnp.einsum("nji,nj->ni", b.rn, x * b.free).reshape(-1) for b, x in zip(bodies, r)]
        modal = [None] * len(backs)
        if coarse is not None:   # Φᵀ r of every body, once: the coarse solve's input and P₀'s projection
            cs = [back @ a["modes"].astype(dtype) for a, back in zip(arrays, backs)]
            modal = list(zip(cs, coarse(cs)))
        return tuple(jnp.einsum("nij,nj->ni", b.rn, apply_rest_preconditioner(a, back, m).reshape(-1, 3)) * b.free
                     for a, b, back, m in zip(arrays, bodies, backs, modal))

    dot = lambda a, b: sum(jnp.vdot(x, y) for x, y in zip(a, b))  # noqa: E731
    add = lambda a, b, t=1.0: tuple(x + t * y for x, y in zip(a, b))  # noqa: E731
    where = lambda cond, a, b: tuple(jnp.where(cond, x, y) for x, y in zip(a, b))  # noqa: E731
    first, most = int(config.cg_iterations), int(config.cg_max_iterations)
    tol2 = jnp.asarray(config.cg_tolerance, dtype) ** 2
    xl = tuple(b.x_lin for b in bodies)
    rhs = tuple(b.rhs for b in bodies)
    base = tuple((b.rhs - b.c * b.m * b.x_lin) * b.free for b in bodies)    # b − A x_lin, with A x_lin's K part

    def iteration(carry):
        # pass −1 forms the first residual r₀ = b − A x₀ = rhs − c M x_lin − A (x₀ − x_lin) from the same product
        # A d (d = x₀ − x_lin) as the iterations after it: one copy of the tangent in the compiled program
        x, r, d, rz, i, bound = carry
        start = i < 0
        ad = apply_a(d)
        dad = dot(d, ad)
        step = jnp.where(dad > 0, rz / jnp.where(dad > 0, dad, 1.0), 0.0)
        x = where(start, x, add(x, d, step))
        r = where(start, add(base, ad, -1.0), add(r, ad, -step))
        p = precondition(r)
        rz_new = dot(r, p)
        d = where(start, p, add(p, d, jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)))
        # the solve goes on while rᵀPr > tol² bᵀA⁻¹b, with bᵀA⁻¹b ≈ bᵀ(P r₀ + x₀) (P ≈ A⁻¹): relative to the
        # right-hand side, not to the first residual, which is at round-off in a held frame (x₀ = v is the answer)
        # and could never be reduced by tol there
        bound = jnp.where(start, tol2 * jnp.maximum(rz_new, dot(rhs, add(p, x))), bound)
        return x, r, d, rz_new, i + 1, bound

    def more(carry):   # the first iterations always, then on while the residual is large
        i, rz, bound = carry[4], carry[3], carry[5]
        return (i < first) | ((i < most) & (rz > bound))

    zero_s = jnp.zeros((), dtype)
    x0 = where(refine, xl, tuple(b.v for b in bodies))
    start = (x0, tuple(jnp.zeros_like(x) for x in x0), tuple((x - y) * b.free for x, y, b in zip(x0, xl, bodies)),
             zero_s, jnp.asarray(-1, jnp.int32), zero_s)
    v1 = tuple(x * b.free for x, b in zip(jax.lax.while_loop(more, iteration, start)[0], bodies))
    # energy never created, E(z') ≤ E(z) + W: the longest of the steps θ h v' (θ in BACKTRACK) whose potential
    # fits the budget, P(u + θ h v') ≤ E(z) + θ W with W = f · h v' (θ = 0 always fits)
    kinetic0 = sum(0.5 * jnp.sum(b.m * b.v * b.v) for b in bodies)
    e0 = kinetic0 + sum(potential(a, b.kin) for a, b in zip(arrays, bodies))
    if contact is not None:
        e0 = e0 + C.energy(contact, pairs, tuple(q + b.u + h * b.x_lin for q, b in zip(q0, bodies)))
    e0 = e0 if e_start is None else jnp.where(refine, e_start, e0)
    energy_start = e0
    work = sum(jnp.sum(f * h * v * b.free) for f, v, b in zip(fs, v1, bodies))
    # the energies' round-off (float32 sums over the elements): a held frame's true change is far below it, and
    # without this allowance half such frames would be shortened for nothing
    e0 = e0 + ROUNDOFF * (jnp.abs(e0) + jnp.abs(work))
    thetas = jnp.asarray(BACKTRACK, dtype)

    def search(carry):    # the next step length; the last, θ = 0, is taken whatever its energy's round-off
        i = carry[0] + 1
        us = tuple(b.u + thetas[i] * h * v for b, v in zip(bodies, v1))
        trial = tuple(kinematics(a, u) for a, u in zip(arrays, us))
        p = sum(potential(a, k) for a, k in zip(arrays, trial))
        if contact is not None:
            p = p + C.energy(contact, pairs, tuple(q + u for q, u in zip(q0, us)))
        return i, trial, p, (p <= e0 + thetas[i] * work) | (i == len(BACKTRACK) - 1)

    # one loop for every trial: a single copy of the kinematics in the compiled program (it compiles slowly)
    first_trial = jnp.where(hold, len(BACKTRACK) - 2, -1).astype(jnp.int32)
    i, kin1, p1, _ = jax.lax.while_loop(lambda c: ~c[3], search, (first_trial, tuple(b.kin for b in bodies), e0,
                                                                 False))
    theta = thetas[i]
    v_full = v1
    v1 = tuple(theta * v for v in v1)
    budget = e0 + theta * work - p1
    kinetic = sum(0.5 * jnp.sum(b.m * v * v) for b, v in zip(bodies, v1))
    scale = jnp.where(kinetic > budget, jnp.sqrt(jnp.maximum(budget, 0.0) / jnp.maximum(kinetic, 1e-30)), 1.0)
    out = []
    for a, b, z, q, v, k in zip(arrays, bodies, zs, q0, v1, kin1):
        u1 = b.u + h * v
        change = b.kin.jm1 + jnp.sum(b.kin.g * _gather(a, u1 - b.u - h * b.x_lin), axis=(0, 1))
        q1 = jnp.where(b.free > 0, q + u1, z[:, :3])
        out.append(jnp.concatenate([q1, v * scale + (1.0 - b.free) * z[:, 3:6], stress(a, k, change, z.shape[0])],
                                   axis=1))
    return tuple(out), theta, v_full, energy_start
