"""Scenes on a user's own mesh: read and check a tet4 or hex8 mesh, clamp it, and load it as the paper's scenes are.

`read_volume_mesh` reads any file meshio reads and refuses what the FEM cannot run (mixed or unsupported cells,
inverted or degenerate elements); `clamp_nodes` turns plane, half-space and box expressions or a file of node ids
into the clamped set; `mesh_scene` makes the `fem.scenes.Scene` that `fem.generate.run_cases` runs; and
`mesh_forces` draws load cases of three kinds on the free surface:

* ``fingertip``: patches of 1–6 neighbouring nodes that ramp, hold, release or move (`fem.cases.fingertip_forces`,
  C¹ histories), pushed inside a 30° cone around the inward normal;
* ``point``: one node pushed along its inward normal, rising smoothly over ``rise_frames`` and then held
  (`fem.cases.point_load_forces`), optionally spread over a fingertip-sized ``radius``;
* ``pressure``: a uniform pressure on the boundary faces within ``radius`` of a surface point, as the equivalent
  nodal forces of the faces in the reference configuration (a dead load), rising like ``point``.

Each case's peak is drawn uniformly in [0.1, 1] × the level the user gives (total force, or pressure), so a level
is the largest load of the data set. Every check raises ``ValueError`` with one line naming the bad input.
"""
from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .meshes import boundary_faces, cell_volumes, mesh_edges

LOAD_KINDS = ("fingertip", "point", "pressure")
SUPPORTED = {"tetra": 4, "hexahedron": 8}
# volume cell types meshio knows that the FEM does not run (named in the error)
OTHER_VOLUME = ("tetra10", "hexahedron20", "hexahedron24", "hexahedron27", "wedge", "wedge12", "wedge15",
                "pyramid", "pyramid13", "pyramid14", "polyhedron")
DEGENERATE = 1e-8   # an element whose |volume| is below this fraction of the median element volume


class VolumeMesh(NamedTuple):
    """A checked volume mesh.

    Attributes:
      points: [N, 3] float64 node coordinates (length units of the file), only nodes that cells use.
      cells: [K, 4] (tet4) or [K, 8] (hex8) int32, VTK node order, every cell with positive volume.
      cell_type: ``"tetra"`` or ``"hexahedron"``.
      file_ids: [N] int64, each node's id in the file (nodes no cell uses are dropped).
    """
    points: np.ndarray
    cells: np.ndarray
    cell_type: str
    file_ids: np.ndarray


def read_volume_mesh(path) -> VolumeMesh:
    """Read a tet4 or hex8 mesh with meshio and check it.

    Surface cells (triangles, quads, lines, vertices) are ignored; nodes that no volume cell uses are dropped.

    Raises:
      ValueError: an unreadable file, no volume cells, mixed volume cell types, an unsupported cell type (e.g.
        tetra10, wedge), or inverted or degenerate elements (naming how many and the first ids).
    """
    import meshio

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"mesh {path}: no such file")
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said), contextlib.redirect_stdout(said):
            m = meshio.read(path)
    except (Exception, SystemExit) as err:   # meshio raises many types, or exits, on a file it cannot parse
        text = (said.getvalue().strip() or str(err) or type(err).__name__).splitlines()[0]
        raise ValueError(f"mesh {path}: meshio cannot read it ({text})") from None
    kinds = {b.type for b in m.cells}
    volume = sorted(kinds & (set(SUPPORTED) | set(OTHER_VOLUME)))
    if not volume:
        raise ValueError(f"mesh {path}: no tetra or hexahedron cells (found {sorted(kinds) or 'none'})")
    if len(volume) > 1:
        raise ValueError(f"mesh {path}: mixed volume cells {volume}; the FEM runs one type, tetra or hexahedron")
    kind = volume[0]
    if kind not in SUPPORTED:
        raise ValueError(f"mesh {path}: unsupported cells {kind!r}; supported: tetra (tet4), hexahedron (hex8)")
    cells = np.concatenate([np.asarray(b.data, np.int64) for b in m.cells if b.type == kind])
    points = np.asarray(m.points, np.float64)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"mesh {path}: points must be 3-D, got shape {points.shape}")
    points = points[:, :3]
    if not np.all(np.isfinite(points)):
        raise ValueError(f"mesh {path}: non-finite node coordinates")
    used = np.unique(cells)
    remap = np.full(len(points), -1, np.int64)
    remap[used] = np.arange(len(used))
    mesh = VolumeMesh(points[used], remap[cells].astype(np.int32), kind, used)
    check_cells(mesh.points, mesh.cells, where=f"mesh {path}")
    return mesh


