"""The learned linear GENERIC model: quadratic energy, linear dissipation, stepped by backward Euler.

About the rest state z₀ = (X, 0, 0) the GENERIC dynamics dz/dt = L∇E + M∇S of a body at a fixed temperature
reduce to::

    E(z) = ½ vᵀ M v + ½ uᵀ K u,      u = q − X,
    u̇ = v,    M v̇ = f − K u − α M v,    σ̇ = S v,

with M = diag(m_i) the lumped nodal masses, K symmetric positive semi-definite (the stiffness), α ≥ 0 the mass
damping (the dissipation α vᵀ M v ≥ 0 is the entropy production at a fixed temperature) and S [6N, 3N] the stress
observable (σ̇ = S v, stress order S11 S22 S33 S12 S13 S23). One frame Δt is one backward-Euler step::

    A Δv = f Δt / Δt² − α M v / Δt + (c/Δt) M w − ...,   A = K + c M,   c = (1 + αΔt) / Δt²,   w = u + Δt v,
    v' = v + Δv,   u' = u + Δt v',   σ' = σ + Δt S v',

solved exactly by the dense A⁻¹ [3N, 3N] of the free degrees of freedom, computed once when the model is prepared.
Since K is PSD and α, m > 0, backward Euler never creates energy whatever the state, force and step: with f = 0,
E(z') ≤ E(z) at every step (tested). Clamped nodes (node_type ≠ 0) keep q and v.

The operators are learned by `tignn_jax.train.linear` (coefficient networks over the rest geometry, whose options
are `LinearConfig`) or taken from the FEM's rest linearisation (`from_rest_linearization`): the model stores K and
S as lists of 3×3 and 6×3 node blocks, so memory and the products by K and S grow with the mesh; A⁻¹ is dense.
"""
from __future__ import annotations

import dataclasses
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

STORED = ("k_rows", "k_cols", "k", "s_rows", "s_cols", "s", "mass", "alpha", "dt")
S_GROUPS = 4                    # groups of S's rows by their count of blocks (`s_rows_layout`), at most
AINV_SPLIT = 4                  # A⁻¹ of at least AINV_BLOCK_BYTES kept as the upper blocks of a 4 × 4 split
AINV_BLOCK_BYTES = 32 * 2 ** 20


class LinearConfig(NamedTuple):
    """How `tignn_jax.train.linear` parameterises K and S (the step itself reads only the assembled operators).

    Attributes:
      hidden: width of the coefficient networks (flax MLPs over rotation-invariant rest-mesh features).
      mu, kappa: initial shear and bulk modulus scales, in the data's stress units (learned).
      density: initial density, mass per volume in the data's units (learned).
      alpha: initial mass damping α, 1/time (learned).
      stabilisation: initial scale of the edge stabilisation channel.
      tied_pressure: the stress's pressure is the energy's, κ tr ∇u (σ = ∂ψ/∂ε for the volumetric part).
      element_channels: each cell adds its own deviatoric strain energy with a learned shear modulus.
      cell_pressure: with ``element_channels``, each cell also adds its own volume change with a learned bulk
        modulus (the volumetric strain of a hex mesh lives in its cells).
      prior: K and S also hold the FEM's rest linearisation times learned global scales that start at 1.
    """
    hidden: int = 32
    mu: float = 1.0
    kappa: float = 10.0
    density: float = 1.0
    alpha: float = 1.0
    stabilisation: float = 0.1
    tied_pressure: bool = False
    element_channels: bool = False
    cell_pressure: bool = False
    prior: bool = False


