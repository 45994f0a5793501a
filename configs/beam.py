"""Recipe of the shipped `beam`: the learned linear GENERIC model of the paper's 40×10×10 beam.

Data: the Abaqus reference data's published train split (41 cases; val: 5), ../shared/data/abaqus_beam.npz.

    tignn train --config configs/beam.py --data ../shared/data/abaqus_beam.npz --run-dir runs/beam

K and S start at the FEM's rest linearisation of the beam scene identified on these data (`prior`) plus learned
nodal and cell channels; whole 20-frame rollouts, 12 cases per step, float64.
"""
from tignn_jax.train.linear import LinearConfig, TrainConfig

CONFIG = TrainConfig(
    model=LinearConfig(hidden=32, mu=310.0, kappa=2e3, density=7.135e-3, alpha=18.17, tied_pressure=True,
                       element_channels=True, cell_pressure=True, prior=True),
    steps=300, lr=1e-2, batch=12, val_every=20, measure="snapshot", weights=(1.0, 0.5, 1.0), float64=True)
