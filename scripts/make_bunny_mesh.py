"""Build the committed tetrahedral mesh of the Stanford bunny, ``fem/data/bunny.npz``.

Source: the Stanford bunny scan as shipped by the PyPI package ``pymeshfix``
(``pymeshfix/examples/StanfordBunny.ply``, 50,000 vertices). The scan is from the Stanford 3D Scanning
Repository, Stanford University Computer Graphics Laboratory.

Recipe (deterministic: no random numbers are drawn; two runs write identical arrays):

1. repair the scan with MeshFix (fill the holes in the base, keep the largest component, remove
   self-intersections);
2. units and axes: the pymeshfix copy already has z up and stands near z = 0, in arbitrary units
   (49.4 tall, about 320 units per metre of the real bunny). We shift it to stand on z = 0, centre its footprint
   box at x = y = 0 and multiply by ``SCALE`` = 0.2, so the bunny is 9.9 units long (x), 7.6 wide (y) and,
   after the next steps, 9.7 tall (z); one unit is about 1.6 cm of the real bunny. The scene's material
   (C10 = 0.26, D1 = 0.049) and unit load are given in these non-dimensional units;
3. flatten the base: nodes below ``BASE_CUT`` are put on the plane z = ``BASE_CUT`` and the mesh is shifted down
   by it, so the clamped "bottom nodes" are exactly the nodes on z = 0;
4. decimate with quadric edge collapse (fast-simplification) to ``SURFACE_TRIANGLES`` triangles, repair again;
5. make the surface triangles well shaped: alternate Delaunay edge flips (only across nearly flat edges) with
   tangential Laplacian smoothing, projecting the vertices back onto the repaired scan after each sweep
   (``IMPROVE_SWEEPS`` sweeps); base vertices stay on z = 0;
6. tetrahedralise with TetGen keeping the surface triangles as they are (``nobisect``) and refining the
   interior to radius-edge ratio ``MIN_RATIO`` and minimum dihedral ``MIN_DIHEDRAL`` degrees, with TetGen's
   own optimisation pass (``OPT_MAX_DIHEDRAL``, ``OPT_ITERATIONS``);
7. remove the remaining slivers: interior nodes of tets with a dihedral angle below ``SLIVER_ANGLE`` degrees
   climb to better positions (a fixed list of trial moves: towards the neighbours' centroid and along +-x, +-y,
   +-z; a move is kept if it raises the smallest dihedral angle of the node's tets);
8. orient every tet to positive volume (VTK order) and write nodes [N,3] float64, tets [K,4] int32 and a credit
   string.

Run: ``pip install .[mesh]`` then ``python scripts/make_bunny_mesh.py`` (``--out PATH`` to write elsewhere).
Prints the counts and the quality (dihedral angles, aspect ratios) of what it wrote.
"""
from __future__ import annotations

import argparse
import hashlib
import io
import zipfile
from pathlib import Path

import numpy as np

SCALE = 0.2
BASE_CUT = 0.06
SURFACE_TRIANGLES = 2000
IMPROVE_SWEEPS = 30
MIN_RATIO = 1.5
MIN_DIHEDRAL = 12.0
OPT_MAX_DIHEDRAL = 165.0
OPT_ITERATIONS = 10
SLIVER_ANGLE = 15.0
SLIVER_SWEEPS = 30
FLAT_EDGE_COS = np.cos(np.radians(25.0))
CREDIT = ("Stanford bunny: Stanford 3D Scanning Repository, Stanford University Computer Graphics Laboratory "
          "(graphics.stanford.edu/data/3Dscanrep). Scan as shipped by the PyPI package pymeshfix "
          "(examples/StanfordBunny.ply); repaired, decimated and tetrahedralised by scripts/make_bunny_mesh.py "
          "(MeshFix, fast-simplification, TetGen). Units: the pymeshfix copy x 0.2 (9.9 long, 7.6 wide, 9.7 "
          "tall), z up, flat base on z = 0.")
OUT = Path(__file__).resolve().parents[1] / "fem" / "data" / "bunny.npz"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT, help=f"output .npz (default {OUT})")
    args = parser.parse_args(argv)
    nodes, tets = build()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    _save_npz(args.out, nodes=nodes, tets=tets, credit=np.array(CREDIT))
    digest = hashlib.sha256(nodes.tobytes() + tets.tobytes()).hexdigest()[:16]
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.1f} KiB), sha256[:16] of arrays {digest}")
    print(describe(nodes, tets))


