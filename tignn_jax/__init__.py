"""tignn-jax: thermodynamics-informed graph neural networks (GENERIC) in JAX."""
__version__ = "0.1.0"

_LAZY = {name: "tignn_jax.api" for name in
         ("step", "rollout", "load_pretrained", "stepper", "force_check", "state_check", "state_guard",
          "guarded_stepper", "fallback_stepper", "fallback_step", "consistency_bound",
          "step_growth", "growth_terms", "network_is_zero")}


def __getattr__(name):
    """``tignn_jax.step``, ``rollout``, ``load_pretrained`` and the other api functions import the model stack
    only when first used."""
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tignn_jax' has no attribute {name!r}")
