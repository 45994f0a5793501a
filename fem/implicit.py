"""Implicit dynamics (backward Euler) for elastic scenes: output frames without sub-frame ringing.

The explicit solver (`fem.solver`) resolves every wave the mesh carries: on the bunny (K/μ ≈ 78) one output
frame of 0.05 spans 334 sub-steps (the stable step of its smallest element; ~58 wave transits of a median one), and
the frames sample a pressure field that rings at
frequencies far above the frame rate. A network that steps from frame to frame cannot predict such a field
from the last frame alone. Implicit integration with the frame step itself, as a user of Abaqus/Standard's
dynamic procedure would generate such data, solves for each frame directly and damps what the frame step
cannot resolve (modes with ω·Δt ≫ 1) while keeping the slow ones (ω·Δt ≪ 1) nearly undamped.

Backward Euler per step h = frame_dt / n_sub (total-Lagrangian, lumped mass M, Rayleigh mass damping α)::

    R(u) = M [(1 + αh)(u − uₙ) − h vₙ] / h² + f_int(u) − f_ext(tₙ₊₁) = 0   on the free degrees of freedom,
    vₙ₊₁ = (u − uₙ) / h.

Newton's method with the exact tangent A(u) = (1 + αh) M / h² + K(u), applied matrix-free through `jax.jvp`
of the internal force and solved by preconditioned conjugate gradients; the preconditioner is the dense inverse
of the same operator at the reference state, (1 + αh) M / h² + K₀ (computed once per problem by `rest_operator`:
K₀'s columns in the problem's precision, assembled and inverted in float64). The iteration stops when
‖R‖ ≤ tol · (‖f_ext‖ + ‖M vₙ / h‖ + ‖f_int(uₙ)‖ + max_k ‖f_ext(t_k)‖); the final relative residual and the
Newton iteration count of every frame are returned, so unconverged frames are reported, not hidden. In float32
the residual of the bunny (forces of order 1) stalls near 3e-4 of that scale (rounding of the internal force),
so the default tolerance is 1e-3.

Energy: backward Euler dissipates. ``energies.damping`` holds all dissipation that is not viscous — the Rayleigh
term and the scheme's numerical dissipation — as the remainder of the balance
external work − kinetic − stored (≥ 0 for a convex stored energy), so the balance closes by construction and
the remainder is the measured numerical damping.

Scope: hyperelastic tet4 or hex8 scenes with nodal loads and mass damping; no Prony terms, pressure loads or
contact (each raises `ValueError`).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import solver as sv
from .material import Material


class Diagnostics(NamedTuple):
    """Per output frame [.., n_frames]: the largest relative Newton residual of its steps and the most Newton
    iterations any of its steps took (max_newton means it stopped unconverged)."""

    residual: jnp.ndarray
    newton_iterations: jnp.ndarray


def check_scope(problem: sv.Problem, material: Material, loads: sv.Loads | None = None):
    """Raise `ValueError` naming what implicit dynamics does not support: Prony terms, contact, pressure loads."""
    if material.n_prony:
        raise ValueError(f"implicit dynamics supports elastic materials only, got {material.n_prony} Prony terms")
    if problem.config.contact_capacity:
        raise ValueError("implicit dynamics does not support contact (contact_capacity > 0)")
    if loads is not None and loads.pressure is not None:
        raise ValueError("implicit dynamics supports nodal loads only, got loads.pressure")


def _force_fn(arr: sv.Arrays, m: Material, cfg: sv.Config, hg):
    """u ↦ f_int(u) of the elastic material at displacements u (no viscous history)."""
    return lambda u: sv._internal(arr, m, hg, u, (), cfg, 1.0)[0]


def rest_operator(problem: sv.Problem, material: Material, h: float | None = None, chunk: int = 128) -> np.ndarray:
    """Dense (1 + αh) M/h² + K₀ on the free degrees of freedom, identity on the clamped ones: [3N, 3N] float64
    (node-major: row 3a + i is node a, component i). K₀ = ∂f_int/∂u at u = 0 from `coloured_jacobian` in the
    problem's precision, ``chunk`` products per call. h defaults to the problem's frame step over n_sub = 1."""
    arr, cfg = problem.arrays, problem.config
    h = cfg.frame_dt if h is None else h
    n = arr.points.shape[0]
    force = _force_fn(arr, material, cfg, sv._hourglass_for(arr, material, cfg))
    rows, cols, (blocks,) = coloured_jacobian(lambda u: (force(u),), np.asarray(arr.cells), n, _reach(cfg),
                                              arr.points.dtype, chunk)
    K = np.zeros((n, 3, n, 3))
    K[rows, :, cols, :] = blocks
    K = K.reshape(3 * n, 3 * n)
    K = 0.5 * (K + K.T)   # K is a Hessian; symmetrise float32 rounding
    mass = np.repeat(np.asarray(sv.lumped_mass(problem, material), np.float64), 3)
    c = (1.0 + float(arr.damping_alpha) * h) / h ** 2
    A = K + np.diag(c * mass)
    free = np.repeat(np.asarray(arr.free[:, 0]) > 0, 3)
    A[~free, :] = 0.0
    A[:, ~free] = 0.0
    A[~free, ~free] = 1.0
    return A


def _reach(cfg: sv.Config) -> int:
    """Rings of nodes a displacement reaches in the internal force and nodal stress: hexes their cells' nodes; tets
    also through the nodal averages over the cells around a node."""
    return 1 if cfg.cell_type == "hexahedron" else 2


def preconditioner(problem: sv.Problem, material: Material, n_sub: int = 1) -> jnp.ndarray:
    """The inverse of `rest_operator` at h = frame_dt / n_sub, as a device array [3N, 3N] (float32, or float64
    with x64 enabled)."""
    A = rest_operator(problem, material, problem.config.frame_dt / n_sub)
    return jnp.asarray(np.linalg.inv(A))


def simulate_implicit(problem: sv.Problem, material: Material, loads: sv.Loads, precond=None, *, n_sub: int = 1,
                      tol: float = 1e-3, max_newton: int = 12, cg_tol: float = 1e-4, max_cg: int = 60):
    """Backward-Euler run: (`fem.Result`, `Diagnostics`). Same loads and outputs as `fem.simulate`
    (``loads.nodal[k]`` is the load reached at the end of frame k, ramped within the frame for
    load_interp='linear', held for 'step'). ``precond`` from `preconditioner` (built here if None)."""
    check_scope(problem, material, loads)
    sv._validate_loads(problem, loads)
    if precond is None:
        precond = preconditioner(problem, material, n_sub)
    return _run(problem.arrays, material, loads, precond, problem.config, n_sub, tol, max_newton, cg_tol, max_cg)


def simulate_implicit_batch(problem: sv.Problem, material: Material, loads: sv.Loads, precond=None, *,
                            n_sub: int = 1, tol: float = 1e-3, max_newton: int = 12, cg_tol: float = 1e-4,
                            max_cg: int = 60):
    """`simulate_implicit` over a leading case axis of every non-None entry of ``loads`` (`jax.vmap`)."""
    check_scope(problem, material, loads)
    sv._validate_loads(problem, loads, batched=True)
    if precond is None:
        precond = preconditioner(problem, material, n_sub)
    axes = sv.Loads(*(None if a is None else 0 for a in loads))
    run = jax.vmap(lambda ld: _run(problem.arrays, material, ld, precond, problem.config, n_sub, tol, max_newton,
                                   cg_tol, max_cg), in_axes=(axes,))
    return run(loads)


def _run_impl(arr: sv.Arrays, m: Material, loads: sv.Loads, pinv, cfg: sv.Config, n_sub: int, tol: float,
              max_newton: int, cg_tol: float, max_cg: int):
    h = cfg.frame_dt / n_sub
    n = arr.points.shape[0]
    dtype = pinv.dtype
    hg = sv._hourglass_for(arr, m, cfg)
    force = _force_fn(arr, m, cfg, hg)
    mass = sv.lumped_mass(sv.Problem(arr, cfg), m).astype(dtype)[:, None]
    free = arr.free.astype(dtype)
    c = (1.0 + arr.damping_alpha * h) / h ** 2
    nodal = jnp.zeros((cfg.n_frames, n, 3), dtype) if loads.nodal is None else loads.nodal.astype(dtype)
    v0 = jnp.zeros((n, 3), dtype) if loads.v0 is None else loads.v0.astype(dtype) * free
    apply_p = lambda r: (pinv @ r.reshape(-1)).reshape(n, 3) * free
    norm = lambda a: jnp.sqrt(jnp.sum(a * a))
    load_scale = jnp.max(jnp.sqrt(jnp.sum((nodal * free) ** 2, axis=(1, 2)))) + 1e-30   # the largest frame load

    def f_ext_at(frame, j):
        cur = nodal[frame]
        if cfg.load_interp == "step":
            return cur
        prev = jnp.where(frame > 0, nodal[jnp.maximum(frame - 1, 0)], jnp.zeros_like(cur))
        return prev + (j + 1.0) / n_sub * (cur - prev)

    def step(u_n, v_n, f_prev, frame, j):
        """One backward-Euler step: (u, v, f_ext, external work of the step, relative residual, iterations)."""
        f_ext = f_ext_at(frame, j)
        residual = lambda u: free * (mass * (c * (u - u_n) - v_n / h) + force(u) - f_ext)
        scale = norm(free * f_ext) + norm(free * mass * v_n / h) + norm(free * force(u_n)) + load_scale

        def newton(state):
            u, _, it = state
            tangent = lambda d: free * (c * mass * d + jax.jvp(force, (u,), (d,))[1])
            d, _ = jax.scipy.sparse.linalg.cg(tangent, -residual(u), tol=cg_tol, maxiter=max_cg, M=apply_p)
            return u + d, norm(residual(u + d)) / scale, it + 1

        u1 = u_n + h * v_n
        u, rel, it = jax.lax.while_loop(lambda s: (s[1] > tol) & (s[2] < max_newton), newton,
                                        (u1, norm(residual(u1)) / scale, jnp.int32(0)))
        work = 0.5 * jnp.sum((f_prev + f_ext) * (u - u_n))
        return u, (u - u_n) / h, f_ext, work, rel, it

    def frame_fn(carry, frame):
        def sub(s, j):
            u, v, f_prev, w = s
            u, v, f_ext, dw, rel, it = step(u, v, f_prev, frame, j)
            return (u, v, f_ext, w + dw), (rel, it)

        carry, (rel, it) = jax.lax.scan(sub, carry, jnp.arange(n_sub, dtype=dtype))
        u, v, _, w_ext = carry
        return carry, (outputs(u, v, w_ext), jnp.max(rel), jnp.max(it))

    def outputs(u, v, w_ext):
        sig = sv._nodal_stress(arr, sv._element_stress(arr, m, u, (), cfg))
        kin = 0.5 * jnp.sum(mass * v ** 2)
        stored = sv._stored_energy(arr, m, u, (), hg, cfg)
        return arr.points.astype(dtype) + u, v, sig, sv.Energies(kin, stored, jnp.zeros((), dtype),
                                                                 w_ext + e_start - kin - stored, w_ext)

    zero = jnp.zeros((n, 3), dtype)
    u0 = zero if loads.u0 is None else loads.u0.astype(dtype)
    e_start = 0.5 * jnp.sum(mass * v0 ** 2) + sv._stored_energy(arr, m, u0, (), hg, cfg)   # the balance's start
    f0 = zero if cfg.load_interp == "linear" else nodal[0]
    _, (outs, rel, its) = jax.lax.scan(frame_fn, (u0, v0, f0, jnp.zeros((), dtype)), jnp.arange(cfg.n_frames))
    first = outputs(u0, v0, jnp.zeros((), dtype))
    q, v, sig, en = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), first, outs)
    t = jnp.arange(cfg.n_frames + 1) * cfg.frame_dt
    u_all = q - arr.points.astype(dtype)
    inverted, inv_t = _inversion(arr, u_all, t)
    res = sv.Result(t, q, v, sig, en, inverted, inv_t, None)
    return res, Diagnostics(rel, its)


def _inversion(arr: sv.Arrays, u_all, t):
    """First element with J ≤ 0 over the output frames (−1 if none) and that frame's time (nan if none)."""
    def j_min(u):
        J = sv.det3(sv._deformation_gradient(sv._gather_elements(u, arr.cells), arr.geo.b))
        return jnp.min(J), jnp.argmin(J)

    js, ks = jax.vmap(j_min)(u_all)
    bad = js <= 0.0
    first = jnp.argmax(bad)
    hit = jnp.any(bad)
    return jnp.where(hit, ks[first].astype(jnp.int32), -1), jnp.where(hit, t[first], jnp.nan)