def _save_npz(path, **arrays):
    """Like ``numpy.savez_compressed`` but with fixed zip timestamps, so a rerun rewrites identical bytes."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, array in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, buffer.getvalue())


def build():
    """The bunny as (nodes [N,3] float64, tets [K,4] int32), following the module docstring's recipe."""
    import meshio
    import pymeshfix

    scan = meshio.read(Path(pymeshfix.__file__).parent / "examples" / "StanfordBunny.ply")
    dense_v, dense_f = _repair(np.asarray(scan.points, np.float64), scan.cells_dict["triangle"])
    dense_v = _to_scene_units(dense_v)
    dense_v = _flatten_base(dense_v)
    v, f = _decimate(dense_v, dense_f, SURFACE_TRIANGLES)
    v, f = _improve_surface(v, f, dense_v, dense_f, IMPROVE_SWEEPS)
    nodes, tets = _tetrahedralize(v, f)
    tets = _orient_positive(nodes, tets)
    nodes = _remove_slivers(nodes, tets, movable=np.arange(len(nodes)) >= len(v))
    return nodes, tets


def describe(nodes, tets):
    """A few lines on counts, volumes and shape quality of a tet mesh."""
    vol, dihedral, aspect = tet_quality(nodes, tets)
    bottom = np.sum(nodes[:, 2] <= 1e-9)
    extent = nodes.max(0) - nodes.min(0)
    return (f"nodes {len(nodes)}, tets {len(tets)}, bottom nodes (z = 0) {bottom}, "
            f"extent x,y,z {extent[0]:.2f} {extent[1]:.2f} {extent[2]:.2f}, volume {vol.sum():.2f}\n"
            f"tet volume min {vol.min():.3e} (all positive: {bool(np.all(vol > 0))}), median {np.median(vol):.3e}\n"
            f"dihedral angle min {dihedral.min():.1f} deg, max {dihedral.max():.1f} deg; "
            f"tets with a dihedral < 10 deg: {int(np.sum(dihedral.min(1) < 10))}\n"
            f"aspect ratio (longest edge / (2 sqrt 6 inradius), 1 = regular) median {np.median(aspect):.2f}, "
            f"99th percentile {np.percentile(aspect, 99):.2f}, max {aspect.max():.2f}")


def tet_quality(nodes, tets):
    """Signed volumes [K], the six dihedral angles [K,6] in degrees and aspect ratios [K] of tets."""
    x = nodes[tets]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]) / 6.0
    opposite = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))
    area_normals = np.stack([0.5 * np.cross(x[:, b] - x[:, a], x[:, c] - x[:, a]) for a, b, c in opposite], 1)
    areas = np.linalg.norm(area_normals, axis=2)
    normals = area_normals / areas[..., None]
    dihedral = np.stack([180.0 - np.degrees(np.arccos(np.clip(np.sum(normals[:, i] * normals[:, j], 1), -1, 1)))
                         for i in range(4) for j in range(i + 1, 4)], 1)
    edges = np.stack([np.linalg.norm(x[:, i] - x[:, j], axis=1) for i in range(4) for j in range(i + 1, 4)], 1)
    inradius = 3.0 * np.abs(vol) / areas.sum(1)
    return vol, dihedral, edges.max(1) / (2.0 * np.sqrt(6.0) * inradius)


def _repair(v, f):
    import pymeshfix

    fix = pymeshfix.MeshFix(np.asarray(v, np.float64), np.asarray(f, np.int32))
    fix.repair()
    return np.asarray(fix.points, np.float64), np.asarray(fix.faces, np.int64)


def _to_scene_units(v):
    lo, hi = v.min(0), v.max(0)
    centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    return (v - centre) * SCALE


def _flatten_base(v):
    v = v.copy()
    v[:, 2] = np.maximum(v[:, 2], BASE_CUT) - BASE_CUT
    return v


def _decimate(v, f, n_triangles):
    import fast_simplification

    v, f = fast_simplification.simplify(v, np.asarray(f, np.int32), target_count=n_triangles)
    return _repair(v, f)


def _improve_surface(v, f, dense_v, dense_f, sweeps):
    """Delaunay flips plus tangential smoothing, vertices projected back onto the dense surface each sweep."""
    from scipy.spatial import cKDTree

    dense_n = _vertex_normals(dense_v, dense_f)
    tree = cKDTree(dense_v)
    v, f = v.copy(), f.copy()
    on_base = v[:, 2] <= 1e-6
    for _ in range(sweeps):
        while _flip_sweep(v, f):
            pass
        v = _smooth_tangentially(v, f, fixed_z=on_base)
        _, nearest = tree.query(v)
        normal = dense_n[nearest]
        v = v - np.sum((v - dense_v[nearest]) * normal, 1, keepdims=True) * normal
        v[on_base, 2] = 0.0
        on_base |= v[:, 2] <= 1e-6
    while _flip_sweep(v, f):
        pass
    return v, f


