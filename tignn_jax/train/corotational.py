"""The corotational GENERIC model (`tignn_jax.simulators.CorotationalGeneric`) of a data file's FEM scene.

Nothing is fitted: the energy and the element operators are the FEM's own
(`tignn_jax.simulators.corotational.from_fem`) on the scene the data were generated from
(`tignn_jax.train.linear.fem_problem`: its mesh, clamps, material, density and damping). The data give the mesh,
the frame step and the envelope the guards compare states and forces with.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

from tignn_jax.simulators.corotational import CorotationalConfig


class TrainConfig(NamedTuple):
    """A recipe for the corotational model.

    Attributes:
      model: the step's options (`CorotationalConfig`).
      train_split: the data's split (a name, or sim ids) whose range is the model's envelope.
    """
    model: CorotationalConfig = CorotationalConfig()
    train_split: str | tuple = "train"


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
      ValueError: an unknown split or a viscoelastic material (`from_fem`).
    """
    from tignn_jax.simulators.corotational import CorotationalGeneric, from_fem
    from tignn_jax.train.linear import fem_problem, save_run

    paths, data, split, rows = scene_data(data_paths, config.train_split)
    recipe = {"model": config.model._asdict(), "train_split": split}
    write_recipe(run_dir, recipe, paths)
    problem, material = fem_problem(paths[0])
    stored = from_fem(problem, material, float(data.dt))
    return save_run(run_dir, paths, data, rows, CorotationalGeneric(config.model), stored, recipe,
                    {"kind": "the FEM's energy and element operators, corotated (not learned)"})


def scene_data(data_paths, train_split):
    """(the data files as a list, their concatenated data, the split's name or sim ids, its rows) for a model
    built from the data's FEM scene.

    Raises:
      ValueError: an unknown split.
    """
    from tignn_jax import data as D
    from tignn_jax.train.linear import _split

    paths = [data_paths] if isinstance(data_paths, (str, Path)) else list(data_paths)
    data = D.concatenate(*(D.load(p) for p in paths))
    split = _split(train_split)
    return paths, data, split, D.split_rows(data, split)


def write_recipe(run_dir, recipe: dict, paths) -> None:
    """Write ``run_dir``/config.json: the recipe as JSON and the data files (the folder is created)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps({"recipe": recipe, "data": [str(p) for p in paths]}, indent=1))