@dataclasses.dataclass(frozen=True)
class LinearGeneric:
    """The linear GENERIC model class (see the module docstring); ``config`` records how K and S were learned.

    Stored arrays (``stored``): ``k_rows``, ``k_cols`` [B] int32 and ``k`` [B, 3, 3] (K's non-zero node blocks,
    force per length), ``s_rows``, ``s_cols`` [C] int32 and ``s`` [C, 6, 3] (S's node blocks, stress per
    length), ``mass`` [N] (nodal masses), ``alpha`` [1] (1/time), ``dt`` [1] (the frame step, time).
    """
    config: LinearConfig = LinearConfig()
    name: ClassVar[str] = "linear"
    stable_by_construction: ClassVar[bool] = True   # no step creates energy: guard for finiteness only

    def prepare(self, stored: dict, mesh: dict) -> dict:
        """The arrays the step reads: the stored operators, A⁻¹ (dense, or its upper blocks when large), S's rows
        in groups (`s_rows_layout`), the rest positions ``q0`` and the free-node mask ``free`` [N, 1].

        Raises:
          ValueError: an operator is missing or sized for another mesh.
        """
        missing = [k for k in STORED if k not in stored]
        if missing:
            raise ValueError(f"a linear model needs the arrays {list(STORED)}, missing {missing}")
        node_type = np.asarray(mesh["node_type"])
        n = len(node_type)
        if np.shape(stored["mass"]) != (n,):
            raise ValueError(f"the operators are for {np.shape(stored['mass'])[0]} nodes, the mesh has {n}")
        out = {k: np.asarray(stored[k]) for k in STORED}
        ainv = inverse(out, node_type)
        if 4 * ainv.size >= AINV_BLOCK_BYTES and ainv_blocks(ainv, n):
            out["ainv_blocks"] = ainv_blocks(ainv, n)
        else:
            out["ainv"] = ainv
        out["s_layout"] = s_rows_layout(out, n)
        out["q0"] = np.asarray(mesh["q0"], np.float32)
        out["free"] = (node_type == 0)[:, None].astype(np.float32)
        return jax.tree_util.tree_map(jnp.asarray, out)

    def stored(self, arrays: dict) -> dict:
        """The arrays a model file keeps (``STORED``); A⁻¹ and the row layout are derived when loading."""
        return {k: np.asarray(arrays[k]) for k in STORED}

    def step_state(self, arrays: dict, z, f):
        """One backward-Euler frame of one body: z [N, 12], f [N, 3] (force) → z' [N, 12] (in z's dtype)."""
        return z + increment(arrays, z, f.astype(z.dtype))

    def diagnostics(self, arrays: dict, z, f, z_next) -> dict:
        """The energy balance of one frame z → z_next under f: {"energy": E(z_next), "work": W = f · Δu over the
        free nodes, "dissipation": D = W − (E(z_next) − E(z))}, work units. D ≥ 0 for a backward-Euler step of a
        PSD K with α ≥ 0: the model never creates energy."""
        return energy_balance(energy, arrays, z, f, z_next)


def from_rest_linearization(lin, frame_dt: float) -> dict:
    """Stored arrays (`LinearGeneric.stored`) of a `fem.implicit.RestLinearization`: the FEM's rest
    linearisation of a scene, or operators learned by `tignn_jax.train.linear`, stepped every ``frame_dt``."""
    return {"k_rows": np.asarray(lin.k_rows, np.int32), "k_cols": np.asarray(lin.k_cols, np.int32),
            "k": np.asarray(lin.k_blocks, np.float32), "s_rows": np.asarray(lin.s_rows, np.int32),
            "s_cols": np.asarray(lin.s_cols, np.int32), "s": np.asarray(lin.s_blocks, np.float32),
            "mass": np.asarray(lin.mass, np.float32), "alpha": np.array([lin.alpha], np.float32),
            "dt": np.array([frame_dt], np.float32)}


def increment(arrays: dict, z, f):
    """z' − z [N, 12] of the backward-Euler frame (module docstring), with one sparse product (by S).

    On the free degrees of freedom A = K + c M, so A⁻¹ K w = w − c A⁻¹ M w: the stiffness term of the right-hand
    side enters through A⁻¹ and no product by K is needed.
    """
    h, alpha, free, m = _constants(arrays, z.dtype)
    c = (1.0 + alpha * h) / h ** 2
    u, v = (z[:, :3] - arrays["q0"].astype(z.dtype)) * free, z[:, 3:6] * free
    w = u + h * v
    rhs = ((f - alpha * m * v) / h + (c / h) * m * w) * free
    dv = (apply_ainv(arrays, rhs.reshape(-1)).reshape(-1, 3) - w / h) * free
    return jnp.concatenate([h * v + h * dv, dv, h * apply_s(arrays, v + dv)], axis=1)


def energy_balance(energy_fn, arrays: dict, z, f, z_next) -> dict:
    """{"energy": E(z_next), "work": W = f · Δq over the free nodes, "dissipation": W − (E(z_next) − E(z))} of one
    frame z → z_next [N, 12] under f [N, 3], with E = ``energy_fn(arrays, z)`` (a model class's ``diagnostics``)."""
    free = arrays["free"].astype(z.dtype)
    work = jnp.sum(f.astype(z.dtype) * (z_next[:, :3] - z[:, :3]) * free)
    e0, e1 = energy_fn(arrays, z), energy_fn(arrays, z_next)
    return {"energy": e1, "work": work, "dissipation": work - (e1 - e0)}