_run = jax.jit(_run_impl, static_argnames=("cfg", "n_sub", "tol", "max_newton", "cg_tol", "max_cg"))


class RestLinearization(NamedTuple):
    """The linear dynamics of a scene about its rest state, as sparse node blocks (numpy, float64).

    K₀ = ∂f_int/∂u at u = 0 ([N·3]² stiffness; ``k_rows``, ``k_cols`` [B] node pairs with ``k_blocks`` [B,3,3],
    block (a, b) = ∂f_a/∂u_b, symmetrised); S₀ = ∂σ/∂u at u = 0, the nodal Cauchy stress the data store
    (``s_rows``, ``s_cols`` [B'] with ``s_blocks`` [B',6,3], Voigt order S11 S22 S33 S12 S13 S23); ``mass`` [N]
    lumped nodal masses; ``alpha`` the Rayleigh mass-damping coefficient; ``free`` [N] bool. Node pairs whose
    block is below 1e-9 of the largest entry are dropped. About the rest state the frame dynamics are
    u̇ = v, M v̇ = f − K₀u − αMv, σ̇ = S₀v."""
    k_rows: np.ndarray
    k_cols: np.ndarray
    k_blocks: np.ndarray
    s_rows: np.ndarray
    s_cols: np.ndarray
    s_blocks: np.ndarray
    mass: np.ndarray
    alpha: float
    free: np.ndarray


