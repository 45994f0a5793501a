"""tignn-jax: thermodynamics-informed (GENERIC) simulators of deformable bodies, learned from a JAX FEM.

The public API::

    params, graph = tignn_jax.load_pretrained("beam")     # a model and the rest graph of its mesh
    graph = tignn_jax.step(params, graph, forces)          # one frame under forces [N, 3]
    states = tignn_jax.rollout(params, graph, forces_seq)  # [T + 1, N, 12]
    fn = tignn_jax.contact_stepper(params, poses, radius, stiffness)   # bodies that touch: zs = fn(zs, forces)

Model classes (`tignn_jax.simulators`): `GenericGNN`, the paper's thermodynamics-informed graph network,
`RestStartGNN`, that network started from rest at the quasi-static rate of its load, `LinearGeneric`, the learned
linear GENERIC model, `CorotationalGeneric`, the corotational GENERIC model for large deformations, and
`EmbeddedCorotational`, a large mesh carried by a coarse corotational cage.
Training: `train`, with a recipe from ``configs/``.

The names below are imported on first use (PEP 562), so ``import tignn_jax`` and the ``tignn`` command's ``--help``
and usage errors do not wait for JAX to load.
"""
import importlib
import sys
import types

__version__ = "0.2.0"
DEFAULT_MODEL = "beam-corot"     # the shipped model `load_pretrained` and the CLI take by default

_EXPORTS = {
    "tignn_jax.api": ("contact_stepper", "load_model", "load_pretrained", "make_params", "rest_graph", "rollout",
                      "save_model", "shipped_models", "step", "stepper"),
    "tignn_jax.evaluation": ("evaluate",),
    "tignn_jax.guards": ("fallback_step", "fallback_stepper", "force_check", "guarded_stepper", "state_check",
                         "state_guard"),
    "tignn_jax.newton": ("fem_stepper",),
    "tignn_jax.simulators": ("CorotationalConfig", "CorotationalGeneric", "GenericGNN", "GNNConfig", "LinearConfig",
                             "LinearGeneric"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}
_SUBMODULES = ("api", "cli", "data", "evaluation", "graph", "guards", "model_card", "mr", "newton", "simulators",
               "view")


def __getattr__(name: str):
    if name in _MODULE_OF:
        value = getattr(importlib.import_module(_MODULE_OF[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"tignn_jax.{name}")
    else:
        raise AttributeError(f"module 'tignn_jax' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_MODULE_OF) | set(_SUBMODULES) | {"train"})


class _Package(types.ModuleType):
    """The package's module type: ``tignn_jax.train`` is the training function, also after its submodule
    ``tignn_jax.train`` has been imported (the import system binds a submodule to its name in the package)."""

    @property
    def train(self):
        return importlib.import_module("tignn_jax.train").train

    @train.setter
    def train(self, module):   # the import system binding the submodule: it stays in sys.modules
        pass


sys.modules[__name__].__class__ = _Package


__all__ = [
    "load_pretrained", "shipped_models", "load_model", "save_model", "make_params", "rest_graph",
    "step", "rollout", "stepper", "contact_stepper",
    "force_check", "state_check", "state_guard", "guarded_stepper", "fallback_step", "fallback_stepper",
    "fem_stepper",
    "GenericGNN", "GNNConfig", "LinearGeneric", "LinearConfig", "CorotationalGeneric", "CorotationalConfig",
    "train", "evaluate",
]
