"""The meshes of the paper's scenes: the bending beam and the Stanford bunny.

Every mesh is returned as ``(q0, cells, edges)``:

- ``q0`` [N,3] float64: reference nodal coordinates (length units of the scene, see each function),
- ``cells`` [K,8] (hex8) or [K,4] (tet4) int32: connectivity in meshio/VTK node order, every cell with positive
  volume,
- ``edges`` [2,E] int32: directed graph edges, both directions of every unique mesh edge, sorted by
  (sender, receiver) — ``edges[0]`` are the senders, ``edges[1]`` the receivers.

The beam is meshed here in closed form. The bunny is read from ``fem/data/bunny.npz``, which
``scripts/make_bunny_mesh.py`` builds once from the scan (nothing needs a mesher at run time).

Beam node order. The reference data set (Abaqus, published with the TIGNN reference implementation) numbers the
756 nodes the way Gmsh numbers a transfinite mesh of a partitioned block: all geometric corner points first,
then the interior nodes of each curve, then of each surface, then of each volume, entity by entity. The block is
partitioned at x = 0, 8, 16, 18, 20, ..., 40 (the load positions and one extra cut at 8), so the entities are
the blocks [0,8] and [8,16], the slabs [16,18] ... [38,40] (whose x-curves have no interior nodes) and their
faces. ``_reference_entities`` lists these entities in that order with, for each, the direction in which its
interior nodes are numbered; ``beam_mesh()`` (``order="reference"``) reproduces the reference ``q0`` exactly,
and the reference ``edges`` array is exactly our ``edges`` (both are sorted by sender, then receiver).
``order="lexicographic"`` numbers nodes by (x, y, z) with z fastest; ``reference_permutation`` maps any node
order onto a given reference ``q0`` by coordinates.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

BEAM_ELEMENT_SIZE = 2.0
BEAM_SHAPE = (20, 5, 5)

# Load lines of the reference data set, in sim-id order: (axis of the face normal, face coordinate, load sign).
# sims 1-13: face y=10 pushed along -y; 14-26: z=10, -z; 27-39: y=0, +y; 40-52: z=0, +z.
BEAM_LOAD_FACES = ((1, 10.0, -1.0), (2, 10.0, -1.0), (1, 0.0, 1.0), (2, 0.0, 1.0))
BEAM_LOAD_X = tuple(40.0 - 2.0 * i for i in range(13))

BUNNY_FILE = Path(__file__).resolve().parent / "data" / "bunny.npz"

HEX_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))
TET_EDGES = ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))
# Faces with their nodes ordered so that the right-hand normal points out of a positive-volume cell.
HEX_FACES = ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))
TET_FACES = ((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2))
_HEX_TETS = ((0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6))


def beam_mesh(order: str = "reference"):
    """The reference beam: x in [0,40], y, z in [0,10], 20x5x5 hex8 of edge 2, 756 nodes, 1980 edges.

    Args:
      order: ``"reference"`` numbers the nodes as the Abaqus reference data set does (see the module
        docstring); ``"lexicographic"`` numbers them by (x, y, z), z fastest.

    Returns:
      ``(q0 [756,3] float64, cells [500,8] int32, edges [2,3960] int32)``; lengths in the data set's units.
    """
    if order not in ("reference", "lexicographic"):
        raise ValueError(f"order must be 'reference' or 'lexicographic', got {order!r}")
    nx, ny, nz = BEAM_SHAPE
    h = BEAM_ELEMENT_SIZE
    ijk = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    ijk = ijk.reshape(-1, 3)
    if order == "reference":
        ijk = np.rint(_reference_coordinates() / h).astype(np.int64)
    node_id = np.full((nx + 1, ny + 1, nz + 1), -1, np.int64)
    node_id[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = np.arange(len(ijk))
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    corners = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))
    cells = np.stack([node_id[i + a, j + b, k + c] for a, b, c in corners], axis=1).astype(np.int32)
    q0 = ijk.astype(np.float64) * h
    return q0, cells, mesh_edges(cells)


def reference_permutation(q0_ref, q0, tol: float = 1e-4):
    """Indices ``perm`` with ``q0[perm] == q0_ref`` (nodes matched by coordinates within ``tol``).

    Use it to bring a mesh in any node order into the order of a reference data set read at run time.
    """
    q0_ref = np.asarray(q0_ref, np.float64)
    q0 = np.asarray(q0, np.float64)
    if q0_ref.shape != q0.shape or q0.ndim != 2:
        raise ValueError(f"q0_ref has shape {q0_ref.shape} and q0 {q0.shape}; expected the same [N,3]")
    perm = np.empty(len(q0_ref), np.int64)
    distance = np.empty(len(q0_ref))
    for start in range(0, len(q0_ref), 1024):
        d2 = np.sum((q0_ref[start:start + 1024, None, :] - q0[None, :, :]) ** 2, axis=-1)
        perm[start:start + 1024] = np.argmin(d2, axis=1)
        distance[start:start + 1024] = np.sqrt(np.min(d2, axis=1))
    if np.any(distance > tol):
        bad = int(np.argmax(distance > tol))
        raise ValueError(f"q0_ref node {bad} has no node of q0 within tol={tol} (nearest at {distance[bad]:.3g})")
    if len(np.unique(perm)) != len(perm):
        raise ValueError("q0_ref matches some node of q0 twice")
    return perm


def clamped_nodes(q0, axis: int = 0, value: float = 0.0, tol: float = 1e-6):
    """Ids of the nodes with ``q0[:, axis] == value`` (within ``tol``): the beam's encastre face x = 0."""
    q0 = np.asarray(q0)
    return np.flatnonzero(np.abs(q0[:, axis] - value) <= tol).astype(np.int32)


