"""Training: one trainer per model class, each with a `TrainConfig` that holds the class's own config.

* `tignn_jax.train.gnn`: the GENERIC graph network (`tignn_jax.simulators.GenericGNN`), by teacher-forced
  single steps with noise, Adam and a cosine schedule.
* `tignn_jax.train.linear`: the linear GENERIC model (`tignn_jax.simulators.LinearGeneric`), by whole rollouts
  through its backward-Euler solve.
* `tignn_jax.train.corotational`: the corotational GENERIC model
  (`tignn_jax.simulators.CorotationalGeneric`), built from the FEM of the data's scene (nothing fitted).
* `tignn_jax.train.embedded`: the embedded corotational model (`tignn_jax.simulators.EmbeddedCorotational`),
  the data's mesh carried by a cage built from the FEM of the data's scene (nothing fitted).

`tignn train --config FILE` runs either from a recipe in ``configs/`` (`load_recipe`).
"""
from __future__ import annotations

import runpy
from pathlib import Path

TRAINERS = {"generic_gnn": "tignn_jax.train.gnn", "linear": "tignn_jax.train.linear",
            "corotational": "tignn_jax.train.corotational", "embedded": "tignn_jax.train.embedded"}


def is_number(value) -> bool:
    """Whether a recipe's ``value`` is a finite real number (a Python or numpy int or float; a bool is not one)."""
    import numpy as np

    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
            and bool(np.isfinite(value)))


def is_count(value, least: int = 1) -> bool:
    """Whether a recipe's ``value`` is an integer (Python or numpy; a bool is not one) of at least ``least``."""
    import numpy as np

    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= least


def load_recipe(path: str | Path):
    """The ``CONFIG`` of a recipe file (a Python file in ``configs/`` that defines ``CONFIG``, a `TrainConfig` of
    one of the trainers) and the trainer module that runs it.

    Raises:
      ValueError: the file does not exist, fails to run, or defines no ``CONFIG`` of a known trainer.
    """
    import importlib

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no recipe file {str(path)!r}")
    try:
        config = runpy.run_path(str(path)).get("CONFIG")
    except Exception as err:   # the recipe is the user's Python: any error in it is bad input, named here
        raise ValueError(f"{path}: cannot run the recipe ({type(err).__name__}: {err})") from err
    for name in TRAINERS.values():
        module = importlib.import_module(name)
        if isinstance(config, module.TrainConfig):
            return config, module
    raise ValueError(f"{path} defines no CONFIG = <a TrainConfig of {sorted(TRAINERS.values())}>")


def train(data, recipe, run_dir, progress: bool = True) -> dict:
    """Train a model from a recipe and return it (the model written to ``run_dir``/model/model.npz).

    Args:
      data: a data file, or a list of data files on one mesh.
      recipe: a recipe file (``configs/*.py``) or a `TrainConfig` of one of the trainers.
      run_dir: folder for checkpoints, metrics and the model; a second call resumes.
      progress: show progress bars.

    Raises:
      ValueError: an unknown recipe, or bad data.
    """
    import importlib

    if isinstance(recipe, (str, Path)):
        config, trainer = load_recipe(recipe)
    else:
        config, trainer = recipe, None
        for name in TRAINERS.values():
            module = importlib.import_module(name)
            if isinstance(recipe, module.TrainConfig):
                trainer = module
        if trainer is None:
            raise ValueError(f"recipe must be a recipe file or a TrainConfig, got {type(recipe).__name__}")
    return trainer.run(data, config, run_dir, progress=progress)
