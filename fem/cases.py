"""Load cases beyond the paper's: fingertip-like interactions on the beam and point loads on the bunny.

A fingertip case is a patch of 1–6 neighbouring free-surface nodes pushed along a direction inside a cone around
the inward normal, with one of four time profiles (all reach the peak within the run):

* ``ramp``: linear from 0 to the peak at the last frame (like the reference cases);
* ``hold``: linear to the peak at a random frame, then held;
* ``release``: up to the peak, held, then back to zero (the solid recovers);
* ``move``: the peak force slides from one patch to a neighbouring patch half-way through the run.

With ``smooth=True`` every change of the force is C¹ in time (a fingertip does not jump): the rises and falls
follow the smooth step 3s² − 2s³ (zero slope at both ends; a release falls over ``FALL_FRAMES``) and ``move``
cross-fades the two patches over ``FADE_FRAMES`` frames. A piecewise-linear history changes the loading rate
within one frame, and the solid's velocity, which follows the loading rate, jumps with it inside a frame
(README, learned model `beam`).

Peak totals are drawn uniformly in [0.1, 1] × the reference maximum (6 nodes × 100 000 = 600 000 for the beam).
"""
from __future__ import annotations

import numpy as np

from .meshes import hop_distances, surface_nodes_and_normals

PROFILES = ("ramp", "hold", "release", "move")


FADE_FRAMES = 4   # smooth ``move``: frames over which the force passes from one patch to the next
FALL_FRAMES = 6   # smooth ``release``: frames over which the force falls to zero (3 for the piecewise-linear one)


def fingertip_forces(scene, n_cases: int, seed: int, *, peak_total: float = 600_000.0, cone_deg: float = 30.0,
                     smooth: bool = False):
    """Forces [n_cases, T, N, 3] and a list of case descriptions (JSON-able dicts). ``smooth``: C¹ profiles
    (module docstring); the same seed draws the same patches, directions, peaks and profile times either way."""
    if n_cases < 1:
        raise ValueError(f"n_cases must be positive, got {n_cases}")
    if peak_total <= 0:
        raise ValueError(f"peak_total must be positive, got {peak_total}")
    rng = np.random.default_rng(seed)
    nodes, normals = free_surface(scene)
    T, N = scene.n_frames, len(scene.points)
    out = np.zeros((n_cases, T, N, 3))
    described = []
    for c in range(n_cases):
        profile = PROFILES[rng.integers(len(PROFILES))]
        size = int(rng.integers(1, 7))
        centre = int(rng.integers(len(nodes)))
        patch = _patch(scene.points, nodes, centre, size)
        direction = _cone_direction(rng, -normals[centre], np.radians(cone_deg))
        peak = rng.uniform(0.1, 1.0) * peak_total
        amp = _amplitude(rng, profile, T, smooth)
        if profile == "move":
            other = _patch(scene.points, nodes, _neighbour(scene.points, nodes, centre, rng), size)
            half = T // 2
            if smooth:   # weight of the second patch: 0 before the fade, 1 after, a smooth step across it
                w = smooth_step((np.arange(1, T + 1) - (half - FADE_FRAMES / 2)) / FADE_FRAMES)
            else:
                w = (np.arange(1, T + 1) > half).astype(float)
            out[c][:, nodes[patch]] += ((1 - w) * amp)[:, None, None] * (peak / size) * direction
            out[c][:, nodes[other]] += (w * amp)[:, None, None] * (peak / size) * direction
        else:
            out[c][:, nodes[patch]] = (amp[:, None, None] * peak / size) * direction
        described.append({"profile": profile, "nodes": nodes[patch].tolist(), "direction": direction.tolist(),
                          "peak_total": peak})
    return out, described