def beam_node_type(q0):
    """[N] int8: 1 on the clamped face x = 0, 0 elsewhere."""
    node_type = np.zeros(len(q0), np.int8)
    node_type[clamped_nodes(q0)] = 1
    return node_type


def beam_load_nodes(q0, face: int, x: float, tol: float = 1e-6):
    """The 6 nodes of a load line: on face ``BEAM_LOAD_FACES[face]`` at ``x``, ordered along the line."""
    if face not in range(len(BEAM_LOAD_FACES)):
        raise ValueError(f"face must be 0..{len(BEAM_LOAD_FACES) - 1}, got {face}")
    q0 = np.asarray(q0)
    axis, value, _ = BEAM_LOAD_FACES[face]
    ids = np.flatnonzero((np.abs(q0[:, axis] - value) <= tol) & (np.abs(q0[:, 0] - x) <= tol))
    if len(ids) != BEAM_SHAPE[1] + 1:
        raise ValueError(f"no load line of {BEAM_SHAPE[1] + 1} nodes at x={x} on face {face}")
    along = 3 - axis
    return ids[np.argsort(q0[ids, along])].astype(np.int32)


def beam_reference_load(q0, sim_id: int):
    """Load line of reference case ``sim_id`` (1..52): ``(node ids [6] int32, unit direction [3] float64)``.

    The force per node in step k is ``5000 * (k + 1)`` along the direction (see the data README).
    """
    n_x = len(BEAM_LOAD_X)
    if not 1 <= int(sim_id) <= n_x * len(BEAM_LOAD_FACES):
        raise ValueError(f"sim_id must be in 1..{n_x * len(BEAM_LOAD_FACES)}, got {sim_id}")
    face, position = divmod(int(sim_id) - 1, n_x)
    axis, _, sign = BEAM_LOAD_FACES[face]
    direction = np.zeros(3)
    direction[axis] = sign
    return beam_load_nodes(q0, face, BEAM_LOAD_X[position]), direction


def bunny_mesh(path: str | Path | None = None):
    """The Stanford bunny as linear tetrahedra, read from ``fem/data/bunny.npz``.

    Non-dimensional units: the scan as shipped by pymeshfix scaled by 0.2, so the bunny is 9.9 long (x),
    7.6 wide (y) and 9.7 tall (z, up); it stands on a flat base on z = 0 (the nodes to clamp, see
    ``bunny_bottom_nodes``). Built by ``scripts/make_bunny_mesh.py`` (recipe, quality and credit there:
    Stanford 3D Scanning Repository, Stanford University Computer Graphics Laboratory).

    Returns:
      ``(q0 [N,3] float64, cells [K,4] int32, edges [2,E] int32)``.
    """
    with np.load(BUNNY_FILE if path is None else path) as data:
        q0 = np.asarray(data["nodes"], np.float64)
        cells = np.asarray(data["tets"], np.int32)
    return q0, cells, mesh_edges(cells)


