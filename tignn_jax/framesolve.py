"""The ``frame_solve`` integrator and the ``linear_prior``: the rest state's linear dynamics inside the step.

On a mesh whose frame step is long against its fastest waves (the bunny at the data's density: dilatational
waves cross 3.3 edges per frame, and the exact frame map of backward Euler reaches 6 edges — truncated to 3,
its rollouts miss u by 26 %, to 6 by 2 %, see README), a forward-Euler network must learn a local map that
differs from the truncated operator: the best 4-hop linear map fitted on the rollouts' states reproduces them to
u 0.7 % over 20 frames, but amplifies some unforced state (spectral radius 1.35), and at 2–3 hops only a
regularised fit keeps 20-frame rollouts near u 6–8 % (`benchmarks/bunny_local_fit.py`). The standard answer to
stiffness is an
implicit integrator. Here it is a W-method (a Rosenbrock method with a fixed approximate Jacobian) whose
Jacobian J₀ is the rest state's linear dynamics from the FEM (`fem.implicit.rest_linearization`)::

    u̇ = v,   M v̇ = f − K₀ u − α M v,   σ̇ = S₀ v            (J₀ on z = (q, v, σ))
    z_{k+1} = z_k + W⁻¹ e,   W = I − Δt J₀,   e = Δt F(z_k, f_k) the network's forward-Euler increment.

W⁻¹ in closed form: with A₀ = (1 + αΔt) M / Δt² + K₀ (symmetric positive definite on the free nodes),
Δv = A₀⁻¹ (M e_v − Δt K₀ e_u) / Δt², Δu = e_u + Δt Δv, Δσ = e_σ + Δt S₀ Δv. Clamped nodes keep q and v. A W-method
is consistent for any fixed J₀ (J₀ only sets its stability), so F remains the model of the whole dynamics;
training targets are W (z_{k+1} − z_k) / Δt, which for data from backward Euler are local (for a linear
elastic body F = J₀z + Bf exactly: one node's rate depends on its element neighbours only).

``linear_prior`` adds J₀ z + B f (B f = f / m in the velocity rows) to the network's vector field (`prior_step`), so that an
untrained model is the linearised backward-Euler frame map of the FEM and the network learns what the rest
linearisation misses (the stress's second-order volumetric terms of a nearly incompressible material, large
rotations). Both need the operators in ``norm`` (`norm_entries`); A₀⁻¹ is dense ([3N, 3N], 64 MB for the
bunny's 1330 nodes; one product per step) and is recomputed from K₀ when a model is built (`with_inverse`),
never stored; for a large one (the bunny's, not the beam's) the step multiplies by its upper-triangular blocks
(`ainv_blocks`, `apply_ainv`: 40 MB read per step for the bunny instead of 64).
"""
from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

KEYS = ("fs_k_rows", "fs_k_cols", "fs_k", "fs_s_rows", "fs_s_cols", "fs_s", "fs_mass", "fs_alpha")
MAX_ROW_GROUPS = 4   # s_rows_layout's groups of rows, at most
S_ROW_KEYS = ("fs_s_ell_order",) + tuple(f"fs_s_ell{g}{x}" for g in range(MAX_ROW_GROUPS)
                                         for x in ("", "_cols"))   # s_rows_layout's arrays
AINV_BLOCKS = 4   # ainv_blocks' split of the DOFs: A₀⁻¹ kept as the upper-triangular blocks of a 4 × 4 split
# ... for an A₀⁻¹ of at least this many bytes (float32): session 46 measured the blocks ahead in the bunny's loop
# (64 MB: p50 3.45 against 3.65-3.94 ms, p99/p50 1.31 against 1.52-1.55) and behind in the beam's (20.6 MB: p50 1.64
# against 1.41 ms) and in every tight loop of the step alone (beam 1.94 against 1.44 ms, bunny 4.10 against 3.61)
AINV_BLOCK_MIN_BYTES = 32 * 2 ** 20
AINV_BLOCK_KEYS = tuple(f"fs_ainv_sb{i}_{j}" for i in range(AINV_BLOCKS) for j in range(i, AINV_BLOCKS))
DERIVED = ("fs_ainv",) + S_ROW_KEYS + AINV_BLOCK_KEYS   # recomputed by with_inverse, not saved


