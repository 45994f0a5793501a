"""Recipes made from a data file: ``tignn train --config linear|corotational|embedded|tignn`` on any mesh.

A data file of ``tignn generate`` records its FEM scene (`tignn_jax.train.linear.data_metadata`): the material,
density and mass damping. The named recipes take their scales from it:

* ``linear``: the learned linear GENERIC model (`tignn_jax.train.linear`) on top of the FEM's rest linearisation
  (``prior``), with learned nodal and cell channels whose moduli start at 10⁻³ of the material's shear modulus
  μ = 2 (C10 + C01) and bulk modulus κ = 2 / D1, the density and damping of the data; 100 Adam steps on whole
  rollouts, in float64.
* ``corotational``: the corotational GENERIC model (`tignn_jax.train.corotational`; nothing fitted).
* ``embedded``: the mesh carried by a corotational cage of cells a tenth of its longest side
  (`tignn_jax.train.embedded`; nothing fitted): large meshes in real time.
* ``tignn``: the paper's graph network (`tignn_jax.train.gnn`) with its default architecture and schedule.

`override` changes any field of a recipe from ``KEY=VALUE`` text (``steps=20``, ``model.hidden=16``).
"""
from __future__ import annotations

import ast

NAMES = ("linear", "corotational", "embedded", "tignn")


def default_recipe(name: str, data_path):
    """The recipe ``name`` (one of ``NAMES``) with scales from the data file's FEM scene.

    Returns:
      (the recipe, a `TrainConfig` of its trainer; the trainer module).

    Raises:
      ValueError: an unknown name.
    """
    import importlib

    from tignn_jax.train import TRAINERS
    from tignn_jax.train.linear import data_metadata

    if name not in NAMES:
        raise ValueError(f"unknown recipe {name!r}; named recipes: {', '.join(NAMES)} (or a recipe file)")
    if name in ("corotational", "embedded"):
        module = importlib.import_module(TRAINERS[name])
        return module.TrainConfig(), module
    if name == "tignn":
        module = importlib.import_module(TRAINERS["generic_gnn"])
        return module.TrainConfig(), module
    module = importlib.import_module(TRAINERS["linear"])
    meta = data_metadata(data_path)
    mat = meta["material"]
    mu = 2.0 * (float(mat["c10"]) + float(mat.get("c01", 0.0)))
    kappa = 2.0 / float(mat["d1"])
    hexes = meta.get("cell_type", "hexahedron") == "hexahedron"
    model = module.LinearConfig(hidden=16, mu=_round(1e-3 * mu), kappa=_round(1e-3 * kappa),
                                density=_round(mat["density"]), alpha=_round(meta.get("damping", 0.0)),
                                tied_pressure=True, element_channels=True, cell_pressure=hexes, prior=True)
    return module.TrainConfig(model=model, steps=100, lr=1e-2, val_every=10, float64=True), module


def _round(x) -> float:
    """A recorded value to 6 significant digits (the data's metadata carries float32 round-off)."""
    return float(f"{float(x):.6g}")


def override(config, assignments):
    """The recipe with fields changed by ``KEY=VALUE`` strings (a dotted key reaches into the ``model`` field;
    a value is read as a Python literal, else kept as text).

    Raises:
      ValueError: an assignment without ``=``, or a key that is not a field of the recipe (naming it and the
        fields there are).
    """
    for text in assignments or ():
        key, sep, raw = str(text).partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set {text!r}: expected KEY=VALUE, e.g. steps=20")
        try:
            value = ast.literal_eval(raw.strip())
        except (ValueError, SyntaxError):
            value = raw.strip()
        path = key.strip().split(".")
        config = _set(config, path, value, key.strip())
    return config


def _set(obj, path, value, key):
    fields = getattr(obj, "_fields", None)
    if fields is None:
        raise ValueError(f"--set {key}: {path[0]!r} is inside a value of type {type(obj).__name__}, which has no "
                         f"fields")
    if path[0] not in fields:
        raise ValueError(f"--set {key}: no field {path[0]!r}; fields: {', '.join(fields)}")
    if len(path) == 1:
        current = getattr(obj, path[0])
        if isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        return obj._replace(**{path[0]: value})
    return obj._replace(**{path[0]: _set(getattr(obj, path[0]), path[1:], value, key)})
