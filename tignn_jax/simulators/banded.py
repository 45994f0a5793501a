"""A banded Cholesky factor of a symmetric positive definite operator, applied as A⁻¹r in JAX.

A mesh's rest operator A₀ = c M + K₀ couples only nodes that share an element (or, for the nodal-averaged tet
volume term, a node's neighbours' neighbours). Numbered along a reverse Cuthill–McKee ordering its non-zeros lie
within a band of half-width w, so in blocks of size b ≥ w it is block tridiagonal and its Cholesky factor is block
lower bidiagonal,

    P A Pᵀ = L Lᵀ,   L = [[L₁₁], [C₂, L₂₂], [C₃, L₃₃], ...],   Lᵢᵢ Lᵢᵢᵀ = Aᵢᵢ − Cᵢ Cᵢᵀ,   Cᵢ₊₁ = Aᵢ₊₁,ᵢ Lᵢᵢ⁻ᵀ,

with no fill outside the band. A⁻¹r is then two sweeps over the blocks (forward yᵢ = Lᵢᵢ⁻¹(rᵢ − Cᵢ yᵢ₋₁),
backward xᵢ = Lᵢᵢ⁻ᵀ(yᵢ − Cᵢ₊₁ᵀ xᵢ₊₁)), 4 n b multiply-adds and 2 n b stored numbers, where the dense inverse
takes n² of both (n = 3N degrees of freedom).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

KEYS = ("perm", "linv", "lower")


def node_ordering(a: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
    """A node numbering [N] int that narrows the band of ``a`` [3N, 3N]: whichever has the narrowest band of the
    given numbering, reverse Cuthill–McKee (scipy) on the graph of its non-zero 3 × 3 node blocks, and, given the
    node ``points`` [N, 3], the nodes sorted along the mesh's longest principal axis (a slender body's
    cross-sections one after the other)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    n = a.shape[0] // 3
    blocks = np.abs(a).reshape(n, 3, n, 3).max(axis=(1, 3)) > 0
    orders = [np.arange(n), np.asarray(reverse_cuthill_mckee(csr_matrix(blocks), symmetric_mode=True), np.int64)]
    if points is not None:
        x = np.asarray(points, np.float64) - np.mean(points, axis=0)
        axis = np.linalg.svd(x, full_matrices=False)[2][0]
        orders.append(np.argsort(x @ axis, kind="stable"))
    return min(orders, key=lambda order: half_bandwidth(blocks[np.ix_(order, order)]))


def half_bandwidth(a: np.ndarray) -> int:
    """max |i − j| over the non-zeros of ``a`` [n, n]."""
    i, j = np.nonzero(a)
    return int(np.abs(i - j).max()) if len(i) else 0


def factor(a: np.ndarray, points: np.ndarray | None = None, dtype=np.float32) -> dict:
    """The block bidiagonal Cholesky factor of a symmetric positive definite ``a`` [3N, 3N].

    Args:
      a: the operator, any float dtype (factored in float64), symmetric positive definite, its rows in node
        blocks of 3.
      points: the node positions [N, 3], to try an ordering along the mesh's longest axis (`node_ordering`).
      dtype: the dtype of the stored blocks.

    Returns:
      {"perm": [3N] int32, the degree of freedom at each position of the band ordering; "linv": [K, b, b] the
      inverses of the diagonal blocks Lᵢᵢ; "lower": [K, b, b] the sub-diagonal blocks Cᵢ (C₁ = 0)}, where
      b ≥ the half-bandwidth of the reordered operator and K b ≥ 3N (the padding is identity).

    Raises:
      ValueError: ``a`` is not square in node blocks of 3, or not positive definite.
    """
    a = np.asarray(a, np.float64)
    n = a.shape[0]
    if a.ndim != 2 or a.shape != (n, n) or n % 3:
        raise ValueError(f"a banded factor needs a square operator in node blocks of 3, got shape {a.shape}")
    nodes = node_ordering(a, points)
    perm = (3 * nodes[:, None] + np.arange(3)).reshape(-1)
    p = a[np.ix_(perm, perm)]
    b = max(3, half_bandwidth(p))
    k = -(-n // b)
    padded = np.eye(k * b)
    padded[:n, :n] = p
    linv, lower = np.zeros((k, b, b)), np.zeros((k, b, b))
    for i in range(k):
        s = slice(i * b, (i + 1) * b)
        d = padded[s, s] - (lower[i] @ lower[i].T if i else 0.0)
        try:
            li = np.linalg.cholesky(d)
        except np.linalg.LinAlgError:
            raise ValueError("the operator is not positive definite: its banded Cholesky factor fails") from None
        linv[i] = np.linalg.inv(li)
        if i + 1 < k:
            lower[i + 1] = padded[(i + 1) * b:(i + 2) * b, s] @ linv[i].T
    return {"perm": perm.astype(np.int32), "linv": linv.astype(dtype), "lower": lower.astype(dtype)}


def solve(fac: dict, r: jax.Array) -> jax.Array:
    """A⁻¹ r for a flat right-hand side r [3N] with the factor of `factor` (two sweeps over its K blocks)."""
    perm, linv, lower = fac["perm"], fac["linv"].astype(r.dtype), fac["lower"].astype(r.dtype)
    k, b, _ = linv.shape
    n = r.shape[0]
    rp = jnp.zeros(k * b, r.dtype).at[:n].set(r[perm]).reshape(k, b)

    def forward(y_prev, blk):
        li, ci, ri = blk
        y = li @ (ri - ci @ y_prev)
        return y, y

    _, y = jax.lax.scan(forward, jnp.zeros(b, r.dtype), (linv, lower, rp), unroll=k)
    upper = jnp.concatenate([lower[1:], jnp.zeros((1, b, b), r.dtype)])   # C_{i+1}, zero past the last block

    def backward(x_next, blk):
        li, ci1, yi = blk
        x = li.T @ (yi - ci1.T @ x_next)
        return x, x

    _, x = jax.lax.scan(backward, jnp.zeros(b, r.dtype), (linv, upper, y), reverse=True, unroll=k)
    return jnp.zeros(n, r.dtype).at[perm].set(x.reshape(-1)[:n])
