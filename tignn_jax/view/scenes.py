"""The viewer's scenes: the demo's beam, two beams and bunny, or any model's own mesh.

`load_scene` builds a `tignn_jax.view.interaction.Scene` from a scene name and a model: a shipped model name, a model
folder written by ``tignn train`` (``DIR/model/model.npz`` or ``DIR/model.npz``), a model ``.npz`` file, or
``fem-newton`` (the FEM's own backward-Euler step, `tignn_jax.newton.fem_stepper`, on the scene's mesh). The
dynamics come from `tignn_jax.cli.demo._dynamics` and `tignn_jax.cli.demo._fem_newton`, the demo's own.

A model without a scene is shown on its own mesh, whose surface is drawn from the cells the model keeps
(``params["mesh"]["cells"]``), or, for a model written before models kept their cells, from the beam's or the
bunny's cells when its nodes are those meshes (up to a scale).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tignn_jax.view.interaction import Body, Scene

SCENES = ("beam", "two-beams", "bunny")
# B of the two beams in A's model frame (`tignn_jax.cli.demo.build_scene`): turned 90° about z, across A's free
# half with a gap of 10 (x_A = R x_B + t)
TWO_BEAMS_B = (np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.array([36.0, -25.0, 20.0]))
# the two beams' contact in model units (radius, force per length): the FEM's (`fem.scenes.TWO_BEAMS_CONTACT`)
# inside the implicit frame of a corotational model (benchmarks/contact_beams.py), else the explicit penalty's
TWO_BEAMS_CONTACT = (1.2, 2.5e5)
TWO_BEAMS_IMPLICIT_CONTACT = (2.0, 2.5e5)
LEGEND_FRACTION = 0.5   # the legend spans this fraction of the training envelope's extreme


def resolve_model(model: str) -> str:
    """The path or shipped name `tignn_jax.load_pretrained` reads for ``model``: a folder ``DIR`` written by
    ``tignn train`` resolves to ``DIR/model/model.npz`` or ``DIR/model.npz``.

    Raises:
      ValueError: neither a shipped model, nor ``fem-newton``, nor an existing model file or folder; or a model
        that is not for interaction (`tignn_jax.api.for_interaction`), since the viewer's user pushes the body.
    """
    from tignn_jax import api
    from tignn_jax.cli.demo import FEM_NEWTON

    if model == FEM_NEWTON:
        return model
    if not api.for_interaction(model):
        raise ValueError(f"model {model!r}: {api.NOT_INTERACTIVE}")
    if model in api.shipped_models():
        return model
    path = Path(model)
    if path.is_dir():
        for candidate in (path / "model" / "model.npz", path / "model.npz"):
            if candidate.is_file():
                return str(candidate)
        raise ValueError(f"model folder {model!r} holds neither model/model.npz nor model.npz")
    if path.is_file():
        return str(path)
    raise ValueError(f"model {model!r}: no such model; shipped models: {', '.join(api.shipped_models())} "
                     f"(or a model folder or .npz file, or {FEM_NEWTON!r})")


def load_scene(scene: str | None = None, model: str | None = None) -> Scene:
    """A scene for the viewer.

    Args:
      scene: one of ``SCENES``, or None for the model's own mesh (then ``model`` is required and must not be
        ``fem-newton``).
      model: a shipped model name, a model folder or file, or ``fem-newton`` (default: the demo's model of the
        scene, `tignn_jax.cli.demo.DEFAULT_MODELS`).

    Returns:
      The `tignn_jax.view.interaction.Scene`.

    Raises:
      ValueError: an unknown scene or model, or a model that is not on the scene's mesh.
    """
    import jax

    from tignn_jax import api
    from tignn_jax.cli import demo
    from tignn_jax.mr.surface import surface_triangles

    if scene is not None and scene not in SCENES:
        raise ValueError(f"scene must be one of {SCENES}, got {scene!r}")
    if scene is None and model is None:
        raise ValueError("give a scene or a model")
    if scene is None and model == demo.FEM_NEWTON:
        raise ValueError(f"{demo.FEM_NEWTON!r} runs on a scene's mesh: give a scene")
    given = model
    model = resolve_model(model or demo.DEFAULT_MODELS[scene])
    if scene is None:
        params, _ = api.load_pretrained(model)
        q0 = np.asarray(params["mesh"]["q0"], np.float32)
        cells = params["mesh"].get("cells")
        cells = _known_cells(params) if cells is None else np.asarray(cells)
        if cells is None:
            raise ValueError(f"model {model!r} keeps no cells to draw its surface from: retrain it with tignn train")
        triangles = surface_triangles(cells, q0)
        step, dynamics, q0, _ = demo._dynamics(model, q0, "")
        name, poses = f"{given} (its own mesh)", [None]
    else:
        mesh_q0, cells = _scene_mesh(scene)
        if model == demo.FEM_NEWTON:
            step, dynamics, q0, _ = demo._fem_newton(demo.LINEAR_OF_SCENE[scene], mesh_q0)
            params, _ = api.load_pretrained(demo.LINEAR_OF_SCENE[scene])
        else:
            step, dynamics, q0, _ = demo._dynamics(model, mesh_q0, demo.LINEAR_OF_SCENE[scene])
            params, _ = api.load_pretrained(model)
        triangles = surface_triangles(cells, q0)
        name = scene
        poses = [None, TWO_BEAMS_B] if scene == "two-beams" else [None]
    free = np.asarray(params["mesh"]["node_type"]) == 0
    bodies = tuple(Body(q0=q0, triangles=triangles, free=free,
                        rotation=np.eye(3) if pose is None else pose[0],
                        offset=np.zeros(3) if pose is None else pose[1]) for pose in poses)
    envelope = params["envelope"]
    f_max = float(np.asarray(envelope["f_max"]).reshape(-1)[0])
    u_max = float(np.asarray(envelope["u_max"]).reshape(-1)[0])
    contact, joint = (TWO_BEAMS_CONTACT if scene == "two-beams" else None), None
    if len(bodies) > 1 and hasattr(params["model"], "step_together"):
        contact = TWO_BEAMS_IMPLICIT_CONTACT
        poses = [np.block([[b.rotation, b.offset[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]) for b in bodies]
        joint = api.contact_stepper(params, poses, *contact)
        dynamics += " (contact in the implicit step)"
    return Scene(name=name, bodies=bodies, step=step, guard=jax.jit(step.guard), dynamics=dynamics,
                 f_max=f_max, u_max=u_max, ranges=_ranges(envelope), contact=contact, joint=joint)


def models_for(scene: str | None) -> list[str]:
    """The shipped models on ``scene``'s mesh that are for interaction (`tignn_jax.api.for_interaction`), then
    ``fem-newton``, for the page's model menu (None: [])."""
    if scene is None:
        return []
    from tignn_jax import api
    from tignn_jax.cli import demo

    mesh = "beam" if scene in ("beam", "two-beams") else "bunny"
    shipped = [m for m in api.shipped_models() if m.split("-")[0] == mesh and api.for_interaction(m)]
    return shipped + [demo.FEM_NEWTON]


