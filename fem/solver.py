"""Total-Lagrangian explicit dynamics: central differences, lumped mass, sub-stepping between output frames.

    M a = f_ext(t) − f_int(x, H) − α M v,     (α: optional Rayleigh mass damping)

advanced with the velocity-Verlet form of the central-difference scheme (one internal-force evaluation per
sub-step)::

    v⁽ⁿ⁺½⁾ = vⁿ + h/2 aⁿ,   xⁿ⁺¹ = xⁿ + h v⁽ⁿ⁺½⁾,   aⁿ⁺¹ = M⁻¹(f_ext − f_int)(xⁿ⁺¹),   vⁿ⁺¹ = v⁽ⁿ⁺½⁾ + h/2 aⁿ⁺¹

(with damping, the implicit mid-point form of −αv). The sub-step h = frame_dt / n_sub where n_sub is the
smallest integer with h ≤ safety · min_e L_e / c_d, c_d = √((K0 + 4μ0/3)/ρ) the dilatational wave speed and L_e
the element length (volume / largest face area). n_sub is fixed when the problem is set up, so a whole run is
one `lax.scan` of frames, each a `lax.scan` of sub-steps.

Gradients: reverse mode through every sub-step would store n_frames·n_sub states. With ``checkpoint=True`` (the
default) each frame's sub-step scan is wrapped in `jax.checkpoint`, so the forward pass stores only the frame
states and the backward pass recomputes one frame's sub-steps at a time: memory O(n_frames + n_sub) instead of
O(n_frames · n_sub), for about one extra forward pass of compute.

Contact between bodies (optional): node-to-node penalty between the surface nodes of body A and body B. A pair
closer than r0 (the contact thickness, about one element size) repels with f = k (r0 − d) n_AB on the A node and
−f on the B node: equal and opposite, so momentum is conserved; the force derives from the potential
½ k (r0 − d)², which is counted in the stored energy, so the energy balance still closes. Candidate pairs closer
than r0 + skin are searched once per frame over all A×B surface pairs (dense, inside `jit`, fixed capacity) and
only those are evaluated in the sub-steps; the run reports if the capacity overflowed or a pair moved more than
the skin (``Result.contact_overflow``).

What a scene does not use is not traced: without Prony terms there are no internal variables and no
dissipation integral; without damping no damping term; without pressure faces no pressure loads. These are
Python-level (static) decisions in :class:`Config`.
"""
from __future__ import annotations

import math
import warnings
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from . import elements as el
from .material import (Material, bulk_modulus, det3, inv3, isochoric_energy, isochoric_pk2, matmul3, pressure,
                       shear_modulus, to_voigt, transpose3, volumetric_energy)


class Config(NamedTuple):
    """Static (compile-time) description of a problem."""

    cell_type: str
    n_frames: int
    n_sub: int
    frame_dt: float
    n_prony: int
    damping: bool
    pressure: bool
    load_interp: str
    checkpoint: bool
    contact_capacity: int = 0   # 0: no contact
    tet_formulation: str = "anp"   # tet4 only: "anp" or "nodal" (see fem.elements)
    tet_blend: float = 1.0         # tet4 "nodal": weight α of the element-wise isochoric energy


class Arrays(NamedTuple):
    """Array data of a problem (a pytree; passed as arguments, never closed over)."""

    points: jnp.ndarray      # [N, 3] reference coordinates
    cells: jnp.ndarray       # [K, n_per]
    free: jnp.ndarray        # [N, 1] 1.0 for free nodes, 0.0 for clamped
    incidence: jnp.ndarray   # [N, w] gather table into the flattened element-node array
    geo: tuple               # HexGeometry or TetGeometry as jnp arrays
    pressure_faces: Optional[jnp.ndarray]  # [P, 3|4] or None
    damping_alpha: jnp.ndarray
    contact_a: Optional[jnp.ndarray] = None   # [Sa] surface node ids of body A
    contact_b: Optional[jnp.ndarray] = None   # [Sb] surface node ids of body B
    contact_params: Optional[jnp.ndarray] = None  # [r0, k, skin]


class Problem(NamedTuple):
    arrays: Arrays
    config: Config


class Loads(NamedTuple):
    """External loading over the run.

    nodal: [n_frames, N, 3] nodal forces [force]; entry k acts during frame k (t_k → t_k+1).
    pressure: [n_frames, P] pressure on each pressure face [force/area], positive into the body (follower).
    v0: [N, 3] initial velocity [length/time] (zero if None).
    u0: [N, 3] initial displacement from the reference positions [length] (zero if None); a clamped node keeps
    its u0 throughout (a prescribed displacement), and the viscous branches start unrelaxed, so a stretch held
    from t = 0 relaxes as the Prony series says. The energies' balance then holds for their changes from t = 0.
    With ``load_interp='step'`` the value is held within a frame; with 'linear' it ramps linearly from the
    previous frame's value (zero before the first) to entry k at the end of frame k.
    """

    nodal: Optional[jnp.ndarray] = None
    pressure: Optional[jnp.ndarray] = None
    v0: Optional[jnp.ndarray] = None
    u0: Optional[jnp.ndarray] = None


class Energies(NamedTuple):
    """Per-frame energies [n_frames + 1]; balance: kinetic + strain + viscous + damping = external."""

    kinetic: jnp.ndarray
    strain: jnp.ndarray      # stored: hyperelastic + energy held in the viscous branches
    viscous: jnp.ndarray     # cumulative viscous dissipation (≥ 0)
    damping: jnp.ndarray     # cumulative Rayleigh-damping dissipation (≥ 0)
    external: jnp.ndarray    # cumulative work of the external loads


class Result(NamedTuple):
    """Frame outputs of a run. t [T+1]; q, v [T+1, N, 3]; sigma [T+1, N, 6] nodal Cauchy stress (S11, S22,
    S33, S12, S13, S23, tension positive; volume average of the adjacent elements' stresses, for tet4 'nodal' the
    blended element stress defined in `fem.elements`);
    inverted: first element with J ≤ 0 (−1 if none) and its time inversion_time (nan if none)."""

    t: jnp.ndarray
    q: jnp.ndarray
    v: jnp.ndarray
    sigma: jnp.ndarray
    energies: Energies
    inverted: jnp.ndarray
    inversion_time: jnp.ndarray
    contact_overflow: jnp.ndarray = None


class State(NamedTuple):
    """Sub-step state carried by the scan (u: displacements x − X, which keeps F − I accurate in float32)."""

    u: jnp.ndarray
    v: jnp.ndarray
    a: jnp.ndarray
    f_ext: jnp.ndarray
    visco: tuple             # () without Prony terms
    w_ext: jnp.ndarray
    w_visc: jnp.ndarray
    w_damp: jnp.ndarray
    inverted: jnp.ndarray
    inversion_time: jnp.ndarray


