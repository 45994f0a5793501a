"""Training the linear GENERIC model (`tignn_jax.simulators.LinearGeneric`): its operators from graph networks.

The model is E = ½ vᵀ M v + ½ uᵀ K u, dissipation α vᵀ M v and σ̇ = S v (see `tignn_jax.simulators.linear`).
Here K and S are *learned* from trajectories: K = Σ_i B_iᵀ B_i (+ Σ_t B_tᵀ B_t) is assembled from channels
computed by message passing over each node's one-ring (and, with ``element_channels``, each cell),

    ∇u_i = Σ_j (u_j − u_i) ⊗ g_ij        (a learned gradient operator; it starts at the mesh's volume-averaged one)
    B_i u = [√(2 μ_i V_i) dev sym ∇u_i,  √(κ_i V_i) tr ∇u_i,  √k_ij (u_j − u_i − ∇u_i Δx_ij) for each edge]
    B_t u = √(2 μ_t V_t) dev sym ∇u_t     (the cell's own strain)

(nodal and cell strain energies with learned shear and bulk moduli fields and a learned edge stabilisation; the
gradient weights are projected so that every linear displacement field is read exactly, so rigid motions store
no energy), and the stress observable S: the nodes' deviatoric stress 2 μˢ_i dev sym ∇ˢu_i by a second learned
gradient operator and the pressure κ tr ∇u (the energy's with ``tied_pressure``), recovered at the nodes through
the mesh's node → cell → node averaging with a learned share. The coefficients come from flax MLPs over
rotation-invariant features of the rest mesh, so the model is equivariant to rotations of the mesh; density and
damping are learned scalars. With ``prior`` K and S also hold the FEM's rest linearisation times learned scales.
K is PSD by construction and α, ρ > 0, so the trained model's backward-Euler step never creates energy.

`train` fits whole rollouts from rest through a dense Cholesky factor of A = (1 + αΔt) M / Δt² + K on the free
degrees of freedom (the solve differentiated implicitly); `run` is the recipe-level entry point that
`tignn train --config` calls: it trains, packs the operators into a model (`to_rest_linearization`) and writes it.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import flax.linen as nn
from flax import serialization
import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax.simulators.linear import LinearConfig
from tignn_jax.train import is_count, is_number

VOIGT = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))   # S11 S22 S33 S12 S13 S23, the data's order


class Geometry(NamedTuple):
    """Rest-mesh data of the model (numpy; fixed, never learned).

    nbr [N, D] neighbour node ids (padded with the node itself), mask [N, D] real neighbours, dx [N, D, 3] rest
    edge vectors x_j − x_i over ``h`` (the median edge length), g_ls [N, D, 3] least-squares gradient weights
    (Σ_j dx_ij ⊗ g_ls_ij = I, in units of 1/h), g_avg [N, D, 3] the volume-averaged gradient weights of the
    linear tets around each node (Σ_t V_t ∇N_j^t / Σ_t V_t over the tets t holding i and j; the mesh's own
    discrete gradient, also consistent; g_ls for hexes, whose averaged gradient reaches the cells' diagonal
    nodes, outside the one-ring), volume [N] lumped nodal volumes (sum over a node's cells of a quarter or an
    eighth of their volume), free [N] bool (node_type == 0), h the length scale; cells [K, 4] or [K, 8],
    cell_grad [K, 4|8, 3] the cells' shape-function gradients ∇N_a (1/length; for hexes the uniform gradient
    (1/V) ∫ ∇N_a dV of `fem.elements.hex_geometry`) and cell_volume [K]. The node → cell → node averaging of a
    nodal field (`smooth`) is Σ_{t ∋ i} (V_t / n_t) mean_{j ∈ t} x_j / V_i, built from the cells. k0 [3N, 3N] and
    s0 [6N, 3N]: a prior's stiffness and nodal stress operators (`with_prior`), None without one."""
    nbr: np.ndarray
    mask: np.ndarray
    dx: np.ndarray
    g_ls: np.ndarray
    g_avg: np.ndarray
    volume: np.ndarray
    free: np.ndarray
    h: float
    cells: np.ndarray
    cell_grad: np.ndarray
    cell_volume: np.ndarray
    k0: np.ndarray | None = None
    s0: np.ndarray | None = None


def with_prior(geo: Geometry, lin) -> Geometry:
    """The geometry with a prior's operators: K₀ and S₀ of a `fem.implicit.RestLinearization` on the same nodes
    (the FEM's rest linearisation), as dense arrays, for a model with ``LinearConfig(prior=True)``."""
    n = geo.nbr.shape[0]
    if np.asarray(lin.mass).shape != (n,):
        raise ValueError(f"the prior has {np.asarray(lin.mass).shape[0]} nodes, the mesh {n}")
    k0 = np.zeros((n, 3, n, 3))
    k0[lin.k_rows, :, lin.k_cols, :] = lin.k_blocks
    s0 = np.zeros((n, 6, n, 3))
    s0[lin.s_rows, :, lin.s_cols, :] = lin.s_blocks
    return geo._replace(k0=k0.reshape(3 * n, 3 * n), s0=s0.reshape(6 * n, 3 * n))


