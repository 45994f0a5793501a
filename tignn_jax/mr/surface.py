"""The surface of a volume mesh: its outward boundary triangles, their nodes, and vertex normals.

Triangles are counter-clockwise seen from outside the body, the winding `tignn_jax.mr.render` culls back faces
by and `vertex_normals` orients its normals by.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

# Faces of a VTK hexahedron (nodes 0-3 bottom counter-clockwise seen from above, 4-7 above them), each
# counter-clockwise seen from outside the element.
HEX8_FACES = np.array([
    [0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7],
], dtype=np.int32)
# Faces of a VTK tetrahedron with positive volume ((x1-x0) x (x2-x0) · (x3-x0) > 0), outward.
TET4_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], dtype=np.int32)


def surface_triangles(cells, points) -> np.ndarray:
    """The boundary triangles of a hex8 or tet4 mesh, outward.

    A face is on the boundary when no other element shares it. Each boundary quad is split into two triangles
    along its 0-2 diagonal. Every triangle is oriented counter-clockwise seen from outside by the geometry, so
    elements given with inverted orientation are handled. Not jit-able.

    Args:
      cells: [E, 8] (hex8) or [E, 4] (tet4) node ids in the VTK / meshio node order.
      points: [N, 3] reference coordinates.

    Returns:
      [T, 3] int32 indices into ``points``.

    Raises:
      ValueError: ``cells`` is not [E, 4] or [E, 8], or indexes a node outside ``points``.
    """
    cells = np.asarray(cells)
    points = np.asarray(points, np.float64)
    if cells.ndim != 2 or cells.shape[1] not in (4, 8):
        raise ValueError(f"cells must be [E,4] (tet4) or [E,8] (hex8), got shape {cells.shape}")
    if cells.size and (cells.min() < 0 or cells.max() >= len(points)):
        raise ValueError(f"cells index nodes outside 0..{len(points) - 1}")
    faces_of = HEX8_FACES if cells.shape[1] == 8 else TET4_FACES
    faces = cells[:, faces_of]                                   # [E,F,k]
    owner = np.repeat(np.arange(len(cells)), faces_of.shape[0])
    faces = faces.reshape(-1, faces_of.shape[1])
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = counts[inverse.reshape(-1)] == 1
    faces, owner = faces[boundary], owner[boundary]
    if faces.shape[1] == 4:
        faces = np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])
        owner = np.concatenate([owner, owner])
    tri = points[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = tri.mean(1) - points[cells[owner]].mean(1)
    flip = np.einsum("ij,ij->i", normal, outward) < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces.astype(np.int32)


def surface_nodes(triangles) -> np.ndarray:
    """The sorted ids [S] (int32) of the nodes that lie on the surface ``triangles`` [T, 3]."""
    return np.unique(np.asarray(triangles)).astype(np.int32)


def vertex_normals(positions, triangles) -> Array:
    """Unit outward vertex normals of a (deformed) surface.

    Each vertex averages the unit normals of its triangles weighted by the triangle's angle at that vertex,
    n_i ∝ Σ_t α_t,i n_t, which makes the result independent of how faces were split into triangles (a cube's
    corner gets the diagonal).

    Args:
      positions: [N, 3] node positions.
      triangles: [T, 3] triangles, counter-clockwise seen from outside.

    Returns:
      [N, 3] unit normals; the zero vector for nodes on no triangle.
    """
    p = positions[triangles]                                                 # [T,3,3]
    face = _normalise_rows(jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    e_next = _normalise_rows(jnp.roll(p, -1, axis=1) - p)
    e_prev = _normalise_rows(jnp.roll(p, 1, axis=1) - p)
    angle = jnp.arccos(jnp.clip(jnp.sum(e_next * e_prev, axis=-1), -1.0, 1.0))  # [T,3]
    contrib = angle[:, :, None] * face[:, None, :]
    summed = jnp.zeros_like(positions).at[triangles.reshape(-1)].add(contrib.reshape(-1, 3))
    norm = jnp.linalg.norm(summed, axis=-1, keepdims=True)
    return jnp.where(norm > 0, summed / jnp.maximum(norm, 1e-30), 0.0)


def _normalise_rows(v):
    return v / jnp.maximum(jnp.linalg.norm(v, axis=-1, keepdims=True), 1e-30)
