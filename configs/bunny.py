"""Recipe of the shipped `bunny`: the learned linear GENERIC model of the Stanford bunny (1330 nodes, tet4).

Data: 100 fingertip-sized patch presses made by our FEM (backward Euler at the frame step):

    tignn generate bunny --integrator implicit --density 1e-3 --load-radius 5 --rise-frames 10 --cases 100 \
        --seed 0 --out data/bunny.npz
    tignn train --config configs/bunny.py --data data/bunny.npz --run-dir runs/bunny

Split: positions 1–80 less nine for training, 81–90 validation (91–100 are the test cases).
"""
from tignn_jax.train.linear import LinearConfig, TrainConfig

LEFT_OUT = (1, 8, 12, 21, 34, 50, 58, 61, 79)

CONFIG = TrainConfig(
    model=LinearConfig(hidden=32, mu=0.52, kappa=40.8, density=1e-3, alpha=2.0, tied_pressure=True,
                       element_channels=True),
    steps=400, lr=1e-2, batch=12, val_every=10, measure="snapshot",
    train_split=tuple(i for i in range(1, 81) if i not in LEFT_OUT), val_split=tuple(range(81, 91)))
