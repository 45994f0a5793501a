"""The paper's graph network started from rest at the quasi-static rate of its load.

The Abaqus beam data that the paper's network (`tignn_jax.simulators.generic_gnn`) learns from are quasi-static:
a load ramped from zero is followed from its first frame, and the data's velocity is the central difference of the
positions, v = dq/dt (``numpy.gradient``). A case's first state is at rest in q and σ, but its velocity is
(−3 q₀ + 4 q₁ − q₂) / 2Δt, made of the positions of the two frames to come. A network of k message passes reads
the response from that velocity; from the body's true state at rest (v = 0) it sees the load only within k edges
of it, and the beam responds far beyond them (docs/research_log.md, "The paper's TIGNN from rest").

This class gives the network that first velocity from the load instead of from the data: a body at rest (v = 0
and σ = 0 on every node) loaded by f starts from the rate of its quasi-static response under a load ramped
linearly from zero, whose first frame reaches f::

    v₀ = K₀⁻¹ f / Δt,

K₀ the FEM's stiffness at rest on the model's mesh (clamped degrees of freedom removed) and Δt the data's frame
step: for such a ramp q₂ − q₀ = 2 (q₁ − q₀), so that difference is (q₁ − q₀)/Δt = K₀⁻¹ f/Δt. Every other
state is stepped as the paper's network steps it (`GenericGNN.step_state`); so is the first frame, from
(q₀, v₀, 0). The network, its weights and its GENERIC step are unchanged.

It is a start, not an interaction model: once moving, the network reads the load's effect from its own velocity,
as in the data, and a load that changes otherwise (held, released, moved) is outside what it learned.
"""
from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax.simulators import linear as LG
from tignn_jax.simulators.generic_gnn import GenericGNN

STIFFNESS_KEYS = ("k_rows", "k_cols", "k")


@dataclasses.dataclass(frozen=True)
class RestStartGNN(GenericGNN):
    """The paper's graph network (`GenericGNN`) that starts from rest at the quasi-static rate of its load
    (module docstring).

    Stored arrays (``stored``): those of `GenericGNN` (``weights``, ``norm``, whose ``dt`` [1] is the data's frame
    step) and ``rest_stiffness``: K₀ as 3 × 3 node blocks, ``k_rows`` [B] and ``k_cols`` [B] int (node indices) and
    ``k`` [B, 3, 3] (force per length), the layout of `tignn_jax.simulators.linear.LinearGeneric`'s ``k``.
    ``prepare`` adds ``rest_rate`` [3N, 3N] float32, K₀⁻¹ / Δt on the free degrees of freedom (zero on the clamped
    ones).
    """
    name: ClassVar[str] = "generic_gnn_rest_start"

    def prepare(self, stored: dict, mesh: dict) -> dict:
        """`GenericGNN.prepare`'s arrays, with ``rest_stiffness`` kept and ``rest_rate`` added.

        Raises:
          ValueError: as `GenericGNN.prepare`; ``rest_stiffness`` or the frame step ``norm["dt"]`` is missing,
            the blocks do not fit the mesh, or K₀ is singular on the free degrees of freedom.
        """
        blocks = stored.get("rest_stiffness")
        if not isinstance(blocks, dict) or any(k not in blocks for k in STIFFNESS_KEYS):
            raise ValueError(f"a {self.name} model needs the stored arrays rest_stiffness/{list(STIFFNESS_KEYS)}")
        if "dt" not in stored.get("norm", {}):
            raise ValueError(f"a {self.name} model needs the data's frame step as norm/dt")
        arrays = super().prepare({k: stored[k] for k in ("weights", "norm")}, mesh)
        blocks = {k: np.asarray(blocks[k]) for k in STIFFNESS_KEYS}
        dt = float(np.asarray(stored["norm"]["dt"]).reshape(-1)[0])
        arrays["rest_stiffness"] = blocks
        arrays["rest_rate"] = jnp.asarray(rest_rate(blocks, np.asarray(mesh["node_type"]), dt), jnp.float32)
        return arrays

    def stored(self, arrays: dict) -> dict:
        """`GenericGNN.stored`'s arrays and ``rest_stiffness`` (``rest_rate`` is derived from it)."""
        return {**super().stored(arrays), "rest_stiffness": dict(arrays["rest_stiffness"])}

    def step_state(self, arrays: dict, z, f):
        """`GenericGNN.step_state` (its arguments and shapes, ``arrays`` from ``prepare``) from `start_from_rest`'s
        state: z [N, 12] → the state one frame later."""
        return super().step_state(arrays, start_from_rest(arrays, z, f), f)


