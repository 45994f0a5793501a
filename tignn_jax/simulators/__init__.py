"""The model classes behind one step protocol.

A *model class* is a frozen, hashable object (its configuration) with three methods::

    arrays = model.prepare(stored, mesh)        # once, outside jit: what the step reads, derived arrays included
    stored = model.stored(arrays)               # the arrays a model file keeps (derived ones dropped)
    z_next = model.step_state(arrays, z, f)     # one body: z [N, 12], f [N, 3] -> z_next [N, 12]; pure, jittable

and, optionally, a class attribute ``stable_by_construction = True`` where no step can create energy whatever the
state and force (the demo then guards the class's bodies for finiteness only, not by the training envelope).

``step_state`` advances the state z = (q, v, σ) [N, 12] of one body of the model's mesh by one frame Δt under the
external nodal forces f [N, 3] (constant during the frame). It is pure and traceable, so `tignn_jax.step`,
`tignn_jax.rollout` and `tignn_jax.stepper` jit it with the model's arrays closed over: one compiled program per
model and number of bodies (`tignn_jax.api`), and with the arrays as arguments where a caller traces them.

A model (what `tignn_jax.load_pretrained` returns as ``params``) is a plain dict::

    {"model": <model class instance>, "arrays": {...}, "mesh": {"q0", "senders", "receivers", "node_type"},
     "edges": (senders, receivers) on the device, "envelope": {"z_mean", "z_std", "z_dev_max", "u_max", "f_max"},
     "info": {...}}

(`tignn_jax.make_params` builds it). ``edges`` are the arrays of the rest graph `tignn_jax.rest_graph` returns, so
`tignn_jax.step` recognises the model's own graph without comparing its edges. ``envelope`` holds the training
data's range, which the guards (`tignn_jax.guards`) compare states and forces with; ``info`` is provenance (data,
recipe, errors) written to the model file as JSON.
"""
from __future__ import annotations

from tignn_jax.simulators.corotational import CorotationalConfig, CorotationalGeneric
from tignn_jax.simulators.embedded import EmbeddedCorotational
from tignn_jax.simulators.generic_gnn import GenericGNN, GNNConfig
from tignn_jax.simulators.linear import LinearConfig, LinearGeneric
from tignn_jax.simulators.rest_start import RestStartGNN

CLASSES = {cls.name: cls for cls in (GenericGNN, RestStartGNN, LinearGeneric, CorotationalGeneric,
                                      EmbeddedCorotational)}

__all__ = ["CLASSES", "CorotationalConfig", "CorotationalGeneric", "EmbeddedCorotational", "GenericGNN", "GNNConfig",
           "LinearConfig", "LinearGeneric", "RestStartGNN"]
