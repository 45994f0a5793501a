"""The public simulator: load a model, step it, roll it out.

A model (``params``) is the dict described in `tignn_jax.simulators`: a model class instance (its configuration),
its arrays, the mesh it was trained on, its training envelope and its provenance. `step`, `rollout` and `stepper`
compile the model's frame map once per model (`_programs`): its arrays are constants of the program, which XLA:CPU
runs faster than the same program reading them as arguments (docs/research_log.md). Where a caller's own trace
holds the arrays as tracers (a gradient with respect to them), `_advance` and `_rollout` take them as arguments.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import jraph
import numpy as np
from flax import traverse_util

from tignn_jax import DEFAULT_MODEL  # noqa: F401 (the package defines it: the CLI reads it without JAX)
from tignn_jax import graph as G
from tignn_jax.data import NOT_AN_ARCHIVE, STATE_DIM
from tignn_jax.simulators import CLASSES

PRETRAINED_DIR = Path(__file__).resolve().parent / "pretrained"
ENVELOPE = ("z_mean", "z_std", "z_dev_max", "u_max", "f_max")
FORMAT = 2   # the model file's layout version (`save_model`)
# The frame programs are compiled without XLA:CPU's YNNPACK fusions, as `tignn_jax.mr.real_time_xla_flags` sets for
# a whole process: the corotational frame's gathers and reductions run several times faster as XLA's own loops, and
# the other classes' frames take the same time (docs/research_log.md). A user's own choice of that option in
# XLA_FLAGS is kept.
YNN_FUSION_OPTION = "xla_cpu_experimental_ynn_fusion_type"
FRAME_COMPILER_OPTIONS = {} if YNN_FUSION_OPTION in os.environ.get("XLA_FLAGS", "") else {YNN_FUSION_OPTION: ""}


def step(params: dict, graph: jraph.GraphsTuple, forces) -> jraph.GraphsTuple:
    """Advance the body (or bodies) in ``graph`` by one frame under ``forces``.

    z_{k+1} = Φ(z_k, f_k), with Φ the model's frame map (for a GENERIC model an integration over Δt of
    dz/dt = L∇E + M∇S + B f), z = (q, v, σ) per node.

    Args:
      params: a model, from `load_pretrained` or `load_model`.
      graph: a graph of the model's mesh (`load_pretrained`'s rest graph, a graph `step` returned, or
        `tignn_jax.graph.batch` of k such graphs) with ``nodes["z"]`` [N, 12]: positions q (length), velocities
        v (length/time) and Cauchy stress σ (S11, S22, S33, S12, S13, S23; stress) of every node.
      forces: [N, 3] external nodal forces (force units of the model's data) held during the frame.

    Returns:
      The same graph with the new state in ``nodes["z"]`` [N, 12].

    Raises:
      ValueError: the graph is not the model's mesh (or k copies of it), or ``forces`` has another shape or
        non-finite values.
    """
    _check_graph(params, graph)
    forces, host = _forces(forces, graph.nodes["z"].shape[0], "forces")
    z = _programs(params)[0](graph.nodes["z"], forces)
    _finite(host, "forces")     # while the frame computes: a bad input discards it
    return G.with_state(graph, z)


def rollout(params: dict, graph: jraph.GraphsTuple, forces_seq) -> jax.Array:
    """The states of T frames from the graph's state, by ``lax.scan`` over `step`'s frame map.

    Args:
      params: a model.
      graph: as for `step`; its ``nodes["z"]`` [N, 12] is the first state.
      forces_seq: [T, N, 3] the external nodal forces of each frame.

    Returns:
      [T + 1, N, 12] the states, the graph's first.

    Raises:
      ValueError: as `step`.
    """
    _check_graph(params, graph)
    forces_seq, host = _forces(forces_seq, graph.nodes["z"].shape[0], "forces_seq", seq=True)
    zs = _programs(params)[1](graph.nodes["z"], forces_seq)
    _finite(host, "forces_seq")
    return zs


def stepper(params: dict, copies: int = 1):
    """`step`'s compiled frame map without the per-call checks: ``z_next = fn(z, forces)``.

    For real-time loops that hold the state as an array. ``fn`` runs the same compiled program as `step`.

    Args:
      params: a model.
      copies: the number of bodies of the model's mesh stacked in z (each stepped on its own).

    Returns:
      ``fn(z [copies·N, 12], forces [copies·N, 3]) -> [copies·N, 12]``.

    Raises:
      ValueError: ``copies`` is not a positive integer (and ``fn`` on arrays of other shapes).
    """
    if not isinstance(copies, (int, np.integer)) or isinstance(copies, bool) or copies < 1:
        raise ValueError(f"copies must be a positive integer, got {copies!r}")
    frame = _programs(params)[0]
    shape = (int(copies) * _nodes(params), STATE_DIM)

    def fn(z, forces):
        if z.shape != shape or forces.shape != shape[:1] + (3,):
            raise ValueError(f"this stepper takes z {list(shape)} and forces [{shape[0]}, 3], got "
                             f"{list(z.shape)} and {list(forces.shape)}")
        return frame(z, forces)

    return fn


def contact_stepper(params, poses, radius: float, stiffness: float, capacity: int = 128):
    """One frame of several bodies that touch one another: ``zs_next = fn(zs, forces)``.

    Each body has a pose in a common world frame; where surface nodes of two bodies come closer than ``radius``
    they repel by the penalty energy E_c = Σ_ij ½ k max(r − d_ij, 0)² (d_ij the world distance of the pair). The
    contact is inside the bodies' implicit frame: all bodies are solved together, E_c in their potential and its
    stiffness in their one linear solve, so they never end a frame with more energy than their external forces
    put in, however stiff the contact (`tignn_jax.simulators.contact`). For models whose class steps bodies
    together (``step_together``: `tignn_jax.simulators.CorotationalGeneric`).

    Args:
      params: a model, shared by every body, or a list with one model per body.
      poses: per body, its [4, 4] model-to-world matrix (a rotation times a scale, the same scale for every body,
        then a translation; `tignn_jax.mr.model_matrix`).
      radius: the contact distance r (world length).
      stiffness: the penalty stiffness k (force per world length; forces in the models' units).
      capacity: the most surface nodes of a body, and of the others, taking part in its contact (those nearest to
        the other bodies' surface nodes; `tignn_jax.simulators.contact.candidate_pairs`).

    Returns:
      ``fn(zs, forces) -> zs``, tuples over the bodies of z [N_b, 12] and forces [N_b, 3] (each in its body's
      model frame), jitted.

    Raises:
      ValueError: fewer than two poses, a model list of another length, models of a class that cannot step
        bodies together or of different configurations, a pose that is not a finite [4, 4] similarity of one
        common scale, or a non-positive radius, stiffness or capacity (and ``fn`` on tuples of other lengths or
        shapes).
    """
    from tignn_jax.mr.surface import surface_nodes, surface_triangles
    from tignn_jax.simulators.contact import contact

    models = list(params) if isinstance(params, (list, tuple)) else [params] * len(poses)
    if len(models) != len(poses):
        raise ValueError(f"contact_stepper needs one model per pose, got {len(poses)} poses and {len(models)} "
                         f"models")
    first = models[0]["model"] if models else None
    for b, m in enumerate(models):
        if not hasattr(m["model"], "step_together"):
            raise ValueError(f"the model of body {b} ({type(m['model']).__name__}) cannot be stepped together with "
                             f"others; contact_stepper takes models of the corotational class")
        if m["model"] != first:
            raise ValueError(f"every body's model must have the same class and configuration, got {m['model']} "
                             f"and {first}")
    surfaces = [surface_nodes(surface_triangles(np.asarray(m["arrays"]["cells"]), np.asarray(m["mesh"]["q0"])))
                for m in models]
    spec = contact(poses, surfaces, radius, stiffness, capacity)
    shapes = [_nodes(m) for m in models]
    arrays = tuple(m["arrays"] for m in models)
    frame = _frame_program(lambda zs, fs: first.step_together(arrays, zs, fs, spec))

    def fn(zs, forces):
        if len(zs) != len(shapes) or len(forces) != len(shapes) or any(
                tuple(z.shape) != (n, STATE_DIM) or tuple(f.shape) != (n, 3) for z, f, n in zip(zs, forces, shapes)):
            raise ValueError(f"this stepper takes {len(shapes)} states [N_b, {STATE_DIM}] and forces [N_b, 3] with "
                             f"N_b = {shapes}, got {[tuple(z.shape) for z in zs]} and "
                             f"{[tuple(f.shape) for f in forces]}")
        return frame(tuple(zs), tuple(forces))

    return fn


def load_pretrained(name: str = DEFAULT_MODEL):
    """A shipped model by name, or a model folder or file, with the rest graph of its mesh.

    Args:
      name: a folder of ``tignn_jax/pretrained`` (`shipped_models`), or a path to a model folder, a run folder of
        ``tignn train`` (its ``model/model.npz``) or a model ``.npz``.

    Returns:
      (params, graph): the model and the graph of its mesh at rest (q = q0, v = 0, σ = 0).

    Raises:
      ValueError: no such model.
    """
    path = Path(name)
    if not path.exists():
        path = PRETRAINED_DIR / name
    if path.is_dir() and not (path / "model.npz").exists() and (path / "model" / "model.npz").exists():
        path = path / "model"          # a run folder of `tignn train`
    if path.is_dir():
        path = path / "model.npz"
    if not path.exists():
        raise ValueError(f"no model named {name!r}; shipped models: {shipped_models()}")
    params = load_model(path)
    return params, rest_graph(params)


def shipped_models() -> list[str]:
    """The names of the shipped models (folders of ``tignn_jax/pretrained``) that `load_pretrained` accepts."""
    return sorted(p.name for p in PRETRAINED_DIR.iterdir() if (p / "model.npz").exists())


NOT_INTERACTIVE = ("is the paper's network reproduced, which follows a load ramped from rest as its training data "
                   "do, not a model for interaction (its MODEL_CARD.md)")


def for_interaction(model: str | Path) -> bool:
    """Whether a model is meant to be pushed around, as the demo and the viewer do: False where its file's ``info``
    says ``"interactive": false``. The paper's reproduction ``beam-tignn`` does: it follows a load ramped from rest,
    as the Abaqus data do, and a load held, released or moved is outside what it learned. Read with numpy alone.

    Args:
      model: a shipped model's name, a model file, or a folder holding ``model.npz`` or ``model/model.npz``.

    Returns:
      False for a model file marked so; True otherwise (also where no model file is found: loading names that).
    """
    path = PRETRAINED_DIR / str(model) / "model.npz" if str(model) in shipped_models() else Path(model)
    if path.is_dir():
        path = path / "model.npz" if (path / "model.npz").is_file() else path / "model" / "model.npz"
    try:
        with np.load(path, allow_pickle=False) as raw:
            info = json.loads(str(raw["info"])) if "info" in raw.files else {}
    except (OSError, AttributeError, TypeError) + NOT_AN_ARCHIVE:   # not a model file
        return True
    return info.get("interactive") is not False


def rest_graph(params: dict, copies: int = 1) -> jraph.GraphsTuple:
    """The graph of ``copies`` bodies of the model's mesh at rest.

    Args:
      params: a model.
      copies: bodies in the graph (`tignn_jax.graph.batch` of the one-body graph).

    Returns:
      A ``jraph.GraphsTuple`` with ``nodes["z"]`` [copies·N, 12] at rest (q = q0, v = 0, σ = 0) and
      ``nodes["node_type"]`` [copies·N] int32 (0 free, 1 clamped).
    """
    mesh, n = params["mesh"], _nodes(params)
    one = jraph.GraphsTuple(
        nodes={"z": jnp.asarray(G.rest_state(mesh["q0"])), "node_type": jnp.asarray(mesh["node_type"])},
        edges=None, senders=params["edges"][0], receivers=params["edges"][1], globals=None,
        n_node=jnp.array([n], jnp.int32), n_edge=jnp.array([len(mesh["senders"])], jnp.int32))
    if copies == 1:
        return one
    graph = G.batch([one] * int(copies))
    _remember_batched_edges(params, int(copies), graph)
    return graph


_BATCHED_EDGES: dict = {}    # (id of a model's sender array, copies) -> (that array, ((senders, receivers), ...))
_BATCHED_EDGES_KEPT = 16     # rest graphs of that many (model, copies) pairs are recognised by identity


def _remember_batched_edges(params, copies: int, graph) -> None:
    """Keep the edge arrays of a batched rest graph, so `step` recognises them (and the graphs it returns, which
    carry them) by identity, as it does the one-body graph's. The model's own sender array is kept with them, so
    its id cannot be reused by another model's while the entry lives."""
    key = (id(params["edges"][0]), copies)
    if key not in _BATCHED_EDGES and len(_BATCHED_EDGES) >= _BATCHED_EDGES_KEPT:
        _BATCHED_EDGES.pop(next(iter(_BATCHED_EDGES)))
    model_senders, pairs = _BATCHED_EDGES.get(key, (params["edges"][0], ()))
    _BATCHED_EDGES[key] = (model_senders, ((graph.senders, graph.receivers),) + pairs[:3])   # the 4 latest


def make_params(model, stored: dict, mesh: dict, envelope: dict, info: dict | None = None) -> dict:
    """A model dict from a model class instance, its stored arrays, its mesh and its training envelope.

    Args:
      model: an instance of a class of `tignn_jax.simulators`.
      stored: the arrays ``model.stored`` keeps.
      mesh: {"q0" [N, 3], "senders" [E], "receivers" [E], "node_type" [N]} (0 free, 1 clamped), and optionally
        "cells" [K, 4|8] (tet4 or hex8 node ids, VTK order), which the viewers draw the surface from.
      envelope: the training data's {"z_mean" [12], "z_std" [12], "z_dev_max" [12], "u_max" [1], "f_max" [1]}.
      info: provenance, written as JSON.

    Raises:
      ValueError: a missing mesh or envelope entry, or arrays that do not fit the mesh.
    """
    if getattr(model, "name", None) not in CLASSES:
        raise ValueError(f"model must be one of the classes {sorted(CLASSES)}, got {model!r}")
    missing = [k for k in ("q0", "senders", "receivers", "node_type") if k not in mesh]
    missing += [k for k in ENVELOPE if k not in envelope]
    if missing:
        raise ValueError(f"a model needs the mesh and envelope entries {missing}")
    cells = mesh.get("cells")
    mesh = {"q0": np.asarray(mesh["q0"], np.float32), "senders": np.asarray(mesh["senders"], np.int32),
            "receivers": np.asarray(mesh["receivers"], np.int32),
            "node_type": np.asarray(mesh["node_type"], np.int32)}
    if cells is not None:      # the mesh's cells, for drawing its surface (`tignn_jax.mr.surface_triangles`)
        cells = np.asarray(cells, np.int32)
        if cells.ndim != 2 or cells.shape[1] not in (4, 8) or cells.min() < 0 or cells.max() >= len(mesh["q0"]):
            raise ValueError(f"mesh cells must be [K, 4|8] node ids below {len(mesh['q0'])}, got {cells.shape}")
        mesh["cells"] = cells
    return {"model": model, "arrays": model.prepare(stored, mesh), "mesh": mesh,
            "edges": (jnp.asarray(mesh["senders"]), jnp.asarray(mesh["receivers"])),
            "envelope": {k: np.asarray(envelope[k], np.float32) for k in ENVELOPE}, "info": dict(info or {})}


def save_model(params: dict, path: str | Path, info: dict | None = None) -> Path:
    """Write a model to one compressed ``.npz`` that `load_model` and `load_pretrained` read.

    Args:
      params: a model.
      path: the file to write (its folder is created).
      info: provenance to store instead of the model's own ``info``.

    Returns:
      The path written. The file holds the class and configuration as JSON, the stored arrays, the mesh, the
      envelope and the info.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = params["model"]
    stored = traverse_util.flatten_dict(jax.device_get(model.stored(params["arrays"])), sep="/")
    arrays = {f"stored/{k}": np.asarray(v) for k, v in stored.items()}
    arrays.update({f"mesh/{k}": np.asarray(v) for k, v in params["mesh"].items()})
    arrays.update({f"envelope/{k}": np.asarray(v) for k, v in params["envelope"].items()})
    arrays["model"] = np.array(json.dumps({"class": model.name, "config": model.config._asdict(),
                                           "format": FORMAT}))
    arrays["info"] = np.array(json.dumps(params.get("info", {}) if info is None else info))
    np.savez_compressed(path, **arrays)
    return path


def load_model(path: str | Path) -> dict:
    """Read a model written by `save_model`.

    Raises:
      ValueError: the file is not a model file of this format, or names an unknown class or option.
    """
    try:
        with np.load(path, allow_pickle=False) as npz:
            flat = {k: npz[k] for k in npz.files}
    except NOT_AN_ARCHIVE as err:
        raise ValueError(f"{path} is not a tignn-jax model file (not a .npz archive)") from err
    if "model" not in flat:
        raise ValueError(f"{path} is not a tignn-jax model file (no 'model' entry)")
    try:
        head = json.loads(str(flat["model"]))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not a tignn-jax model file (its 'model' entry is not JSON)") from err
    if not isinstance(head, dict) or not isinstance(head.get("config"), dict):
        raise ValueError(f"{path} is not a tignn-jax model file (its 'model' entry names no class and config)")
    cls = CLASSES.get(head.get("class"))
    if cls is None:
        raise ValueError(f"{path}: unknown model class {head.get('class')!r}; known: {sorted(CLASSES)}")
    config_type = cls.__dataclass_fields__["config"].type
    config_type = cls().config.__class__ if isinstance(config_type, str) else config_type
    unknown = sorted(set(head["config"]) - set(config_type._fields))
    if unknown:
        raise ValueError(f"{path}: options {unknown} are not options of {cls.__name__}")
    group = lambda p: {k[len(p) + 1:]: v for k, v in flat.items() if k.startswith(p + "/")}
    stored = traverse_util.unflatten_dict({tuple(k.split("/")): v for k, v in group("stored").items()})
    info = json.loads(str(flat["info"])) if "info" in flat else {}
    return make_params(cls(config_type(**head["config"])), stored, group("mesh"), group("envelope"), info)


def _nodes(params) -> int:
    return len(params["mesh"]["node_type"])


def _frame_program(fn, static_argnums=()):
    """``fn`` jitted with ``FRAME_COMPILER_OPTIONS`` where it is called at the top level; inside a caller's own
    trace (``jit``, ``scan``, ``grad``: an argument is a tracer), where JAX takes compiler options only at the top
    level, jitted plainly, as part of the caller's program."""
    top = jax.jit(fn, static_argnums=static_argnums, compiler_options=FRAME_COMPILER_OPTIONS)
    nested = jax.jit(fn, static_argnums=static_argnums)

    def call(*args):
        traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(args))
        return (nested if traced else top)(*args)

    return call


def _frame_map(model, n: int, arrays: dict, z, forces):
    """The frame map of the bodies stacked in z [k·n, 12] under forces [k·n, 3]: one body as it is, several one
    after another on a CPU (``lax.map``, the faster there) or side by side elsewhere (``vmap``)."""
    forces = forces.astype(z.dtype)
    if z.shape[0] == n:
        return model.step_state(arrays, z, forces)
    bodies = (z.reshape(-1, n, STATE_DIM), forces.reshape(-1, n, 3))
    one = lambda zf: model.step_state(arrays, *zf)
    out = jax.lax.map(one, bodies) if jax.default_backend() == "cpu" else jax.vmap(one)(bodies)
    return out.reshape(z.shape)


def _scan_frames(model, n: int, arrays: dict, z0, forces_seq):
    """The states [T + 1, k·n, 12] of T frames from z0 under forces_seq [T, k·n, 3], one ``lax.scan`` of
    `_frame_map`."""
    def body(z, f):
        z = _frame_map(model, n, arrays, z, f)
        return z, z

    _, zs = jax.lax.scan(body, z0, forces_seq)
    return jnp.concatenate([z0[None], zs])


_advance = _frame_program(_frame_map, static_argnums=(0, 1))
_rollout = _frame_program(_scan_frames, static_argnums=(0, 1))
_PROGRAMS: dict = {}   # id(arrays) → (arrays, model, array leaves, programs) of the last models compiled
_PROGRAMS_KEPT = 8


def _programs(params: dict) -> tuple:
    """``(frame(z, forces), frames(z0, forces_seq))``: `_frame_map` and `_scan_frames` of the model with its arrays
    closed over, compiled once per model and number of bodies (those of the last ``_PROGRAMS_KEPT`` models compiled
    are kept, and keep the models' arrays alive); where the arrays are traced (a caller differentiating with respect
    to them), `_advance` and `_rollout`, which take them as arguments."""
    model, n, arrays = params["model"], _nodes(params), params["arrays"]
    leaves = jax.tree_util.tree_leaves(arrays)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return (lambda z, forces: _advance(model, n, arrays, z, forces),
                lambda z0, forces_seq: _rollout(model, n, arrays, z0, forces_seq))
    kept = _PROGRAMS.get(id(arrays))      # the same dict, model and array objects: the same programs
    if (kept is not None and kept[0] is arrays and kept[1] is model and len(kept[2]) == len(leaves)
            and all(a is b for a, b in zip(kept[2], leaves))):
        return kept[3]
    programs = (_frame_program(lambda z, forces: _frame_map(model, n, arrays, z, forces)),
                _frame_program(lambda z0, forces_seq: _scan_frames(model, n, arrays, z0, forces_seq)))
    _PROGRAMS.pop(id(arrays), None)
    _PROGRAMS[id(arrays)] = (arrays, model, leaves, programs)
    while len(_PROGRAMS) > _PROGRAMS_KEPT:
        _PROGRAMS.pop(next(iter(_PROGRAMS)))
    return programs


def _check_graph(params, graph) -> None:
    """Check the graph's type, its state's shape ([k·N, 12]) and its edges (k copies of the model's mesh). The
    model's own edge arrays, and those of a recent `rest_graph` of k copies, are known by identity (no comparison
    of values): `step` returns graphs that carry them, so a loop pays a few attribute look-ups."""
    if not isinstance(graph, jraph.GraphsTuple) or not isinstance(graph.nodes, dict) or "z" not in graph.nodes:
        raise ValueError(f"graph must be a jraph.GraphsTuple with nodes {{'z': [N, {STATE_DIM}], ...}}, got "
                         f"{type(graph).__name__}")
    edges, shape, n_mesh = params["edges"], graph.nodes["z"].shape, _nodes(params)
    if graph.senders is edges[0] and graph.receivers is edges[1] and shape == (n_mesh, STATE_DIM):
        return
    n = shape[0]
    if n % n_mesh or tuple(shape) != (n, STATE_DIM):
        raise ValueError(f"graph.nodes['z'] has shape {tuple(shape)}, expected [k·{n_mesh}, {STATE_DIM}] "
                         f"for the model's mesh of {n_mesh} nodes")
    k = n // n_mesh
    if tuple(np.shape(graph.senders)) != (k * len(params["mesh"]["senders"]),) \
            or tuple(np.shape(graph.receivers)) != tuple(np.shape(graph.senders)):
        raise ValueError("graph.senders / graph.receivers are not the edges of the model's mesh")
    _check_edges(params, graph, k)


def _forces(forces, n: int, name: str, seq: bool = False):
    """Check the forces' shape ([n, 3], or [T, n, 3] with ``seq``) and type; returns (the forces as a numpy or jax
    array of the state's dtype, the forces as a numpy array for `_finite`)."""
    if type(forces) is np.ndarray and forces.dtype is _FLOAT32 and forces.shape == (n, 3) and not seq:
        return forces, forces     # what a real-time loop hands over: nothing to convert
    shape = tuple(np.shape(forces))
    want = ((shape[0] if len(shape) == 3 else -1,) if seq else ()) + (n, 3)
    if shape != want:
        raise ValueError(f"{name} has shape {list(shape)}, expected {'[T, ' if seq else '['}{n}, 3]")
    host = np.asarray(forces)   # a jax array on the CPU: a view, no reduction dispatched to the device
    if host.dtype.kind not in "fiu":
        raise ValueError(f"{name} must be numbers, got dtype {host.dtype}")
    return (forces if isinstance(forces, jax.Array) else host.astype(np.float32, copy=False)), host


_FLOAT32 = np.dtype(np.float32)


def _finite(host, name: str) -> None:
    """Raise if the forces ``host`` hold a NaN or an infinity. The sum of squares (one BLAS dot product, the
    cheapest reduction numpy calls) is non-finite if an entry is; only then, since huge finite forces may overflow
    it, are the entries tested one by one. Integer forces are always finite."""
    if host.dtype.kind == "f" and not math.isfinite(np.vdot(host, host)) and not np.isfinite(host).all():
        raise ValueError(f"{name} contains NaN or infinite values")


def _check_edges(params, graph, k: int):
    """The graph's edges and node types are the model's mesh's (k copies): at once where the graph carries the edge
    arrays of a recent `rest_graph` of k copies (kept by `step`; the mesh's own arrays `_check_graph` knows), else
    by value."""
    model_senders, pairs = _BATCHED_EDGES.get((id(params["edges"][0]), k), (None, ()))
    if model_senders is params["edges"][0] and any(graph.senders is a and graph.receivers is b for a, b in pairs):
        return
    mesh = params["mesh"]
    offsets = np.repeat(np.arange(k) * len(mesh["node_type"]), len(mesh["senders"]))
    senders, receivers = np.asarray(graph.senders), np.asarray(graph.receivers)
    if senders.shape != offsets.shape or not np.array_equal(senders, np.tile(mesh["senders"], k) + offsets) \
            or not np.array_equal(receivers, np.tile(mesh["receivers"], k) + offsets):
        raise ValueError("graph.senders / graph.receivers are not the edges of the model's mesh")
    if "node_type" in graph.nodes and not np.array_equal(np.asarray(graph.nodes["node_type"]),
                                                         np.tile(mesh["node_type"], k)):
        raise ValueError("graph.nodes['node_type'] differs from the model's mesh")