def geometry(q0, edges, cells, node_type) -> Geometry:
    """`Geometry` of a mesh: q0 [N,3], edges [2,E] directed (both directions), cells [K,4] tets or [K,8] hexes,
    node_type [N] (0 free)."""
    q0 = np.asarray(q0, np.float64)
    n = q0.shape[0]
    edges = np.asarray(edges)
    if edges.ndim != 2 or edges.shape[0] != 2:
        raise ValueError(f"edges must be [2, E], got shape {edges.shape}")
    cells = np.asarray(cells)
    if cells.ndim != 2 or cells.shape[1] not in (4, 8):
        raise ValueError(f"cells must be [K, 4] tets or [K, 8] hexes, got shape {cells.shape}")
    node_type = np.asarray(node_type)
    if node_type.shape != (n,):
        raise ValueError(f"node_type must be [{n}], got shape {node_type.shape}")
    lists = [[] for _ in range(n)]
    for s, r in zip(*edges):
        if s != r and s not in lists[r]:
            lists[r].append(int(s))
    deg = max(len(x) for x in lists)
    nbr = np.tile(np.arange(n)[:, None], (1, deg))
    mask = np.zeros((n, deg), bool)
    for i, x in enumerate(lists):
        nbr[i, :len(x)] = x
        mask[i, :len(x)] = True
    d = q0[nbr] - q0[:, None, :]
    h = float(np.median(np.linalg.norm(d[mask], axis=-1)))
    dx = d / h * mask[..., None]
    gram = np.einsum("nda,ndb->nab", dx, dx)
    g_ls = np.einsum("nab,ndb->nda", np.linalg.inv(gram), dx) * mask[..., None]
    volume = np.zeros(n)
    x = q0[cells]
    g_avg = g_ls
    if cells.shape[1] == 4:
        vol = np.abs(np.einsum("ka,ka->k", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])) / 6
        grads = _tet_gradients(x)
    else:
        from fem.elements import hex_geometry

        hexes = hex_geometry(q0, cells)
        vol, grads = hexes.volume, hexes.b
        if np.any(vol <= 0):
            raise ValueError(f"hex {int(np.argmin(vol))} has volume {vol.min():.3g} <= 0 (node order inverted?)")
    np.add.at(volume, cells.reshape(-1), np.repeat(vol / cells.shape[1], cells.shape[1]))
    if cells.shape[1] == 4:
        g_avg = _averaged_gradient(grads, cells, vol, volume, nbr, mask) * h
    return Geometry(nbr.astype(np.int32), mask, dx, g_ls, g_avg, volume, node_type == 0, h,
                    cells.astype(np.int32), grads, vol)


def _slots(nbr, mask) -> dict:
    """(i, j) → the slot of neighbour j in node i's row of ``nbr`` (real neighbours only)."""
    return {(int(i), int(j)): d for i in range(nbr.shape[0]) for d, j in enumerate(nbr[i]) if mask[i, d]}


def geometry_from_file(path):
    """(`tignn_jax.data.Dataset`, `Geometry`) of a data-set file, or of several on the same mesh (a list of paths:
    their cases concatenated by `tignn_jax.data.concatenate`): the mesh, edges, clamps and cells.
    Raises ValueError when the files' cells differ."""
    from tignn_jax import data as D

    paths = [path] if isinstance(path, (str, bytes)) or hasattr(path, "__fspath__") else list(path)
    sets, cells = [], None
    for p in paths:
        sets.append(D.load(p))
        with np.load(p, allow_pickle=False) as raw:
            c = raw["cells"] if "cells" in raw.files else _reference_beam_cells(sets[-1].q0, p)
        if cells is not None and not np.array_equal(c, cells):
            raise ValueError(f"data file {p} has other cells than {paths[0]} (not the same mesh)")
        cells = c
    data = D.concatenate(*sets)
    return data, geometry(data.q0, data.edges, cells, data.node_type)


def _reference_beam_cells(q0, path):
    """The cells of a data file that stores none: the reference beam's hexes when its nodes are the reference
    beam's (the Abaqus data, `tignn_jax.data.reference_path`, store nodes and edges only)."""
    from fem import meshes

    ref, cells, _ = meshes.beam_mesh()
    if np.shape(q0) != np.shape(ref) or not np.allclose(q0, ref, atol=1e-5):
        raise ValueError(f"data file {path} has no 'cells' and its nodes are not the reference beam's")
    return np.asarray(cells)


def _tet_gradients(x):
    """[K, 4, 3] shape-function gradients ∇N_a of linear tets with corners x [K, 4, 3]."""
    jac = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=1)     # rows: edges
    inv = np.linalg.inv(jac)                                                                # columns: ∇N_1..3
    return np.concatenate([-inv.sum(axis=2, keepdims=True), inv], axis=2).transpose(0, 2, 1)


def _averaged_gradient(grads, cells, vol, volume, nbr, mask):
    """[N, D, 3]: Σ_{t ∋ i, j} (V_t / 4) ∇N_j^t / V_i, the weight of u_j − u_i in node i's volume-averaged
    gradient over its tets (grads [K,4,3] their ∇N, vol [K], volume [N] lumped volumes)."""
    slot = _slots(nbr, mask)
    out = np.zeros(nbr.shape + (3,))
    for t, cell in enumerate(cells):
        for a, i in enumerate(cell):
            for b, j in enumerate(cell):
                if a != b:
                    out[i, slot[(int(i), int(j))]] += vol[t] / 4 * grads[t, b] / volume[i]
    return out


class MLP(nn.Module):
    """Two swish layers of ``width`` and a zero-initialised linear head of ``out`` units."""
    width: int
    out: int

    @nn.compact
    def __call__(self, x):
        x = nn.swish(nn.Dense(self.width)(x))
        x = nn.swish(nn.Dense(self.width)(x))
        return nn.Dense(self.out, kernel_init=nn.initializers.zeros)(x)


EDGE_OUT = 7    # gradient weights (a, b, c) of the energy, stabilisation, gradient weights (a, b, c) of the stress
NODE_OUT = 5    # log μ, log κ, log μˢ, log κˢ corrections, logit of β