def problem_from_file(path: str | Path):
    """(`fem.solver.Problem`, `fem.material.Material`) of the scene a data-set file was generated from (its mesh,
    clamped nodes and the material, density and damping in its metadata), one frame long."""
    from fem.material import mooney_rivlin
    from fem.solver import setup

    with np.load(path, allow_pickle=False) as d:
        if "cells" not in d.files or "metadata" not in d.files:
            raise ValueError(f"{path}: frame_solve needs a data file with 'cells' and 'metadata' (written by "
                             "tignn generate); this one has neither the mesh cells nor the material")
        meta = json.loads(str(d["metadata"]))
        q0, cells, node_type, dt = d["q0"], d["cells"], d["node_type"], float(d["dt"])
        cell_type = str(d["cell_type"])
    mat = meta.get("material")
    if not mat or "damping" not in meta:
        raise ValueError(f"{path}: the metadata has no material or damping, so the rest linearisation of its "
                         "scene cannot be built")
    material = mooney_rivlin(mat["c10"], mat["c01"], mat["d1"], mat["density"], mat.get("g", ()), mat.get("tau", ()))
    extra = {"tet_formulation": meta["tet_formulation"]} if "tet_formulation" in meta else {}
    problem = setup(q0, cells, material=material, frame_dt=dt, n_frames=1, clamped=np.where(node_type != 0)[0],
                    cell_type=cell_type, damping=float(meta["damping"]), n_sub=1, **extra)
    return problem, material


def operators_from_file(path: str | Path, chunk: int = 128):
    """`fem.implicit.RestLinearization` of the scene a data-set file was generated from (`problem_from_file`)."""
    from fem import implicit

    problem, material = problem_from_file(path)
    return implicit.rest_linearization(problem, material, chunk=chunk)


def norm_entries(lin) -> dict:
    """The ``norm`` entries (float32 numpy) that carry a `RestLinearization` with a model."""
    return {"fs_k_rows": lin.k_rows, "fs_k_cols": lin.k_cols, "fs_k": lin.k_blocks, "fs_s_rows": lin.s_rows,
            "fs_s_cols": lin.s_cols, "fs_s": lin.s_blocks, "fs_mass": lin.mass, "fs_alpha": np.array([lin.alpha])}


def check(norm: dict, n_nodes: int):
    missing = [k for k in KEYS if k not in norm]
    if missing:
        raise ValueError(f"frame_solve / linear_prior need the rest linearisation in the normalisation, missing "
                         f"{missing}: train with it (tignn train computes it from the data file)")
    if np.shape(norm["fs_mass"])[0] != n_nodes:
        raise ValueError(f"the rest linearisation is for {np.shape(norm['fs_mass'])[0]} nodes, the mesh has {n_nodes}")


def operator(norm: dict, node_type) -> np.ndarray:
    """A₀ = K₀ + (1 + αΔt)/Δt² M [3N, 3N] float64, dense, identity on the clamped nodes' rows and columns: the
    matrix of the backward-Euler step's velocity solve (``inverse`` inverts it)."""
    n = int(np.shape(norm["fs_mass"])[0])
    check(norm, n)
    h, alpha = float(np.asarray(norm["dt"]).reshape(-1)[0]), float(np.asarray(norm["fs_alpha"]).reshape(-1)[0])
    K = np.zeros((n, n, 3, 3))
    K[np.asarray(norm["fs_k_rows"], np.int64), np.asarray(norm["fs_k_cols"], np.int64)] = np.asarray(norm["fs_k"])
    A = K.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    A[np.diag_indices(3 * n)] += (1.0 + alpha * h) / h ** 2 * np.repeat(np.asarray(norm["fs_mass"], np.float64), 3)
    free = np.repeat(np.asarray(node_type) == 0, 3)
    A[~free, :] = 0.0
    A[:, ~free] = 0.0
    A[~free, ~free] = 1.0
    return A


def inverse(norm: dict, node_type) -> np.ndarray:
    """A₀⁻¹ [3N, 3N] float32 (float64 inversion of ``operator``), identity on the clamped nodes' rows and columns."""
    return np.linalg.inv(operator(norm, node_type)).astype(np.float32)