def check_cells(points, cells, where: str = "mesh") -> None:
    """Refuse inverted (volume ≤ 0) and degenerate (|volume| < 1e-8 × the median) elements.

    Raises:
      ValueError: naming the count and the first ids of the bad elements.
    """
    vol = cell_volumes(points, cells)
    scale = float(np.median(np.abs(vol)))
    degenerate = np.where(np.abs(vol) <= DEGENERATE * scale)[0]
    if scale <= 0 or degenerate.size:
        ids = degenerate if scale > 0 else np.arange(len(vol))
        raise ValueError(f"{where}: {ids.size} degenerate elements (volume ~ 0), ids {ids[:10].tolist()}")
    inverted = np.where(vol < 0)[0]
    if inverted.size:
        raise ValueError(f"{where}: {inverted.size} inverted elements (negative volume: node order not VTK's), "
                         f"ids {inverted[:10].tolist()}")


_CONDITION = re.compile(r"^\s*([xyz])\s*(<=|>=|=|<|>)\s*(min|max|[-+0-9.eE]+)\s*$")


def clamp_nodes(points, expressions, file_ids=None, tol: float = 1e-5) -> np.ndarray:
    """The clamped node ids: the union of the nodes each expression selects.

    An expression is a plane ``x=0`` (within ``tol`` × the mesh's diagonal), a half-space ``z<=0.5``
    (``<``, ``<=``, ``>``, ``>=``), a coordinate extreme ``z=min`` or ``x=max``, a box ``box:x0,y0,z0,x1,y1,z1``
    (corners inclusive), or the path of a text file of node ids (whitespace or comma separated; ids of the mesh
    file, translated by ``file_ids``).

    Args:
      points: [N, 3] node coordinates.
      expressions: a string or a list of them.
      file_ids: [N] each node's id in the mesh file (`VolumeMesh.file_ids`); None: ids are positions.
      tol: plane tolerance, a fraction of the bounding box's diagonal.

    Returns:
      Sorted int32 node ids.

    Raises:
      ValueError: an expression that does not parse, a file of ids not in the mesh, or a set that is empty or
        holds every node.
    """
    points = np.asarray(points, np.float64)
    if isinstance(expressions, str):
        expressions = [expressions]
    if not expressions:
        raise ValueError("no clamp given: a body needs clamped nodes (e.g. --clamp x=min)")
    lo, hi = points.min(axis=0), points.max(axis=0)
    eps = tol * float(np.linalg.norm(hi - lo))
    chosen = np.zeros(len(points), bool)
    for expr in expressions:
        chosen |= _select(points, str(expr), lo, hi, eps, file_ids)
    if not chosen.any():
        raise ValueError(f"clamp {list(map(str, expressions))} selects no node (mesh box {lo.tolist()} to "
                         f"{hi.tolist()})")
    if chosen.all():
        raise ValueError(f"clamp {list(map(str, expressions))} selects every node: nothing could move")
    return np.flatnonzero(chosen).astype(np.int32)