def stress_of(arrays: dict, u):
    """S u [N, 6]: the stress of a displacement u [N, 3] from rest (zero at clamped nodes' u)."""
    return apply_s(arrays, u * arrays["free"].astype(u.dtype))


def energy(arrays: dict, z):
    """E(z) = ½ vᵀ M v + ½ uᵀ K u over the free nodes (work units), z [N, 12] → []."""
    free = arrays["free"].astype(z.dtype)
    u, v = (z[:, :3] - arrays["q0"].astype(z.dtype)) * free, z[:, 3:6] * free
    m = arrays["mass"].astype(z.dtype)[:, None]
    return 0.5 * jnp.sum(m * v * v) + 0.5 * jnp.sum(u * apply_k(arrays, u))


def apply_k(arrays: dict, x):
    """K x: [N, 3] → [N, 3], by K's node blocks."""
    y = jnp.einsum("bij,bj->bi", arrays["k"].astype(x.dtype), x[arrays["k_cols"]])
    return jax.ops.segment_sum(y, arrays["k_rows"], x.shape[0])


def apply_s(arrays: dict, x):
    """S x: [N, 3] → [N, 6], row by row in `s_rows_layout`'s groups (a gather and a contraction per group)."""
    layout = arrays["s_layout"]
    parts = [jnp.einsum("nik,nk->ni", blocks.astype(x.dtype), x[cols].reshape(cols.shape[0], -1))
             for cols, blocks in zip(layout["cols"], layout["blocks"])]
    return jnp.concatenate(parts)[layout["order"]]


def apply_ainv(arrays: dict, r):
    """A⁻¹ r for a flat [3N] right-hand side: one dense product, or by the upper blocks of `ainv_blocks`, each
    off-diagonal block used for both of its products one after the other (it is read from memory once)."""
    if "ainv" in arrays:
        return arrays["ainv"].astype(r.dtype) @ r
    blocks = arrays["ainv_blocks"]
    k = len(blocks["diag"])
    edges = np.concatenate([[0], np.cumsum([b.shape[0] for b in blocks["diag"]])])
    xs = [r[edges[i]:edges[i + 1]] for i in range(k)]
    ys = [blocks["diag"][i].astype(r.dtype) @ xs[i] for i in range(k)]
    for (i, j), b in zip(_upper_pairs(k), blocks["upper"]):
        b = b.astype(r.dtype)
        ys[i] = ys[i] + b @ xs[j]
        ys[j] = ys[j] + xs[i] @ b
    return jnp.concatenate(ys)


def _upper_pairs(k: int):
    return [(i, j) for i in range(k) for j in range(i + 1, k)]


def _constants(arrays, dtype):
    h = arrays["dt"].reshape(-1)[0].astype(dtype)
    alpha = arrays["alpha"].reshape(-1)[0].astype(dtype)
    return h, alpha, arrays["free"].astype(dtype), arrays["mass"].astype(dtype)[:, None]


def operator(stored: dict, node_type) -> np.ndarray:
    """A = K + (1 + αΔt)/Δt² M [3N, 3N] float64, dense, identity on the clamped nodes' rows and columns."""
    n = len(np.asarray(node_type))
    K = np.zeros((n, n, 3, 3))
    K[np.asarray(stored["k_rows"], np.int64), np.asarray(stored["k_cols"], np.int64)] = np.asarray(stored["k"])
    return with_mass_and_clamps(K.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n), stored, node_type)


def with_mass_and_clamps(K, stored: dict, node_type) -> np.ndarray:
    """K + (1 + αΔt)/Δt² M for a dense stiffness K [3N, 3N] (changed in place) and the stored masses, α and Δt,
    made the identity on the clamped nodes' rows and columns."""
    h = float(np.asarray(stored["dt"]).reshape(-1)[0])
    alpha = float(np.asarray(stored["alpha"]).reshape(-1)[0])
    A = K
    A[np.diag_indices(A.shape[0])] += (1.0 + alpha * h) / h ** 2 * np.repeat(np.asarray(stored["mass"], np.float64), 3)
    free = np.repeat(np.asarray(node_type) == 0, 3)
    A[~free, :] = 0.0
    A[:, ~free] = 0.0
    A[~free, ~free] = 1.0
    return A


def inverse(stored: dict, node_type) -> np.ndarray:
    """A⁻¹ [3N, 3N] float32 (inverted in float64), identity on the clamped nodes' rows and columns."""
    return np.linalg.inv(operator(stored, node_type)).astype(np.float32)


