"""Structured meshes, meshio reading, and ParaView output (a VTU series with a .pvd time index)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

# Six tets per hex cube around the main diagonal 0–6 (VTK node order), all positively oriented.
_HEX_TO_TETS = np.array([[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]])


def box_hex_mesh(size=(40.0, 10.0, 10.0), divisions=(20, 5, 5), origin=(0.0, 0.0, 0.0)):
    """Structured hex8 mesh of a box: (points [N,3] float64, cells [K,8] int32, VTK node order).

    Nodes are numbered lexicographically with x fastest.
    """
    size, divisions = np.asarray(size, float), np.asarray(divisions, int)
    if size.shape != (3,) or np.any(size <= 0):
        raise ValueError(f"size must be three positive lengths, got {size.tolist()}")
    if divisions.shape != (3,) or np.any(divisions < 1):
        raise ValueError(f"divisions must be three positive integers, got {divisions.tolist()}")
    nx, ny, nz = divisions
    axes = [np.linspace(o, o + s, d + 1) for o, s, d in zip(origin, size, divisions)]
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    points = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], -1)
    node = lambda i, j, k: (k * (ny + 1) + j) * (nx + 1) + i
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    cells = np.stack([node(i, j, k), node(i + 1, j, k), node(i + 1, j + 1, k), node(i, j + 1, k),
                      node(i, j, k + 1), node(i + 1, j, k + 1), node(i + 1, j + 1, k + 1), node(i, j + 1, k + 1)], -1)
    return points, cells.astype(np.int32)


def hex_to_tet(cells: np.ndarray) -> np.ndarray:
    """Split each hex8 into six tet4 (conforming across a structured mesh): [6K, 4]."""
    return cells[:, _HEX_TO_TETS].reshape(-1, 4).astype(np.int32)


def read_mesh(path):
    """Read a hex8 or tet4 mesh with meshio: (points [N,3], cells [K,n], cell_type)."""
    import meshio

    m = meshio.read(path)
    for block in m.cells:
        if block.type in ("hexahedron", "tetra"):
            return np.asarray(m.points, float)[:, :3], np.asarray(block.data, np.int32), block.type
    raise ValueError(f"{path}: no hexahedron or tetra cells (found {[b.type for b in m.cells]})")


def write_series(path, points, cells, cell_type, t, q, v=None, sigma=None, extra=None):
    """Write a frame sequence for ParaView: one VTU file per frame plus a ``.pvd`` collection indexed by time.

    ``path`` is the .pvd file; frames go to ``<stem>_frames/frame_XXXX.vtu`` beside it. q [T, N, 3] current
    positions are written as point data ``u`` = q − points (the mesh stays in the reference configuration, so
    ParaView's 'Warp By Vector' shows the motion); v [T, N, 3], sigma [T, N, 6] (S11, S22, S33, S12, S13, S23)
    and its von Mises value as point data; extra: dict name → [T, N, ...]. VTU needs no HDF5 library.
    """
    import meshio

    path = Path(path).with_suffix(".pvd")
    frames_dir = path.with_name(path.stem + "_frames")
    frames_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    for k in range(len(t)):
        data = {"u": np.asarray(q[k] - points, np.float64)}
        if v is not None:
            data["v"] = np.asarray(v[k], np.float64)
        if sigma is not None:
            data["sigma"] = np.asarray(sigma[k], np.float64)
            data["von_mises"] = von_mises(data["sigma"])
        for name, arr in (extra or {}).items():
            data[name] = np.asarray(arr[k])
        name = f"frame_{k:04d}.vtu"
        meshio.write(frames_dir / name, meshio.Mesh(np.asarray(points, float), [(cell_type, np.asarray(cells))],
                                                    point_data=data))
        entries.append(f'    <DataSet timestep="{float(t[k])!r}" part="0" file="{frames_dir.name}/{name}"/>')
    path.write_text('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
                    + "\n".join(entries) + "\n  </Collection>\n</VTKFile>\n")
    return path


def von_mises(sigma):
    """Von Mises stress from [..., 6] stress (S11, S22, S33, S12, S13, S23)."""
    s = np.asarray(sigma)
    s11, s22, s33, s12, s13, s23 = (s[..., i] for i in range(6))
    return np.sqrt(0.5 * ((s11 - s22) ** 2 + (s22 - s33) ** 2 + (s33 - s11) ** 2)
                   + 3.0 * (s12 ** 2 + s13 ** 2 + s23 ** 2))