def s_rows_layout(norm: dict, n_nodes: int, max_groups: int = MAX_ROW_GROUPS, group_slots: int = 2048) -> dict:
    """S₀'s node blocks row by row (an ELLPACK layout in groups of rows): the nodes sorted by their count of
    blocks and split into at most ``max_groups`` groups, each padded to its own widest row, the split chosen to
    minimise the padded slots (plus ``group_slots`` per group, for its extra program). Returns the arrays
    ``fs_s_ell{g}_cols`` [n_g, D_g] int32 and ``fs_s_ell{g}`` [n_g, D_g, 6, 3] float32 of each group (padding
    blocks zero, their column the row's own node) and ``fs_s_ell_order`` [N] int32, each node's row in the groups'
    concatenated output. ``apply_s`` with them is a gather and a batched contraction per group and one gather
    back, no scatter. On this CPU (a probe of S alone, 200 interleaved calls): the beam's 40 960 blocks 0.92 ms by
    the block list's segment sum, 0.55 ms as one group, 0.45 ms in four; the bunny's 61 816 blocks (rows of 1–144
    blocks) 1.38 ms, 1.61 ms as one group (padded to 144), 0.85 ms in four. The whole step: ``benchmarks/
    realtime.py``, linear_variants."""
    rows = np.asarray(norm["fs_s_rows"]).astype(np.int64)
    cols = np.asarray(norm["fs_s_cols"]).astype(np.int64)
    blocks = np.asarray(norm["fs_s"], np.float32)
    if rows.size and (rows.min() < 0 or rows.max() >= n_nodes):
        raise ValueError(f"fs_s_rows reach node {rows.max()} of a mesh of {n_nodes} nodes")
    if max_groups < 1:
        raise ValueError(f"max_groups must be at least 1, got {max_groups}")
    count = np.bincount(rows, minlength=n_nodes)
    nodes = np.argsort(count, kind="stable")            # rows by their count of blocks
    sorted_count = np.maximum(count[nodes], 1)
    # best[g][k]: fewest slots for the first k sorted rows in g groups (a group's width is its last row's count)
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
    out, position = {}, np.empty(n_nodes, np.int64)
    for gi, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
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
        out[f"fs_s_ell{gi}_cols"], out[f"fs_s_ell{gi}"] = g_cols, g_blocks
    out["fs_s_ell_order"] = position.astype(np.int32)
    return out


def ainv_blocks(ainv, n_nodes: int, k: int = AINV_BLOCKS, tol: float = 1e-5) -> dict:
    """A symmetric A₀⁻¹ [3N, 3N] as the upper-triangular blocks of a ``k`` × ``k`` split of the DOFs at node
    boundaries: ``fs_ainv_sb{i}_{j}`` for i ≤ j (block (j, i) is the transpose of (i, j)). `apply_ainv` uses each
    off-diagonal block for both of its products, one right after the other, so the step reads (k + 1)/(2k) of the
    dense matrix's bytes from memory (the second use finds the block in cache): for the bunny's 64 MB, 40 MB.
    On this 2-core CPU (session 46, the bunny's demo loop, alternating rounds of 500 frames in one process) the
    simulation p50 / p99 went from 3.74–3.94 / 5.61–5.84 ms with the dense product to 3.49–3.59 / 4.22–4.43 with
    k = 4 (p99/p50 1.48–1.50× → 1.18–1.24×); k = 8 gave 1.28–1.31×, k = 2 1.35–1.45×. Returns {} (the step keeps
    the dense product) where ``ainv`` is not symmetric to ``tol`` of its largest entry, or is too small to split."""
    a = np.asarray(ainv, np.float32)
    if a.shape != (3 * n_nodes, 3 * n_nodes):
        raise ValueError(f"A⁻¹ of shape {a.shape} does not match a mesh of {n_nodes} nodes")
    if k < 1:
        raise ValueError(f"the number of blocks must be at least 1, got {k}")
    scale = float(np.abs(a).max()) if a.size else 0.0
    if n_nodes < k or not np.isfinite(scale) or float(np.abs(a - a.T).max()) > tol * scale:
        return {}
    edges = 3 * np.round(np.linspace(0, n_nodes, k + 1)).astype(int)
    return {f"fs_ainv_sb{i}_{j}": a[edges[i]:edges[i + 1], edges[j]:edges[j + 1]].copy()
            for i in range(k) for j in range(i, k)}