def bunny_bottom_nodes(q0, tol: float = 1e-6):
    """Ids of the nodes within ``tol`` of the lowest z: the bunny's flat base, to be clamped."""
    q0 = np.asarray(q0)
    return np.flatnonzero(q0[:, 2] <= q0[:, 2].min() + tol).astype(np.int32)


def mesh_edges(cells):
    """[2,E] int32: both directions of every unique edge of hex8 ([K,8]) or tet4 ([K,4]) ``cells``."""
    cells = np.asarray(cells)
    pairs = _element_table(cells, HEX_EDGES, TET_EDGES)
    pairs = cells[:, np.array(pairs)].reshape(-1, 2)
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    both = np.concatenate([pairs, pairs[:, ::-1]])
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    return both.T.astype(np.int32)


def hop_distances(edges, n_nodes: int, sources=None) -> np.ndarray:
    """Graph distances in edges between mesh nodes: [len(sources), n_nodes] from each source (all nodes when
    ``sources`` is None; unreachable nodes at inf). ``edges`` [2, E]: directed edges, both directions present."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import shortest_path

    edges = np.asarray(edges)
    adj = coo_matrix((np.ones(edges.shape[1]), (edges[0], edges[1])), shape=(n_nodes, n_nodes)).tocsr()
    return shortest_path(adj, unweighted=True, indices=sources)


def cell_volumes(q0, cells):
    """[K] signed volumes of hex8 or tet4 ``cells`` (each hex split into 6 tets); positive means VTK order."""
    q0 = np.asarray(q0, np.float64)
    cells = np.asarray(cells)
    split = np.array(_element_table(cells, _HEX_TETS, ((0, 1, 2, 3),)))
    tets = cells[:, split]
    x = q0[tets]
    a, b, c = (x[..., m, :] - x[..., 0, :] for m in (1, 2, 3))
    return np.einsum("...i,...i->...", np.cross(a, b), c).sum(axis=-1) / 6.0


def boundary_faces(cells):
    """Faces that belong to one cell only, outward-ordered: [F,4] for hex8 (quads), [F,3] for tet4 (triangles)."""
    cells = np.asarray(cells)
    local = np.array(_element_table(cells, HEX_FACES, TET_FACES))
    faces = cells[:, local].reshape(-1, local.shape[1])
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1].astype(np.int32)


def surface_triangles(cells):
    """[T,3] outward-ordered triangles of the boundary (quads split along their 0-2 diagonal)."""
    faces = boundary_faces(cells)
    if faces.shape[1] == 3:
        return faces
    return np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])


def surface_nodes_and_normals(q0, cells):
    """Boundary nodes and their outward unit normals (area-weighted mean of the adjacent face normals).

    Returns:
      ``(nodes [S] int32, normals [S,3] float64)``; use it to push a surface node along ``-normal``.
    """
    q0 = np.asarray(q0, np.float64)
    tri = surface_triangles(cells)
    x = q0[tri]
    area_normal = 0.5 * np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    acc = np.zeros_like(q0)
    for m in range(3):
        np.add.at(acc, tri[:, m], area_normal)
    nodes = np.unique(tri).astype(np.int32)
    normals = acc[nodes]
    return nodes, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _element_table(cells, hex_table, tet_table):
    if cells.ndim != 2 or cells.shape[1] not in (4, 8):
        raise ValueError(f"cells has shape {cells.shape}, expected [K,8] (hex8) or [K,4] (tet4)")
    return hex_table if cells.shape[1] == 8 else tet_table


def _reference_coordinates():
    """[756,3] beam node coordinates in the reference data set's order (see the module docstring)."""
    return np.concatenate([_entity_nodes(spec) for spec in _reference_entities()])


