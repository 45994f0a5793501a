"""External forces of a mixed-reality scene: fingertips pushing on a body, and penalty contact between bodies.

Pure and jit-able; the fingertip forces live in a body's model frame, the contact forces in world space.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def fingertip_forces(tips, positions, normals, radius, magnitude) -> Array:
    """The external nodal forces of fingertips pushing on a body.

    Every node within ``radius`` of a fingertip receives a force of constant ``magnitude`` along its inward
    normal (the finger pushes into the surface, like the training data's loads: a fixed force per node on a
    patch of the surface, into the body), once per such fingertip::

        f_i = -magnitude · #{k : |x_i - t_k| < radius} · n_i.

    There is no falloff inside the radius and the force is exactly zero outside it, which keeps the loads inside
    the distribution the model was trained on. Interior nodes have n = 0 and receive nothing.

    Args:
      tips: [K, 3] fingertip positions in the body's model frame; a missing fingertip is a row of NaN and
        contributes nothing.
      positions: [N, 3] current nodal positions (model units).
      normals: [N, 3] outward unit normals, zero for interior nodes (`tignn_jax.mr.vertex_normals`).
      radius: contact radius (model units).
      magnitude: force per node (model force units).

    Returns:
      [N, 3] nodal forces.
    """
    distance = jnp.linalg.norm(positions[None, :, :] - tips[:, None, :], axis=-1)  # [K,N]
    touched = jnp.sum(jnp.where(distance < radius, 1.0, 0.0), axis=0)  # NaN compares false
    return -magnitude * touched[:, None] * normals


def fingertip_pads(tips, positions, surface, direction, radius):
    """Where fingertips pressing along ``direction`` meet a body's surface (`fingertip_spring_forces`).

    A fingertip's pad is the set of surface nodes within ``radius`` of the line through the fingertip along
    ``direction`` d and within ``radius`` of the first of them along d (the top layer it meets, not the far side
    of the body); its depth is how far the fingertip has gone past that first node along d::

        pad_k = {i ∈ surface : |(x_i − t_k) − ((x_i − t_k)·d) d| < radius,  x_i·d < s_k + radius},
        s_k = min over the cylinder's surface nodes of x_i·d,   depth_k = t_k·d − s_k.

    Args:
      tips: [K, 3] fingertip positions (model frame); a missing fingertip is a row of NaN (no pad).
      positions: [N, 3] current nodal positions.
      surface: [N] bool, the surface nodes.
      direction: [3] unit press direction (model frame).
      radius: the pad's radius (model units).

    Returns:
      (pad [K, N] bool, depth [K]: −inf where the cylinder holds no surface node).
    """
    d = jnp.asarray(direction, positions.dtype)
    rel = positions[None, :, :] - tips[:, None, :]                                     # [K, N, 3]
    along = rel @ d
    lateral = jnp.linalg.norm(rel - along[..., None] * d, axis=-1)
    inside = (lateral < radius) & surface[None, :]                                     # NaN compares false
    level = positions @ d                                                              # [N]
    first = jnp.min(jnp.where(inside, level[None, :], jnp.inf), axis=1)               # [K]
    pad = inside & (level[None, :] < first[:, None] + radius)
    depth = jnp.where(jnp.isfinite(first), tips @ d - first, -jnp.inf)
    return pad, depth


def fingertip_spring_forces(tips, positions, surface, direction, radius, stiffness) -> Array:
    """The external nodal forces of fingertips that push like springs from the surface under them.

    A tracked fingertip presses deeper than the body gives way; here it pulls the point of the surface it meets
    towards itself with a spring of ``stiffness`` (force per length), the total force spread evenly over its pad
    (`fingertip_pads`) along the press direction d::

        F_k = stiffness · max(depth_k, 0),   f_i = Σ_k F_k · [i ∈ pad_k] / |pad_k| · d.

    Unlike a fixed force per touched node (`fingertip_forces`), the force follows how far the finger has gone
    past the surface, so a finger that goes deep cannot pass through the body between its nodes: the body settles
    where its elastic force balances the spring (with stiffness · compliance ≲ 1, the body's compliance at the
    pad, without overshooting in a quasi-static press).

    Args:
      tips: [K, 3] fingertip positions (model frame); NaN rows contribute nothing.
      positions: [N, 3] current nodal positions (model units).
      surface: [N] bool, the surface nodes.
      direction: [3] unit press direction (model frame).
      radius: the pad's radius (model units).
      stiffness: force per length of depth (model units).

    Returns:
      [N, 3] nodal forces.
    """
    pad, depth = fingertip_pads(tips, positions, surface, direction, radius)
    count = jnp.maximum(jnp.sum(pad, axis=1), 1)
    share = stiffness * jnp.maximum(depth, 0.0) / count                                # [K]
    return jnp.sum(jnp.where(pad, share[:, None], 0.0), axis=0)[:, None] * jnp.asarray(direction, positions.dtype)


def contact_forces(positions_a, positions_b, radius, stiffness, capacity: int | None = None):
    """Penalty contact between two bodies.

    Every pair of nodes (i in a, j in b) closer than ``radius`` repels with a linear spring
    ``stiffness · (radius - r_ij)`` along the line between them, minus the gradient of the energy
    (`contact_energy`)::

        E = Σ_ij ½ · stiffness · max(radius - r_ij, 0)².

    Each pair force acts equally and oppositely on its two nodes, so the forces on the two bodies sum to zero,
    and they are exactly zero when no pair is within ``radius``. Passing only surface nodes is enough.

    Exact in every case, with no state to carry: bodies whose bounding boxes, grown by ``radius``, are disjoint
    get zeros at once (``lax.cond``); with a static ``capacity`` only the nodes of each body inside the other's
    grown box take part (at most ``capacity`` per body, gathered with ``jnp.nonzero(size=capacity)``), then all
    pairs among them, falling back to all pairs of the full bodies when more nodes than ``capacity`` are inside;
    with ``capacity=None`` all pairs of the full bodies. Against a jax-md neighbour list: see
    benchmarks/ar_contact.py.

    Args:
      positions_a: [Na, 3] node positions of body a, in a frame common to both bodies (world space).
      positions_b: [Nb, 3] node positions of body b, same frame.
      radius: contact distance (length).
      stiffness: penalty stiffness (force per length).
      capacity: static bound on the nodes per body taking part, or None for all pairs.

    Returns:
      (forces_a [Na, 3], forces_b [Nb, 3]) in the positions' frame, in units of stiffness × length.
    """
    lo_a, hi_a = positions_a.min(0) - radius, positions_a.max(0) + radius
    lo_b, hi_b = positions_b.min(0) - radius, positions_b.max(0) + radius
    apart = jnp.any((lo_a > hi_b) | (lo_b > hi_a))
    zeros = (jnp.zeros_like(positions_a), jnp.zeros_like(positions_b))
    full = lambda: _dense_contact(positions_a, positions_b, radius, stiffness)  # noqa: E731
    if capacity is None:
        return jax.lax.cond(apart, lambda: zeros, full)
    near_a = jnp.all((positions_a >= lo_b) & (positions_a <= hi_b), axis=-1)
    near_b = jnp.all((positions_b >= lo_a) & (positions_b <= hi_a), axis=-1)
    fits = (near_a.sum() <= capacity) & (near_b.sum() <= capacity)
    pruned = lambda: _pruned_contact(positions_a, positions_b, near_a, near_b, radius, stiffness,  # noqa: E731
                                     capacity)
    return jax.lax.cond(apart, lambda: zeros, lambda: jax.lax.cond(fits, pruned, full))


def contact_energy(positions_a, positions_b, radius, stiffness) -> Array:
    """The penalty energy E = Σ_ij ½ · stiffness · max(radius - r_ij, 0)² whose negative gradient
    `contact_forces` returns (a scalar; arguments as there)."""
    r = jnp.linalg.norm(positions_a[:, None, :] - positions_b[None, :, :], axis=-1)
    return 0.5 * stiffness * jnp.sum(jnp.maximum(radius - r, 0.0) ** 2)


def _dense_contact(positions_a, positions_b, radius, stiffness):
    d = positions_a[:, None, :] - positions_b[None, :, :]
    r = jnp.sqrt(jnp.maximum(jnp.sum(d * d, axis=-1), 1e-30))
    scale = stiffness * jnp.maximum(radius - r, 0.0) / r
    pair = scale[:, :, None] * d
    return pair.sum(1), -pair.sum(0)


def _pruned_contact(positions_a, positions_b, near_a, near_b, radius, stiffness, capacity):
    n_a, n_b = positions_a.shape[0], positions_b.shape[0]
    ia = jnp.nonzero(near_a, size=capacity, fill_value=n_a)[0]
    ib = jnp.nonzero(near_b, size=capacity, fill_value=n_b)[0]
    far = 1e6 * (1.0 + jnp.abs(positions_a).max() + jnp.abs(positions_b).max() + radius)
    xa = jnp.where((ia < n_a)[:, None], positions_a[jnp.minimum(ia, n_a - 1)], far)
    xb = jnp.where((ib < n_b)[:, None], positions_b[jnp.minimum(ib, n_b - 1)], -far)
    fa, fb = _dense_contact(xa, xb, radius, stiffness)
    return (jnp.zeros((n_a + 1, 3), fa.dtype).at[ia].add(fa)[:n_a],
            jnp.zeros((n_b + 1, 3), fb.dtype).at[ib].add(fb)[:n_b])