def point_load_forces(scene, n_cases: int = 100, seed: int = 0, load_nodes=None, magnitude: float = 1.0,
                      rise_frames: int = 0, radius: float = 0.0):
    """Unit point loads normal to the surface (pushing inwards): [C, T, N, 3], and the loaded node ids [C].

    Load nodes are spread over the free surface by farthest-point sampling from a seeded start, or given.
    ``rise_frames = 0`` applies the full load from the first frame (a step, which rings the loaded node's local
    modes far above the frame rate); ``rise_frames = R > 0`` raises it by the C¹ smooth step
    a = 3s² − 2s³, s = min(k/R, 1) in frame k = 1..T, then holds it (a press that settles).

    ``radius = 0`` puts the whole load on the one node (a point force: on linear tets its dent is set by the
    elements around that node and grows without bound as the mesh is refined). ``radius > 0`` spreads the same
    total force, along the load node's inward normal, over the free surface nodes within ``radius`` of it with
    weights ∝ (1 − (d/radius)²)², a fingertip-sized press whose response converges with the mesh.
    """
    if not 0 <= rise_frames <= scene.n_frames:
        raise ValueError(f"rise_frames must be in 0..{scene.n_frames}, got {rise_frames}")
    if not (np.isfinite(radius) and radius >= 0):
        raise ValueError(f"radius must be a finite number >= 0, got {radius}")
    nodes, normals = free_surface(scene)
    if load_nodes is None:
        if not 1 <= n_cases <= len(nodes):
            raise ValueError(f"n_cases must be in 1..{len(nodes)} (free surface nodes), got {n_cases}")
        picked = _farthest_points(scene.points[nodes], n_cases, np.random.default_rng(seed))
    else:
        load_nodes = np.asarray(load_nodes, int).ravel()
        where = {int(n): i for i, n in enumerate(nodes)}
        missing = [int(n) for n in load_nodes if int(n) not in where]
        if missing:
            raise ValueError(f"load nodes are not free surface nodes: {missing[:10]}")
        picked = np.array([where[int(n)] for n in load_nodes])
    out = np.zeros((len(picked), scene.n_frames, len(scene.points), 3))
    amp = smooth_rise(scene.n_frames, rise_frames)
    for c, i in enumerate(picked):
        if radius > 0:
            d = np.linalg.norm(scene.points[nodes] - scene.points[nodes[i]], axis=1)
            near = np.where(d < radius)[0]
            w = (1.0 - (d[near] / radius) ** 2) ** 2
            w = w / w.sum()
            out[c][:, nodes[near]] = (amp[:, None, None] * w[None, :, None]) * (-magnitude * normals[i])
        else:
            out[c, :, nodes[i]] = amp[:, None] * (-magnitude * normals[i])
    return out, nodes[picked]


def multi_point_load_forces(scene, n_cases: int, per_case: int, seed: int = 0, *, exclude_nodes=(),
                            exclude_hops: int = 2, min_hops: int = 6, magnitude: float = 1.0, rise_frames: int = 10):
    """Cases of ``per_case`` simultaneous unit point loads (normal to the surface, inwards, each rising like
    ``point_load_forces``'s), on free surface nodes at least ``min_hops`` mesh edges apart: [C, T, N, 3] and
    the loaded nodes [C, per_case]. Nodes within ``exclude_hops`` edges of any of ``exclude_nodes`` (held-out
    load positions) are never loaded.

    Training data for a body whose response to a point load is local (the implicit bunny at density 1e-3 keeps
    94 % of the velocity increments within 3 edges of the load): each case shows the model ``per_case``
    loaded nodes instead of one, at the same simulation cost, and what the model must learn about a loaded
    node (how the mesh around it responds) varies from node to node."""
    if per_case < 1 or n_cases < 1:
        raise ValueError(f"n_cases and per_case must be positive, got {n_cases} and {per_case}")
    if not 0 <= rise_frames <= scene.n_frames:
        raise ValueError(f"rise_frames must be in 0..{scene.n_frames}, got {rise_frames}")
    nodes, normals = free_surface(scene)
    n = len(scene.points)
    exclude_nodes = np.asarray(exclude_nodes, int).ravel()
    allowed = np.ones(len(nodes), bool)
    if exclude_nodes.size:
        bad = exclude_nodes[(exclude_nodes < 0) | (exclude_nodes >= n)]
        if bad.size:
            raise ValueError(f"exclude_nodes outside 0..{n - 1}: {bad[:10].tolist()}")
        near = hop_distances(scene.edges, n, exclude_nodes).min(axis=0)
        allowed = near[nodes] > exclude_hops
    candidates = np.where(allowed)[0]
    hops = hop_distances(scene.edges, n, nodes[candidates])[:, nodes[candidates]]
    rng = np.random.default_rng(seed)
    amp = smooth_rise(scene.n_frames, rise_frames)
    out = np.zeros((n_cases, scene.n_frames, n, 3))
    picked = np.zeros((n_cases, per_case), int)
    for c in range(n_cases):
        chosen = []
        for k in rng.permutation(len(candidates)):
            if all(hops[k, j] >= min_hops for j in chosen):
                chosen.append(k)
                if len(chosen) == per_case:
                    break
        if len(chosen) < per_case:
            raise ValueError(f"cannot place {per_case} loads {min_hops} edges apart on the allowed surface "
                             f"({len(candidates)} nodes); lower per_case or min_hops")
        for k in chosen:
            i = candidates[k]
            out[c, :, nodes[i]] = amp[:, None] * (-magnitude * normals[i])
        picked[c] = nodes[candidates[chosen]]
    return out, picked