def rest_rate(blocks: dict, node_type, dt: float) -> np.ndarray:
    """K₀⁻¹ / Δt [3N, 3N] float64 on the free degrees of freedom, zero on the clamped nodes' rows and columns.

    Args:
      blocks: ``{"k_rows" [B], "k_cols" [B], "k" [B, 3, 3]}``, the rest stiffness's node blocks.
      node_type: [N], 0 on free nodes.
      dt: the frame step Δt (time).

    Raises:
      ValueError: a block names a node outside the mesh, Δt is not positive, or K₀ is singular on the free
        degrees of freedom (a free node with no stiffness).
    """
    node_type = np.asarray(node_type)
    n = len(node_type)
    rows, cols = (np.asarray(blocks[k], np.int64) for k in ("k_rows", "k_cols"))
    if rows.size and max(rows.max(), cols.max()) >= n:
        raise ValueError(f"the rest stiffness names node {max(rows.max(), cols.max())}, the mesh has {n} nodes")
    if not dt > 0.0:
        raise ValueError(f"the frame step must be positive, got {dt!r}")
    K = LG.operator({**blocks, "mass": np.zeros(n), "dt": np.ones(1), "alpha": np.zeros(1)}, node_type)
    free = np.repeat(node_type == 0, 3)
    try:
        inverse = np.linalg.inv(K)
    except np.linalg.LinAlgError:
        raise ValueError("the rest stiffness is singular on the free degrees of freedom") from None
    inverse[~free, :] = 0.0
    inverse[:, ~free] = 0.0
    return inverse / dt


def start_from_rest(arrays: dict, z, f):
    """z [N, 12] as it is, except a body at rest (v = 0 and σ = 0 on every node): its velocity then becomes
    K₀⁻¹ f / Δt [N, 3] (module docstring), the quasi-static rate of f ramped from zero."""
    at_rest = jnp.all(z[:, 3:] == 0)

    def started(z):
        v = (arrays["rest_rate"].astype(z.dtype) @ f.astype(z.dtype).reshape(-1)).reshape(-1, 3)
        return z.at[:, 3:6].set(v)

    return jax.lax.cond(at_rest, started, lambda z: z, z)


def with_rest_start(params: dict, rest: dict) -> tuple:
    """A `GenericGNN` model's class and stored arrays as a `RestStartGNN`, its rest stiffness taken from a
    `tignn_jax.simulators.linear.LinearGeneric` model on the same mesh (e.g. the FEM's rest linearisation,
    ``beam-linear``).

    Args:
      params: the graph network (`tignn_jax.load_pretrained`'s params).
      rest: the linear model (its ``arrays`` hold ``k_rows``, ``k_cols``, ``k``).

    Returns:
      (the `RestStartGNN`, its stored arrays), for `tignn_jax.make_params` with the network's mesh and envelope.

    Raises:
      ValueError: ``params`` is not a graph network, or the two models' meshes differ.
    """
    if type(params["model"]) is not GenericGNN:
        raise ValueError(f"the model must be a GenericGNN, got {type(params['model']).__name__}")
    if not np.array_equal(np.asarray(params["mesh"]["q0"]), np.asarray(rest["mesh"]["q0"])):
        raise ValueError("the rest stiffness's model is on another mesh")
    model = RestStartGNN(params["model"].config)
    stored = params["model"].stored(params["arrays"])
    stored["rest_stiffness"] = {k: np.asarray(rest["arrays"][k]) for k in STIFFNESS_KEYS}
    return model, stored
