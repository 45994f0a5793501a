"""tignn-jax: thermodynamics-informed graph neural networks (GENERIC) in JAX."""
__version__ = "0.1.0"

_LAZY = {"step": "tignn_jax.api", "rollout": "tignn_jax.api", "load_pretrained": "tignn_jax.api"}


def __getattr__(name):
    """``tignn_jax.step``, ``rollout`` and ``load_pretrained`` import the model stack only when first used."""
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tignn_jax' has no attribute {name!r}")