class Coefficients(nn.Module):
    """Per-node and per-edge coefficients of the operators from rotation-invariant rest-mesh features: one
    message-passing round (edge MLP → masked mean at the node), node and edge heads, a cell head with
    ``cells``, and the global log-scales. The zero-initialised heads start the model at the mesh's
    volume-averaged gradient and uniform moduli."""
    width: int
    cells: bool = False
    cell_out: int = 1

    @nn.compact
    def __call__(self, geo):
        mask = geo["mask"][..., None]
        length = jnp.linalg.norm(geo["dx"], axis=-1, keepdims=True)
        along = jnp.sum(geo["dx"] * geo["g_ls"], axis=-1, keepdims=True)
        gnorm = jnp.linalg.norm(geo["g_ls"], axis=-1, keepdims=True)
        along_avg = jnp.sum(geo["dx"] * geo["g_avg"], axis=-1, keepdims=True)
        avg_norm = jnp.linalg.norm(geo["g_avg"], axis=-1, keepdims=True)
        deg = jnp.sum(mask, axis=1) / jnp.mean(jnp.sum(mask, axis=1))
        vol = geo["volume"][:, None] / jnp.mean(geo["volume"])
        clamp = 1.0 - geo["free"][:, None]
        node = jnp.concatenate([jnp.log(vol), deg, clamp], axis=-1)
        edge_in = jnp.concatenate([length, along, gnorm, along_avg, avg_norm,
                                   jnp.broadcast_to(node[:, None], length.shape[:2] + (3,)), node[geo["nbr"]]], axis=-1)
        msg = MLP(self.width, self.width)(edge_in) * mask
        pooled = jnp.sum(msg, axis=1) / jnp.maximum(jnp.sum(mask, axis=1), 1.0)
        node_h = jnp.concatenate([node, pooled], axis=-1)
        node_out = MLP(self.width, NODE_OUT)(node_h)
        edge_h = jnp.concatenate([edge_in, jnp.broadcast_to(node_h[:, None], length.shape[:2] + node_h.shape[-1:]),
                                  node_h[geo["nbr"]]], axis=-1)
        edge_out = MLP(self.width, EDGE_OUT)(edge_h) * mask
        scales = self.param("log_scales", nn.initializers.zeros, (8,))   # μ, κ, μˢ, κˢ, k, μ of the cells, β
        if self.cells:
            cvol = geo["cell_volume"][:, None] / jnp.mean(geo["cell_volume"])
            gsize = jnp.linalg.norm(geo["cell_grad"], axis=-1) * jnp.mean(geo["cell_volume"]) ** (1 / 3)
            cell_in = jnp.concatenate([jnp.log(cvol), jnp.sort(gsize, axis=-1),
                                       jnp.mean(node_h[geo["cells"]], axis=1)], axis=-1)
            cell_out = MLP(self.width, self.cell_out)(cell_in)
        else:
            cell_out = jnp.zeros((0, self.cell_out), node_out.dtype)
        return node_out, edge_out, scales, cell_out


def geometry_arrays(geo: Geometry) -> dict:
    """The `Geometry` as jax arrays in jax's float type (the networks' and operators' input)."""
    real = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    return {"nbr": jnp.asarray(geo.nbr), "mask": jnp.asarray(geo.mask, real), "dx": jnp.asarray(geo.dx),
            "g_ls": jnp.asarray(geo.g_ls), "g_avg": jnp.asarray(geo.g_avg), "volume": jnp.asarray(geo.volume),
            "free": jnp.asarray(geo.free, jnp.float32), "cells": jnp.asarray(geo.cells),
            "cell_grad": jnp.asarray(geo.cell_grad), "cell_volume": jnp.asarray(geo.cell_volume),
            "k0": jnp.asarray(geo.k0 if geo.k0 is not None else np.zeros((0, 0)), real),
            "s0": jnp.asarray(geo.s0 if geo.s0 is not None else np.zeros((0, 0)), real)}


class Operators(NamedTuple):
    """Per-node operator coefficients (jax arrays): g, gs [N, D, 3] gradient weights (1/length) of the energy and
    the stress; mu, kappa, mu_s, kappa_s [N]; k [N, D] edge stabilisation stiffness; gp, kappa_p the stress's
    pressure operator and modulus (the energy's g and κ with ``tied_pressure``, else gs and κˢ); mu_e [K] the
    cells' shear moduli (empty without ``element_channels``); kappa_e [K] the cells' bulk moduli (empty without
    ``cell_pressure``) and kappa_pe [K] the cells' pressure moduli in the stress (kappa_e with ``tied_pressure``,
    else empty); prior_k, prior_s () the scales of the prior's K₀ and S₀ (0 without a prior); beta [N] the share
    of the smoothed deviatoric stress; mass [N]; alpha ()."""
    g: jax.Array
    gs: jax.Array
    mu: jax.Array
    kappa: jax.Array
    mu_s: jax.Array
    kappa_s: jax.Array
    k: jax.Array
    gp: jax.Array
    kappa_p: jax.Array
    mu_e: jax.Array
    kappa_e: jax.Array
    kappa_pe: jax.Array
    prior_k: jax.Array
    prior_s: jax.Array
    beta: jax.Array
    mass: jax.Array
    alpha: jax.Array


def operators(weights, geo: dict, h: float, config: LinearConfig, extra) -> Operators:
    """The learned coefficients. ``extra`` holds the global log-scales of density and damping."""
    if config.cell_pressure and not config.element_channels:
        raise ValueError("cell_pressure needs element_channels")
    if config.prior and geo["k0"].shape[0] == 0:
        raise ValueError("LinearConfig(prior=True) needs a geometry with a prior (tignn_jax.train.linear.with_prior)")
    node_out, edge_out, scales, cell_out = _coefficients(config).apply(weights, geo)
    share = 0.5 if config.element_channels else 1.0
    share_k = 0.5 if config.cell_pressure else 1.0
    unit = geo["dx"] / jnp.maximum(jnp.sum(geo["dx"] ** 2, -1, keepdims=True), 1e-12)
    g = consistent(geo["g_avg"] * (1.0 + edge_out[..., 0:1]) + geo["g_ls"] * edge_out[..., 1:2]
                   + unit * edge_out[..., 2:3], geo) / h
    gs = consistent(geo["g_avg"] * (1.0 + edge_out[..., 4:5]) + geo["g_ls"] * edge_out[..., 5:6]
                    + unit * edge_out[..., 6:7], geo) / h
    mu = share * config.mu * jnp.exp(scales[0] + node_out[:, 0])
    mu_e = share * config.mu * jnp.exp(scales[6] + cell_out[:, 0])
    # the cells' bulk moduli share the nodes' global scale; their own correction is the cell head's second output
    kappa_e = (share_k * config.kappa * jnp.exp(scales[1] + cell_out[:, 1]) if config.cell_pressure
               else jnp.zeros((0,), mu_e.dtype))
    kappa = share_k * config.kappa * jnp.exp(scales[1] + node_out[:, 1])
    mu_s = config.mu * jnp.exp(scales[2] + node_out[:, 2])
    kappa_s = config.kappa * jnp.exp(scales[3] + node_out[:, 3])
    k = config.stabilisation * config.mu * h * jnp.exp(scales[4] + edge_out[..., 3]) * geo["mask"]
    mass = config.density * jnp.exp(extra["log_density"]) * geo["volume"]
    alpha = config.alpha * jnp.exp(extra["log_alpha"])
    gp, kappa_p = (g, kappa) if config.tied_pressure else (gs, kappa_s)
    beta = jax.nn.sigmoid(scales[7] + node_out[:, 4])
    kappa_pe = kappa_e if config.tied_pressure else jnp.zeros((0,), mu_e.dtype)
    prior_k, prior_s = ((jnp.exp(extra["log_k0"]), jnp.exp(extra["log_s0"])) if config.prior
                        else (jnp.zeros((), mu.dtype), jnp.zeros((), mu.dtype)))
    return Operators(g, gs, mu, kappa, mu_s, kappa_s, k, gp, kappa_p, mu_e, kappa_e, kappa_pe, prior_k, prior_s,
                     beta, mass, alpha)


