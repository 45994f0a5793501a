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
in a frame: every pair left out is then farther apart than r throughout.
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
    """
    gradient: tuple
    normals: tuple
    active: tuple


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
        picks = []
        for k, x, other in ((a, ya, yb), (b, yb, ya)):
            idx, inside = _nearest(x, other, contact.reach, contact.capacity)
            picks.append(jnp.where(inside, contact.surfaces[k][idx], zs[k].shape[0]).astype(jnp.int32))
        out.append(tuple(picks))
    return tuple(out)


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
    normals, active = [], []
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
    return Linearised(tuple(gradient), tuple(normals), tuple(active))


def apply_stiffness(contact: Contact, pairs, lin: Linearised, ws) -> tuple:
    """H_c w: per body [N_b, 3], for velocities or displacements ws (per body [N_b, 3])."""
    out = [jnp.zeros_like(w) for w in ws]
    for (a, b), (ia, ib), n, act in zip(_pairs(contact), pairs, lin.normals, lin.active):
        wa = ws[a].at[ia].get(mode="fill", fill_value=0) @ contact.rotations[a].T
        wb = ws[b].at[ib].get(mode="fill", fill_value=0) @ contact.rotations[b].T
        s = contact.stiffness * act * (jnp.einsum("ijc,ic->ij", n, wa) - jnp.einsum("ijc,jc->ij", n, wb))
        out[a] = out[a].at[ia].add(jnp.einsum("ij,ijc->ic", s, n) @ contact.rotations[a], mode="drop")
        out[b] = out[b].at[ib].add(-jnp.einsum("ij,ijc->jc", s, n) @ contact.rotations[b], mode="drop")
    return tuple(out)


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


def _nearest(x, others, reach, capacity: int):
    """(indices [C] of the rows of x nearest to any row of ``others``, nearest first; [C] bool: within
    ``reach``), C = min(capacity, len(x)). One dense [len(x), len(others)] distance table."""
    d2 = jnp.sum(x * x, 1)[:, None] + jnp.sum(others * others, 1)[None, :] - 2.0 * x @ others.T
    nearest = jnp.min(d2, axis=1)
    top, idx = jax.lax.top_k(-nearest, min(int(capacity), x.shape[0]))
    return idx, -top <= reach * reach