def force_and_stress(problem: sv.Problem, material: Material):
    """(f_int, σ): the elastic scene's internal nodal force u [N,3] → [N,3] (hourglass control included) and
    nodal Cauchy stress u [N,3] → [N,6] (Voigt order S11 S22 S33 S12 S13 S23, as the data store it) at a
    displacement, as pure jit-able functions; `rest_linearization` differentiates them at u = 0."""
    check_scope(problem, material)
    arr, cfg = problem.arrays, problem.config
    force = _force_fn(arr, material, cfg, sv._hourglass_for(arr, material, cfg))
    return force, lambda u: sv._nodal_stress(arr, sv._element_stress(arr, material, u, (), cfg))


def rest_linearization(problem: sv.Problem, material: Material, chunk: int = 128) -> RestLinearization:
    """`RestLinearization` of an elastic scene: the node blocks of K₀ and S₀ by forward-mode products of the
    internal force and the nodal stress together, in the problem's precision, with the degrees of freedom coloured
    so that one `jax.jvp` yields the columns of many nodes at once (`coloured_jacobian`; ``chunk`` products per
    call). Memory and time grow with the mesh's node pairs, not with N².

    Raises:
      ValueError: for what implicit dynamics does not support (`check_scope`).
      RuntimeError: if a random direction's product differs from the assembled blocks' (`coloured_jacobian`).
    """
    arr = problem.arrays
    force, stress = force_and_stress(problem, material)
    rows, cols, (K, S) = coloured_jacobian(lambda u: (force(u), stress(u)), np.asarray(arr.cells),
                                           arr.points.shape[0], _reach(problem.config), arr.points.dtype, chunk)
    K = 0.5 * (K + K[_transposed(rows, cols)].transpose(0, 2, 1))   # a Hessian: symmetrise the float32 rounding
    k_rows, k_cols, k_blocks = _kept(rows, cols, K)
    s_rows, s_cols, s_blocks = _kept(rows, cols, S)
    mass = np.asarray(sv.lumped_mass(problem, material), np.float64)
    return RestLinearization(k_rows, k_cols, k_blocks, s_rows, s_cols, s_blocks, mass,
                             float(arr.damping_alpha), np.asarray(arr.free[:, 0]) > 0)


