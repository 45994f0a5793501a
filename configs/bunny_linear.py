"""Recipe of the shipped `bunny-linear`: the FEM's rest linearisation of the bunny, not learned (steps=0).

    tignn train --config configs/bunny_linear.py --data data/bunny.npz --run-dir runs/bunny-linear

(data/bunny.npz as in configs/bunny.py).
"""
from tignn_jax.train.linear import LinearConfig, TrainConfig

CONFIG = TrainConfig(model=LinearConfig(prior=True), steps=0, train_split=tuple(range(1, 81)),
                     val_split=tuple(range(81, 91)))