def apply_ainv(norm, r):
    """A₀⁻¹ r for a flat [3N] right-hand side: by `ainv_blocks`' upper-triangular blocks where ``norm`` has
    them, else one dense product by ``fs_ainv``."""
    if "fs_ainv_sb0_0" not in norm:
        return norm["fs_ainv"].astype(r.dtype) @ r
    k = 0
    while f"fs_ainv_sb{k}_{k}" in norm:   # the split's size, from its diagonal blocks
        k += 1
    sizes = [norm[f"fs_ainv_sb{i}_{i}"].shape[0] for i in range(k)]
    edges = np.concatenate([[0], np.cumsum(sizes)])
    xs = [r[edges[i]:edges[i + 1]] for i in range(k)]
    ys = [None] * k
    for i in range(k):
        for j in range(i, k):
            b = norm[f"fs_ainv_sb{i}_{j}"].astype(r.dtype)
            ys[i] = b @ xs[j] if ys[i] is None else ys[i] + b @ xs[j]
            if i != j:   # the transposed block's product right after, while the block is in cache
                ys[j] = xs[i] @ b if ys[j] is None else ys[j] + xs[i] @ b
    return jnp.concatenate(ys)


def with_inverse(norm: dict, node_type, block_bytes: int = AINV_BLOCK_MIN_BYTES) -> dict:
    """``norm`` with what a model derives from its operators once (`DERIVED`): ``fs_ainv`` (the step only
    multiplies by it), for an A₀⁻¹ of at least ``block_bytes`` (float32) its upper-triangular blocks
    (`ainv_blocks`, what `apply_ainv` then multiplies by), and S₀ row by row (`s_rows_layout`). Built after any
    change of ``fs_s`` or ``fs_k``."""
    out = dict(norm)
    if "fs_ainv" not in out:
        out["fs_ainv"] = inverse(norm, node_type)
    if "fs_ainv_sb0_0" not in out and 4 * np.asarray(out["fs_ainv"]).size >= block_bytes:
        out.update(ainv_blocks(out["fs_ainv"], len(np.asarray(node_type))))
    if "fs_s_ell_order" not in out and "fs_s" in out:
        out.update(s_rows_layout(norm, len(np.asarray(node_type))))
    return out


def _apply(norm, prefix, x, out_dim):
    rows = norm[f"fs_{prefix}_rows"].astype(jnp.int32)
    cols = norm[f"fs_{prefix}_cols"].astype(jnp.int32)
    y = jnp.einsum("bij,bj->bi", norm[f"fs_{prefix}"].astype(x.dtype), x[cols])
    return jax.ops.segment_sum(y, rows, x.shape[0]) if out_dim else y


def apply_k(norm, x):
    """K₀ x: [N,3] → [N,3]."""
    return _apply(norm, "k", x, 3)


def apply_s(norm, x):
    """S₀ x: [N,3] → [N,6] (row by row where ``norm`` has `s_rows_layout`'s arrays, else from the block list)."""
    if "fs_s_ell_order" in norm:
        parts = [jnp.einsum("ndij,ndj->ni", norm[f"fs_s_ell{g}"].astype(x.dtype),
                            x[norm[f"fs_s_ell{g}_cols"].astype(jnp.int32)])
                 for g in range(MAX_ROW_GROUPS) if f"fs_s_ell{g}" in norm]
        return jnp.concatenate(parts)[norm["fs_s_ell_order"].astype(jnp.int32)]
    return _apply(norm, "s", x, 6)


def _constants(norm, node_type, dtype):
    h = norm["dt"].reshape(-1)[0].astype(dtype)
    alpha = norm["fs_alpha"].reshape(-1)[0].astype(dtype)
    free = (node_type == 0)[:, None].astype(dtype)
    return h, alpha, free, norm["fs_mass"].astype(dtype)[:, None]


def forward(norm, dz, node_type):
    """W dz [N,12] for a state increment dz [N,12] (the training target's transform; local)."""
    h, alpha, free, m = _constants(norm, node_type, dz.dtype)
    du, dv, ds = dz[:, :3] * free, dz[:, 3:6] * free, dz[:, 6:]
    e_u = du - h * dv
    e_v = (h * apply_k(norm, du) / m + (1.0 + alpha * h) * dv) * free
    e_s = ds - h * apply_s(norm, dv)
    return jnp.concatenate([e_u, e_v, e_s], axis=1)


