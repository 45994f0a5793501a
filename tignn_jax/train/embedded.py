"""The embedded corotational model (`tignn_jax.simulators.EmbeddedCorotational`) of a data file's FEM scene.

Nothing is fitted: the data file's mesh is embedded in a cage of cells of size ``cell``
(`tignn_jax.simulators.embedded.embed`), whose elements carry the FEM's energy and element operators of the scene
the data were generated from (`tignn_jax.train.linear.fem_problem`: its mesh, clamps, material, density and
damping). The data give the mesh, the frame step and the envelope the guards compare states and forces with.
"""
from __future__ import annotations

from typing import NamedTuple

from tignn_jax.simulators.corotational import CorotationalConfig


class TrainConfig(NamedTuple):
    """A recipe for the embedded corotational model.

    Attributes:
      cell: the cage's cell size [length]; None: a tenth of the mesh's longest side.
      model: the cage's step options (`CorotationalConfig`).
      train_split: the data's split (a name, or sim ids) whose range is the model's envelope.
    """
    cell: float | None = None
    model: CorotationalConfig = CorotationalConfig()
    train_split: str | tuple = "train"

    def check(self) -> None:
        """Raise `ValueError` naming ``cell`` where it is not None nor a positive number."""
        from tignn_jax.train import is_number

        if self.cell is not None and not (is_number(self.cell) and self.cell > 0):
            raise ValueError(f"cell must be a positive length or None, got cell={self.cell!r}")


def run(data_paths, config: TrainConfig, run_dir, progress: bool = True) -> dict:
    """Build the model of the data's scene and write it to ``run_dir``/model/model.npz.

    Args:
      data_paths: a data file or a list of files on the same mesh (the first one's scene is the FEM's).
      config: the recipe.
      run_dir: folder for config.json and the model.
      progress: unused (the build takes seconds).

    Returns:
      The model (`tignn_jax.api.load_model` of the written file).

    Raises:
      ValueError: a ``cell`` that is not a positive number, an unknown split or a viscoelastic material.
    """
    import numpy as np

    from tignn_jax.simulators.embedded import EmbeddedCorotational, embed
    from tignn_jax.train.corotational import scene_data, write_recipe
    from tignn_jax.train.linear import fem_problem, save_run

    config.check()
    paths, data, split, rows = scene_data(data_paths, config.train_split)
    q0 = np.asarray(data.q0, np.float64)
    cell = float(config.cell) if config.cell is not None else float((q0.max(0) - q0.min(0)).max()) / 10.0
    recipe = {"cell": cell, "model": config.model._asdict(), "train_split": split}
    write_recipe(run_dir, recipe, paths)
    problem, material = fem_problem(paths[0])
    stored = embed(problem, material, cell, float(data.dt))
    return save_run(run_dir, paths, data, rows, EmbeddedCorotational(config.model), stored, recipe,
                    {"kind": f"the FEM's energy and element operators on a cage of cell {cell:g}, corotated "
                             "(not learned)"})