def _select(points, expr, lo, hi, eps, file_ids):
    m = _CONDITION.match(expr)
    if m:
        axis, op, value = "xyz".index(m.group(1)), m.group(2), m.group(3)
        if value in ("min", "max"):
            if op != "=":
                raise ValueError(f"clamp {expr!r}: min and max go with '=' only (e.g. z=min)")
            v = lo[axis] if value == "min" else hi[axis]
        else:
            try:
                v = float(value)
            except ValueError:
                raise ValueError(f"clamp {expr!r}: {value!r} is not a number") from None
        c = points[:, axis]
        return {"=": np.abs(c - v) <= eps, "<": c < v, "<=": c <= v + eps, ">": c > v,
                ">=": c >= v - eps}[op]
    if expr.startswith("box:"):
        try:
            b = np.array([float(t) for t in expr[4:].split(",")])
        except ValueError:
            b = np.zeros(0)
        if b.shape != (6,) or not np.all(np.isfinite(b)):
            raise ValueError(f"clamp {expr!r}: a box is box:x0,y0,z0,x1,y1,z1 (six numbers)")
        return np.all((points >= b[:3] - eps) & (points <= b[3:] + eps), axis=1)
    path = Path(expr)
    if path.is_file():
        try:
            ids = np.array([int(t) for t in re.split(r"[\s,]+", path.read_text().strip()) if t], np.int64)
        except ValueError:
            raise ValueError(f"clamp file {expr}: not a list of integer node ids") from None
        table = np.arange(len(points)) if file_ids is None else np.asarray(file_ids)
        where = {int(f): i for i, f in enumerate(table)}
        missing = [int(i) for i in ids if int(i) not in where]
        if missing:
            raise ValueError(f"clamp file {expr}: node ids not in the mesh's volume cells: {missing[:10]}")
        out = np.zeros(len(points), bool)
        out[[where[int(i)] for i in ids]] = True
        return out
    raise ValueError(f"clamp {expr!r}: not a plane (x=0), half-space (z<=0.5), extreme (z=min), box "
                     "(box:x0,y0,z0,x1,y1,z1) or a file of node ids")


def check_surface(points, cells) -> None:
    """Refuse a boundary that is not a closed 2-manifold, where fingertip loads need outward normals: every
    boundary edge must be shared by exactly two boundary faces.

    Raises:
      ValueError: naming the number of non-manifold edges and one of them (its two node ids).
    """
    faces = boundary_faces(cells)
    k = faces.shape[1]
    e = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    _, counts = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)
    keys = np.unique(np.sort(e, axis=1), axis=0)
    bad = keys[counts != 2]
    if bad.size:
        raise ValueError(f"the mesh's surface is not manifold: {len(bad)} boundary edges are not shared by exactly "
                         f"two faces (e.g. nodes {bad[0].tolist()}); loads need outward normals ({k}-node faces)")


def mesh_scene(mesh: VolumeMesh, material, clamped, *, frame_dt: float = 0.05, n_frames: int = 20,
               damping: float = 0.0, name: str = "mesh"):
    """The `fem.scenes.Scene` of a user's mesh (graph edges: the cells' edges; node type 1 where clamped).

    Raises:
      ValueError: a non-positive frame step or frame count, or negative damping.
    """
    from .scenes import Scene

    if not (np.isfinite(frame_dt) and frame_dt > 0):
        raise ValueError(f"frame_dt must be a positive number, got {frame_dt}")
    if int(n_frames) != n_frames or n_frames < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames}")
    if not (np.isfinite(damping) and damping >= 0):
        raise ValueError(f"damping must be a finite number >= 0, got {damping}")
    node_type = np.zeros(len(mesh.points), np.int8)
    node_type[np.asarray(clamped, int)] = 1
    return Scene(name, mesh.points, mesh.cells, mesh.cell_type, mesh_edges(mesh.cells), node_type, material,
                 float(frame_dt), int(n_frames), float(damping), "linear")


