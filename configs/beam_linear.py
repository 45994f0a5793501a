"""Recipe of the shipped `beam-linear`: the FEM's rest linearisation of the beam, not learned (steps=0).

The reference for the learned beam and the preconditioner of the FEM's Newton step (``tignn demo --model
fem-newton``). Its training envelope is the Abaqus train split's.

    tignn train --config configs/beam_linear.py --data ../shared/data/abaqus_beam.npz --run-dir runs/beam-linear
"""
from tignn_jax.train.linear import LinearConfig, TrainConfig

CONFIG = TrainConfig(model=LinearConfig(prior=True), steps=0)