class ElementInversionError(RuntimeError):
    """Raised by :func:`check` when an element inverted (J ≤ 0) during a run."""


# ------------------------------------------------------------------------------------------------------------
# public API


def setup(points, cells, *, material: Material, frame_dt: float, n_frames: int, clamped=(),
          cell_type: Optional[str] = None, safety: float = 0.9, n_sub: Optional[int] = None, damping: float = 0.0,
          pressure_faces=None, load_interp: str = "step", checkpoint: bool = True, contact=None,
          tet_formulation: str = el.TET_DEFAULT, tet_blend: float = el.TET_BLEND) -> Problem:
    """Validate a mesh and build a :class:`Problem`.

    points [N, 3] reference coordinates [length]; cells [K, 8] (hex8, VTK order) or [K, 4] (tet4);
    material: used for the stable time step (the run itself takes the material as an argument, so it can be
    differentiated); frame_dt [time] > 0 between output frames; clamped: node ids with fixed position;
    safety: fraction of the element-size stability limit; n_sub: sub-steps per frame (overrides the automatic
    choice); damping: Rayleigh mass-damping coefficient α [1/time]; pressure_faces [P, 4|3] node ids of loaded
    faces (outward orientation); contact: optional dict(a=node ids, b=node ids, r0=contact thickness,
    stiffness=k [force/length], skin=search margin, capacity=max candidate pairs) for body–body contact;
    tet_formulation: tet4 element, 'nodal' (stabilised averaged-nodal deformation gradient) or 'anp' (average
    nodal pressure); tet_blend: α ∈ [0, 1], the weight of the element-wise isochoric energy in 'nodal' (see
    `fem.elements`).
    """
    pts = np.asarray(points, dtype=float)
    cl = np.asarray(cells)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"points must be a finite [N, 3] array, got shape {pts.shape}")
    if cl.ndim != 2 or cl.shape[1] not in (4, 8) or not np.issubdtype(cl.dtype, np.integer):
        raise ValueError(f"cells must be an integer [K, 8] (hex8) or [K, 4] (tet4) array, got {cl.shape} {cl.dtype}")
    if cl.min() < 0 or cl.max() >= len(pts):
        raise ValueError(f"cells reference node ids outside [0, {len(pts) - 1}]: min {cl.min()}, max {cl.max()}")
    kind = cell_type or ("hexahedron" if cl.shape[1] == 8 else "tetra")
    if kind not in ("hexahedron", "tetra") or (kind == "hexahedron") != (cl.shape[1] == 8):
        raise ValueError(f"cell_type {cell_type!r} does not match cells with {cl.shape[1]} nodes")
    if not (isinstance(frame_dt, (int, float)) and frame_dt > 0 and math.isfinite(frame_dt)):
        raise ValueError(f"frame_dt must be a positive number, got frame_dt={frame_dt!r}")
    if int(n_frames) != n_frames or n_frames < 1:
        raise ValueError(f"n_frames must be a positive integer, got n_frames={n_frames!r}")
    if not 0.0 < safety <= 1.0:
        raise ValueError(f"safety must be in (0, 1], got safety={safety!r}")
    if damping < 0.0:
        raise ValueError(f"damping must be non-negative, got damping={damping!r}")
    if tet_formulation not in ("anp", "nodal"):
        raise ValueError(f"tet_formulation must be 'anp' or 'nodal', got {tet_formulation!r}")
    if not (isinstance(tet_blend, (int, float)) and 0.0 <= tet_blend <= 1.0):
        raise ValueError(f"tet_blend must be a number in [0, 1], got tet_blend={tet_blend!r}")
    if load_interp not in ("step", "linear"):
        raise ValueError(f"load_interp must be 'step' or 'linear', got {load_interp!r}")
    clamped = np.asarray(clamped, dtype=int).ravel()
    if clamped.size and (clamped.min() < 0 or clamped.max() >= len(pts)):
        bad = clamped[(clamped < 0) | (clamped >= len(pts))]
        raise ValueError(f"clamped node ids out of range [0, {len(pts) - 1}]: {bad.tolist()[:10]}")
    vol = el.element_volumes(pts, cl, kind)
    if np.any(vol <= 0):
        raise ValueError("elements with non-positive volume (inverted or mis-ordered): "
                         f"ids {np.where(vol <= 0)[0][:10].tolist()}")
    if n_sub is None:
        h_max = stable_time_step(pts, cl, material, kind, safety)
        if contact is not None:
            h_max = min(h_max, _contact_time_step(pts, cl, material, contact, safety))
        n_sub = int(math.ceil(frame_dt / h_max - 1e-9))
    elif int(n_sub) != n_sub or n_sub < 1:
        raise ValueError(f"n_sub must be a positive integer, got n_sub={n_sub!r}")
    geo = el.hex_geometry(pts, cl) if kind == "hexahedron" else el.tet_geometry(pts, cl)
    free = np.ones((len(pts), 1))
    free[clamped] = 0.0
    pf = None
    if pressure_faces is not None:
        pf = np.asarray(pressure_faces)
        if pf.ndim != 2 or pf.shape[1] not in (3, 4) or pf.min() < 0 or pf.max() >= len(pts):
            raise ValueError(f"pressure_faces must be [P, 3|4] node ids in range, got shape {pf.shape}")
        pf = jnp.asarray(pf, dtype=jnp.int32)
    arrays = Arrays(
        points=jnp.asarray(pts), cells=jnp.asarray(cl, dtype=jnp.int32), free=jnp.asarray(free),
        incidence=jnp.asarray(el.incidence_table(cl, len(pts))), geo=_element_last(geo),
        pressure_faces=pf, damping_alpha=jnp.asarray(float(damping)))
    capacity = 0
    if contact is not None:
        ca, cb = (np.asarray(contact[k], int).ravel() for k in ("a", "b"))
        for name, ids in (("contact['a']", ca), ("contact['b']", cb)):
            if ids.size == 0 or ids.min() < 0 or ids.max() >= len(pts):
                raise ValueError(f"{name} must be non-empty node ids in [0, {len(pts) - 1}]")
        r0, k_c = float(contact["r0"]), float(contact["stiffness"])
        skin = float(contact.get("skin", r0))
        if r0 <= 0 or k_c <= 0 or skin < 0:
            raise ValueError("contact needs r0 > 0, stiffness > 0, skin >= 0; "
                             f"got r0={r0}, stiffness={k_c}, skin={skin}")
        capacity = int(contact.get("capacity", 4096))
        arrays = arrays._replace(contact_a=jnp.asarray(ca, jnp.int32), contact_b=jnp.asarray(cb, jnp.int32),
                                 contact_params=jnp.asarray([r0, k_c, skin]))
    config = Config(kind, int(n_frames), int(n_sub), float(frame_dt), material.n_prony, damping > 0.0,
                    pf is not None, load_interp, bool(checkpoint), capacity,
                    tet_formulation if kind == "tetra" else "anp", float(tet_blend) if kind == "tetra" else 1.0)
    return Problem(arrays, config)


