"""The viewer's scenes: the demo's beam, two beams and bunny, or any model's own mesh.

`load_scene` builds a `tignn_jax.view.session.Scene` from a scene name and a model: a shipped model name, a model
folder written by ``tignn train`` (``DIR/model/model.npz`` or ``DIR/model.npz``), a model ``.npz`` file, or
``fem-newton`` (the FEM's own backward-Euler step, `tignn_jax.newton.fem_stepper`, on the scene's mesh). The
dynamics come from `tignn_jax.cli.demo._dynamics` and `tignn_jax.cli.demo._fem_newton`, the demo's own.

A model without a scene is shown on its own mesh. A model stores its nodes and graph but not its cells, so its
surface is found as follows: the beam's or the bunny's cells when the model's nodes are those meshes (up to a
scale); else the Delaunay tetrahedra of the nodes whose six edges are all edges of the model's graph (exact for a
tet4 mesh whose graph is its edges); else, e.g. for hexahedra, the Delaunay tetrahedra whose circumradius is at
most the graph's longest edge (an alpha shape). Their boundary faces are the surface.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tignn_jax.view.session import Body, Scene

SCENES = ("beam", "two-beams", "bunny")
# B of the two beams in A's model frame (`tignn_jax.cli.demo.build_scene`): turned 90° about z, across A's free
# half with a gap of 10 (x_A = R x_B + t)
TWO_BEAMS_B = (np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.array([36.0, -25.0, 20.0]))
# the demo's contact (0.006 m, 5e7 per m at 0.005 m per model unit) in model units: radius, force per length
TWO_BEAMS_CONTACT = (1.2, 2.5e5)
LEGEND_FRACTION = 0.5   # the legend spans this fraction of the training envelope's extreme


def resolve_model(model: str) -> str:
    """The path or shipped name `tignn_jax.load_pretrained` reads for ``model``: a folder ``DIR`` written by
    ``tignn train`` resolves to ``DIR/model/model.npz`` or ``DIR/model.npz``.

    Raises:
      ValueError: neither a shipped model, nor ``fem-newton``, nor an existing model file or folder.
    """
    from tignn_jax import api
    from tignn_jax.cli.demo import FEM_NEWTON

    if model == FEM_NEWTON or model in api.shipped_models():
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
      The `tignn_jax.view.session.Scene`.

    Raises:
      ValueError: an unknown scene or model, or a model that is not on the scene's mesh.
    """
    from tignn_jax import api
    from tignn_jax.cli import demo

    if scene is not None and scene not in SCENES:
        raise ValueError(f"scene must be one of {SCENES}, got {scene!r}")
    if scene is None and model is None:
        raise ValueError("give a scene or a model")
    if scene is None and model == demo.FEM_NEWTON:
        raise ValueError(f"{demo.FEM_NEWTON!r} runs on a scene's mesh: give a scene")
    model = resolve_model(model or demo.DEFAULT_MODELS[scene])
    if scene is None:
        params, _ = api.load_pretrained(model)
        q0 = np.asarray(params["mesh"]["q0"], np.float32)
        cells = _known_cells(params)
        triangles = _surface(params, cells)
        step, dynamics, q0, _ = demo._dynamics(model, q0, "beam-linear")
        name, poses = f"model {Path(model).stem if Path(model).is_file() else model}", [None]
    else:
        mesh_q0, cells = _scene_mesh(scene)
        if model == demo.FEM_NEWTON:
            step, dynamics, q0, _ = demo._fem_newton(demo.LINEAR_OF_SCENE[scene], mesh_q0)
            params, _ = api.load_pretrained(demo.LINEAR_OF_SCENE[scene])
        else:
            step, dynamics, q0, _ = demo._dynamics(model, mesh_q0, demo.LINEAR_OF_SCENE[scene])
            params, _ = api.load_pretrained(model)
        from tignn_jax.mr.surface import surface_triangles
        triangles = surface_triangles(cells, q0)
        name = scene
        poses = [None, TWO_BEAMS_B] if scene == "two-beams" else [None]
    import jax

    free = np.asarray(params["mesh"]["node_type"]) == 0
    bodies = tuple(Body(q0=q0, triangles=triangles, free=free,
                        rotation=np.eye(3) if pose is None else pose[0],
                        offset=np.zeros(3) if pose is None else pose[1]) for pose in poses)
    envelope = params["envelope"]
    f_max = float(np.asarray(envelope["f_max"]).reshape(-1)[0])
    u_max = float(np.asarray(envelope["u_max"]).reshape(-1)[0])
    return Scene(name=name, bodies=bodies, step=step, guard=jax.jit(step.guard), dynamics=dynamics,
                 f_max=f_max, u_max=u_max, ranges=_ranges(envelope),
                 contact=TWO_BEAMS_CONTACT if scene == "two-beams" else None)


def models_for(scene: str | None) -> list[str]:
    """The shipped models on ``scene``'s mesh, then ``fem-newton``, for the page's model menu (None: [])."""
    if scene is None:
        return []
    from tignn_jax import api
    from tignn_jax.cli import demo

    mesh = "beam" if scene in ("beam", "two-beams") else "bunny"
    return [m for m in api.shipped_models() if m.split("-")[0] == mesh] + [demo.FEM_NEWTON]


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


def _surface(params, cells):
    """Outward surface triangles [T, 3] of the model's mesh (module docstring)."""
    from scipy.spatial import Delaunay

    from tignn_jax.mr.surface import surface_triangles

    q0 = np.asarray(params["mesh"]["q0"], np.float64)
    if cells is None:
        senders, receivers = (np.asarray(params["mesh"][k]) for k in ("senders", "receivers"))
        tets = Delaunay(q0).simplices
        edges = set(zip(senders.tolist(), receivers.tolist()))
        pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        exact = np.array([all((t[i], t[j]) in edges or (t[j], t[i]) in edges for i, j in pairs)
                          for t in tets.tolist()], bool)
        if exact.sum() >= 0.5 * len(q0):
            cells = tets[exact]
        else:
            longest = float(np.linalg.norm(q0[senders] - q0[receivers], axis=1).max())
            cells = tets[_circumradius(q0[tets]) <= longest * (1 + 1e-6)]
    return surface_triangles(cells, q0)


def _circumradius(x):
    """Circumradii [K] of tetrahedra x [K, 4, 3] (inf for flat ones)."""
    a = x[:, 1:] - x[:, :1]
    rhs = 0.5 * np.sum(a * a, axis=2)
    det = np.linalg.det(a)
    ok = np.abs(det) > 1e-12 * np.abs(a).max() ** 3
    centre = np.zeros((len(x), 3))
    centre[ok] = np.linalg.solve(a[ok], rhs[ok][..., None])[..., 0]
    return np.where(ok, np.linalg.norm(centre, axis=1), np.inf)


def _ranges(envelope) -> dict:
    """{quantity: (vmin, vmax)} of the legend: ``LEGEND_FRACTION`` of the training envelope's extremes."""
    mean, std, dev = (np.asarray(envelope[k], np.float64).reshape(-1) for k in ("z_mean", "z_std", "z_dev_max"))
    bound = np.abs(mean) + dev * std
    s11 = LEGEND_FRACTION * bound[6]
    u = LEGEND_FRACTION * float(np.asarray(envelope["u_max"]).reshape(-1)[0])
    return {"von Mises": (0.0, LEGEND_FRACTION * float(bound[6:9].max())), "σxx": (-s11, s11), "|u|": (0.0, u)}