def _flip_sweep(v, f):
    """One pass of Delaunay flips over independent edges, in place; returns the number of flips."""
    edge_faces = {}
    for face_id, face in enumerate(f):
        for k in range(3):
            edge_faces[(int(face[k]), int(face[(k + 1) % 3]))] = face_id
    touched = np.zeros(len(f), bool)
    flips = 0
    for (a, b), f1 in edge_faces.items():
        if a > b or (b, a) not in edge_faces:
            continue
        f2 = edge_faces[(b, a)]
        if touched[f1] or touched[f2]:
            continue
        c = int(next(x for x in f[f1] if x != a and x != b))
        d = int(next(x for x in f[f2] if x != a and x != b))
        if c == d or (c, d) in edge_faces or (d, c) in edge_faces:
            continue
        n1, n2 = _face_normal(v, a, b, c), _face_normal(v, b, a, d)
        if np.dot(n1, n2) < FLAT_EDGE_COS:
            continue
        if _angle(v, c, a, b) + _angle(v, d, a, b) <= np.pi + 1e-9:
            continue
        m1, m2 = _face_normal(v, a, d, c), _face_normal(v, d, b, c)
        mean = n1 + n2
        if np.dot(m1, mean) <= 0 or np.dot(m2, mean) <= 0 or np.dot(m1, m2) < FLAT_EDGE_COS:
            continue
        f[f1] = (a, d, c)
        f[f2] = (d, b, c)
        touched[f1] = touched[f2] = True
        flips += 1
    return flips


def _smooth_tangentially(v, f, fixed_z, weight=0.5):
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    total = np.zeros_like(v)
    count = np.zeros(len(v))
    np.add.at(total, edges[:, 0], v[edges[:, 1]])
    np.add.at(count, edges[:, 0], 1.0)
    step = weight * (total / count[:, None] - v)
    normal = _vertex_normals(v, f)
    step -= np.sum(step * normal, 1, keepdims=True) * normal
    step[fixed_z, 2] = 0.0
    return v + step


def _vertex_normals(v, f):
    area_normal = 0.5 * np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], area_normal)
    return acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-300)


def _face_normal(v, a, b, c):
    n = np.cross(v[b] - v[a], v[c] - v[a])
    return n / np.linalg.norm(n)


def _angle(v, apex, a, b):
    p, q = v[a] - v[apex], v[b] - v[apex]
    return np.arccos(np.clip(np.dot(p, q) / (np.linalg.norm(p) * np.linalg.norm(q)), -1.0, 1.0))


def _tetrahedralize(v, f):
    import tetgen

    mesher = tetgen.TetGen(np.asarray(v, np.float64), np.asarray(f, np.int32))
    nodes, tets, *_ = mesher.tetrahedralize(plc=True, quality=True, nobisect=True, minratio=MIN_RATIO,
                                            mindihedral=MIN_DIHEDRAL, optmaxdihedral=OPT_MAX_DIHEDRAL,
                                            opt_iterations=OPT_ITERATIONS)
    if not np.allclose(nodes[: len(v)], v):
        raise RuntimeError("TetGen moved or reordered the surface nodes")
    return np.asarray(nodes, np.float64), np.asarray(tets, np.int64)


def _remove_slivers(nodes, tets, movable):
    """Hill-climb the movable nodes of tets whose smallest dihedral angle is below ``SLIVER_ANGLE``."""
    nodes = nodes.copy()
    node_tets = [[] for _ in range(len(nodes))]
    for t, tet in enumerate(tets):
        for n in tet:
            node_tets[n].append(t)
    node_tets = [np.array(ts) for ts in node_tets]
    x = nodes[tets]
    length = np.median(np.linalg.norm(x[:, 0] - x[:, 1], axis=1))
    steps = [d * length * h for h in (0.2, 0.08, 0.03) for d in np.concatenate([np.eye(3), -np.eye(3)])]
    for _ in range(SLIVER_SWEEPS):
        bad = np.flatnonzero(_min_dihedral(nodes, tets) < SLIVER_ANGLE)
        candidates = np.unique(tets[bad])
        moved = 0
        for n in candidates[movable[candidates]]:
            local = tets[node_tets[n]]
            neighbours = np.setdiff1d(np.unique(local), [n])
            start = nodes[n].copy()
            best, best_position = _min_dihedral(nodes, local).min(), start
            for step in [nodes[neighbours].mean(0) - start] + steps:
                nodes[n] = start + step
                value = _min_dihedral(nodes, local).min()
                if value > best + 1e-6:
                    best, best_position = value, nodes[n].copy()
            nodes[n] = best_position
            moved += not np.array_equal(best_position, start)
        if not moved:
            break
    return nodes


def _min_dihedral(nodes, tets):
    vol, dihedral, _ = tet_quality(nodes, tets)
    return np.where(vol > 0, dihedral.min(1), -1.0)


def _orient_positive(nodes, tets):
    x = nodes[tets]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
    tets = tets.copy()
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    return tets.astype(np.int32)


if __name__ == "__main__":
    main()