def stable_time_step(points, cells, material: Material, cell_type: str, safety: float = 0.9) -> float:
    """safety · min_e L_e / c_d with c_d = √((K0 + 4μ0/3) / ρ) [time]."""
    mu, kappa, rho = (float(x) for x in (shear_modulus(material), bulk_modulus(material), material.density))
    c_d = math.sqrt((kappa + 4.0 * mu / 3.0) / rho)
    lengths = el.characteristic_lengths(np.asarray(points, float), np.asarray(cells), cell_type)
    return safety * float(lengths.min()) / c_d


def _contact_time_step(points, cells, material: Material, contact: dict, safety: float) -> float:
    """Sub-step limit of the penalty springs: 0.5/ω with ω² = 8k/m_min (up to four active pairs on the lightest
    contact node, both ends moving). A quarter of the stability limit 2/ω, for accuracy: the spring switches on
    and off within a collision, and at ωh ≈ 2 the central-difference energy error through an impact is ~4 %
    (tests/test_fem_scenes.py)."""
    vol = el.element_volumes(points, cells, "hexahedron" if cells.shape[1] == 8 else "tetra")
    node_vol = np.zeros(len(points))
    np.add.at(node_vol, cells.ravel(), np.repeat(vol / cells.shape[1], cells.shape[1]))
    ids = np.concatenate([np.asarray(contact["a"], int).ravel(), np.asarray(contact["b"], int).ravel()])
    m_min = float(material.density) * node_vol[ids].min()
    return safety * 0.5 / math.sqrt(8.0 * float(contact["stiffness"]) / m_min)


def simulate(problem: Problem, material: Material, loads: Loads, *, on_inversion: str = "warn") -> Result:
    """Run the explicit dynamics and return the frame outputs (jit-compiled; differentiable in material, loads).

    on_inversion: 'warn' (default), 'raise' or 'ignore' — what to do, after the run, when an element inverted.
    Validation and the inversion report happen only with concrete inputs (not under jit/vmap/grad tracing).
    """
    _validate_loads(problem, loads)
    res = _simulate(problem.arrays, material, loads, problem.config)
    if not isinstance(res.inverted, jax.core.Tracer):
        check(res, on_inversion)
    return res


def simulate_batch(problem: Problem, material: Material, loads: Loads) -> Result:
    """`simulate` over a leading load-case axis of every non-None entry of ``loads``; the same result as
    ``jax.vmap`` of `simulate` (to float rounding), computed with the cases as the trailing, vectorised axis of
    the sub-step state (see `_simulate_impl`). Inversions are recorded per case; report them with `check`.

    One call uses one CPU core for the sub-steps; to use several, split the cases over processes (as
    ``tignn generate --worker K/N`` does). Splitting them over host devices with `jax.shard_map` in one process
    hung in the XLA CPU runtime here (jax 0.10.2; see benchmarks/fem_throughput.py).
    """
    _validate_loads(problem, loads, batched=True)
    if all(a is None for a in loads):
        raise ValueError("simulate_batch needs at least one batched entry in loads (nodal, pressure or v0)")
    return _simulate(problem.arrays, material, loads, problem.config, batched=True)


def check(res: Result, on_inversion: str = "raise") -> None:
    """Report element inversion recorded in a result (for batched results, every case)."""
    if on_inversion not in ("warn", "raise", "ignore"):
        raise ValueError(f"on_inversion must be 'warn', 'raise' or 'ignore', got {on_inversion!r}")
    inv = np.atleast_1d(np.asarray(res.inverted))
    if on_inversion == "ignore" or np.all(inv < 0):
        return
    t = np.atleast_1d(np.asarray(res.inversion_time))
    cases = np.where(inv >= 0)[0]
    msg = "; ".join(f"case {c}: element {int(inv[c])} inverted (J <= 0) at t = {float(t[c]):.6g}" for c in cases[:5])
    msg = f"element inversion during the run ({msg}); results after that time are not physical"
    if on_inversion == "raise":
        raise ElementInversionError(msg)
    warnings.warn(msg, RuntimeWarning, stacklevel=3)


def internal_energy(problem: Problem, material: Material, x) -> jnp.ndarray:
    """Instantaneous elastic energy Π_int(x) (no viscous history); its gradient is the internal force."""
    arr, cfg = problem.arrays, problem.config
    hg = _hourglass_for(arr, material, cfg)
    return _stored_energy(arr, material, x - arr.points, (), hg, cfg, elastic=True)


def internal_force(problem: Problem, material: Material, x) -> jnp.ndarray:
    """Instantaneous elastic nodal internal forces f_int(x) [N, 3] of the hand-derived element routines (no
    viscous history: the Prony series at t = 0, g_R = 1)."""
    arr, cfg = problem.arrays, problem.config._replace(n_prony=0)
    elastic = material._replace(g=jnp.zeros(0), tau=jnp.zeros(0))   # instantaneous response
    hg = _hourglass_for(arr, elastic, cfg)
    f, *_ = _internal(arr, elastic, hg, x - arr.points, (), cfg, 1.0)
    return f


def lumped_mass(problem: Problem, material: Material) -> jnp.ndarray:
    """Nodal masses [N] = ρ Σ_e V_e / n_per."""
    arr = problem.arrays
    n_per = arr.cells.shape[1]
    return material.density * _gather_sum(arr.incidence, jnp.tile(arr.geo.volume / n_per, n_per))


# ------------------------------------------------------------------------------------------------------------
# implementation