def _reference_entities():
    """Entity specs in the reference numbering: vertices, then curves, surfaces, volumes.

    A spec is a string of tokens. ``x16`` fixes a coordinate; ``y0:10+`` runs over the grid values strictly
    inside (0, 10) in increasing (``+``) or decreasing (``-``) order; the first running token varies fastest.
    """
    vertices = ["x16 y0 z10", "x16 y10 z10", "x8 y10 z10", "x8 y0 z10",
                "x16 y10 z0", "x8 y10 z0", "x8 y0 z0", "x16 y0 z0"]
    curves = ["x16 z10 y0:10+", "y10 z10 x8:16-", "x8 z10 y0:10-", "y0 z10 x8:16+",
              "x16 z0 y0:10-", "y10 z0 x8:16+", "x8 z0 y0:10+", "y0 z0 x8:16-",
              "x8 y0 z0:10-", "x16 y0 z0:10+", "x8 y10 z0:10+", "x16 y10 z0:10-"]
    surfaces = ["z10 y0:10+ x8:16-", "z0 y0:10+ x8:16-", "y0 x8:16- z0:10-", "y10 x8:16- z0:10-",
                "x16 y0:10+ z0:10-", "x8 y0:10+ z0:10-"]
    # The slab faces x = 18 ... 36 alternate between two numberings.
    slab_faces = (
        (["y0 z0", "y0 z10", "y10 z0", "y10 z10"],
         ["y0 z0:10+", "y10 z0:10-", "z10 y0:10+", "z0 y0:10-"], "z0:10- y0:10+"),
        (["y10 z10", "y10 z0", "y0 z10", "y0 z0"],
         ["y10 z0:10-", "y0 z0:10+", "z0 y0:10-", "z10 y0:10+"], "z0:10+ y0:10-"),
    )
    for n, x in enumerate(range(18, 38, 2)):
        v, c, s = slab_faces[n % 2]
        vertices += [f"x{x} {t}" for t in v]
        curves += [f"x{x} {t}" for t in c]
        surfaces.append(f"x{x} {s}")
    vertices += ["x38 y0 z10", "x38 y10 z10", "x38 y10 z0", "x38 y0 z0",
                 "x40 y10 z0", "x40 y0 z0", "x40 y10 z10", "x40 y0 z10",
                 "x0 y10 z10", "x0 y0 z10", "x0 y10 z0", "x0 y0 z0"]
    curves += ["x38 z10 y0:10+", "x38 z0 y0:10-", "x38 y0 z0:10+", "x38 y10 z0:10-",
               "x40 z0 y0:10-", "x40 z10 y0:10+", "x40 y0 z0:10+", "x40 y10 z0:10-",
               "y10 z10 x0:8-", "x0 z10 y0:10-", "y0 z10 x0:8+", "y10 z0 x0:8+",
               "x0 z0 y0:10+", "y0 z0 x0:8-", "x0 y0 z0:10-", "x0 y10 z0:10+"]
    surfaces += ["x38 y0:10+ z0:10-", "x40 y0:10+ z0:10+",
                 "z10 y0:10+ x0:8-", "z0 y0:10+ x0:8-", "y0 x0:8- z0:10-", "y10 x0:8- z0:10-",
                 "x0 y0:10+ z0:10-"]
    volumes = ["y0:10+ x8:16- z0:10-", "y0:10+ x0:8- z0:10-"]
    return vertices + curves + surfaces + volumes


def _entity_nodes(spec):
    """[n,3] grid coordinates of the interior nodes of one entity spec, in its numbering order."""
    fixed = {}
    running = []
    for token in spec.split():
        axis = "xyz".index(token[0])
        if ":" in token:
            lo, hi = (float(t) for t in token[1:-1].split(":"))
            values = np.arange(lo + BEAM_ELEMENT_SIZE, hi - 0.5 * BEAM_ELEMENT_SIZE, BEAM_ELEMENT_SIZE)
            running.append((axis, values if token[-1] == "+" else values[::-1]))
        else:
            fixed[axis] = float(token[1:])
    grids = np.meshgrid(*[values for _, values in running[::-1]], indexing="ij") if running else []
    out = np.zeros((int(np.prod([len(v) for _, v in running])), 3))
    for axis, value in fixed.items():
        out[:, axis] = value
    for (axis, _), grid in zip(running[::-1], grids):
        out[:, axis] = grid.ravel()
    return out
