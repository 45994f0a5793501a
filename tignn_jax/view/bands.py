"""Contour bands of a nodal field on a triangulated surface, one triangle mesh per band.

A web viewer whose meshes take one colour each (viser's) shows a field as FEM post-processors do: the range
[lo, hi] is cut into K equal bands, the field is linear on each triangle, and each triangle is split along the
band levels into the pieces where lo + j (hi - lo) / K ≤ f < lo + (j + 1) (hi - lo) / K; band j's mesh holds its
pieces. Values outside [lo, hi] fall in the end bands.

On a triangle with vertices sorted by value, a ≤ b ≤ c, the piece between levels L1 < L2 (clamped to [a, c]) is
the convex polygon

    AC(L1), AC(L2), P(L2), [B if L1 ≤ b ≤ L2], P(L1),

AC(L) the point at level L on the edge a-c and P(L) the one on the path a-b-c, drawn as a fan of three triangles
(degenerate where the polygon has fewer corners) wound as the input triangle.
"""
from __future__ import annotations

import numpy as np


def contour_bands(positions, values, triangles, lo: float, hi: float, bands: int) -> list:
    """Split a surface into the pieces of each colour band.

    Args:
      positions: [N, 3] vertex positions.
      values: [N] the field at the vertices (non-finite values count as ``lo``).
      triangles: [T, 3] int vertex ids, counter-clockwise seen from outside.
      lo, hi: the range cut into bands (hi > lo).
      bands: the number of bands K ≥ 1.

    Returns:
      K pairs (vertices [5 M_j, 3] float32, faces [3 M_j, 3] uint32), M_j the pieces in band j (each piece
      five vertices and three triangles, wound as its triangle).
    """
    p = np.asarray(positions, np.float64)[triangles]                           # [T,3,3]
    v = np.asarray(values, np.float64)[triangles]
    v = np.clip(np.where(np.isfinite(v), v, lo), lo, hi)
    order = np.argsort(v, axis=1, kind="stable")
    even = _even(order)
    v = np.take_along_axis(v, order, 1)
    p = np.take_along_axis(p, order[:, :, None], 1)
    a, b, c = v[:, 0], v[:, 1], v[:, 2]
    pa, pb, pc = p[:, 0], p[:, 1], p[:, 2]
    width = (hi - lo) / bands
    flat = c - a <= 1e-12 * max(abs(hi - lo), 1e-30)
    flat_band = np.clip(((a - lo) / width).astype(np.int64), 0, bands - 1)
    out = []
    for j in range(bands):
        low = -np.inf if j == 0 else lo + j * width
        high = np.inf if j == bands - 1 else lo + (j + 1) * width
        l1, l2 = np.maximum(low, a), np.minimum(high, c)
        take = np.where(flat, flat_band == j, l1 < l2)
        if not take.any():
            out.append((np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)))
            continue
        s = take
        ac1, ac2 = _on_edge(pa[s], pc[s], a[s], c[s], l1[s]), _on_edge(pa[s], pc[s], a[s], c[s], l2[s])
        path1 = _on_path(pa[s], pb[s], pc[s], a[s], b[s], c[s], l1[s])
        path2 = _on_path(pa[s], pb[s], pc[s], a[s], b[s], c[s], l2[s])
        corner = ((l1[s] <= b[s]) & (b[s] <= l2[s]))[:, None]
        poly = np.stack([ac1, ac2, path2, np.where(corner, pb[s], path1), path1], 1)    # [M,5,3]
        whole = flat[s]
        poly[whole] = np.stack([pa[s][whole], pc[s][whole], pb[s][whole], pb[s][whole], pb[s][whole]], 1)
        # the polygon runs a -> c -> b: against the input winding where the sort permutation is even
        poly = np.where(even[s][:, None, None], poly[:, ::-1], poly)
        m = len(poly)
        base = 5 * np.arange(m, dtype=np.uint32)[:, None]
        fan = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]], np.uint32)
        faces = (base[:, None, :] + fan[None]).reshape(-1, 3)
        out.append((poly.reshape(-1, 3).astype(np.float32), faces))
    return out


def _even(order) -> np.ndarray:
    """[T] bool: each row of ``order`` [T, 3] is an even permutation of (0, 1, 2)."""
    return np.isin(order[:, 0] * 9 + order[:, 1] * 3 + order[:, 2], [0 * 9 + 1 * 3 + 2, 1 * 9 + 2 * 3 + 0,
                                                                       2 * 9 + 0 * 3 + 1])


def _on_edge(p0, p1, v0, v1, level):
    t = np.divide(level - v0, v1 - v0, out=np.zeros_like(level), where=v1 != v0)
    return p0 + np.clip(t, 0.0, 1.0)[:, None] * (p1 - p0)


def _on_path(pa, pb, pc, a, b, c, level):
    first = (level <= b)[:, None]
    return np.where(first, _on_edge(pa, pb, a, b, level), _on_edge(pb, pc, b, c, level))