def _validate_loads(problem: Problem, loads: Loads, batched: bool = False):
    cfg, n = problem.config, problem.arrays.points.shape[0]
    lead = "[cases, " if batched else "["
    if not isinstance(loads, Loads):
        raise TypeError(f"loads must be a fem.Loads, got {type(loads).__name__}")
    if loads.nodal is not None:
        shp = np.shape(loads.nodal)[1:] if batched else np.shape(loads.nodal)
        if shp != (cfg.n_frames, n, 3):
            raise ValueError(f"loads.nodal must have shape {lead}{cfg.n_frames}, {n}, 3], got {np.shape(loads.nodal)}")
        if not isinstance(loads.nodal, jax.core.Tracer) and not np.all(np.isfinite(loads.nodal)):
            raise ValueError("loads.nodal contains NaN or Inf")
    if loads.pressure is not None:
        if not cfg.pressure:
            raise ValueError("loads.pressure given but the problem was set up without pressure_faces")
        p = problem.arrays.pressure_faces.shape[0]
        shp = np.shape(loads.pressure)[1:] if batched else np.shape(loads.pressure)
        if shp != (cfg.n_frames, p):
            raise ValueError(f"loads.pressure must have shape {lead}{cfg.n_frames}, {p}], "
                             f"got {np.shape(loads.pressure)}")
    for name in ("v0", "u0"):
        value = getattr(loads, name)
        if value is None:
            continue
        shp = np.shape(value)[1:] if batched else np.shape(value)
        if shp != (n, 3):
            raise ValueError(f"loads.{name} must have shape {lead}{n}, 3], got {np.shape(value)}")
        if not isinstance(value, jax.core.Tracer) and not np.all(np.isfinite(value)):
            raise ValueError(f"loads.{name} contains NaN or Inf")


def _element_last(geo):
    """Move reference geometry to the hot-path layout: components first, elements last (b → [3, n_per, K])."""
    if isinstance(geo, el.HexGeometry):
        return el.HexGeometry(jnp.asarray(geo.b.transpose(2, 1, 0)), jnp.asarray(geo.volume),
                              jnp.asarray(geo.gamma.transpose(1, 2, 0)),
                              tuple(map(jnp.asarray, geo.hg_lam)), tuple(map(jnp.asarray, geo.hg_mu)))
    return el.TetGeometry(jnp.asarray(geo.b.transpose(2, 1, 0)), jnp.asarray(geo.volume), jnp.asarray(geo.node_volume),
                          jnp.asarray(geo.node_elements))


def _gather_sum(incidence, values):
    """Nodal sums [N, ...] of node-major element-node values [n_per·K, ...] through the padded incidence table."""
    pad = jnp.zeros((1,) + values.shape[1:], values.dtype)
    return jnp.concatenate([values, pad])[incidence].sum(axis=1)


def _assemble(incidence, fe):
    """Nodal forces [N, 3, *B] from element-node forces fe [3, n_per, K, *B] (B: optional trailing case axes)."""
    return _gather_sum(incidence, jnp.moveaxis(fe.reshape((3, -1) + fe.shape[3:]), 0, 1))


def _gather_elements(u, cells):
    """Element nodal values [3, n_per, K, *B] (e.g. displacements) from u [N, 3, *B]."""
    return jnp.moveaxis(u[cells.T], 2, 0)


def _deformation_gradient(ue, b):
    """F [3, 3, K] = I + Σ_a u_a ⊗ b_a from element nodal displacements ue (explicit sums: XLA on CPU reduces
    middle axes slowly).

    Displacements, not positions: Σ_a x_a ⊗ b_a adds terms of the size of the coordinates (~ the body's size
    over the element size) that cancel to ~1, which in float32 leaves F − I with an absolute error ~1e-5;
    times the bulk modulus of a nearly incompressible solid (K = 2e7 for the paper's beam) that is a pressure
    noise of ~200 (docs/research_log.md, "F from displacements"). The displacement form is exact for the same
    reason (Σ_a X_a ⊗ b_a = I for the uniform gradients)."""
    grad_u = _sum_over(lambda a: ue[:, None, a] * b[None, :, a], b.shape[1])
    return grad_u + jnp.eye(3, dtype=grad_u.dtype).reshape((3, 3) + (1,) * (grad_u.ndim - 2))


def _sum_over(term, n):
    """Σ_{a<n} term(a), unrolled."""
    out = term(0)
    for a in range(1, n):
        out = out + term(a)
    return out


def _polar_rotation(F, iterations: int = 2):
    """Rotation of the polar decomposition F = R U by Higham's iteration R ← (R + R⁻ᵀ)/2; F [3, 3, ...].

    Every iterate is exactly objective (F → QF gives R → QR), so rigid rotations stay stress-free whatever the
    count; the iteration converges quadratically, the error after k steps being O(|ε|^(2^k)) for a stretch
    U = I + ε. R only orients the hourglass stiffness, so two steps (orientation error ~1e-5 rad at 5 % strain,
    ~1e-2 rad at 30 %) are enough.
    """
    R = F
    for _ in range(iterations):
        R = 0.5 * (R + transpose3(inv3(R)))
    return R


def _hourglass_for(arr: Arrays, m: Material, cfg: Config):
    """`_hourglass_stiffness` for a hex8 problem, None for tet4 (which has no hourglass modes)."""
    return _hourglass_stiffness(arr.geo, m) if cfg.cell_type == "hexahedron" else None


def _hourglass_stiffness(geo, m: Material):
    """Condensed QM6 hourglass stiffness, split into long-term and relaxing parts: (K̂_eq, ΔK̂) [12, 12, K]."""
    mu0, k0 = shear_modulus(m), bulk_modulus(m)
    ginf = 1.0 - jnp.sum(m.g)

    def condense(lam, mu):
        kuu, kua, kaa = (lam * a + mu * b for a, b in zip(geo.hg_lam, geo.hg_mu))
        k = kuu - kua @ jnp.linalg.solve(kaa, jnp.swapaxes(kua, -1, -2))
        return jnp.moveaxis(k, 0, -1)

    k_inst = condense(k0 - 2.0 * mu0 / 3.0, mu0)
    if m.n_prony == 0:
        return k_inst, None, None
    k_eq = condense(k0 - 2.0 * ginf * mu0 / 3.0, ginf * mu0)
    dk = k_inst - k_eq
    dk_inv = jnp.moveaxis(jnp.linalg.inv(jnp.moveaxis(dk, -1, 0)), 0, -1)
    return k_eq, dk, dk_inv


def _zero_visco(arr: Arrays, cfg: Config, batch: tuple = ()):
    """Zero viscous variables; ``batch`` appends trailing case axes."""
    if cfg.n_prony == 0:
        return ()
    k, b = arr.cells.shape[0], tuple(batch)
    z = (jnp.zeros((cfg.n_prony, 3, 3, k) + b), jnp.zeros((3, 3, k) + b))
    if cfg.cell_type == "hexahedron":
        z = z + (jnp.zeros((cfg.n_prony, 12, k) + b), jnp.zeros((12, k) + b))
    elif _nodal_tet(cfg):
        n = arr.points.shape[0]
        z = z + (jnp.zeros((cfg.n_prony, 3, 3, n) + b), jnp.zeros((3, 3, n) + b))
    return z