def solve(norm, e, node_type):
    """W⁻¹ e [N,12] (the inverse of `forward`): the state increment of the W-method step."""
    h, _, free, m = _constants(norm, node_type, e.dtype)
    e_u, e_v, e_s = e[:, :3] * free, e[:, 3:6] * free, e[:, 6:]
    rhs = (m * e_v - h * apply_k(norm, e_u)) * free / h ** 2
    dv = apply_ainv(norm, rhs.reshape(-1)).reshape(-1, 3) * free
    du = e_u + h * dv
    return jnp.concatenate([du, dv, e_s + h * apply_s(norm, dv)], axis=1)


def prior_step(norm, z, f, e, node_type, q0, solve_a=None):
    """The state increment [N,12] of a ``linear_prior`` step: W⁻¹ (Δt (J₀ z + B f) + e) for the network's
    forward-Euler increment e [N,12], with one product by K₀ and one by S₀ (the prior's and the solve's merged:
    Δt K₀ (u + Δt v + e_u) in the right-hand side, Δt S₀ (v + Δv) in the stress). ``solve_a``: A₀⁻¹ applied to
    a flat [3N] right-hand side; default `apply_ainv` (benchmarks pass factor solves instead)."""
    h, alpha, free, m = _constants(norm, node_type, z.dtype)
    u, v = (z[:, :3] - q0.astype(z.dtype)) * free, z[:, 3:6] * free
    e_u, e_v, e_s = e[:, :3] * free, e[:, 3:6] * free, e[:, 6:]
    rhs = (m * e_v + h * (f - alpha * m * v) - h * apply_k(norm, u + h * v + e_u)) * free / h ** 2
    if solve_a is None:
        dv = apply_ainv(norm, rhs.reshape(-1)).reshape(-1, 3) * free
    else:
        dv = solve_a(rhs.reshape(-1)).reshape(-1, 3) * free
    return jnp.concatenate([h * v + e_u + h * dv, dv, e_s + h * apply_s(norm, v + dv)], axis=1)


def linear_step(norm, z, f, node_type, q0):
    """The state increment [N,12] of ``prior_step`` with no network (e = 0), without the product by K₀: on the
    free DOFs A₀ = K₀ + c M with c = (1 + αΔt)/Δt², so A₀⁻¹ K₀ w = w − c A₀⁻¹ M w, and the K₀ term of the
    right-hand side, −Δt K₀ w / Δt² with w = u + Δt v, becomes (c/Δt) M w inside the product by A₀⁻¹ and −w/Δt
    outside it. The same step in exact arithmetic, with one sparse product (S₀) where ``prior_step`` has two; in
    float32 it differs by rounding (tested). What ``api.stepper`` runs for a model whose network is zero."""
    h, alpha, free, m = _constants(norm, node_type, z.dtype)
    c = (1.0 + alpha * h) / h ** 2
    u, v = (z[:, :3] - q0.astype(z.dtype)) * free, z[:, 3:6] * free
    w = u + h * v
    rhs = (h * (f - alpha * m * v) / h ** 2 + (c / h) * m * w) * free
    dv = (apply_ainv(norm, rhs.reshape(-1)).reshape(-1, 3) - w / h) * free
    return jnp.concatenate([h * v + h * dv, dv, h * apply_s(norm, v + dv)], axis=1)


def energy_balance(norm: dict, z, f, node_type, q0) -> dict:
    """The rest-linearised system's energy and dissipation along a rollout z [T+1,N,12] under f [T,N,3]
    (float64 numpy): E_k = ½ v_kᵀ M v_k + ½ u_kᵀ K₀ u_k over the free nodes (u = q − q0), the external work
    W_k = f_k · (u_{k+1} − u_k), and the dissipation D_k = W_k − (E_{k+1} − E_k), the entropy production of the
    step at unit temperature. For `linear_step`, the backward-Euler step of M v̇ = f − K₀u − αMv with u̇ = v,
    D_k = αΔt |v_{k+1}|²_M + ½|v_{k+1} − v_k|²_M + ½|u_{k+1} − u_k|²_K ≥ 0 in exact arithmetic (the physical
    damping and the scheme's own dissipation). Returns {"E" [T+1], "W" [T], "D" [T], "S" [T+1] = cumulative D}."""
    free = np.asarray(node_type) == 0
    m = np.asarray(norm["fs_mass"], np.float64)
    rows, cols = np.asarray(norm["fs_k_rows"], np.int64), np.asarray(norm["fs_k_cols"], np.int64)
    kb = np.asarray(norm["fs_k"], np.float64)
    z = np.asarray(z, np.float64)
    u = (z[..., :3] - np.asarray(q0, np.float64)) * free[:, None]
    v = z[..., 3:6] * free[:, None]
    ku = np.zeros_like(u)
    for t in range(len(u)):   # K₀ u per snapshot: block-sparse product
        np.add.at(ku[t], rows, np.einsum("bij,bj->bi", kb, u[t][cols]))
    ku *= free[:, None]
    e = 0.5 * np.einsum("n,tni->t", m, v ** 2) + 0.5 * np.einsum("tni,tni->t", u, ku)   # u, v are 0 where clamped
    w = np.einsum("tni,tni->t", np.asarray(f, np.float64) * free[:, None], np.diff(u, axis=0))
    d = w - np.diff(e)
    return {"E": e, "W": w, "D": d, "S": np.concatenate([[0.0], np.cumsum(d)])}


