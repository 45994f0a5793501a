"""A linear model recipe that trains in seconds, for the tests (on `tignn_jax.data.synthetic_beam`-sized data)."""
from tignn_jax.train.linear import LinearConfig, TrainConfig

CONFIG = TrainConfig(model=LinearConfig(hidden=8, mu=1.0, kappa=10.0, density=1.0, alpha=1.0), steps=6, lr=1e-2,
                     val_every=3)