def _hourglass_coordinates(geo, R, ue):
    """g [12, K] = G Rᵀ x: hourglass coordinates of the co-rotated element nodes (index 3·mode + component).

    Computed as Rᵀ (Σ_a γ_a u_a) from the displacements u = x − X: Σ_a γ_a X_a = 0 (γ is orthogonal to linear
    fields), and rotating the four mode vectors is cheaper than rotating the eight nodes.
    """
    gx = _sum_over(lambda a: geo.gamma[:, None, a] * ue[None, :, a], 8)   # [4, 3, K] in the global frame
    return _sum_over(lambda j: R[j][None] * gx[:, j, None], 3).reshape((12,) + gx.shape[2:])


def _internal(arr: Arrays, m: Material, hg, u, visco, cfg: Config, h):
    """Internal nodal forces at the displacements u = x − X, advancing the viscous variables over a sub-step h.

    Returns (f_int [N, 3], new visco, min J, element of min J, dissipation rate).
    """
    geo = arr.geo
    ue = _gather_elements(u, arr.cells)
    F = _deformation_gradient(ue, geo.b)
    if _nodal_tet(cfg):
        P, J, new_visco, diss = _nodal_tet_stress(arr, m, F, visco, cfg, h)
        fe = geo.volume * _sum_over(lambda j: P[:, j, None] * geo.b[None, j], 3)
        return _assemble(arr.incidence, fe), new_visco, jnp.min(J, axis=0), jnp.argmin(J, axis=0), diss
    S0, J, Cinv = isochoric_pk2(m, F)
    p = pressure(m, J) if cfg.cell_type == "hexahedron" else _anp_pressure(arr, m, J)
    S = (J * p) * Cinv
    new_visco, diss = (), 0.0
    if cfg.n_prony:
        S_iso, new_visco, d = _prony_step(m, S0, visco[:2], h)
        S = S + S_iso
        diss = jnp.sum(geo.volume * d, axis=0)
        decay = jnp.exp(-h / m.tau)
        coef = m.tau / h * (1.0 - decay)
    else:
        S = S + S0
    P = matmul3(F, S)
    fe = geo.volume * _sum_over(lambda j: P[:, j, None] * geo.b[None, j], 3)   # [3, n_per, K]
    if cfg.cell_type == "hexahedron":
        R = _polar_rotation(F)
        g = _hourglass_coordinates(geo, R, ue)
        k_eq, dk, dk_inv = hg
        Q = _sum_over(lambda j: k_eq[:, j] * g[None, j], 12)
        if cfg.n_prony:
            HQ, Q0_prev = visco[2], visco[3]
            Q0 = _sum_over(lambda j: dk[:, j] * g[None, j], 12)
            HQ = _per_term(decay, HQ) * HQ + _per_term(coef, HQ) * (Q0 - Q0_prev)[None]
            w = m.g / jnp.sum(m.g)
            Q = Q + jnp.sum(_per_term(w, HQ) * HQ, axis=0)
            dkinv_hq = jnp.sum(dk_inv[None] * HQ[:, None], axis=2)       # [P, 12, K, *B]
            diss = diss + jnp.sum(_per_term(w / m.tau, HQ) * HQ * dkinv_hq, axis=(0, 1, 2))
            new_visco = new_visco + (HQ, Q0)
        Q = Q.reshape((4, 3) + Q.shape[1:])
        RQ = _sum_over(lambda j: R[None, :, j] * Q[:, j, None], 3)           # [4, 3, K] = R Q_m
        fe = fe + _sum_over(lambda mo: geo.gamma[mo, None] * RQ[mo, :, None], 4)
    f = _assemble(arr.incidence, fe)
    return f, new_visco, jnp.min(J, axis=0), jnp.argmin(J, axis=0), diss


def _anp_pressure(arr: Arrays, m: Material, J):
    """Average-nodal-pressure element pressures [K] from element Jacobians J [K] (tet4)."""
    geo = arr.geo
    v_share = jnp.tile(geo.volume * J / 4.0, 4)
    J_node = _gather_sum(arr.incidence, v_share) / geo.node_volume
    return jnp.mean(pressure(m, J_node)[arr.cells], axis=1)


def _nodal_tet(cfg: Config) -> bool:
    return cfg.cell_type == "tetra" and cfg.tet_formulation == "nodal"


def _nodal_average(geo, value):
    """Volume average over the elements around each node: [..., K] → [..., N], Σ_{e∋a} (V_e/4) value_e / V_a.

    Gathers whole rows (elements-major layout), which XLA on CPU does faster than one gather per component."""
    lead = value.shape[:-1]
    rows = value.reshape(-1, value.shape[-1]).T * (geo.volume / 4.0)[:, None]          # [K, C]
    rows = jnp.concatenate([rows, jnp.zeros((1, rows.shape[1]), rows.dtype)])
    avg = rows[geo.node_elements].sum(axis=1) / geo.node_volume[:, None]              # [N, C]
    return avg.T.reshape(lead + (-1,))


def _element_mean(cells, nodal):
    """Mean over each element's four nodes: [..., N] → [..., K]."""
    lead = nodal.shape[:-1]
    rows = nodal.reshape(-1, nodal.shape[-1]).T                                         # [N, C]
    return (0.25 * rows[cells].sum(axis=1)).T.reshape(lead + (-1,))


def _per_term(c, history):
    """Per-Prony-term constants c [P] shaped to broadcast against a history [P, ...] (any trailing axes)."""
    return c.reshape((-1,) + (1,) * (history.ndim - 1))


def _prony_step(m: Material, S0, hist, h):
    """Isochoric PK2 g∞ S⁰ + Σ ḡ_i H_i with the history advanced over h, the new history (H, S⁰), and the
    dissipation rate density Σ_i |ḡ_i H_i|²/(2 ḡ_i μ0 τ_i) [..]; S0 [3, 3, n]."""
    decay = jnp.exp(-h / m.tau)
    coef = m.tau / h * (1.0 - decay)
    H, S0_prev = hist
    H = _per_term(decay, H) * H + _per_term(coef, H) * (S0 - S0_prev)[None]
    S = (1.0 - jnp.sum(m.g)) * S0 + jnp.sum(_per_term(m.g, H) * H, axis=0)
    rate = m.g / (2.0 * shear_modulus(m) * m.tau)
    return S, (H, S0), jnp.sum(_per_term(rate, H) * H * H, axis=(0, 1, 2))