def _coefficients(config: LinearConfig) -> Coefficients:
    return Coefficients(config.hidden, config.element_channels, 2 if config.cell_pressure else 1)


def consistent(g_raw, geo: dict):
    """Gradient weights [N, D, 3] that reproduce the gradient of every linear field exactly
    (Σ_j Δx_ij ⊗ g_ij = I): g = g̃ + (I − Σ_j Δx_ij ⊗ g̃_ij)ᵀ g_ls. So rigid motions carry no strain and a uniform
    strain is seen as itself, whatever the networks output."""
    g_raw = g_raw * geo["mask"][..., None]
    defect = jnp.eye(3) - jnp.einsum("nda,ndb->nab", geo["dx"], g_raw)
    return g_raw + jnp.einsum("nab,nda->ndb", defect, geo["g_ls"])


def _gradient(u_local, g):
    """∇u_i [3,3] (∂u_a/∂x_b) from the one-ring's displacements u_local [D+1, 3] (slot 0: the node)."""
    return jnp.einsum("da,db->ab", u_local[1:] - u_local[:1], g)


def channels(u_local, g, mu, kappa, k, volume, dx_len):
    """B_i u: the node's energy channels (½|B_i u|² is its share of the stored energy)."""
    grad = _gradient(u_local, g)
    eps = 0.5 * (grad + grad.T)
    tr = jnp.trace(eps)
    dev = eps - tr / 3.0 * jnp.eye(3)
    lin = u_local[1:] - u_local[:1] - jnp.einsum("ab,db->da", grad, dx_len)
    return jnp.concatenate([jnp.sqrt(2.0 * mu * volume) * dev.reshape(-1), jnp.sqrt(kappa * volume) * tr[None],
                            (_safe_sqrt(k)[:, None] * lin).reshape(-1)])


def _safe_sqrt(x):
    """√x with a zero (not NaN) gradient at the padded slots' x = 0."""
    return jnp.where(x > 0, jnp.sqrt(jnp.where(x > 0, x, 1.0)), 0.0)


def stress_parts(u_local, gs, mu_s, gp, kappa_p):
    """(2 μˢ dev sym ∇ˢu [6] in the data's Voigt order, κᵖ tr ∇ᵖu) at a node from its one-ring's displacements:
    the deviatoric part by the gradient weights gs, the pressure by gp."""
    grad = _gradient(u_local, gs)
    eps = 0.5 * (grad + grad.T)
    dev = 2.0 * mu_s * (eps - jnp.trace(eps) / 3.0 * jnp.eye(3))
    return jnp.stack([dev[a, b] for a, b in VOIGT]), kappa_p * jnp.trace(_gradient(u_local, gp))


def local_blocks(ops: Operators, geo: dict, h: float):
    """K_local [N, 3(D+1), 3(D+1)]: each node's stiffness share B_iᵀB_i on its one-ring's displacements (slot 0
    the node, slots 1.. its neighbours)."""
    d = geo["nbr"].shape[1]
    zero = jnp.zeros((d + 1, 3), ops.mu.dtype)
    dx_len = geo["dx"] * h

    def per_node(g, mu, kappa, k, volume, dxl):
        b = jax.jacfwd(lambda u: channels(u, g, mu, kappa, k, volume, dxl))(zero).reshape(-1, 3 * (d + 1))
        return b.T @ b

    return jax.vmap(per_node)(ops.g, ops.mu, ops.kappa, ops.k, geo["volume"], dx_len)


def local_dofs(geo: dict):
    """[N, 3(D+1)] global degree-of-freedom ids of each node's one-ring slots."""
    nodes = jnp.concatenate([jnp.arange(geo["nbr"].shape[0])[:, None], geo["nbr"]], axis=1)
    return (3 * nodes[..., None] + jnp.arange(3)).reshape(nodes.shape[0], -1)


def dense_stiffness(k_local, dofs, n_nodes: int):
    """K [3N, 3N] assembled from the nodes' shares."""
    k = jnp.zeros((3 * n_nodes, 3 * n_nodes), k_local.dtype)
    return k.at[dofs[:, :, None], dofs[:, None, :]].add(k_local)


def stiffness(ops: Operators, geo: dict, h: float):
    """K [3N, 3N]: the nodes' shares and, with element channels, the cells' B_tᵀB_t."""
    k_local = local_blocks(ops, geo, h)
    K = dense_stiffness(k_local, local_dofs(geo), geo["nbr"].shape[0])
    if geo["k0"].shape[0]:
        K = K + ops.prior_k * geo["k0"]
    if ops.mu_e.shape[0] == 0:
        return K

    n_per = geo["cells"].shape[1]
    kappa_e = ops.kappa_e if ops.kappa_e.shape[0] else jnp.zeros_like(ops.mu_e)

    def per_cell(grad, mu, kappa, vol):
        def b(u):
            g = jnp.einsum("da,db->ab", u, grad)
            eps = 0.5 * (g + g.T)
            tr = jnp.trace(eps)
            return jnp.concatenate([jnp.sqrt(2.0 * mu * vol) * (eps - tr / 3.0 * jnp.eye(3)).reshape(-1),
                                    _safe_sqrt(kappa * vol) * tr[None]])
        m = jax.jacfwd(b)(jnp.zeros((n_per, 3), grad.dtype)).reshape(10, 3 * n_per)
        return m.T @ m

    k_cells = jax.vmap(per_cell)(geo["cell_grad"], ops.mu_e, kappa_e, geo["cell_volume"])
    dofs = (3 * geo["cells"][..., None] + jnp.arange(3)).reshape(geo["cells"].shape[0], 3 * n_per)
    return K.at[dofs[:, :, None], dofs[:, None, :]].add(k_cells)