class JacobianBlocks(NamedTuple):
    """A mesh function's Jacobian as node blocks over a fixed sparsity pattern (`jacobian_blocks`).

    Attributes:
      rows, cols: [P] int32, the node pairs (a, b) within ``reach`` rings of each other, sorted by (a, b).
      at: u [N, 3] ↦ one float64 array [P, k_t, 3] per output, whose block p is ∂out_{rows[p]}/∂u_{cols[p]} at u.
    """
    rows: np.ndarray
    cols: np.ndarray
    at: Callable


def jacobian_blocks(fn, cells: np.ndarray, n: int, reach: int, dtype=jnp.float32,
                    chunk: int = 128) -> JacobianBlocks:
    """The Jacobian of a mesh function ``fn``: u [N,3] ↦ tuple of [N, k] arrays whose node a depends only on the
    nodes within ``reach`` rings of a (two nodes are one ring apart when they share a cell), as node blocks at any u.

    Two nodes more than 2·reach rings apart touch no common output node, so they share a colour (greedy colouring of
    that distance graph) and one `jax.jvp` per colour and component reads all their columns: a few dozen (hexes,
    reach 1) to a few hundred (tets, reach 2) products instead of 3N. The pattern and the compiled products are built
    once; each call of ``at`` runs them at its u. Nothing checks ``reach`` here (`coloured_jacobian` does).

    Args:
      fn: u [N, 3] ↦ tuple of [N, k_t] arrays.
      cells: [C, n_per] node ids of the mesh's cells.
      n: the number of nodes N.
      reach: how many rings away a displacement can change an output node.
      dtype: the displacements' dtype.
      chunk: products per compiled call (every call one shape: one compilation).

    Returns:
      `JacobianBlocks`.
    """
    rows, cols, evaluate = _coloured(fn, cells, n, reach, dtype, chunk)
    return JacobianBlocks(rows, cols, lambda u: evaluate(u)[0])