def _nodal_tet_stress(arr: Arrays, m: Material, F, visco, cfg: Config, h):
    """First Piola–Kirchhoff stress [3, 3, K] of the stabilised nodal tet4, conjugate to its energy
    α Σ_e V_e Ψ_iso(F_e) + (1 − α) Σ_a V_a Ψ_iso(F_a) + Σ_a V_a U(J_a), with F_a, J_a the nodal volume averages
    of F_e, J_e: ∂/∂F_e of a nodal term is V_e/4 times the nodal stress, so each element carries the mean of its
    four nodes' stresses. Returns (P, element J [K], new visco, dissipation rate)."""
    geo, a = arr.geo, cfg.tet_blend
    S0, J, Cinv = isochoric_pk2(m, F)
    Fn, Jn = _nodal_average_F_J(geo, F, J)
    S0n, _, _ = isochoric_pk2(m, Fn)
    new_visco, diss = (), 0.0
    if cfg.n_prony:
        S0, he, de = _prony_step(m, S0, visco[:2], h)
        S0n, hn, dn = _prony_step(m, S0n, visco[2:], h)
        new_visco = he + hn
        diss = a * jnp.sum(geo.volume * de) + (1.0 - a) * jnp.sum(geo.node_volume * dn)
    n = Jn.shape[-1]
    nodal = jnp.concatenate([((1.0 - a) * matmul3(Fn, S0n)).reshape(9, n), pressure(m, Jn)[None]])
    Pn_mean, p = jnp.split(_element_mean(arr.cells, nodal), [9])   # one gather for both
    P = matmul3(F, a * S0 + (J * p[0]) * Cinv) + Pn_mean.reshape(F.shape)
    return P, J, new_visco, diss


def _nodal_average_F_J(geo, F, J):
    """Nodal averages of F [3, 3, K] and J [K] in one gather: ([3, 3, N], [N])."""
    k = J.shape[-1]
    avg = _nodal_average(geo, jnp.concatenate([F.reshape(9, k), J[None]]))
    return avg[:9].reshape(3, 3, -1), avg[9]


def _nodal_tet_cauchy(arr: Arrays, m: Material, F, visco, cfg: Config):
    """Element Cauchy stress [3, 3, K] of the stabilised nodal tet4: α σ_iso(F_e) + (1 − α) · mean over the
    element's nodes of σ_iso(F_a) + mean nodal pressure; current viscous variables (no update)."""
    geo, a = arr.geo, cfg.tet_blend
    S0, J, _ = isochoric_pk2(m, F)
    Fn, Jn_vol = _nodal_average_F_J(geo, F, J)
    S0n, Jn, _ = isochoric_pk2(m, Fn)
    if cfg.n_prony:
        ginf = 1.0 - jnp.sum(m.g)
        S0 = ginf * S0 + jnp.sum(m.g[:, None, None, None] * visco[0], axis=0)
        S0n = ginf * S0n + jnp.sum(m.g[:, None, None, None] * visco[2], axis=0)
    cauchy = lambda F_, S_, J_: matmul3(matmul3(F_, S_), transpose3(F_)) / J_
    p = _element_mean(arr.cells, pressure(m, Jn_vol))
    return (a * cauchy(F, S0, J) + (1.0 - a) * _element_mean(arr.cells, cauchy(Fn, S0n, Jn))
            + p * jnp.eye(3, dtype=F.dtype)[:, :, None])


def _element_stress(arr: Arrays, m: Material, u, visco, cfg: Config):
    """Element Cauchy stress [K, 6] at the displacements u with the current viscous variables (no update)."""
    F = _deformation_gradient(_gather_elements(u, arr.cells), arr.geo.b)
    if _nodal_tet(cfg):
        return to_voigt(_nodal_tet_cauchy(arr, m, F, visco, cfg))
    S0, J, Cinv = isochoric_pk2(m, F)
    p = pressure(m, J) if cfg.cell_type == "hexahedron" else _anp_pressure(arr, m, J)
    if cfg.n_prony:
        S_iso = (1.0 - jnp.sum(m.g)) * S0 + jnp.sum(m.g[:, None, None, None] * visco[0], axis=0)
    else:
        S_iso = S0
    sig = matmul3(matmul3(F, S_iso), transpose3(F)) / J + p * jnp.eye(3, dtype=F.dtype)[:, :, None]
    return to_voigt(sig)


def _nodal_stress(arr: Arrays, sig_e):
    n_per = arr.cells.shape[1]
    vol = arr.geo.volume
    num = _gather_sum(arr.incidence, jnp.tile(sig_e * vol[:, None], (n_per, 1)))
    return num / _gather_sum(arr.incidence, jnp.tile(vol, n_per))[:, None]


def _stored_energy(arr: Arrays, m: Material, u, visco, hg, cfg: Config, elastic: bool = False):
    """Stored energy at the displacements u: volumetric + long-term isochoric + energy held in the viscous
    branches."""
    geo = arr.geo
    ue = _gather_elements(u, arr.cells)
    F = _deformation_gradient(ue, geo.b)
    ginf = 1.0 if (elastic or cfg.n_prony == 0) else 1.0 - jnp.sum(m.g)
    if cfg.cell_type == "hexahedron":
        e = jnp.sum(geo.volume * (ginf * isochoric_energy(m, F) + volumetric_energy(m, det3(F))))
        g = _hourglass_coordinates(geo, _polar_rotation(F), ue)
        k_eq, dk, _ = hg
        k_use = k_eq + dk if (elastic and dk is not None) else k_eq
        e = e + 0.5 * jnp.sum(g * jnp.sum(k_use * g[None], axis=1))
    elif _nodal_tet(cfg):
        a = cfg.tet_blend
        Fn, Jn = _nodal_average_F_J(geo, F, det3(F))
        e = ginf * (a * jnp.sum(geo.volume * isochoric_energy(m, F))
                    + (1.0 - a) * jnp.sum(geo.node_volume * isochoric_energy(m, Fn)))
        e = e + jnp.sum(geo.node_volume * volumetric_energy(m, Jn))
    else:
        J = det3(F)
        J_node = _gather_sum(arr.incidence, jnp.tile(geo.volume * J / 4.0, 4)) / geo.node_volume
        e = (jnp.sum(geo.volume * ginf * isochoric_energy(m, F))
             + jnp.sum(geo.node_volume * volumetric_energy(m, J_node)))
    if cfg.n_prony and not elastic:
        c = (m.g / (4.0 * shear_modulus(m)))[:, None, None, None]
        held = lambda vol, H: jnp.sum(vol * jnp.sum(c * H * H, axis=(0, 1, 2)))
        if _nodal_tet(cfg):   # element branches weighted α, nodal branches 1 − α
            e = e + cfg.tet_blend * held(geo.volume, visco[0]) + (1.0 - cfg.tet_blend) * held(geo.node_volume, visco[2])
        else:
            e = e + held(geo.volume, visco[0])
        if cfg.cell_type == "hexahedron":
            w = m.g / jnp.sum(m.g)
            HQ = visco[2]
            e = e + 0.5 * jnp.sum(w[:, None, None] * HQ * jnp.sum(hg[2][None] * HQ[:, None], axis=2))
    return e