def cell_to_node(x_cell, geo: dict):
    """[N, c]: the volume-weighted mean over each node's cells of the cell values x_cell [K, c]
    (Σ_{t ∋ i} (V_t / n_t) x_t / V_i)."""
    n_per = geo["cells"].shape[1]
    w = (geo["cell_volume"] / n_per)[:, None, None] * jnp.broadcast_to(x_cell[:, None], (x_cell.shape[0], n_per)
                                                                        + x_cell.shape[1:])
    total = jnp.zeros((geo["volume"].shape[0],) + x_cell.shape[1:], x_cell.dtype).at[geo["cells"]].add(w)
    return total / geo["volume"][:, None]


def smooth(x, geo: dict):
    """[N, c]: the node → cell → node average of a nodal field x [N, c] (the mean of each cell's nodes, then
    `cell_to_node`): what a nodal value recovered from cell values is."""
    return cell_to_node(jnp.mean(x[geo["cells"]], axis=1), geo)


def nodal_stress(u, ops: Operators, geo: dict):
    """σ [..., N, 6] of displacements u [..., N, 3]: the nodes' own deviatoric stresses σ̂ and pressures p̂
    (`stress_parts`), smoothed over each node's one-ring by the mesh's node → cell → node averaging W (what a
    nodal stress recovered from cell stresses is): σ_i = (1 − β_i) σ̂_i + β_i (W σ̂)_i + (W p̂)_i I, with β_i ∈ (0, 1)
    learned. With cell bulk moduli and a tied pressure the cells' own pressures κ_t tr ∇u_t, averaged to the nodes,
    join the nodes' (the energy's volumetric stress)."""
    def one(uu):
        local = jnp.concatenate([uu[:, None], uu[geo["nbr"]]], axis=1)
        dev, p = jax.vmap(stress_parts)(local, ops.gs, ops.mu_s, ops.gp, ops.kappa_p)
        dev = (1.0 - ops.beta)[:, None] * dev + ops.beta[:, None] * smooth(dev, geo)
        p = smooth(p[:, None], geo)
        if ops.kappa_pe.shape[0]:
            volume_change = jnp.einsum("kda,kda->k", uu[geo["cells"]], geo["cell_grad"])     # tr ∇u_t
            p = p + cell_to_node((ops.kappa_pe * volume_change)[:, None], geo)
        out = dev + p * jnp.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], dev.dtype)
        if geo["s0"].shape[0]:
            out = out + ops.prior_s * (geo["s0"] @ uu.reshape(-1)).reshape(out.shape)
        return out
    flat = u.reshape((-1,) + u.shape[-2:])
    return jax.vmap(one)(flat).reshape(u.shape[:-1] + (6,))


def rollout(ops: Operators, geo: dict, h: float, forces, dt: float, v0=None):
    """Backward-Euler rollouts from the rest positions: forces [C, T, N, 3] → (u, v, σ) each [C, T, N, ·]
    (frames 1..T), starting with velocities v0 [C, N, 3] (None: at rest). Clamped nodes stay at rest."""
    K = stiffness(ops, geo, h)
    u, v = solve_rollout(K, ops.mass, ops.alpha, np.asarray(geo["free"]) > 0, forces, dt, v0)
    return u, v, nodal_stress(u, ops, geo)


def solve_rollout(K, mass, alpha, free, forces, dt: float, v0=None):
    """(u, v) [C, T, N, 3]: backward Euler of M v̇ = f − K u − α M v, u̇ = v from u = 0 and v = v0 [C, N, 3]
    (None: 0) under forces [C, T, N, 3] (force k acts during frame k → k+1), by one Cholesky factor of
    A = (1 + αΔt) M / Δt² + K on the free degrees of freedom (``free`` [N] bool, numpy)."""
    n = mass.shape[0]
    idx = np.where(np.repeat(np.asarray(free), 3))[0]
    m3 = jnp.repeat(mass, 3)[idx]
    c = (1.0 + alpha * dt) / dt ** 2
    A = K[idx][:, idx] + jnp.diag(c * m3)
    # the factor is not differentiated: gradients reach A through its product alone (implicit differentiation of
    # the solve, `lax.custom_linear_solve`), which saves the Cholesky factor's own backward pass (2n³ flops)
    chol = (jax.lax.stop_gradient(jax.scipy.linalg.cho_factor(A, lower=True)[0]), True)
    f = forces.reshape(forces.shape[:2] + (-1,))[..., idx]          # [C, T, F]

    def solve(b):
        return jax.lax.custom_linear_solve(lambda x: A @ x, b, lambda _, r: jax.scipy.linalg.cho_solve(chol, r),
                                           symmetric=True)

    def frame(carry, fk):
        u, v = carry
        u_next = solve((c * m3 * u + m3 * v / dt + fk).T).T
        v_next = (u_next - u) / dt
        return (u_next, v_next), (u_next, v_next)

    zeros = jnp.zeros((forces.shape[0], idx.size), A.dtype)
    start = zeros if v0 is None else jnp.asarray(v0, A.dtype).reshape(forces.shape[0], -1)[:, idx]
    _, (us, vs) = jax.lax.scan(frame, (zeros, start), jnp.swapaxes(f, 0, 1))

    def full(x):
        x = jnp.swapaxes(x, 0, 1)
        return jnp.zeros(x.shape[:2] + (3 * n,), x.dtype).at[..., idx].set(x).reshape(x.shape[:2] + (n, 3))

    return full(us), full(vs)


MEASURES = ("snapshot", "peak")


def relative_errors(u, v, sigma, target, measure: str = "snapshot"):
    """[C, T, 3] relative L2 errors (u, v, σ) per snapshot against target (u, v, σ) [C, T, N, ·] arrays: over
    the snapshot's own true norm (``measure`` "snapshot"), or over the case's largest true norm ("peak": for
    cases that hold still or come back to rest, where a snapshot's own norm vanishes)."""
    if measure not in MEASURES:
        raise ValueError(f"measure must be one of {MEASURES}, got {measure!r}")

    def rel(p, t):
        norm = jnp.sum(t ** 2, axis=(-2, -1))
        if measure == "peak":
            norm = jnp.broadcast_to(jnp.max(norm, axis=-1, keepdims=True), norm.shape)
        return jnp.sqrt(jnp.sum((p - t) ** 2, axis=(-2, -1)) / jnp.maximum(norm, 1e-30))
    return jnp.stack([rel(u, target[0]), rel(v, target[1]), rel(sigma, target[2])], axis=-1)


