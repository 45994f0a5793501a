"""The embedded corotational GENERIC model: a fine mesh carried by a coarse hexahedral cage that the corotational
model steps, so a frame costs the cage's solve plus two sparse products with the fine mesh.

A body of N nodes (any hex8 or tet4 mesh, rest positions X) is embedded in a cage: cells of a regular grid that
hold its nodes or element centres (`embed`), of Nc nodes with rest positions Y. Every fine node i follows the 8
corners c of its cage cell (or of the nearest one, where its own is not in the cage) with trilinear weights w_ic,
Σ_c w_ic = 1::

    u = W u_c,   v = W v_c,   σ = W σ_c         (W [N, Nc], 8 non-zeros a row; exact for a displacement that is
                                                 trilinear in each cell, e.g. any rigid motion)

The cage carries the body's material in proportion to how much of each cell the body fills: a cage element of
volume V_e filled to the fraction φ_e (the volume of the fine elements whose centres lie in it, over V_e) has the
energy, stiffness and lumped mass of `tignn_jax.simulators.corotational` times φ_e, so the cage's mass is the
body's. The cage's state z_c = (Y + u_c, v_c) is stepped by `tignn_jax.simulators.corotational.frame` (backward
Euler, Mooney–Rivlin's energy exact under rotation, energy never created) under the external forces' virtual-work
share f_c = Wᵀ f. A fine state is read back into the cage by least squares, u_c = (WᵀW)⁻¹ Wᵀ u: exact for every
state the model produces (those are W u_c), the nearest cage state for any other.

GENERIC structure, inherited from the cage: E(z) = E_c(z_c) with ½ v_cᵀ M_c v_c the kinetic energy (M_c the cage's
lumped masses), the canonical coupling of q and v, and dissipation α v_cᵀ M_c v_c ≥ 0. The external work is the
same on both meshes, f · W Δu_c = (Wᵀ f) · Δu_c, so the cage's budget E_c(z_c') ≤ E_c(z_c) + W is the body's (up
to the float32 round-off of the cage's budget and of reading the state back).

Clamps: a cage node is clamped when a clamped fine node has weight on it, so a clamped fine node never moves.
What the cage cannot represent — a deformation finer than a cell, a dent under a fingertip smaller than a cell —
the model does not have: its accuracy against the corotational model of the fine mesh itself (the FEM's energy
there) is measured in ``benchmarks/embedded.py``. The step's cost: the cage's frame, one [Nc, Nc] × [Nc, 6]
product and 8 N-term gathers and scatters (memory 16 N + Nc² numbers besides the cage's own).
"""
from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax.simulators import corotational as C
from tignn_jax.simulators import linear as LG

FILL_FLOOR = 0.05   # the least fill φ_e a cage cell is given: one holding only a fringe of the body keeps a stiffness
SEEN = 0.1          # the least weight some fine node must give each corner of a cage cell (`embed`)
CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])  # VTK
CONDITION_LIMIT = 1e6   # the largest condition number of WᵀW a cage may have (its least-squares read-back)
MAX_CAGE_NODES = 4096   # the read-back (WᵀW)⁻¹ is dense: Nc² numbers, 64 MB at this size


