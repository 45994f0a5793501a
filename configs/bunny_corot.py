"""Recipe of the shipped `bunny-corot`: the corotational GENERIC model of the bunny scene (tet4, nodal volume change
and the nodes' share of the deviatoric energy, as the FEM's nodal tet4), made from the FEM's element operators (not
learned). Its envelope is the bunny data's train split's (the data of `configs/bunny.py`):

    tignn train --config configs/bunny_corot.py --data data/bunny.npz --run-dir runs/bunny-corot
"""
from tignn_jax.train.corotational import CorotationalConfig, TrainConfig

LEFT_OUT = (1, 8, 12, 21, 34, 50, 58, 61, 79)   # the positions `configs/bunny.py` leaves out of its train split

CONFIG = TrainConfig(model=CorotationalConfig(cg_iterations=2, cg_max_iterations=12, cg_tolerance=1e-2, modes=32),
                     train_split=tuple(i for i in range(1, 81) if i not in LEFT_OUT))
