"""A graph network recipe that trains in seconds, for the tests and the small-model notebook."""
from tignn_jax.train.gnn import GNNConfig, TrainConfig

CONFIG = TrainConfig(GNNConfig(hidden=8, passes=1), batch_size=4, epochs=2, warmup_steps=2, eval_every=1,
                     ckpt_every=1)
