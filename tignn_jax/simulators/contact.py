"""Contact between bodies inside their implicit frame: a penalty energy in one solve of all the bodies.

Bodies b have poses y = s (R_b q + t_b) in a common world frame (R_b a rotation, one scale s for all, so the
bodies' energies share their units). Two bodies touch where nodes of their surfaces come closer than a radius
r; the pairs (i of body a, j of body b) at distance d_ij = |y_a,i − y_b,j| / s (model length) store the penalty
energy::

    E_c = Σ_ij ½ k max(r − d_ij, 0)²

(r and k in model units: a world radius ρ is ρ / s, a world stiffness κ is κ s). It is part of the bodies'
potential in their frame (`tignn_jax.simulators.corotational.joint_frame`): its gradient among the internal
forces, its Gauss–Newton stiffness H_c (k n_ij n_ijᵀ on the pair's relative displacement, n_ij the unit vector
from j to i: symmetric positive semi-definite, coupling the bodies) in the operator of the one CG solve of all the
bodies' velocities, and E_c in the frame's energy budget, so the bodies together never end a frame with more
energy than their external forces put in, however stiff the contact. Stepped explicitly instead, a penalty is
stable only when soft against the nodes' masses and the frame step; stepped body by body against the others held
fixed, a stiff one sticks (the bodies move together only as far as the penalty lets one enter the other's old
place each frame; docs/research_log.md).

Only nodes near the other body take part: at each frame's start, of each pair of bodies, at most ``capacity``
surface nodes of each that lie within ``reach`` of the other's surface nodes (the nearest first,
`candidate_pairs`). That is exact while no more are within reach and no node moves farther than (reach − r) / 2
from where they were chosen: every pair left out is then farther apart than r throughout (`still_exact`). The
pairs closer than r at the linearisation are also listed (`Listed`), so that H_c w costs their number, not the
candidates' table.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

FAR = 1e7   # where unused candidate slots sit (model length): never within a radius of anything real


class Contact(NamedTuple):
    """The contact of a set of bodies (`contact`): static for a scene.

    Attributes:
      rotations: per body, R_b [3, 3] (model to world directions).
      offsets: per body, t_b [3] (the pose's translation over the scale: model length).
      surfaces: per body, its surface node indices [S_b] int32.
      radius: r (model length).
      stiffness: k (force per model length).
      capacity: the most candidate nodes of a body per pair of bodies (a Python int).
      reach: how near to the other body's surface nodes a node is a candidate (model length, ≥ r).
    """
    rotations: tuple
    offsets: tuple
    surfaces: tuple
    radius: float
    stiffness: float
    capacity: int
    reach: float


class Linearised(NamedTuple):
    """The contact at the frame's linearisation point (`linearise`).

    Attributes:
      gradient: per body ∂E_c/∂q [N_b, 3] (work per model length).
      normals: per pair of bodies, n_ij [C_a, C_b, 3] (world directions).
      active: per pair of bodies, [C_a, C_b]: 1 where the pair is closer than r.
      listed: per pair of bodies, its active pairs listed (`Listed`: up to ``SLOTS_PER_CANDIDATE`` × capacity).
    """
    gradient: tuple
    normals: tuple
    active: tuple
    listed: tuple


class Listed(NamedTuple):
    """The active pairs of two bodies a, b in a list of P slots (unused slots: weight 0).

    Attributes:
      nodes: (i [P], j [P]) int32, the pairs' nodes of a and of b.
      normals: (n_ij in a's model directions [P, 3], in b's [P, 3]).
      weight: [P], k on a used slot, else 0.
      overflow: [] bool, True where more pairs are active than the list holds (it then holds some of them).
    """
    nodes: tuple
    normals: tuple
    weight: jax.Array
    overflow: jax.Array


SLOTS_PER_CANDIDATE = 4   # the active pairs listed per pair of bodies, per candidate slot (`Listed`)


def contact(poses, surfaces, radius: float, stiffness: float, capacity: int = 128,
            reach: float | None = None) -> Contact:
    """The penalty contact of bodies with these poses (module docstring).

    Args:
      poses: per body, its [4, 4] model-to-world matrix: a rotation times a scale s, the same for all, then a
        translation.
      surfaces: per body, its surface node indices [S_b].
      radius: the contact distance (world length).
      stiffness: the penalty stiffness (force per world length).
      capacity: the most candidate nodes of a body per pair of bodies.
      reach: a node within this distance of a surface node of the other body is a candidate (world length;
        default 2 × radius).

    Returns:
      A `Contact` in model units.

    Raises:
      ValueError: fewer than two bodies, a pose that is not a finite [4, 4] similarity of the common scale, a
        non-positive radius or stiffness, a reach below the radius, or a capacity that is not a positive integer.
    """
    poses = [np.asarray(p, np.float64) for p in poses]
    if len(poses) < 2 or len(surfaces) != len(poses):
        raise ValueError(f"contact needs two or more bodies with a pose and a surface each, got {len(poses)} poses "
                         f"and {len(surfaces)} surfaces")
    scales = []
    for b, pose in enumerate(poses):
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"poses[{b}] must be a finite [4, 4] matrix, got shape {pose.shape}")
        a = pose[:3, :3]
        s = float(np.cbrt(np.linalg.det(a)))
        if not s > 0 or not np.allclose(a.T @ a, s * s * np.eye(3), rtol=1e-5, atol=1e-9 * s * s):
            raise ValueError(f"poses[{b}] must be a rotation times a positive scale, got {a.tolist()}")
        scales.append(s)
    if not np.allclose(scales, scales[0], rtol=1e-6):
        raise ValueError(f"every pose must have the same scale (the bodies' energies add up), got {scales}")
    reach = 2.0 * radius if reach is None else reach
    for name, value in (("radius", radius), ("stiffness", stiffness), ("reach", reach)):
        if not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    if reach < radius:
        raise ValueError(f"reach must be at least the radius {radius!r}, got {reach!r}")
    if not isinstance(capacity, (int, np.integer)) or isinstance(capacity, bool) or capacity < 1:
        raise ValueError(f"capacity must be a positive integer, got {capacity!r}")
    s = scales[0]
    return Contact(tuple(jnp.asarray(p[:3, :3] / s, jnp.float32) for p in poses),
                   tuple(jnp.asarray(p[:3, 3] / s, jnp.float32) for p in poses),
                   tuple(jnp.asarray(np.asarray(x), jnp.int32) for x in surfaces),
                   float(radius / s), float(stiffness * s), int(capacity), float(reach / s))


def candidate_pairs(contact: Contact, zs) -> tuple:
    """Per pair of bodies (a < b), the candidate nodes (i_a [C], i_b [C]) int32 at the states zs (index N_b:
    an unused slot)."""
    out = []
    for a, b in _pairs(contact):
        ya, yb = (_world(contact, k, zs[k][:, :3], contact.surfaces[k]) for k in (a, b))
        d2 = jnp.sum(ya * ya, 1)[:, None] + jnp.sum(yb * yb, 1)[None, :] - 2.0 * ya @ yb.T   # one table for both
        picks = []
        for k, nearest in ((a, jnp.min(d2, axis=1)), (b, jnp.min(d2, axis=0))):
            top, idx = jax.lax.top_k(-nearest, min(contact.capacity, nearest.shape[0]))
            inside = -top <= contact.reach * contact.reach
            picks.append(jnp.where(inside, contact.surfaces[k][idx], zs[k].shape[0]).astype(jnp.int32))
        out.append(tuple(picks))
    return tuple(out)


def still_exact(contact: Contact, pairs, q_from, q_to) -> jax.Array:
    """[] bool: True where the candidate ``pairs`` chosen at the positions ``q_from`` still hold every pair closer
    than r at ``q_to`` (per body [N_b, 3]): no surface node moved farther than (reach − r) / 2 in the world
    between them, and no candidate list shorter than its surface is full (then every node within reach of the
    other body was listed)."""
    ok = jnp.asarray(True)
    for nodes, a, b in zip(contact.surfaces, q_from, q_to):
        moved = jnp.max(jnp.sum((b[nodes] - a[nodes]) ** 2, axis=-1))   # rotations keep lengths
        ok = ok & (moved <= (0.5 * (contact.reach - contact.radius)) ** 2)
    for (a, b), (ia, ib) in zip(_pairs(contact), pairs):
        for k, nodes in ((a, ia), (b, ib)):   # a list as long as the surface holds every node within reach
            if len(nodes) < len(contact.surfaces[k]):
                ok = ok & ~jnp.all(nodes < q_from[k].shape[0])
    return ok


def energy(contact: Contact, pairs, qs) -> jax.Array:
    """E_c over the candidate pairs at the positions qs (per body [N_b, 3]) → [] (work units)."""
    total = 0.0
    for (a, b), (ia, ib) in zip(_pairs(contact), pairs):
        d = jnp.linalg.norm(_differences(contact, a, b, ia, ib, qs), axis=-1)
        total = total + 0.5 * contact.stiffness * jnp.sum(jnp.maximum(contact.radius - d, 0.0) ** 2)
    return total


def linearise(contact: Contact, pairs, qs) -> Linearised:
    """The gradient of E_c and the pairs' normals and contact state at the positions qs (per body [N_b, 3])."""
    gradient = [jnp.zeros_like(q) for q in qs]
    normals, active, listed = [], [], []
    for (a, b), (ia, ib) in zip(_pairs(contact), pairs):
        diff = _differences(contact, a, b, ia, ib, qs)
        d = jnp.sqrt(jnp.maximum(jnp.sum(diff * diff, axis=-1), 1e-30))
        gap = jnp.maximum(contact.radius - d, 0.0)
        n = diff / d[..., None]
        g = -contact.stiffness * gap[..., None] * n                                  # ∂E_c/∂y_a,i per pair
        gradient[a] = gradient[a].at[ia].add(jnp.sum(g, axis=1) @ contact.rotations[a], mode="drop")
        gradient[b] = gradient[b].at[ib].add(-jnp.sum(g, axis=0) @ contact.rotations[b], mode="drop")
        normals.append(n)
        active.append((gap > 0).astype(qs[a].dtype))
        listed.append(_listed(contact, a, b, ia, ib, n, active[-1]))
    return Linearised(tuple(gradient), tuple(normals), tuple(active), tuple(listed))


def _listed(contact: Contact, a: int, b: int, ia, ib, n, act) -> Listed:
    cb = act.shape[1]
    flat = jnp.nonzero(act.reshape(-1) > 0, size=SLOTS_PER_CANDIDATE * contact.capacity, fill_value=act.size)[0]
    i, j = jnp.minimum(flat // cb, act.shape[0] - 1), jnp.minimum(flat % cb, cb - 1)
    normal = n[i, j]
    return Listed((ia[i], ib[j]), (normal @ contact.rotations[a], normal @ contact.rotations[b]),
                  contact.stiffness * (flat < act.size).astype(n.dtype), jnp.sum(act) > len(flat))


def apply_stiffness(contact: Contact, pairs, lin: Linearised, ws) -> tuple:
    """H_c w: per body [N_b, 3], for velocities or displacements ws (per body [N_b, 3]).

    Over the listed active pairs (`Listed`), or over every candidate pair where more are active than listed."""
    out = [jnp.zeros_like(w) for w in ws]
    for (a, b), (ia, ib), n, act, li in zip(_pairs(contact), pairs, lin.normals, lin.active, lin.listed):
        def dense(wa, wb, ia=ia, ib=ib, n=n, act=act):
            ya = wa.at[ia].get(mode="fill", fill_value=0) @ contact.rotations[a].T
            yb = wb.at[ib].get(mode="fill", fill_value=0) @ contact.rotations[b].T
            sn = (contact.stiffness * act * jnp.sum(n * (ya[:, None, :] - yb[None, :, :]), -1))[..., None] * n
            return (jnp.zeros_like(wa).at[ia].add(jnp.sum(sn, 1) @ contact.rotations[a], mode="drop"),
                    jnp.zeros_like(wb).at[ib].add(-jnp.sum(sn, 0) @ contact.rotations[b], mode="drop"))

        def listed(wa, wb, li=li):
            (i, j), (na, nb) = li.nodes, li.normals
            s = li.weight * (jnp.sum(na * wa.at[i].get(mode="fill", fill_value=0), -1)
                             - jnp.sum(nb * wb.at[j].get(mode="fill", fill_value=0), -1))
            return (jnp.zeros_like(wa).at[i].add(s[:, None] * na, mode="drop"),
                    jnp.zeros_like(wb).at[j].add(-s[:, None] * nb, mode="drop"))

        fa, fb = jax.lax.cond(li.overflow, dense, listed, ws[a], ws[b])
        out[a], out[b] = out[a] + fa, out[b] + fb
    return tuple(out)


def coarse_stiffness(contact: Contact, lin: Linearised, bases) -> jax.Array:
    """Vᵀ H_c V [M, M] for per-body bases V_b [N_b, 3, m_b] (model directions; M = Σ m_b, the bodies' blocks in
    order): Σ over the listed active pairs (`Listed`) of k w wᵀ, w = (n ⋅ V_a,i, −n ⋅ V_b,j) the pair's relative
    normal motion (positive semi-definite; where more pairs are active than listed, over those listed)."""
    starts = np.concatenate([[0], np.cumsum([v.shape[-1] for v in bases])])
    out = jnp.zeros((starts[-1], starts[-1]), bases[0].dtype)
    for (a, b), li in zip(_pairs(contact), lin.listed):
        (i, j), (na, nb) = li.nodes, li.normals
        w = jnp.zeros((len(i), starts[-1]), bases[0].dtype)
        w = w.at[:, starts[a]:starts[a + 1]].set(
            jnp.einsum("pc,pcm->pm", na, bases[a].at[i].get(mode="fill", fill_value=0)))
        w = w.at[:, starts[b]:starts[b + 1]].set(
            -jnp.einsum("pc,pcm->pm", nb, bases[b].at[j].get(mode="fill", fill_value=0)))
        out = out + (li.weight[:, None] * w).T @ w
    return out


def _pairs(contact: Contact):
    n = len(contact.rotations)
    return [(a, b) for a in range(n) for b in range(a + 1, n)]


def _world(contact: Contact, k: int, q, nodes):
    """y / s of the nodes of body k [len(nodes), 3]."""
    return q[nodes] @ contact.rotations[k].T + contact.offsets[k]


def _differences(contact: Contact, a: int, b: int, ia, ib, qs):
    """y_a,i − y_b,j over the candidates [C_a, C_b, 3]; unused slots far apart (a's at +FAR, b's at −FAR)."""
    ya = jnp.where((ia < qs[a].shape[0])[:, None], _world(contact, a, qs[a], jnp.minimum(ia, qs[a].shape[0] - 1)),
                   FAR)
    yb = jnp.where((ib < qs[b].shape[0])[:, None], _world(contact, b, qs[b], jnp.minimum(ib, qs[b].shape[0] - 1)),
                   -FAR)
    return ya[:, None, :] - yb[None, :, :]
