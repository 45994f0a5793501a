"""Recipe for a large mesh in real time: the data file's mesh carried by a corotational cage
(`tignn_jax.simulators.EmbeddedCorotational`), cells of a tenth of the mesh's longest side, made from the FEM of the
data's scene (nothing fitted). Set the cell size for your mesh with ``--set cell=...``.

    tignn train --config configs/embedded.py --data my_mesh.npz --run-dir runs/my-mesh-embedded --set cell=2
"""
from tignn_jax.train.embedded import CorotationalConfig, TrainConfig

CONFIG = TrainConfig(cell=None, model=CorotationalConfig(cg_iterations=3, cg_max_iterations=12, cg_tolerance=1e-2,
                                                         modes=32))