def prior_rate(norm, z, f, node_type, q0):
    """Δt (J₀ z + B f) [N,12]: the rest linearisation's forward-Euler increment at z under f (u̇ = v,
    M v̇ = f − K₀ u − α M v, σ̇ = S₀ v; zero in the clamped nodes' q and v rows). ``prior_step`` is
    ``solve(prior_rate + e)`` with the products merged."""
    h, alpha, free, m = _constants(norm, node_type, z.dtype)
    u, v = (z[:, :3] - q0.astype(z.dtype)) * free, z[:, 3:6] * free
    r_v = (h * (f - apply_k(norm, u)) / m - h * alpha * v) * free
    return jnp.concatenate([h * v, r_v, h * apply_s(norm, v)], axis=1)


def residual(norm, z, z_next, f, node_type, q0):
    """e* [N,12]: the network increment with which a ``linear_prior`` step from z under f lands exactly on
    z_next, W (z_next − z) − Δt (J₀ z + B f): what the rest linearisation misses, in the W-method's coordinates.
    Local (one product with K₀ and one with S₀), but on a stiff mesh dominated by stiff components that the solve
    all but removes (the bunny's patch loads: 2000× the velocity increments in the velocity rows, from small
    errors of the displacement near the load), so it sets an output scale (``TrainConfig.residual_scale``) rather
    than a one-step training target: fitted directly, it fitted nothing (README, bunny session 18)."""
    return forward(norm, z_next - z, node_type) - prior_rate(norm, z, f, node_type, q0)


def residuals(norm: dict, z, f, node_type, q0) -> np.ndarray:
    """`residual` of every transition of z [C,T+1,N,12] under f [C,T,N,3]: [C,T,N,12] float32."""
    x0 = jnp.asarray(q0, jnp.float32)
    return _per_transition(lambda ops, nt, a, b, g: residual(ops, a, b, g, nt, x0), norm, z, node_type, f)


def increments(norm: dict, z, node_type) -> np.ndarray:
    """W (z[k+1] − z[k]) / 1 for every transition of z [C,T+1,N,12]: [C,T,N,12] float32, the per-frame
    increments a ``frame_solve`` model's forward-Euler part must produce (what its normalisation scales)."""
    return _per_transition(lambda ops, nt, a, b, g: forward(ops, b - a, nt), norm, z, node_type)


def _per_transition(fn, norm: dict, z, node_type, f=None) -> np.ndarray:
    """fn(ops, node_type, z_k, z_{k+1}, f_k) [N,12] of every transition of z [C,T+1,N,12] (f [C,T,N,3], or zeros
    where not given): [C,T,N,12] float32, one jitted call per case over its frames."""
    nt = jnp.asarray(node_type)
    ops = {k: jnp.asarray(norm[k]) for k in KEYS + ("dt",)}
    step = jax.jit(jax.vmap(lambda a, b, g: fn(ops, nt, a, b, g)))
    z = np.asarray(z, np.float32)
    f = np.zeros(z[:, 1:, :, :3].shape, np.float32) if f is None else np.asarray(f, np.float32)
    return np.stack([np.asarray(step(jnp.asarray(c[:-1]), jnp.asarray(c[1:]), jnp.asarray(g))) for c, g in zip(z, f)])