def mesh_forces(scene, kinds, n_cases: int, seed: int, *, force: float | None = None,
                pressure: float | None = None, radius: float = 0.0, rise_frames: int = 10):
    """Load cases on a scene's free surface: [n_cases, T, N, 3] nodal forces and a JSON-able description per case.

    Case c is of kind ``kinds[c % len(kinds)]`` (see the module docstring); each kind draws its cases from its
    own seed ``seed + 1000 k``, and each case's peak is uniform in [0.1, 1] × the level.

    Args:
      scene: a `fem.scenes.Scene`.
      kinds: load kinds from ``LOAD_KINDS``.
      n_cases: number of cases.
      seed: random seed.
      force: the largest total force of a fingertip or point case (force units of the mesh and material).
      pressure: the largest pressure of a pressure case (force per area).
      radius: of a point case's spread (0: one node) and of a pressure case's patch (0: twice the median edge).
      rise_frames: frames over which point and pressure loads rise (the C¹ smooth step), then held.

    Raises:
      ValueError: an unknown kind, a missing or non-positive level, or bad counts.
    """
    from . import cases as cs

    kinds = list(kinds)
    unknown = [k for k in kinds if k not in LOAD_KINDS]
    if not kinds or unknown:
        raise ValueError(f"load kinds must be among {LOAD_KINDS}, got {kinds}")
    if n_cases < 1:
        raise ValueError(f"n_cases must be positive, got {n_cases}")
    for name, level, needed in (("force", force, {"fingertip", "point"}), ("pressure", pressure, {"pressure"})):
        if needed & set(kinds) and not (level is not None and np.isfinite(level) and level > 0):
            raise ValueError(f"{sorted(needed & set(kinds))} loads need a positive {name} level, got {level}")
    if not (np.isfinite(radius) and radius >= 0):
        raise ValueError(f"radius must be a finite number >= 0, got {radius}")
    T, N = scene.n_frames, len(scene.points)
    out = np.zeros((n_cases, T, N, 3), np.float32)
    described = [None] * n_cases
    for k, kind in enumerate(dict.fromkeys(kinds)):
        rows = [c for c in range(n_cases) if kinds[c % len(kinds)] == kind]
        if not rows:
            continue
        rng = np.random.default_rng(seed + 1000 * k)
        if kind == "fingertip":
            f, info = cs.fingertip_forces(scene, len(rows), seed + 1000 * k, peak_total=force, smooth=True)
        elif kind == "point":
            f, nodes = cs.point_load_forces(scene, min(len(rows), _free_count(scene)), seed + 1000 * k,
                                            rise_frames=rise_frames, radius=radius)
            f = np.concatenate([f] * -(-len(rows) // len(f)))[: len(rows)]
            nodes = np.concatenate([nodes] * -(-len(rows) // len(nodes)))[: len(rows)]
            peaks = rng.uniform(0.1, 1.0, len(rows)) * force
            f = f * peaks[:, None, None, None]
            info = [{"node": int(n), "peak_total": float(p), "rise_frames": rise_frames}
                    for n, p in zip(nodes, peaks)]
        else:
            f, info = pressure_forces(scene, len(rows), rng, pressure, radius, rise_frames)
        for j, c in enumerate(rows):
            out[c] = f[j]
            described[c] = {"kind": kind, **info[j]}
    return out, described


def _free_count(scene) -> int:
    from .cases import free_surface

    return len(free_surface(scene)[0])


def pressure_forces(scene, n_cases: int, rng, pressure: float, radius: float, rise_frames: int):
    """Pressure patches (module docstring): [n_cases, T, N, 3] and a description per case. A face is loaded when
    its centroid lies within ``radius`` of the patch centre, a random free surface node; clamped nodes take no
    force."""
    from .cases import free_surface, smooth_rise

    faces = boundary_faces(scene.cells)
    x = scene.points[faces]
    if faces.shape[1] == 4:
        area_normal = 0.5 * np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1])
    else:
        area_normal = 0.5 * np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    centroid = x.mean(axis=1)
    if radius <= 0:
        edges = scene.edges
        radius = 2.0 * float(np.median(np.linalg.norm(scene.points[edges[0]] - scene.points[edges[1]], axis=1)))
    nodes, _ = free_surface(scene)
    amp = smooth_rise(scene.n_frames, min(rise_frames, scene.n_frames))
    free = (scene.node_type == 0).astype(np.float64)[:, None]
    out = np.zeros((n_cases, scene.n_frames, len(scene.points), 3))
    info = []
    for c in range(n_cases):
        centre = int(nodes[rng.integers(len(nodes))])
        near = np.linalg.norm(centroid - scene.points[centre], axis=1) <= radius
        if not near.any():
            near = np.linalg.norm(centroid - scene.points[centre], axis=1) <= np.linalg.norm(
                centroid - scene.points[centre], axis=1).min()
        p = float(rng.uniform(0.1, 1.0) * pressure)
        f = np.zeros((len(scene.points), 3))
        share = -p * area_normal[near] / faces.shape[1]     # into the body: against the outward normal
        for m in range(faces.shape[1]):
            np.add.at(f, faces[near, m], share)
        out[c] = amp[:, None, None] * (f * free)[None]
        info.append({"centre": centre, "radius": radius, "faces": int(near.sum()), "peak_pressure": p,
                     "rise_frames": rise_frames})
    return out, info