def _coloured(fn, cells: np.ndarray, n: int, reach: int, dtype, chunk: int):
    """(rows, cols, evaluate) of `jacobian_blocks`: ``evaluate(u, extra)`` gives the node blocks at u and the
    products along the directions ``extra`` [E, N, 3] from the same compiled calls."""
    import scipy.sparse as sp

    cells = np.asarray(cells)
    per = cells.shape[1]
    pairs = (np.repeat(cells, per, axis=1).ravel(), np.tile(cells, (1, per)).ravel())
    ring = sp.csr_matrix((np.ones(cells.size * per, np.int8), pairs), shape=(n, n))
    ring = (ring + sp.identity(n, dtype=np.int8, format="csr")).astype(bool).astype(np.int32)
    near = ring
    for _ in range(reach - 1):
        near = (near @ ring).astype(bool).astype(np.int32)
    near = near.tocsr()
    near.sort_indices()
    conflict = (near @ near).tocsr()              # nodes whose output nodes overlap
    colour = np.full(n, -1, np.int64)
    for a in range(n):
        taken = colour[conflict.indices[conflict.indptr[a]:conflict.indptr[a + 1]]]
        free = np.ones(len(taken) + 1, bool)
        free[taken[(taken >= 0) & (taken <= len(taken))]] = False
        colour[a] = int(np.argmax(free))
    colours = int(colour.max()) + 1
    seeds = np.zeros((3 * colours, n, 3), np.dtype(dtype))
    for d in range(3):
        seeds[3 * colour + d, np.arange(n), d] = 1.0
    products = jax.jit(jax.vmap(lambda u, d: jax.jvp(fn, (u,), (d,))[1], in_axes=(None, 0)))
    coo = near.tocoo()
    order = np.lexsort((coo.col, coo.row))
    rows, cols = coo.row[order].astype(np.int32), coo.col[order].astype(np.int32)
    # block (a, b)[i, d] = entry (a, i) of the product along the seed of b's colour and component d
    which = 3 * colour[cols][:, None] + np.arange(3)

    def evaluate(u, extra=np.zeros((0, n, 3))):
        every = np.concatenate([seeds, np.asarray(extra, seeds.dtype)])
        size = min(chunk, len(every))
        padded = jnp.asarray(np.concatenate([every, np.zeros((-len(every) % size, n, 3), seeds.dtype)]))
        u = jnp.asarray(u, dtype)
        parts = [products(u, padded[s:s + size]) for s in range(0, len(padded), size)]
        outs = [np.concatenate([np.asarray(p[t], np.float64) for p in parts]) for t in range(len(parts[0]))]
        blocks = tuple(out[which, rows[:, None]].transpose(0, 2, 1) for out in outs)
        return blocks, tuple(out[len(seeds):len(every)] for out in outs)

    return rows, cols, evaluate


