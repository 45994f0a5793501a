"""tignn-jax: thermodynamics-informed graph neural networks (GENERIC) in JAX."""
__version__ = "0.1.0"