def _scene_mesh(scene: str):
    """(q0 [N, 3], cells) of the demo's mesh of ``scene``, in the mesh's own units."""
    from fem.meshes import beam_mesh, bunny_mesh

    q0, cells, _ = beam_mesh() if scene in ("beam", "two-beams") else bunny_mesh()
    return np.asarray(q0, np.float32), np.asarray(cells)


def _known_cells(params):
    """The beam's or the bunny's cells when ``params`` is on that mesh (up to a scale), else None."""
    from tignn_jax.cli.demo import _model_units

    for scene in ("beam", "bunny"):
        q0, cells = _scene_mesh(scene)
        if _model_units(params, q0)[1] > 0:
            return cells
    return None


def _ranges(envelope) -> dict:
    """{quantity: (vmin, vmax)} of the legend: ``LEGEND_FRACTION`` of the training envelope's extremes."""
    mean, std, dev = (np.asarray(envelope[k], np.float64).reshape(-1) for k in ("z_mean", "z_std", "z_dev_max"))
    bound = np.abs(mean) + dev * std
    s11 = LEGEND_FRACTION * bound[6]
    u = LEGEND_FRACTION * float(np.asarray(envelope["u_max"]).reshape(-1)[0])
    return {"von Mises": (0.0, LEGEND_FRACTION * float(bound[6:9].max())), "σxx": (-s11, s11), "|u|": (0.0, u)}
