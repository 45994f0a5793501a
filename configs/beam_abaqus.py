"""Recipe of the paper's thermodynamics-informed graph network on the Abaqus beam: the reproduction.

A `GenericGNN` of width 64, 2 MLP layers per block and 3 message passes, trained on single steps of the published
train split with state noise 0.2 and the degeneracy penalties, each case weighted by its size:

    tignn train --config configs/beam_abaqus.py --data ../shared/data/abaqus_beam.npz --run-dir runs/beam-abaqus

This is the last phase of the recipe that beat the published network's test errors (docs/research_log.md): the
earlier phases were the same at lr 3e-3 (set ``init_from`` to the previous phase's run folder to continue one).
The width-64, 2-pass variant: ``model=GNNConfig(hidden=64, passes=2)``, 60 epochs, warm-started from the 3-pass
network with its second pass removed; shipped as ``beam-tignn``, a `RestStartGNN` with ``beam-linear``'s rest
stiffness (`tignn_jax.simulators.rest_start.with_rest_start`), which starts from rest at the quasi-static rate of its
load (its MODEL_CARD.md).
"""
from tignn_jax.train.gnn import GNNConfig, TrainConfig

CONFIG = TrainConfig(GNNConfig(hidden=64, mlp_layers=2, passes=3), lr=3e-4, lr_end=2e-5, weight_decay=1e-6,
                     batch_size=2, epochs=8, warmup_steps=50, noise=0.2, deg_weight=1.0, case_weight=1.0)