@dataclasses.dataclass(frozen=True)
class EmbeddedCorotational:
    """The embedded corotational GENERIC model class (module docstring); ``config`` is the cage's solve.

    Stored arrays (``stored``): ``cage``, the cage's corotational arrays (`CorotationalGeneric.stored`) with its
    rest positions ``q0`` [Nc, 3] and ``node_type`` [Nc] (1 clamped); ``parents`` [N, 8] int32 (each fine node's
    cage cell, its corners in VTK order) and ``weights`` [N, 8] (the trilinear weights, rows summing to 1).
    """
    config: C.CorotationalConfig = C.CorotationalConfig()
    name: ClassVar[str] = "embedded"
    stable_by_construction: ClassVar[bool] = True   # the cage's step creates no energy, nor does the embedding

    def prepare(self, stored: dict, mesh: dict) -> dict:
        """The arrays the step reads: the cage's (`CorotationalGeneric.prepare`) under ``cage``; ``parents``,
        ``weights``; the read-back ``project`` = (WᵀW)⁻¹ [Nc, Nc]; the fine rest positions ``q0`` and free-node
        mask ``free`` [N, 1].

        Raises:
          ValueError: an array is missing or does not fit the mesh, the weights are not a partition of unity,
            a clamped fine node follows a free cage node, or WᵀW is too ill-conditioned to read a state back
            (a cage node that hardly any fine node follows: embed with a larger cell).
        """
        missing = [k for k in ("cage", "parents", "weights") if k not in stored]
        missing += [f"cage/{k}" for k in ("q0", "node_type") if k not in stored.get("cage", {})]
        if missing:
            raise ValueError(f"an embedded model needs the arrays {missing}")
        cage = stored["cage"]
        node_type = np.asarray(mesh["node_type"])
        n, nc = len(node_type), len(np.asarray(cage["q0"]))
        parents = np.asarray(stored["parents"]).astype(np.int32)
        weights = np.asarray(stored["weights"], np.float64)
        if parents.shape != (n, 8) or weights.shape != (n, 8):
            raise ValueError(f"parents and weights must be [{n}, 8] for a mesh of {n} nodes, got {parents.shape} "
                             f"and {weights.shape}")
        if parents.min() < 0 or parents.max() >= nc:
            raise ValueError(f"parents must be cage node ids in [0, {nc}), got [{parents.min()}, {parents.max()}]")
        if not np.isfinite(weights).all() or np.abs(weights.sum(1) - 1.0).max() > 1e-5:
            raise ValueError(f"weights must be finite and sum to 1 on every row, got rows summing to "
                             f"[{weights.sum(1).min():.6g}, {weights.sum(1).max():.6g}]")
        cage_type = np.asarray(cage["node_type"])
        loose = (node_type != 0) & ((weights != 0) & (cage_type[parents] == 0)).any(1)
        if loose.any():
            raise ValueError(f"clamped fine nodes {np.flatnonzero(loose)[:10].tolist()} follow free cage nodes")
        wtw = np.zeros((nc, nc))
        np.add.at(wtw, (parents[:, :, None], parents[:, None, :]), weights[:, :, None] * weights[:, None, :])
        eig = np.linalg.eigvalsh(wtw)
        if eig[0] <= eig[-1] / CONDITION_LIMIT:
            raise ValueError(f"the cage cannot read a state back: WᵀW has condition number "
                             f"{eig[-1] / max(eig[0], 1e-300):.3g} > {CONDITION_LIMIT:.0e} (cage nodes that hardly any "
                             f"fine node follows): embed with a larger cell")
        out = {"cage": C.CorotationalGeneric(self.config).prepare(cage, {"q0": cage["q0"], "node_type": cage_type}),
               "parents": parents, "weights": weights.astype(np.float32),
               "project": np.linalg.inv(wtw).astype(np.float32),
               "q0": np.asarray(mesh["q0"], np.float32), "free": (node_type == 0)[:, None].astype(np.float32)}
        out["cage"] = {**out["cage"], "node_type": jnp.asarray(cage_type.astype(np.int32))}
        return jax.tree_util.tree_map(jnp.asarray, out)

    def stored(self, arrays: dict) -> dict:
        """The arrays a model file keeps: the cage's stored arrays, rest positions and clamps; parents, weights."""
        cage = C.CorotationalGeneric(self.config).stored(arrays["cage"])
        cage.update(q0=np.asarray(arrays["cage"]["q0"]), node_type=np.asarray(arrays["cage"]["node_type"]))
        return {"cage": cage, "parents": np.asarray(arrays["parents"]), "weights": np.asarray(arrays["weights"])}

    def step_state(self, arrays: dict, z, f):
        """One frame of one body: z [N, 12], f [N, 3] (force, constant over the frame) → z' [N, 12]."""
        zc, fc = cage_state(arrays, z, f.astype(z.dtype))
        return fine_state(arrays, C.frame(arrays["cage"], zc, fc, self.config))

    def diagnostics(self, arrays: dict, z, f, z_next) -> dict:
        """The energy balance of one frame z → z_next under f: {"energy": E(z_next), "work": W = f · Δq over the
        free nodes, "dissipation": D = W − (E(z_next) − E(z))}, work units; D ≥ 0 by construction."""
        return LG.energy_balance(energy, arrays, z, f, z_next)