def smooth_rise(n_frames: int, rise_frames: int) -> np.ndarray:
    """Load amplitude per frame k = 1..n_frames: 3s² − 2s³ with s = min(k / rise_frames, 1) (all ones if 0)."""
    if rise_frames == 0:
        return np.ones(n_frames)
    s = np.minimum(np.arange(1, n_frames + 1) / rise_frames, 1.0)
    return s * s * (3.0 - 2.0 * s)


def free_surface(scene):
    """(node ids, outward unit normals) of the scene's surface nodes that are free (node type 0): where loads
    may be placed."""
    nodes, normals = surface_nodes_and_normals(scene.points, scene.cells)
    keep = scene.node_type[nodes] == 0
    return nodes[keep], normals[keep]


def _patch(points, nodes, centre, size):
    d = np.linalg.norm(points[nodes] - points[nodes[centre]], axis=1)
    return np.argsort(d, kind="stable")[:size]


def _neighbour(points, nodes, centre, rng):
    d = np.linalg.norm(points[nodes] - points[nodes[centre]], axis=1)
    near = np.argsort(d, kind="stable")[1:9]
    return int(near[rng.integers(len(near))])


def _cone_direction(rng, axis, half_angle):
    axis = axis / np.linalg.norm(axis)
    cos_t = rng.uniform(np.cos(half_angle), 1.0)
    phi = rng.uniform(0, 2 * np.pi)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    sin_t = np.sqrt(1 - cos_t ** 2)
    return cos_t * axis + sin_t * (np.cos(phi) * e1 + np.sin(phi) * e2)


def smooth_step(s):
    """3s² − 2s³ of s clipped to [0, 1]: 0 → 1 with zero slope at both ends."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def _amplitude(rng, profile, T, smooth=False):
    k = np.arange(1, T + 1, dtype=float)
    shape = smooth_step if smooth else (lambda s: np.clip(s, 0.0, 1.0))
    if profile in ("ramp", "move"):
        return shape(k / T)
    t_peak = int(rng.integers(T // 4, 3 * T // 4))
    a = shape(k / t_peak)
    if profile == "release":
        t_off = int(rng.integers(t_peak + 1, T))
        fall = FALL_FRAMES if smooth else 3.0
        a = np.where(k > t_off, a * (1.0 - shape((k - t_off) / fall)), a)
    return a


def _farthest_points(x, n, rng):
    chosen = [int(rng.integers(len(x)))]
    d = np.linalg.norm(x - x[chosen[0]], axis=1)
    for _ in range(n - 1):
        nxt = int(np.argmax(d))
        chosen.append(nxt)
        d = np.minimum(d, np.linalg.norm(x - x[nxt], axis=1))
    return np.array(chosen)