def targets(z, f, q0, rows):
    """(forces [C,T,N,3], (u, v, σ) [C,T,N,·] and v0 [C,N,3]) of the cases ``rows`` of data states z
    [C,T+1,N,12], in jax's float type (float64 where enabled). The cases must start at their rest positions with
    zero stress, to float32 round-off (v0, the first state's velocity, is the rollouts' start: zero for solver
    velocities, the one-sided difference for the reference data's gradient convention); ValueError otherwise."""
    dt = np.float64 if jax.config.jax_enable_x64 else np.float32
    z = np.asarray(z[rows], np.float64)
    q0 = np.asarray(q0, np.float64)
    scale = max(np.abs(z[:, :, :, :3] - q0).max(), 1e-30)
    s_scale = max(np.abs(z[:, :, :, 6:]).max(), 1e-30)
    if np.abs(z[:, 0, :, :3] - q0).max() > 1e-6 * scale or np.abs(z[:, 0, :, 6:]).max() > 1e-5 * s_scale:
        raise ValueError("the cases do not start at rest (first state's u or σ non-zero): "
                         f"max |u0| {np.abs(z[:, 0, :, :3] - q0).max():.3g}, "
                         f"max |σ0| {np.abs(z[:, 0, :, 6:]).max():.3g}")
    return (np.asarray(f[rows], dt),
            tuple(x.astype(dt) for x in (z[:, 1:, :, :3] - q0, z[:, 1:, :, 3:6], z[:, 1:, :, 6:12],
                                         z[:, 0, :, 3:6])))


def init(config: LinearConfig, geo: Geometry, seed: int = 0) -> dict:
    """Initial parameters: the coefficient networks (zero heads: the least-squares gradient and uniform moduli
    at the config's scales) and the log-scales of density and damping."""
    # jitted: one compiled program instead of each layer's initialisers and first call run (and compiled) op by op
    weights = jax.jit(_coefficients(config).init)(jax.random.PRNGKey(seed), geometry_arrays(geo))
    out = {"net": weights, "log_density": jnp.zeros(()), "log_alpha": jnp.zeros(())}
    if config.prior:
        out.update(log_k0=jnp.zeros(()), log_s0=jnp.zeros(()))
    return out


def loss_fn(params, geo: dict, h: float, config: LinearConfig, forces, target, dt: float,
            measure: str = "snapshot", weights=(1.0, 1.0, 1.0)):
    """Mean over cases and snapshots of the relative errors of u, v and σ (`relative_errors`), summed with
    ``weights``; also the three means."""
    ops = operators(params["net"], geo, h, config, params)
    u, v, sigma = rollout(ops, geo, h, forces, dt, target[3])
    err = relative_errors(u, v, sigma, target, measure)
    return jnp.mean(err @ jnp.asarray(weights, err.dtype)), jnp.mean(err, axis=(0, 1))


def train(data_path, train_rows, val_rows, run_dir, config: LinearConfig = LinearConfig(), steps: int = 300,
          lr: float = 3e-3, seed: int = 0, val_every: int = 10, progress: bool = True,
          until: int | None = None, batch: int | None = None, measure: str = "snapshot", prior=None,
          weights=(1.0, 1.0, 1.0)) -> dict:
    """Fit the model to whole rollouts of the cases ``train_rows`` of the data file ``data_path`` (or of several
    files' cases concatenated, `geometry_from_file`; ``batch`` of them per step, drawn by a
    generator seeded with the seed and the step, or all; Adam with a cosine schedule), selecting on ``val_rows``.
    Runs in float64 where jax has it enabled (``jax.config.update("jax_enable_x64", True)`` before any jax
    work), else in float32 (about twice as fast; A's condition number on the bunny is about 10³).

    Writes ``run_dir``/metrics.jsonl (one line per validation), ckpt.msgpack (parameters, optimiser state and
    step after every validation: a rerun resumes from it and reaches the same result) and best.msgpack (the
    parameters with the lowest validation loss; the start, step 0, is the first candidate). ``measure``: the
    loss's relative errors (`relative_errors`). ``prior``: the `fem.implicit.RestLinearization` of a model with
    ``config.prior`` (`with_prior`). ``weights``: of the u, v and σ errors in the loss (and the selection).
    ``until`` stops after that step as an interruption would (a
    rerun resumes). Returns the best parameters' record."""
    import json
    from pathlib import Path

    import optax
    from flax import serialization
    from tqdm import tqdm

    if steps < 1 or val_every < 1:
        raise ValueError(f"steps and val_every must be positive, got {steps} and {val_every}")
    if measure not in MEASURES:
        raise ValueError(f"measure must be one of {MEASURES}, got {measure!r}")
    if len(weights) != 3 or min(weights) < 0 or max(weights) <= 0:
        raise ValueError(f"weights must be three non-negative numbers (u, v, σ), not all zero; got {weights!r}")
    if batch is not None and not 1 <= batch <= len(train_rows):
        raise ValueError(f"batch must be between 1 and the {len(train_rows)} training cases, got {batch}")
    data, geo = geometry_from_file(data_path)
    if prior is not None:
        geo = with_prior(geo, prior)
    ga = geometry_arrays(geo)
    f_tr, t_tr = targets(data.z, data.f, data.q0, np.asarray(train_rows))
    f_va, t_va = targets(data.z, data.f, data.q0, np.asarray(val_rows))
    schedule = optax.cosine_decay_schedule(lr, steps, alpha=0.05)
    opt = optax.adam(schedule)
    params = init(config, geo, seed)
    state = opt.init(params)
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    ckpt, best_path, log = run / "ckpt.msgpack", run / "best.msgpack", run / "metrics.jsonl"
    start, best = 0, {"val_loss": float("inf")}
    if ckpt.exists():
        saved = serialization.from_bytes({"params": params, "state": state, "step": 0, "best": 0.0},
                                         ckpt.read_bytes())
        params, state, start = saved["params"], saved["state"], int(saved["step"])
        best = {"val_loss": float(saved["best"])}
    fn = lambda p, f, t: loss_fn(p, ga, geo.h, config, f, t, data.dt, measure, tuple(map(float, weights)))

    @jax.jit
    def update(p, s, f, t):
        (loss, parts), grads = jax.value_and_grad(fn, has_aux=True)(p, f, t)
        upd, s = opt.update(grads, s, p)
        return optax.apply_updates(p, upd), s, loss, parts

    evaluate = jax.jit(fn)

    def validate(step, loss, parts):
        nonlocal best
        vloss, vparts = evaluate(params, f_va, t_va)
        record = {"step": step, "train_loss": float(loss), "train": np.asarray(parts).tolist(),
                  "val_loss": float(vloss), "val": np.asarray(vparts).tolist(),
                  "density": float(config.density * jnp.exp(params["log_density"])),
                  "alpha": float(config.alpha * jnp.exp(params["log_alpha"]))}
        with log.open("a") as fh:
            fh.write(json.dumps(record) + "\n")
        if record["val_loss"] < best["val_loss"]:
            best = record
            best_path.write_bytes(serialization.to_bytes(params))

    if start == 0 and not log.exists():    # the start itself is a candidate (with a prior, often a good one)
        validate(0, *evaluate(params, f_tr, t_tr))
    end = steps if until is None else min(steps, until)
    bar = tqdm(range(start, end), desc="linear GENERIC", disable=not progress, initial=start, total=steps)
    for step in bar:
        if batch is None:
            params, state, loss, parts = update(params, state, f_tr, t_tr)
        else:
            pick = np.sort(np.random.default_rng([seed, step]).choice(len(f_tr), batch, replace=False))
            params, state, loss, parts = update(params, state, f_tr[pick], tuple(t[pick] for t in t_tr))
        bar.set_postfix(loss=f"{float(loss):.4f}")
        if (step + 1) % val_every == 0 or step + 1 == steps:
            validate(step + 1, loss, parts)
            tmp = ckpt.with_suffix(".tmp")
            tmp.write_bytes(serialization.to_bytes({"params": params, "state": state, "step": step + 1,
                                                    "best": best["val_loss"]}))
            tmp.replace(ckpt)
    # from the log, so that a resumed run returns the whole record, not only the checkpoint's best loss
    return min((json.loads(x) for x in log.read_text().splitlines()), key=lambda r: r["val_loss"])