def operators_cached(data_path: str | Path, cache: str | Path):
    """`operators_from_file`, kept in ``cache`` (.npz) so that a resumed or repeated run does not rebuild it
    (minutes for the bunny: one `jax.jvp` per degree of freedom)."""
    from fem.implicit import RestLinearization

    cache = Path(cache)
    if cache.exists():
        with np.load(cache) as c:
            return RestLinearization(**{k: (float(c[k]) if k == "alpha" else c[k]) for k in c.files})
    lin = operators_from_file(data_path)
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, **lin._asdict())
    tmp.replace(cache)
    return lin


def linear_model(like: dict, scene, damping: float | None = None) -> tuple[dict, dict]:
    """(params, info): the FEM scene's rest linearisation stepped by backward Euler, as a model on the mesh and
    with the normalisation of the model ``like`` (a ``frame_solve`` + ``linear_prior`` model whose GENERIC
    network has every weight at zero, so its step is exactly the linearised backward-Euler frame map). Not a
    learned simulator: the fallback of ``api.fallback_stepper`` and a baseline. ``scene`` is a `fem.scenes.Scene`
    on the same nodes (order and units) and clamps; ``damping`` (mass-proportional α) overrides the scene's,
    e.g. with the damping of the FEM data ``like`` was trained on (its ``info["fem_damping"]``). The
    linearisation takes about 40 s for the beam's 756 nodes on one core."""
    import time

    from fem import implicit, scenes

    q0 = np.asarray(like["mesh"]["q0"], np.float64)
    if q0.shape != scene.points.shape or not np.allclose(q0, scene.points, atol=1e-4 * np.abs(q0).max()):
        raise ValueError(f"the model is not on the {scene.name} scene's mesh (nodes, order or units differ)")
    node_type = np.asarray(like["mesh"]["node_type"])
    if not np.array_equal(node_type != 0, np.asarray(scene.node_type) != 0):
        raise ValueError(f"the model clamps other nodes than the {scene.name} scene")
    if damping is not None:
        scene = scene._replace(damping=float(damping))
    t0 = time.perf_counter()
    lin = implicit.rest_linearization(scenes.setup_scene(scene), scene.material)
    seconds = time.perf_counter() - t0
    mat = scene.material
    info = {"kind": "rest-linearised FEM (not learned)", "scene": scene.name, "linearisation_s": round(seconds, 1),
            "fem_damping": float(scene.damping), "fem_density": float(mat.density),
            "material": {"c10": float(mat.c10), "c01": float(mat.c01), "d1": float(mat.d1)},
            "velocity": like.get("info", {}).get("velocity", "gradient")}
    return model_from_operators(like, lin, scene.frame_dt), info


def model_from_operators(like: dict, lin, frame_dt: float) -> dict:
    """A ``frame_solve`` + ``linear_prior`` model whose GENERIC network has every weight at zero, so that its
    step is exactly backward Euler of the linear dynamics ``lin`` (a `fem.implicit.RestLinearization`: the FEM's
    rest linearisation, or operators learned by `tignn_jax.linear_generic`), on the mesh and with the
    normalisation of the model ``like``."""
    from tignn_jax import api
    from tignn_jax import model as M

    q0 = np.asarray(like["mesh"]["q0"], np.float64)
    node_type = np.asarray(like["mesh"]["node_type"])
    norm = {k: np.asarray(v, np.float32) for k, v in like["norm"].items() if k not in DERIVED}
    norm.update({k: np.asarray(v, np.float32) for k, v in norm_entries(lin).items()})
    norm["dt"] = np.array([frame_dt], np.float32)
    # the zero network's own architecture, not the parent's: options that act with zero weights (force_port's
    # unit gain, an integrator other than the W-method, a convex model's brackets) would change the linear map
    config = M.ModelConfig(hidden=8, passes=2, frame_solve=True, linear_prior=True)
    edges = np.stack([like["mesh"]["senders"], like["mesh"]["receivers"]])
    shell = api.make_params(config, norm, None, q0, edges, node_type)
    z = jnp.concatenate([jnp.asarray(q0, jnp.float32), jnp.zeros((len(q0), M.STATE_DIM - 3))], axis=1)
    weights = M.init_weights(jax.random.PRNGKey(0), config, shell["norm"], z, jnp.zeros((len(q0), 3)),
                             jnp.asarray(node_type), shell["topo"])
    weights = jax.tree_util.tree_map(jnp.zeros_like, weights)   # the network's rate is exactly zero
    # the shell's normalisation already holds the dense A₀⁻¹: reused, not inverted a second time
    return api.make_params(config, shell["norm"], weights, q0, edges, node_type)