def coloured_jacobian(fn, cells: np.ndarray, n: int, reach: int, dtype=jnp.float32, chunk: int = 128,
                      seed: int = 0) -> tuple:
    """The Jacobian at u = 0 of a mesh function ``fn`` as node blocks (`jacobian_blocks`), checked by one product
    along a random direction against the assembled blocks.

    Args:
      fn, cells, n, reach, dtype, chunk: as `jacobian_blocks`.
      seed: the random check direction's seed.

    Returns:
      (rows [P], cols [P], blocks): the node pairs (a, b) within ``reach`` rings, sorted by (a, b), and per output a
      float64 array [P, k_t, 3] whose block (a, b) is ∂out_a/∂u_b.

    Raises:
      RuntimeError: if the check's product and the blocks' differ by more than 1e-3 of its norm (``fn`` reaches
        further than ``reach``).
    """
    w = np.random.default_rng(seed).standard_normal((1, n, 3)).astype(np.dtype(dtype))   # the check's direction
    rows, cols, evaluate = _coloured(fn, cells, n, reach, dtype, chunk)
    blocks, direct = evaluate(jnp.zeros((n, 3), dtype), w)
    for t, (b, x) in enumerate(zip(blocks, direct)):
        x = x[0]
        assembled = np.zeros((n, b.shape[1]))
        np.add.at(assembled, rows, np.einsum("pij,pj->pi", b, w[0, cols].astype(np.float64)))
        if np.linalg.norm(assembled - x) > 1e-3 * np.linalg.norm(x):
            raise RuntimeError(f"output {t} of the function depends on nodes further than reach = {reach} rings: "
                               f"its Jacobian's blocks miss {np.linalg.norm(assembled - x) / np.linalg.norm(x):.2e} "
                               "of a random direction's product")
    return rows, cols, blocks


def _transposed(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Index of pair (b, a) for each pair (a, b) of a symmetric pattern sorted by (a, b)."""
    n = int(max(rows.max(), cols.max())) + 1
    return np.searchsorted(rows.astype(np.int64) * n + cols, cols.astype(np.int64) * n + rows)


def _kept(rows, cols, blocks, rtol: float = 1e-9):
    """(rows, cols, blocks) of the node pairs whose block is not negligible (above rtol of the largest entry)."""
    size = np.abs(blocks).max(axis=(1, 2))
    keep = size > rtol * size.max()
    return rows[keep], cols[keep], blocks[keep]