def ainv_blocks(ainv, n_nodes: int, k: int = AINV_SPLIT, tol: float = 1e-5) -> dict:
    """A symmetric A⁻¹ [3N, 3N] as {"diag": k diagonal blocks, "upper": the blocks (i, j), i < j, row-major} of a
    ``k`` × ``k`` split of the degrees of freedom at node boundaries; {} where A⁻¹ is not symmetric to ``tol``
    of its largest entry or too small to split (the step then keeps the dense product)."""
    a = np.asarray(ainv, np.float32)
    if a.shape != (3 * n_nodes, 3 * n_nodes):
        raise ValueError(f"A⁻¹ of shape {a.shape} does not match a mesh of {n_nodes} nodes")
    scale = float(np.abs(a).max()) if a.size else 0.0
    if n_nodes < k or not np.isfinite(scale) or float(np.abs(a - a.T).max()) > tol * scale:
        return {}
    e = 3 * np.round(np.linspace(0, n_nodes, k + 1)).astype(int)
    return {"diag": [a[e[i]:e[i + 1], e[i]:e[i + 1]].copy() for i in range(k)],
            "upper": [a[e[i]:e[i + 1], e[j]:e[j + 1]].copy() for i, j in _upper_pairs(k)]}


def s_rows_layout(stored: dict, n_nodes: int, max_groups: int = S_GROUPS, group_slots: int = 2048) -> dict:
    """S's node blocks row by row (ELLPACK in groups of rows): the nodes sorted by their count of blocks and split
    into at most ``max_groups`` groups, each padded to its widest row, the split chosen to minimise the padded
    slots plus ``group_slots`` per group.

    Returns:
      {"cols": [n_g, D_g] int32 per group (padding: the row's own node), "blocks": [n_g, 6, D_g·3] per group
      (row i's blocks side by side, padding zero: one contraction with the gathered [n_g, D_g·3] displacements,
      in the layout the contraction reads, whether the arrays are a program's constants or its arguments),
      "order": [N] int32, each node's row in the groups' concatenated output}.
    """
    rows = np.asarray(stored["s_rows"]).astype(np.int64)
    cols = np.asarray(stored["s_cols"]).astype(np.int64)
    blocks = np.asarray(stored["s"], np.float32)
    if rows.size and (rows.min() < 0 or rows.max() >= n_nodes):
        raise ValueError(f"s_rows reach node {rows.max()} of a mesh of {n_nodes} nodes")
    count = np.bincount(rows, minlength=n_nodes)
    nodes = np.argsort(count, kind="stable")
    sorted_count = np.maximum(count[nodes], 1)
    best = np.full((max_groups + 1, n_nodes + 1), np.inf)
    cut = np.zeros((max_groups + 1, n_nodes + 1), np.int64)
    best[0, 0] = 0.0
    ends = np.unique(np.concatenate([np.searchsorted(sorted_count, sorted_count, side="right"), [n_nodes]]))
    for g in range(1, max_groups + 1):
        for k in ends:
            starts = np.concatenate([[0], ends[ends < k]])
            cost = best[g - 1, starts] + (k - starts) * sorted_count[k - 1] + group_slots
            best[g, k], cut[g, k] = cost.min(), starts[np.argmin(cost)]
    g = int(np.argmin(best[1:, n_nodes])) + 1
    bounds, k = [n_nodes], n_nodes
    while g > 0:
        k = int(cut[g, k])
        bounds.append(k)
        g -= 1
    bounds = bounds[::-1]
    order = np.lexsort((cols, rows))
    rows, cols, blocks = rows[order], cols[order], blocks[order]
    slot = np.arange(len(rows)) - np.concatenate([[0], np.cumsum(count)[:-1]])[rows]
    out = {"cols": [], "blocks": []}
    position = np.empty(n_nodes, np.int64)
    for a, b in zip(bounds[:-1], bounds[1:]):
        members = nodes[a:b]
        position[members] = np.arange(a, b)
        local = np.full(n_nodes, -1)
        local[members] = np.arange(b - a)
        width = int(sorted_count[b - 1])
        g_cols = np.tile(members.astype(np.int32)[:, None], (1, width))
        g_blocks = np.zeros((b - a, width) + blocks.shape[1:], np.float32)
        sel = local[rows] >= 0
        g_cols[local[rows[sel]], slot[sel]] = cols[sel]
        np.add.at(g_blocks, (local[rows[sel]], slot[sel]), blocks[sel])
        out["cols"].append(g_cols)
        out["blocks"].append(np.ascontiguousarray(g_blocks.transpose(0, 2, 1, 3).reshape(b - a, 6, 3 * width)))
    out["order"] = position.astype(np.int32)
    return out