def to_rest_linearization(params, geo: Geometry, config: LinearConfig):
    """The trained operators as a `fem.implicit.RestLinearization` (numpy float64 node blocks), the format a
    `LinearGeneric` model is made from (`tignn_jax.simulators.linear.from_rest_linearization`): K's non-zero node
    blocks, S's one-ring blocks, the masses and α."""
    from fem.implicit import RestLinearization

    ga = geometry_arrays(geo)
    n = geo.nbr.shape[0]
    h = geo.h      # compiled: op by op, the coefficients, K's assembly and S's forward columns take seconds
    ops = jax.jit(lambda w, g, extra: operators(w, g, h, config, extra))(params["net"], ga, params)
    K = np.asarray(jax.jit(lambda o, g: stiffness(o, g, h))(ops, ga), np.float64)
    K = K.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)
    K = 0.5 * (K + K.transpose(1, 0, 3, 2))
    rows, cols = np.nonzero(np.abs(K).max(axis=(2, 3)) > 1e-12 * np.abs(K).max())
    S = jax.jit(jax.jacfwd(nodal_stress))(jnp.zeros((n, 3), ops.mu.dtype), ops, ga)      # [N, 6, N, 3]
    S = np.asarray(S, np.float64).transpose(0, 2, 1, 3)
    s_rows, s_cols = np.nonzero(np.abs(S).max(axis=(2, 3)) > 0)
    return RestLinearization(rows, cols, K[rows, cols], s_rows, s_cols, S[s_rows, s_cols],
                             np.asarray(ops.mass, np.float64), float(ops.alpha), geo.free)


class TrainConfig(NamedTuple):
    """A recipe for the linear model.

    Attributes:
      model: how K and S are parameterised (`LinearConfig`).
      steps: Adam steps (cosine decay from ``lr``); 0: no training, the model is the FEM's rest linearisation of
        the data's scene itself (needs ``model.prior``).
      lr: initial learning rate.
      batch: training cases per step (None: all).
      seed: of the initialisation and the batches.
      val_every: steps between validations (and checkpoints).
      measure: the relative error of the loss, "snapshot" or "peak" (`relative_errors`).
      weights: of the u, v and σ errors in the loss and the selection.
      float64: train in float64 (about twice as slow; the beam's A is ill-conditioned in float32).
      train_split, val_split: split names of the data file, or lists of sim ids.
    """
    model: LinearConfig = LinearConfig()
    steps: int = 300
    lr: float = 1e-2
    batch: int | None = None
    seed: int = 0
    val_every: int = 10
    measure: str = "snapshot"
    weights: tuple = (1.0, 1.0, 1.0)
    float64: bool = False
    train_split: str | tuple = "train"
    val_split: str | tuple = "val"