def _contact_pairs(arr: Arrays, x, capacity: int):
    """Candidate A–B surface-node pairs closer than r0 + skin: ([capacity, 2] ids, overflowed)."""
    r0, _, skin = arr.contact_params[0], arr.contact_params[1], arr.contact_params[2]
    xa, xb = x[arr.contact_a], x[arr.contact_b]
    d2 = jnp.sum((xa[:, None] - xb[None]) ** 2, axis=-1)
    close = d2 < (r0 + skin) ** 2
    ia, ib = jnp.nonzero(close, size=capacity, fill_value=-1)
    valid = ia >= 0
    pairs = jnp.stack([jnp.where(valid, arr.contact_a[ia], -1), jnp.where(valid, arr.contact_b[ib], -1)], -1)
    return pairs, jnp.sum(close) > capacity


def _pairs_missed(arr: Arrays, pairs, x):
    """True if some A–B pair is inside r0 at the end of a frame but was not a candidate (skin too small)."""
    r0 = arr.contact_params[0]
    xa, xb = x[arr.contact_a], x[arr.contact_b]
    inside = jnp.sum(jnp.sum((xa[:, None] - xb[None]) ** 2, axis=-1) < r0 ** 2)
    d = jnp.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=-1)
    counted = jnp.sum((pairs[:, 0] >= 0) & (d < r0))
    return inside > counted


def _contact_force(arr: Arrays, pairs, x):
    """Penalty forces [N, 3]: k (r0 − d) along the B→A direction on A, the opposite on B."""
    r0, k = arr.contact_params[0], arr.contact_params[1]
    valid = pairs[:, 0] >= 0
    ia, ib = jnp.where(valid, pairs[:, 0], 0), jnp.where(valid, pairs[:, 1], 0)
    dx = x[ia] - x[ib]
    d = jnp.sqrt(jnp.sum(dx ** 2, axis=-1) + 1e-30)
    mag = jnp.where(valid & (d < r0), k * (r0 - d), 0.0)
    f = (mag / d)[:, None] * dx
    return jnp.zeros_like(x).at[ia].add(f).at[ib].add(-f)


def _contact_energy(arr: Arrays, x):
    r0, k = arr.contact_params[0], arr.contact_params[1]
    xa, xb = x[arr.contact_a], x[arr.contact_b]
    d = jnp.sqrt(jnp.sum((xa[:, None] - xb[None]) ** 2, axis=-1) + 1e-30)
    return 0.5 * k * jnp.sum(jnp.where(d < r0, (r0 - d) ** 2, 0.0))


def _external_force(arr: Arrays, loads: Loads, cfg: Config, frame, frac, x):
    """External nodal force at time t_frame + frac·frame_dt (frac ∈ (0, 1])."""
    f = jnp.zeros(x.shape, x.dtype)

    def value(series):
        cur = series[frame]
        if cfg.load_interp == "step":
            return cur
        prev = jnp.where(frame > 0, series[jnp.maximum(frame - 1, 0)], jnp.zeros_like(cur))
        return prev + frac * (cur - prev)

    if loads.nodal is not None:
        f = f + value(loads.nodal)
    if cfg.pressure and loads.pressure is not None:
        pf = arr.pressure_faces
        xf = x[pf]
        if pf.shape[1] == 4:
            na = 0.5 * jnp.cross(xf[:, 2] - xf[:, 0], xf[:, 3] - xf[:, 1], axis=1)
        else:
            na = 0.5 * jnp.cross(xf[:, 1] - xf[:, 0], xf[:, 2] - xf[:, 0], axis=1)
        ff = -(jnp.expand_dims(value(loads.pressure), 1) * na) / pf.shape[1]
        f = f.at[pf.ravel()].add(jnp.repeat(ff, pf.shape[1], axis=0))
    return f


def _trailing(tree):
    """Append a singleton axis to every array of a pytree (per-element data against [.., K, B] case arrays)."""
    return jax.tree_util.tree_map(lambda a: a[..., None], tree)


def _internal_fn(arr: Arrays, m: Material, hg, cfg: Config, h, batched: bool):
    """``internal(u, visco) -> _internal(...)`` for one case, or for cases on the trailing axis of u [N, 3, B]
    and of the viscous variables: hex8 natively (per-element data get a trailing singleton axis), tet4 through
    `jax.vmap` over that axis."""
    if batched and cfg.cell_type == "hexahedron":
        arr_hot, hg_hot = arr._replace(geo=_trailing(arr.geo)), _trailing(hg)
        return lambda u, visco: _internal(arr_hot, m, hg_hot, u, visco, cfg, h)
    fn = lambda u, visco: _internal(arr, m, hg, u, visco, cfg, h)
    return jax.vmap(fn, in_axes=(-1, -1), out_axes=-1) if batched else fn


