"""The paper's scenes as FEM problems: the Abaqus bending beam and the Stanford bunny.

Material constants are the paper's. Parameters the paper does not publish (density, damping, how the load
varies inside a frame) are scene arguments; the defaults are the values identified against the Abaqus data
(see `fem.identify` and benchmarks/results/abaqus_agreement.md).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .material import Material, mooney_rivlin
from .meshes import beam_mesh, beam_node_type, beam_reference_load, bunny_bottom_nodes, bunny_mesh

BEAM_FRAME_DT = 0.05
BEAM_FRAMES = 20
BEAM_FORCE_STEP = 5000.0     # force per load node added each frame (reference data README)
# Identified on the train split of the Abaqus data (fem.identify): see benchmarks/results/abaqus_agreement.md.
BEAM_DENSITY = 1e-2
BEAM_DAMPING = 0.0
BEAM_PRONY = True


class Scene(NamedTuple):
    """Everything `fem.setup` needs for one scene (numpy arrays and plain values)."""

    name: str
    points: np.ndarray     # [N, 3]
    cells: np.ndarray      # [K, 8] or [K, 4]
    cell_type: str
    edges: np.ndarray      # [2, E] directed graph edges
    node_type: np.ndarray  # [N] int8, 1 = clamped
    material: Material
    frame_dt: float
    n_frames: int
    damping: float
    load_interp: str


def beam_scene(density: float = BEAM_DENSITY, damping: float = BEAM_DAMPING, prony: bool = BEAM_PRONY,
               load_interp: str = "linear") -> Scene:
    """The 40×10×10 beam of the paper: 500 hex8, 756 nodes (reference node order), clamped at x = 0.

    C10 = 1.5e5, C01 = 5e3, D1 = 1e-7; Prony ḡ = (0.3, 0.49), τ = (0.2, 0.5) when ``prony``.
    """
    q0, cells, edges = beam_mesh()
    g, tau = ((0.3, 0.49), (0.2, 0.5)) if prony else ((), ())
    mat = mooney_rivlin(1.5e5, 5e3, 1e-7, density=density, g=g, tau=tau)
    return Scene("beam", q0, cells, "hexahedron", edges, beam_node_type(q0), mat, BEAM_FRAME_DT, BEAM_FRAMES,
                 damping, load_interp)


def beam_reference_forces(scene: Scene, sim_ids) -> np.ndarray:
    """Nodal forces [len(sim_ids), 20, N, 3] of reference cases (1..52): 5000·(k+1) per load node in frame k."""
    out = np.zeros((len(sim_ids), scene.n_frames, len(scene.points), 3))
    ramp = BEAM_FORCE_STEP * np.arange(1, scene.n_frames + 1)
    for c, sid in enumerate(sim_ids):
        nodes, direction = beam_reference_load(scene.points, int(sid))
        out[c][:, nodes] = ramp[:, None, None] * direction
    return out


BUNNY_SCALE = 5.0      # the committed mesh is 1/5 of the scan's own units; the scene uses the scan's units
BUNNY_DENSITY = 1e-5   # not published; chosen so the first mode (period ~0.9) shows within the 1-unit run
BUNNY_DAMPING = 2.0    # not published; light mass damping (ζ ≈ 0.15 on the first mode)


def bunny_scene(density: float = BUNNY_DENSITY, damping: float = BUNNY_DAMPING) -> Scene:
    """The Stanford bunny: tet4 mesh of `fem.bunny_mesh` (1330 nodes, 4698 tets) in the scan's units (≈49 tall,
    z up), base clamped, C10 = 0.26, C01 = 0, D1 = 0.049 (K/μ ≈ 78), 20 frames of 0.05.

    The load of the paper is a unit point force normal to the surface. At the mesh file's 1/5 scale a unit
    point force inverts the loaded node's elements (local strain ~ F/(4πμh²) ≈ 0.6 for h ≈ 0.5); at the scan's
    own scale the local strain is ≈ 3 %, so the scene uses that scale.
    """
    q0, cells, edges = bunny_mesh()
    q0 = q0 * BUNNY_SCALE
    node_type = np.zeros(len(q0), np.int8)
    node_type[bunny_bottom_nodes(q0)] = 1
    mat = mooney_rivlin(0.26, 0.0, 0.049, density=density)
    return Scene("bunny", q0, cells, "tetra", edges, node_type, mat, 0.05, 20, damping, "linear")


def setup_scene(scene: Scene, **kwargs):
    """`fem.setup` for a scene (keyword arguments are passed on, e.g. n_sub, safety, checkpoint)."""
    from .solver import setup

    return setup(scene.points, scene.cells, material=scene.material, frame_dt=scene.frame_dt,
                 n_frames=scene.n_frames, clamped=np.where(scene.node_type == 1)[0], cell_type=scene.cell_type,
                 damping=scene.damping, load_interp=scene.load_interp, **kwargs)
