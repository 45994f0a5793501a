"""tignn-jax: thermodynamics-informed (GENERIC) simulators of deformable bodies, learned from a JAX FEM.

The public API::

    params, graph = tignn_jax.load_pretrained("beam")     # a model and the rest graph of its mesh
    graph = tignn_jax.step(params, graph, forces)          # one frame under forces [N, 3]
    states = tignn_jax.rollout(params, graph, forces_seq)  # [T + 1, N, 12]
    fn = tignn_jax.contact_stepper(params, poses, radius, stiffness)   # bodies that touch: zs = fn(zs, forces)

Model classes (`tignn_jax.simulators`): `GenericGNN`, the paper's thermodynamics-informed graph network,
`RestStartGNN`, that network started from rest at the quasi-static rate of its load, `LinearGeneric`, the learned
linear GENERIC model, and `CorotationalGeneric`, the corotational GENERIC model for large deformations.
Training: `train`, with a recipe from ``configs/``.
"""
from tignn_jax.api import (contact_stepper, load_model, load_pretrained, make_params, rest_graph, rollout,
                           save_model, shipped_models, step, stepper)
from tignn_jax.evaluation import evaluate
from tignn_jax.guards import (fallback_step, fallback_stepper, force_check, guarded_stepper, state_check,
                              state_guard)
from tignn_jax.newton import fem_stepper
from tignn_jax.simulators import (CorotationalConfig, CorotationalGeneric, GenericGNN, GNNConfig, LinearConfig,
                                  LinearGeneric)
from tignn_jax.train import train

__version__ = "0.2.0"

__all__ = [
    "load_pretrained", "shipped_models", "load_model", "save_model", "make_params", "rest_graph",
    "step", "rollout", "stepper", "contact_stepper",
    "force_check", "state_check", "state_guard", "guarded_stepper", "fallback_step", "fallback_stepper",
    "fem_stepper",
    "GenericGNN", "GNNConfig", "LinearGeneric", "LinearConfig", "CorotationalGeneric", "CorotationalConfig",
    "train", "evaluate",
]