def _simulate_impl(arr: Arrays, m: Material, loads: Loads, cfg: Config, batched: bool = False) -> Result:
    """One run, or with ``batched`` a batch of load cases (leading axis of every entry of ``loads``).

    Batched layout: the cases are carried as the *last* axis of the sub-step state (u, v, a [N, 3, B], viscous
    variables [.., K, B]), so the per-element arithmetic of the hex8 hot path runs with the cases as the
    contiguous, vectorised axis and the element gather copies whole rows of B values (measured in
    benchmarks/fem_throughput.py against `jax.vmap`, which puts the case axis first). Work done once per frame
    (stresses, energies), the tet4 element routines, contact search and pressure loads are `jax.vmap`-ed over that
    trailing axis; the result has the case axis first, like `jax.vmap(simulate)`.
    """
    h = cfg.frame_dt / cfg.n_sub
    n_per = arr.cells.shape[1]
    mass = m.density * _gather_sum(arr.incidence, jnp.tile(arr.geo.volume / n_per, n_per))
    hg = _hourglass_for(arr, m, cfg)
    alpha = arr.damping_alpha
    bshape, bx = (), lambda a: a             # case axes; adds them to per-node data
    if batched:
        n_cases = next(a.shape[0] for a in loads if a is not None)
        bshape = (n_cases,)
        loads = Loads(*(None if a is None else jnp.moveaxis(a, 0, -1) for a in loads))
        bx = lambda a: a[..., None]
    X = bx(arr.points.astype(mass.dtype))     # reference positions; the state carries u = x − X
    u0 = jnp.zeros(arr.points.shape + bshape, mass.dtype) if loads.u0 is None else loads.u0.astype(mass.dtype)
    free = bx(arr.free)
    inv_mass = bx(arr.free / mass[:, None])
    mass_x = bx(mass[:, None])
    case_sum = lambda a: jnp.sum(a, axis=(0, 1))       # over nodes and components: scalar or [B]

    def over_cases(fn, in_axes, out_axes=-1):
        """fn itself, or fn vmapped over the trailing case axis of its batched arguments."""
        return jax.vmap(fn, in_axes=in_axes, out_axes=out_axes) if batched else fn

    internal = _internal_fn(arr, m, hg, cfg, h, batched)
    contact_pairs = over_cases(lambda x: _contact_pairs(arr, x, cfg.contact_capacity), -1, 0)
    contact_force = over_cases(lambda pairs, x: _contact_force(arr, pairs, x), (0, -1))
    pairs_missed = over_cases(lambda pairs, x: _pairs_missed(arr, pairs, x), (0, -1), 0)
    v0 = jnp.zeros_like(u0) if loads.v0 is None else loads.v0 * free
    visco0 = _zero_visco(arr, cfg, bshape)
    f_ext0 = _external_force(arr, loads, cfg, 0, 0.0, X + u0) if cfg.load_interp == "step" else jnp.zeros_like(u0)
    f_int0, *_ = internal(u0, visco0)
    if cfg.contact_capacity:
        f_int0 = f_int0 - contact_force(contact_pairs(X + u0)[0], X + u0)
    a0 = (f_ext0 - f_int0) * inv_mass
    zero = jnp.zeros(bshape, mass.dtype)
    state0 = State(u0, v0, a0, f_ext0, visco0, zero, zero, zero, jnp.full(bshape, -1, jnp.int32),
                   jnp.full(bshape, jnp.nan, mass.dtype))

    def substep(frame, s: State, j, pairs=None):
        v_half = s.v + 0.5 * h * s.a
        if cfg.damping:
            v_half = v_half - 0.5 * h * alpha * s.v
        u = s.u + h * v_half
        f_ext = _external_force(arr, loads, cfg, frame, (j + 1.0) / cfg.n_sub, X + u)
        f_int, visco, j_min, k_min, diss = internal(u, s.visco)
        if cfg.contact_capacity:   # contact is internal to the system of bodies: not external work
            f_int = f_int - contact_force(pairs, X + u)
        a = (f_ext - f_int) * inv_mass
        if cfg.damping:
            v = (v_half + 0.5 * h * a) / (1.0 + 0.5 * h * alpha)   # a stays the undamped acceleration
            w_damp = s.w_damp + 0.5 * h * alpha * (case_sum(mass_x * s.v ** 2) + case_sum(mass_x * v ** 2))
        else:
            v = v_half + 0.5 * h * a
            w_damp = s.w_damp
        w_ext = s.w_ext + 0.5 * case_sum((s.f_ext + f_ext) * (u - s.u))
        t = (frame + (j + 1.0) / cfg.n_sub) * cfg.frame_dt
        newly = (j_min <= 0.0) & (s.inverted < 0)
        inverted = jnp.where(newly, k_min.astype(jnp.int32), s.inverted)
        inv_t = jnp.where(newly, t, s.inversion_time)
        return State(u, v, a, f_ext, visco, w_ext, s.w_visc + h * diss, w_damp, inverted, inv_t)

    def frame_fn(carry, frame):
        s, overflow = carry
        pairs = None
        if cfg.contact_capacity:
            pairs, over = contact_pairs(X + s.u)
            overflow = overflow | over
        s, _ = jax.lax.scan(lambda c, j: (substep(frame, c, j, pairs), None), s,
                            jnp.arange(cfg.n_sub, dtype=mass.dtype))
        if cfg.contact_capacity:
            overflow = overflow | pairs_missed(pairs, X + s.u)
        return (s, overflow), outputs(s)

    def _outputs(s: State):
        x = arr.points.astype(s.u.dtype) + s.u
        sig = _nodal_stress(arr, _element_stress(arr, m, s.u, s.visco, cfg))
        kin = 0.5 * jnp.sum(mass[:, None] * s.v ** 2)
        stored = _stored_energy(arr, m, s.u, s.visco, hg, cfg)
        if cfg.contact_capacity:
            stored = stored + _contact_energy(arr, x)
        return x, s.v, sig, Energies(kin, stored, s.w_visc, s.w_damp, s.w_ext)

    outputs = over_cases(_outputs, -1, 0)     # per frame, case axis first (every State leaf has it last)
    body = jax.checkpoint(frame_fn) if cfg.checkpoint else frame_fn
    (state, overflow), outs = jax.lax.scan(body, (state0, jnp.zeros(bshape, bool)), jnp.arange(cfg.n_frames))
    first = outputs(state0)
    stack = lambda a, b: jnp.concatenate([a[None], b])
    q, v, sig, en = jax.tree_util.tree_map(stack, first, outs)
    t = jnp.arange(cfg.n_frames + 1) * cfg.frame_dt
    if batched:   # frames first → cases first
        q, v, sig, en = jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), (q, v, sig, en))
        t = jnp.broadcast_to(t, bshape + t.shape)
    return Result(t, q, v, sig, en, state.inverted, state.inversion_time, overflow)


_simulate = jax.jit(_simulate_impl, static_argnames=("cfg", "batched"))


def max_frequency(problem: Problem, material: Material, iterations: int = 200, seed: int = 0) -> float:
    """Largest angular eigenfrequency ω_max [1/time] of M⁻¹K at the reference state (power iteration on the
    tangent stiffness, matrix-free through `jax.jvp`). The central-difference scheme is stable for h < 2/ω_max."""
    arr = problem.arrays
    mass = lumped_mass(problem, material)[:, None]
    x0 = arr.points

    @jax.jit
    def apply(u):
        _, ku = jax.jvp(lambda x: internal_force(problem, material, x), (x0,), (u,))
        return ku * arr.free / mass

    u = jax.random.normal(jax.random.PRNGKey(seed), x0.shape) * arr.free
    lam = 0.0
    for _ in range(iterations):
        w = apply(u)
        lam = float(jnp.vdot(u, w) / jnp.vdot(u, u))
        u = w / jnp.linalg.norm(w)
    return math.sqrt(max(lam, 0.0))
