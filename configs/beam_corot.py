"""Recipe of the shipped `beam-corot`: the corotational GENERIC model of the beam scene, made from the FEM's element
operators (not learned). Its envelope is the Abaqus train split's.

    tignn train --config configs/beam_corot.py --data ../shared/data/abaqus_beam.npz --run-dir runs/beam-corot
"""
from tignn_jax.train.corotational import CorotationalConfig, TrainConfig

CONFIG = TrainConfig(model=CorotationalConfig(cg_iterations=3, cg_max_iterations=12, cg_tolerance=1e-2, modes=32))