def run(data_paths, config: TrainConfig, run_dir, progress: bool = True, until: int | None = None) -> dict:
    """Train a linear model on data files (one mesh) and write it to ``run_dir``/model/model.npz.

    Resumable: a second call with the same arguments continues from ``run_dir``'s checkpoint.

    Args:
      data_paths: a data file or a list of files on the same mesh (their cases concatenated).
      config: the recipe.
      run_dir: folder for config.json, prior.npz, metrics.jsonl, checkpoints and the model.
      progress: show a progress bar.
      until: stop after this step, as an interruption would (tests).

    Returns:
      The model (`tignn_jax.api.load_model` of the written file), or None where ``until`` stopped early.

    Raises:
      ValueError: bad options, an unknown split, or data that do not start at rest.
    """
    from tignn_jax import data as D
    from tignn_jax.simulators.linear import LinearGeneric, from_rest_linearization

    if config.measure not in MEASURES:
        raise ValueError(f"measure must be one of {MEASURES}, got {config.measure!r}")
    if not (isinstance(config.steps, int) and config.steps >= 0):
        raise ValueError(f"steps must be a non-negative integer, got {config.steps!r}")
    if config.steps == 0 and not config.model.prior:
        raise ValueError("steps=0 (the FEM's rest linearisation, untrained) needs model.prior=True")
    if not (is_number(config.lr) and config.lr > 0):
        raise ValueError(f"lr must be a positive number, got {config.lr!r}")
    if not is_count(config.val_every):
        raise ValueError(f"val_every must be a positive integer, got {config.val_every!r}")
    if not (config.batch is None or is_count(config.batch)):
        raise ValueError(f"batch must be a positive integer or None, got {config.batch!r}")
    weights = config.weights
    if not (isinstance(weights, (tuple, list)) and len(weights) == 3
            and all(is_number(w) and w >= 0 for w in weights) and sum(weights) > 0):
        raise ValueError(f"weights must be three finite numbers >= 0 (u, v, σ), not all 0, got {weights!r}")
    paths = [data_paths] if isinstance(data_paths, (str, Path)) else list(data_paths)
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", bool(config.float64))
    try:
        data = D.concatenate(*(D.load(p) for p in paths))
        rows_tr = D.split_rows(data, _split(config.train_split))
        rows_va = D.split_rows(data, _split(config.val_split))
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "config.json").write_text(json.dumps({"recipe": _jsonable(config), "data": [str(p) for p in paths]},
                                                        indent=1))
        prior = fem_prior(run_dir, paths[0]) if config.model.prior else None
        if config.steps == 0:
            return save_run(run_dir, paths, data, rows_tr, LinearGeneric(config.model),
                            from_rest_linearization(prior, float(data.dt)), _jsonable(config),
                            {"kind": "the FEM's rest linearisation (not learned)"})
        best = train(paths, rows_tr, rows_va, run_dir, config.model, steps=config.steps, lr=config.lr,
                     seed=config.seed, val_every=config.val_every, progress=progress, until=until,
                     batch=config.batch, measure=config.measure, prior=prior, weights=tuple(config.weights))
        if until is not None and until < config.steps:
            return None
        data, geo = geometry_from_file(paths)
        if prior is not None:
            geo = with_prior(geo, prior)
        params = serialization.from_bytes(init(config.model, geo), (run_dir / "best.msgpack").read_bytes())

        stored = from_rest_linearization(to_rest_linearization(params, geo, config.model), float(data.dt))
        return save_run(run_dir, paths, data, rows_tr, LinearGeneric(config.model), stored, _jsonable(config),
                        {"kind": "learned linear GENERIC model", "best_step": best["step"], "val": best["val"],
                         "learned": {"density": best["density"], "alpha": best["alpha"]}})
    finally:
        jax.config.update("jax_enable_x64", previous)


def save_run(run_dir, paths, data, rows, model, stored: dict, recipe: dict, info: dict) -> dict:
    """Write a model built from data files to ``run_dir``/model/model.npz and load it back.

    Args:
      run_dir: the run's folder.
      paths: the data files; ``data`` their concatenation, ``rows`` the rows whose range is the envelope.
      model: the model class instance; ``stored`` its arrays.
      recipe: the recipe as JSON, recorded in ``info`` with the data files and, where the first file records it,
        the FEM scene's density and damping (the Newton step and the demo rebuild the scene from them).

    Returns:
      The model (`tignn_jax.api.load_model` of the written file).
    """
    from tignn_jax import api
    from tignn_jax import data as D

    meta = data_metadata(paths[0])
    info = {**info, "data": [str(p) for p in paths], "recipe": recipe}
    if "material" in meta and "damping" in meta:
        info.update(fem_density=meta["material"]["density"], fem_damping=meta["damping"])
    mesh = {"q0": data.q0, "senders": data.edges[0], "receivers": data.edges[1], "node_type": data.node_type,
            "cells": D.cells(paths[0])}
    params = api.make_params(model, stored, mesh, D.normalization(data, rows), info)
    return api.load_model(api.save_model(params, Path(run_dir) / "model" / "model.npz"))


def fem_prior(run_dir, data_path):
    """The FEM's rest linearisation (`fem.implicit.RestLinearization`) of the scene of a data file, computed once
    into ``run_dir``/prior.npz and read from there afterwards."""
    from fem import implicit

    path = Path(run_dir) / "prior.npz"
    if path.exists():
        with np.load(path) as raw:
            return implicit.RestLinearization(*(raw[k] if raw[k].ndim else float(raw[k])
                                                for k in implicit.RestLinearization._fields))
    problem, material = fem_problem(data_path)
    lin = implicit.rest_linearization(problem, material)
    np.savez(path, **lin._asdict())
    return lin


def fem_problem(path):
    """(`fem.solver.Problem`, `fem.material.Material`) of the scene a data file was generated from: its mesh,
    clamps, material, density and damping (`data_metadata`), one frame long."""
    from fem.material import mooney_rivlin
    from fem.solver import setup

    data, geo = geometry_from_file(path)
    meta = data_metadata(path)
    mat = meta["material"]
    material = mooney_rivlin(mat["c10"], mat["c01"], mat["d1"], mat["density"], mat.get("g", ()), mat.get("tau", ()))
    extra = {"tet_formulation": meta["tet_formulation"]} if "tet_formulation" in meta else {}
    cells = np.asarray(geo.cells)
    cell_type = "tetra" if cells.shape[1] == 4 else "hexahedron"     # meshio's names, as fem.solver.setup takes
    problem = setup(data.q0, cells, material=material, frame_dt=float(data.dt), n_frames=1,
                    clamped=np.where(data.node_type != 0)[0], cell_type=cell_type,
                    damping=float(meta["damping"]), n_sub=1, **extra)
    return problem, material


def data_metadata(path) -> dict:
    """The generation record of a data file (``tignn generate`` writes one). The Abaqus reference data carry none:
    for them, the FEM scene identified against them (`fem.scenes.beam_scene`'s material, density and damping)."""
    with np.load(path, allow_pickle=False) as raw:
        if "metadata" in raw.files:
            return json.loads(str(raw["metadata"]))
    from fem import scenes

    mat = scenes.beam_scene().material
    return {"material": {"c10": float(mat.c10), "c01": float(mat.c01), "d1": float(mat.d1),
                         "density": scenes.BEAM_DENSITY},
            "damping": scenes.BEAM_DAMPING, "command": "the Abaqus reference data (the FEM scene identified on them)"}


def _split(split):
    return list(split) if isinstance(split, (tuple, list)) else split


def _jsonable(config) -> dict:
    out = config._asdict()
    out["model"] = config.model._asdict()
    return out
