"""Graphs of meshes as jraph ``GraphsTuple``s.

The state of a body lives in its graph: ``graph.nodes = {"z": [N,12] float32, "node_type": [N] int32}`` with z
= (q, v, sigma) in the data format's order (positions, velocities, Cauchy stress S11,S22,S33,S12,S13,S23).
Edges are the directed mesh edges (both directions of each), ``senders`` = edges[0], ``receivers`` = edges[1];
edge features are computed by the model from the positions, so ``graph.edges`` is None.
"""
from __future__ import annotations

from typing import Sequence

import jax.numpy as jnp
import jraph
import numpy as np

from tignn_jax.data import STATE_DIM, Dataset


def from_state(z, edges, node_type) -> jraph.GraphsTuple:
    """One graph from a state ``z`` [N,12], directed ``edges`` [2,E] and ``node_type`` [N] (0 free, 1 clamped)."""
    z = jnp.asarray(z, jnp.float32)
    edges = np.asarray(edges, np.int32)
    node_type = jnp.asarray(node_type, jnp.int32)
    n = z.shape[0]
    if z.ndim != 2 or z.shape[1] != STATE_DIM:
        raise ValueError(f"z has shape {z.shape}, expected [nodes, {STATE_DIM}]")
    if node_type.shape != (n,):
        raise ValueError(f"node_type has shape {node_type.shape}, expected ({n},)")
    if edges.ndim != 2 or edges.shape[0] != 2:
        raise ValueError(f"edges has shape {edges.shape}, expected [2, E]")
    return jraph.GraphsTuple(
        nodes={"z": z, "node_type": node_type}, edges=None,
        senders=jnp.asarray(edges[0]), receivers=jnp.asarray(edges[1]),
        n_node=jnp.array([n], jnp.int32), n_edge=jnp.array([edges.shape[1]], jnp.int32), globals=None)


def rest_state(q0) -> np.ndarray:
    """[N,12] float32: the state of a body at rest, q = q0, v = 0, sigma = 0."""
    q0 = np.asarray(q0, np.float32)
    return np.concatenate([q0, np.zeros((q0.shape[0], STATE_DIM - 3), np.float32)], axis=1)


def rest_graph(q0, edges, node_type) -> jraph.GraphsTuple:
    """The graph of a body at rest: q = q0, v = 0, sigma = 0."""
    return from_state(rest_state(q0), edges, node_type)


def from_data(data: Dataset, row: int = 0, frame: int = 0) -> jraph.GraphsTuple:
    """The graph of case ``row`` (0-based row of ``data.z``) at ``frame``."""
    return from_state(data.z[row, frame], data.edges, data.node_type)


def batch(graphs: Sequence[jraph.GraphsTuple]) -> jraph.GraphsTuple:
    """Disjoint union of graphs (node indices of later graphs shifted), like ``jraph.batch`` without padding."""
    offsets = np.cumsum([0] + [int(np.sum(g.n_node)) for g in graphs[:-1]])
    return jraph.GraphsTuple(
        nodes={k: jnp.concatenate([g.nodes[k] for g in graphs]) for k in graphs[0].nodes},
        edges=None,
        senders=jnp.concatenate([g.senders + o for g, o in zip(graphs, offsets)]),
        receivers=jnp.concatenate([g.receivers + o for g, o in zip(graphs, offsets)]),
        n_node=jnp.concatenate([g.n_node for g in graphs]),
        n_edge=jnp.concatenate([g.n_edge for g in graphs]),
        globals=None)


def with_state(graph: jraph.GraphsTuple, z) -> jraph.GraphsTuple:
    """The same graph carrying the state ``z`` [N,12] (built field by field: `step`'s per-frame hot path, where
    ``NamedTuple._replace`` costs several times as much)."""
    return jraph.GraphsTuple(nodes={**graph.nodes, "z": z}, edges=graph.edges, receivers=graph.receivers,
                             senders=graph.senders, globals=graph.globals, n_node=graph.n_node, n_edge=graph.n_edge)