def embed(problem, material, cell: float, frame_dt: float | None = None) -> dict:
    """Stored arrays (`EmbeddedCorotational.stored`) of an elastic hex8 or tet4 FEM scene embedded in a cage of
    cubes of about ``cell`` on a side (module docstring).

    The grid spans the mesh's bounding box with round(extent / cell) cells along each axis (at least one), so
    the cage of a box meshed by a regular grid of a multiple of its cells is nested in it. The cage is the grid's
    cells that hold a node or an element centre of the mesh, less those with a corner that no node weighs by at
    least ``SEEN`` (a corner the fine state hardly shows could not be read back from it); a node whose cell is
    left out follows the nearest cage cell (trilinear weights extrapolated: they still sum to 1 and reproduce any
    affine motion), and that cell carries the material of the element centres in it. The cage's elements are
    the FEM's hex8 (`tignn_jax.simulators.corotational.from_fem` on the cage) with the problem's material, mass
    damping and frame, scaled by their fill.

    Args:
      problem: a `fem.solver.Problem` (its clamps and damping are the model's).
      material: its `fem.material.Material` (elastic).
      cell: the cage's cell size [length] > 0.
      frame_dt: the frame step Δt (default: the problem's frame).

    Returns:
      {"cage": {..., "q0" [Nc, 3], "node_type" [Nc]}, "parents" [N, 8] int32, "weights" [N, 8] float32}.

    Raises:
      ValueError: ``cell`` is not a positive number, gives a cage of more than ``MAX_CAGE_NODES`` nodes, or is so
        small or large for the mesh that no cage cell has all its corners seen; the material is viscoelastic.
    """
    from scipy.spatial import cKDTree

    from fem import solver as sv

    if not (isinstance(cell, (int, float, np.floating)) and np.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be a positive length, got cell={cell!r}")
    arr = problem.arrays
    points, cells = np.asarray(arr.points, np.float64), np.asarray(arr.cells)
    lo, hi = points.min(0), points.max(0)
    counts = np.maximum(1, np.round((hi - lo) / cell)).astype(int)
    spacing = np.where(hi > lo, (hi - lo) / counts, float(cell))
    home = lambda x: np.clip(np.floor((x - lo) / spacing + 1e-9).astype(int), 0, counts - 1)
    flat = lambda ijk: (ijk[..., 2] * counts[1] + ijk[..., 1]) * counts[0] + ijk[..., 0]
    lattice = lambda ijk: (ijk[..., 2] * (counts[1] + 1) + ijk[..., 1]) * (counts[0] + 1) + ijk[..., 0]
    centres = points[cells].mean(1)
    node_cell = home(points)
    kept = np.unique(np.concatenate([flat(node_cell), flat(home(centres))]))
    while True:   # drop cells with an unseen corner, re-home their nodes, until every kept cell is seen whole
        weights = _trilinear(points, lo, spacing, node_cell)
        corners = lattice(node_cell[:, None, :] + CORNERS[None])
        seen = np.unique(corners[weights >= SEEN])
        ijk = np.stack(np.unravel_index(kept, counts[::-1])[::-1], -1)
        whole = np.isin(lattice(ijk[:, None, :] + CORNERS[None]), seen).all(1)
        if whole.all():
            break
        kept = kept[whole]
        if not len(kept):
            raise ValueError(f"no cage cell of size {cell!r} has all its corners seen by the mesh's nodes: "
                             f"choose another cell")
        node_cell = _nearest_cells(points, kept, counts, lo, spacing, cKDTree)
    ijk = np.stack(np.unravel_index(kept, counts[::-1])[::-1], -1)
    used, cage_cells = np.unique(lattice(ijk[:, None, :] + CORNERS[None]), return_inverse=True)
    if len(used) > MAX_CAGE_NODES:
        raise ValueError(f"cell={cell!r} gives a cage of {len(used)} nodes, more than {MAX_CAGE_NODES} (its read-back "
                         f"is a dense [Nc, Nc] matrix): choose a larger cell")
    cage_cells = cage_cells.reshape(-1, 8).astype(np.int32)
    cage_points = lo + np.stack(np.unravel_index(used, (counts + 1)[::-1])[::-1], -1) * spacing
    parents = np.searchsorted(used, lattice(node_cell[:, None, :] + CORNERS[None])).astype(np.int32)
    owner = np.searchsorted(kept, flat(_nearest_cells(centres, kept, counts, lo, spacing, cKDTree)))
    phi = np.maximum(np.bincount(owner, np.asarray(arr.geo.volume, np.float64), len(kept)) / spacing.prod(),
                     FILL_FLOOR)
    clamped_fine = np.asarray(arr.free)[:, 0] == 0
    cage_clamped = np.zeros(len(used), bool)
    cage_clamped[parents[clamped_fine][np.abs(weights[clamped_fine]) > 1e-9]] = True
    h = float(problem.config.frame_dt if frame_dt is None else frame_dt)
    cage_problem = sv.setup(cage_points, cage_cells, material=material, frame_dt=h, n_frames=1,
                            clamped=np.flatnonzero(cage_clamped), damping=float(arr.damping_alpha))
    stored = C.from_fem(cage_problem, material, h)
    stored["ke"] = (stored["ke"] * phi[:, None, None]).astype(np.float32)
    stored["volume"] = (stored["volume"] * phi).astype(np.float32)
    share = np.repeat(float(material.density) * stored["volume"].astype(np.float64) / 8.0, 8)
    stored["mass"] = np.bincount(cage_cells.reshape(-1), share, minlength=len(used)).astype(np.float32)
    stored.update(q0=cage_points.astype(np.float32), node_type=cage_clamped.astype(np.int32))
    return {"cage": stored, "parents": parents, "weights": weights.astype(np.float32)}


def _trilinear(points, lo, spacing, node_cell):
    """[N, 8] trilinear weights of each point in its cell (``CORNERS`` order); outside the cell, extrapolated."""
    xi = (points - lo) / spacing - node_cell
    return np.prod(np.where(CORNERS[None] == 1, xi[:, None, :], 1.0 - xi[:, None, :]), axis=-1)


def _nearest_cells(points, kept, counts, lo, spacing, tree_type):
    """[P, 3] the grid indices of the kept cell nearest each point: its own where it is kept, else the kept cell
    whose centre is nearest."""
    ijk = np.stack(np.unravel_index(kept, counts[::-1])[::-1], -1)
    own = np.clip(np.floor((points - lo) / spacing + 1e-9).astype(int), 0, counts - 1)
    inside = np.isin((own[:, 2] * counts[1] + own[:, 1]) * counts[0] + own[:, 0], kept)
    out = own.copy()
    if not inside.all():
        _, k = tree_type((ijk + 0.5) * spacing + lo).query(points[~inside])
        out[~inside] = ijk[k]
    return out


def restrict(arrays: dict, x):
    """Wᵀ x [Nc, d] of a fine nodal field x [N, d]: each node's value shared to its cage corners by weight (the
    virtual-work share of a force)."""
    w = arrays["weights"].astype(x.dtype)
    nc = arrays["project"].shape[0]
    return jnp.zeros((nc, x.shape[1]), x.dtype).at[arrays["parents"].reshape(-1)].add(
        (w[:, :, None] * x[:, None, :]).reshape(-1, x.shape[1]))


def interpolate(arrays: dict, xc):
    """W x_c [N, d] of a cage nodal field x_c [Nc, d], corner by corner (no [N, 8, d] temporary)."""
    w, parents = arrays["weights"].astype(xc.dtype), arrays["parents"]
    out = w[:, 0, None] * xc[parents[:, 0]]
    for k in range(1, 8):
        out = out + w[:, k, None] * xc[parents[:, k]]
    return out


def cage_state(arrays: dict, z, f=None):
    """The cage's state z_c [Nc, 12] of a fine state z [N, 12]: (Y + u_c, v_c, 0) with (u_c, v_c) =
    (WᵀW)⁻¹ Wᵀ (u, v), the least-squares read-back (exact for z = W z_c); with forces f [N, 3], also their share
    Wᵀ f [Nc, 3] (one pass over the mesh for both)."""
    cage = arrays["cage"]
    fields = [z[:, :3] - arrays["q0"].astype(z.dtype), z[:, 3:6]] + ([] if f is None else [f])
    shared = restrict(arrays, jnp.concatenate(fields, 1))
    uvc = arrays["project"].astype(z.dtype) @ shared[:, :6]
    free = cage["free"].astype(z.dtype)
    zc = jnp.concatenate([cage["q0"].astype(z.dtype) + uvc[:, :3] * free, uvc[:, 3:] * free,
                          jnp.zeros((uvc.shape[0], 6), z.dtype)], 1)
    return zc if f is None else (zc, shared[:, 6:])


def fine_state(arrays: dict, zc):
    """The fine state z [N, 12] of a cage state z_c [Nc, 12]: (X + W u_c, W v_c, W σ_c)."""
    cage = arrays["cage"]
    fields = interpolate(arrays, jnp.concatenate([zc[:, :3] - cage["q0"].astype(zc.dtype), zc[:, 3:]], 1))
    return jnp.concatenate([arrays["q0"].astype(zc.dtype) + fields[:, :3], fields[:, 3:]], 1)


def energy(arrays: dict, z):
    """E(z) = E_c(z_c), the cage's energy of the fine state's read-back (`cage_state`), z [N, 12] → [] (work)."""
    return C.energy(arrays["cage"], cage_state(arrays, z))
