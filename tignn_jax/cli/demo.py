"""``tignn demo``: a fingertip in a (synthetic) camera image pushes virtual solids; writes a GIF and timings.

Scenes:

* ``two-beams``: the paper's configuration (`fem.scenes.two_beams_scene`): two copies of the 40x10x10 beam (shown
  0.2 m long), the lower one A clamped at x = 0, the upper one B turned 90° about the vertical and lying across A's
  free half with a gap of 10 (5 cm). The fingertip presses B's free end 0.2 m deep, a spring from the surface
  under it (`tignn_jax.mr.forcing.fingertip_spring_forces`), so B bends down onto A, and A bends under it. With
  the corotational model both beams are stepped in one implicit frame with their penalty contact inside it
  (`tignn_jax.contact_stepper`: stiff, and never creating energy); with another model each body steps on its own
  and they interact through `tignn_jax.mr.forcing.contact_forces` between the frames (a soft penalty: a stiffer
  one rings; docs/research_log.md). The demo runs on ``--cores`` cores (default 1), the process pinned to them
  (`tignn_jax.mr.runtime.pin_cores`). With two or more, bodies that step on their own each step on their own CPU
  device, concurrently (``Scene.devices``); with one, all bodies' frames run in one program.
* ``beam``: beam A alone, pressed down at its free end (as B above).
* ``bunny``: the Stanford bunny (10 cm tall) standing on the table, base clamped, pressed 7 mm deep on the top of
  its head by a spring fingertip over a 1 cm pad: a dent of about 7 % of its height, as deep as that of the
  largest patch load the bunny model is validated at (30 times the unit load,
  ``benchmarks/large_deformation_bunny.py``).
* ``own``: the mesh of the ``--model`` (a model trained with ``tignn train`` on a mesh of your own, which keeps its
  cells), 20 cm across, its model z axis up, standing on the table; the camera is framed from the mesh's extent
  and the fingertip presses the free surface node farthest from the clamps among those facing the camera, with
  half the largest nodal force of the model's training data (`own_scene`). The default scene of a ``--model``
  path whose mesh is not one of the paper's.

Dynamics (``--model``): a shipped model (`tignn_jax.api.shipped_models`; default per scene: ``beam-corot`` for the
beams and ``bunny-corot`` for the bunny, the corotational GENERIC models, stepped by backward Euler and never
creating energy, so guarded for finiteness only), a model folder or ``.npz`` file on
the scene's mesh (another non-linear model is guarded by its training envelope, `tignn_jax.guards.state_guard`,
and a flagged body handed to the scene's rest-linearised model,
`tignn_jax.guards.fallback_step`), or ``fem-newton``: the FEM's own backward-Euler frame step
(`tignn_jax.newton.fem_stepper`, not learned). ``--stand-in`` runs a clearly labelled placeholder instead (damped
springs between all nodes of each element, neither learned nor physically calibrated); its output files say so.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from tignn_jax import DEFAULT_MODEL
from tignn_jax.cli import UsageError

BUNNY_PRESS_NODE = 917
# the corotational GENERIC models: the beams `load_pretrained()`'s default, the bunny its own (large deflections
# keep volume and length). They never create energy, so they run without a guard
DEFAULT_MODELS = {"beam": DEFAULT_MODEL, "two-beams": DEFAULT_MODEL, "bunny": "bunny-corot"}
# the beams' fingertip: a spring from the surface under it (`tignn_jax.mr.forcing.fingertip_spring_forces`; force per
# beam unit of depth) and how deep the synthetic press goes past the rest surface (m; the upper beam lies 0.05 m
# above the lower one)
BEAM_TIP_STIFFNESS = 4.0e4
BEAM_PRESS = 0.1
TWO_BEAMS_PRESS = 0.2   # two beams: B bent onto A and on, so that A bends as well
# the bunny's fingertip (force per unit of the model's length: with the head's compliance under a patch, ~0.14,
# the press settles without overshoot), its deepest press past the rest surface (m) and the top of the stress colours
BUNNY_TIP_STIFFNESS = 5.0
BUNNY_PRESS = 0.007
BUNNY_STRESS_MAX = 0.25
# the two beams' penalty contact: radius (m) and stiffness (force per metre). Inside the one implicit frame of models
# that step bodies together (`tignn_jax.contact_stepper`): stiff enough that B bends A; otherwise explicit
# between the frames (`tignn_jax.mr.forcing.contact_forces`), where a stiffer one rings (docs/research_log.md)
IMPLICIT_CONTACT = (0.015, 2e7)
BEAM_CONTACT = (0.015, 1e5)
# ``--model fem-newton``: the FEM's own backward-Euler frame step (`tignn_jax.newton.fem_stepper`, 2 Newton
# iterations of 3 CG each), not learned, on the mesh of the scene's rest-linearised model
FEM_NEWTON = "fem-newton"
# each scene's rest-linearised FEM (a linear model): the mesh of ``fem-newton`` and the fallback of a non-linear
# learned model's body when it leaves the model's training envelope
LINEAR_OF_SCENE = {"two-beams": "beam-linear", "beam": "beam-linear", "bunny": "bunny-linear"}
SCENES = ("two-beams", "beam", "bunny", "own")
SIZE = (640, 480)           # the default image size (pixels)
FOCAL = 540.0               # the camera's focal length (pixels) at the default width
STAND_IN = "STAND-IN spring dynamics (not the learned model)"


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` subcommand to ``sub`` (the ``tignn`` parser's subparsers)."""
    p = sub.add_parser("demo", help="mixed reality: a fingertip pushes virtual solids (GIF + timings)",
                       description="Mixed reality: a fingertip in a (synthetic) camera image pushes virtual solids "
                                   "simulated by a GENERIC model; writes a GIF, the fingertip track (JSON lines) "
                                   "and per-stage timings (p50/p99).")
    p.add_argument("--scene", choices=SCENES, default=None,
                   help="two cantilevers pushed into each other, one beam, the bunny on a table, or the --model's "
                        "own mesh (default: own for a --model path on another mesh, else two-beams)")
    p.add_argument("--out", default="out/demo", help="output folder (default: %(default)s)")
    p.add_argument("--frames", type=int, default=120, help="frames to play, at least 2 (default: %(default)s)")
    p.add_argument("--size", default=f"{SIZE[0]}x{SIZE[1]}", metavar="WxH",
                   help="image width x height in pixels, each 32..4096; the field of view follows the width "
                        "(default: %(default)s)")
    p.add_argument("--model", default=None,
                   help="a shipped model name (default: beam-corot for the beam scenes, bunny-corot for the bunny), "
                        f"a model folder or .npz file on the scene's mesh, or {FEM_NEWTON!r}: the FEM's own "
                        "backward-Euler step by 2 Newton iterations of 3 CG each (tignn_jax.newton; not learned)")
    p.add_argument("--track", default=None,
                   help="fingertip track, JSON lines (format: tignn_jax.mr.track; default: a synthetic press)")
    p.add_argument("--stand-in", action="store_true",
                   help="run a placeholder instead of a model: damped springs between the nodes of each element, "
                        "neither learned nor physically calibrated (labelled STAND-IN in the output)")
    p.add_argument("--cores", type=int, default=1,
                   help="CPU cores the demo runs on: the process is pinned to that many of the CPUs it may use "
                        "(tignn_jax.mr.pin_cores), with one CPU device per core and the bodies that step on their own "
                        "stepped concurrently, one per core (bodies in contact inside one implicit frame step "
                        "together); 1: all bodies in one program on one core, the steadiest frame times "
                        "(default: %(default)s)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Play the scene and write the GIF, the timings (JSON) and the fingertip track.

    Args:
      args: the parsed options of `register`'s parser.

    Returns:
      0.

    Raises:
      UsageError: a bad option value (named in the message).
      ValueError: a model that cannot be loaded or is not on the scene's mesh.
    """
    if args.frames < 2:
        raise UsageError(f"--frames must be at least 2, got {args.frames}")
    if args.cores < 1:
        raise UsageError(f"--cores must be at least 1, got {args.cores}")
    size = _parse_size(args.size)
    _check_model(args.model, args.stand_in)
    args.scene = args.scene or default_scene(args.model)
    if args.scene == "own" and (args.model is None or args.model == FEM_NEWTON or args.stand_in):
        raise UsageError("--scene own shows a --model's own mesh: give --model DIR (a model trained on your mesh)")
    if args.track and not Path(args.track).is_file():
        raise UsageError(f"--track {args.track!r}: no such file")

    from tignn_jax import mr

    if args.model != FEM_NEWTON:      # the FEM's Newton step is faster with YNNPACK's fusions
        mr.real_time_xla_flags()      # before JAX's first operation: XLA:CPU options of the learned loop
    try:                              # before JAX's first operation: pinned, one CPU device per core
        pinned, devices = mr.real_time_cores(args.cores)
    except ValueError as e:
        raise UsageError(f"--cores {args.cores}: {e}")

    import imageio.v2 as imageio

    scene, dynamics = build_scene(args.scene, args.frames, args.model, args.stand_in, devices=devices, size=size)
    if args.track:
        scene = scene._replace(track=mr.load_track(args.track))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    track_path = out / f"{args.scene}_track.jsonl"
    mr.save_track(track_path, scene.track)
    frames = []
    print(f"scene {args.scene}: {sum(len(b.q0) for b in scene.bodies)} nodes, dynamics: {dynamics}; "
          + (f"pinned to CPU {', '.join(map(str, pinned))}" if pinned else f"{args.cores} core(s), not pinned"))
    _, timings = mr.run(scene, frames=args.frames, write=lambda i, rgb: frames.append(rgb))
    suffix = "_STAND-IN" if dynamics.startswith("STAND-IN") else ""
    gif = out / f"{args.scene}{suffix}.gif"
    t0 = time.perf_counter()
    label = "von Mises stress" if scene.colour_by == "stress" else "displacement |u|"
    vmax = scene.bodies[0].vmax
    swatches = (("clamped", mr.CLAMP_COLOUR),) if any(b.clamped is not None for b in scene.bodies) else ()
    imageio.mimsave(gif, [mr.with_legend(f, 0.0, vmax, f"{label} (data units)", swatches=swatches) for f in frames],
                    duration=1 / 30, loop=0)
    summary = {"scene": args.scene, "dynamics": dynamics, "image": [scene.camera.width, scene.camera.height],
               "cores": args.cores, "pinned_cpus": list(pinned),
               "guard": "fallback" if scene.fallback else "reset",
               **timings.summary(), "gif_encode_s": time.perf_counter() - t0,
               "note": "write = handing the frame to the writer (kept in memory); the GIF is encoded after the loop"}
    timings_path = out / f"{args.scene}{suffix}_timings.json"
    timings_path.write_text(json.dumps(summary, indent=2))
    print(f"{'stage':8s} {'p50 ms':>8s} {'p99 ms':>8s}")
    for k in ("forces", "step", "render", "write", "frame"):
        print(f"{k:8s} {summary[k]['p50_ms']:8.2f} {summary[k]['p99_ms']:8.2f}")
    if summary.get("fused_frames"):
        print(f"(in {summary['fused_frames']} frames forces, step and guard were dispatched together: the forces "
              "time is inside the step's)")
    print(f"{summary['fps_at_p50']:.1f} frames per second at the median frame time")
    if summary.get("guard_trips"):
        after = (f"handed to the rest-linearised model for {scene.fallback_hold} frames each time "
                 "(tignn_jax.guards.fallback_step)" if scene.fallback else "reset to rest each time")
        print(f"WARNING: a body's state left the model's training envelope {summary['guard_trips']} times "
              f"(tignn_jax.guards.state_check); that body was {after}")
    print(f"wrote {gif}, {timings_path} and the fingertip track {track_path}")
    if suffix:
        print("NOTE: no model was used: the motion comes from the STAND-IN spring dynamics (--stand-in).")
    return 0


def build_scene(name: str, frames: int, model: str | None = None, stand_in: bool = False, devices: tuple = (),
                size: tuple = SIZE):
    """One of the demo's scenes, with a synthetic press as its fingertip track.

    Args:
      name: one of ``SCENES``.
      frames: the track's length.
      model: a shipped model name, a model folder or file, or ``FEM_NEWTON`` (default: ``DEFAULT_MODELS[name]``).
      stand_in: step the placeholder spring dynamics (`stand_in_step`) instead of a model.
      devices: with two or more (`tignn_jax.mr.cpu_devices`), a scene of several bodies steps each on its own
        device (``Scene.devices``).
      size: (width, height) of the image in pixels.

    Returns:
      (the `tignn_jax.mr.Scene`, a one-line description of its dynamics).

    Raises:
      ValueError: an unknown scene or model, or a model that is not on the scene's mesh.
    """
    import jax.numpy as jnp
    import numpy as np

    from fem.meshes import beam_mesh, bunny_bottom_nodes, bunny_mesh, clamped_nodes
    from tignn_jax import api, mr

    width, height = (int(s) for s in size)
    if name == "own":
        return own_scene(model, frames, size)
    if name in ("two-beams", "beam"):
        q0, cells, edges = beam_mesh()
        clamped = np.zeros(len(q0), bool)
        clamped[clamped_nodes(q0)] = True
        scale = 0.005
        up = mr.rotation_matrix([1.0, 0.0, 0.0], -np.pi / 2)        # model z (the load axis) -> world y (up)
        turn = mr.rotation_matrix([0.0, 0.0, 1.0], np.pi / 2)       # B: x_B = 36 - y, y_B = x - 25, z_B = z + 20
        offset_b = np.asarray(up) @ np.array([36.0, -25.0, 20.0]) * scale
        base = np.array([0.0, 0.02, 0.0])
        poses = [mr.model_matrix(base, up, scale), mr.model_matrix(base + offset_b, np.asarray(up) @ turn, scale)]
        eye, target = [0.33, 0.27, 0.28], [0.13, 0.06, -0.03]
        press_body, press_at, normal = 1, [38.0, 5.0, 10.0], [0.0, 0.0, 1.0]  # B's free end, top face
        tip_radius, tip_force, vmax = 3.0, 2.0e4, 6.0e4
        tip_stiffness, press = BEAM_TIP_STIFFNESS, TWO_BEAMS_PRESS
        if name == "beam":
            poses = poses[:1]
            press_body, press = 0, BEAM_PRESS
    elif name == "bunny":
        q0, cells, edges = bunny_mesh()
        clamped = np.zeros(len(q0), bool)
        clamped[bunny_bottom_nodes(q0)] = True
        scale = 0.01
        poses = [mr.model_matrix([0.1, 0.0, 0.0], mr.rotation_matrix([1.0, 0.0, 0.0], -np.pi / 2), scale)]
        eye, target = [0.17, 0.16, 0.22], [0.1, 0.05, 0.0]
        # the top of the head (node 917), not an ear: a unit load on an ear tip folds it over (|u| up to 37 of
        # the bunny's 49; such cases are left out of the bunny model's training)
        press_body, press_at, normal = 0, q0[BUNNY_PRESS_NODE], [0.0, 0.0, 1.0]
        # a spring fingertip over a pad of 1 cm, the data's patch (radius 5 in the model's units)
        tip_radius, tip_force, vmax = 1.0, 1.0, BUNNY_STRESS_MAX
        tip_stiffness, press = BUNNY_TIP_STIFFNESS, BUNNY_PRESS
    else:
        raise ValueError(f"scene must be one of {SCENES}, got {name!r}")
    q0 = np.asarray(q0, np.float32)
    model = model or DEFAULT_MODELS[name]
    if stand_in:
        step_fn, dynamics, units = stand_in_step(q0, cells, clamped), STAND_IN, 1.0
    elif model == FEM_NEWTON:
        step_fn, dynamics, q0, units = _fem_newton(LINEAR_OF_SCENE[name], q0)
    else:
        step_fn, dynamics, q0, units = _dynamics(model, q0, LINEAR_OF_SCENE[name])
    if units != 1.0:   # the model's mesh is this mesh scaled (the bunny data use the scan's scale)
        poses = [np.asarray(m) @ np.diag([1 / units] * 3 + [1.0]) for m in poses]
        press_at, tip_radius = np.asarray(press_at) * units, tip_radius * units
    triangles = mr.surface_triangles(cells, q0)
    view = np.asarray(mr.look_at(eye, target, [0.0, 1.0, 0.0]))
    focal = FOCAL * width / SIZE[0]
    cam = mr.Camera(fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height, near=0.05,
                    far=5.0, view=view)
    z0 = np.concatenate([q0, np.zeros((len(q0), 9), np.float32)], axis=1)
    bodies = tuple(mr.Body(q0=q0, triangles=triangles, model=np.asarray(m), z=z0, step_fn=step_fn,
                           tip_radius=tip_radius, tip_force=tip_force, vmax=vmax, tip_stiffness=tip_stiffness,
                           guard=getattr(step_fn, "guard", None), clamped=clamped) for m in poses)
    world_point = np.asarray(mr.transform_points(poses[press_body], jnp.asarray([press_at], jnp.float32)))[0]
    world_normal = np.asarray(poses[press_body])[:3, :3] @ np.asarray(normal, np.float64)
    world_normal /= np.linalg.norm(world_normal)
    track = mr.press_track(cam, world_point, world_normal, frames, approach=0.03, press=press)
    fallback = getattr(step_fn, "fallback", None)
    scene = mr.Scene(bodies=bodies, camera=cam, background=mr.table_background(cam), track=track,
                     contact_radius=BEAM_CONTACT[0], contact_stiffness=BEAM_CONTACT[1],
                     fallback=(fallback,) * len(bodies) if fallback is not None else (),
                     handover="next-frame")   # a trip frame runs one learned step, not that and a fallback step
    implicit = getattr(step_fn, "params", None)
    if len(bodies) > 1 and implicit is not None and hasattr(implicit["model"], "step_together"):
        # the contact inside the bodies' one implicit frame (one solve, so not on several cores)
        contact = api.contact_stepper(implicit, poses, *IMPLICIT_CONTACT)
        scene = scene._replace(step=contact, contact_radius=0.0)
        return scene, dynamics + " (contact in the implicit step)"
    if len(devices) > 1 and len(bodies) > 1:
        scene = scene._replace(devices=tuple(devices))
        dynamics += f" (bodies on {min(len(devices), len(bodies))} cores)"
    return scene, dynamics


def default_scene(model: str | None) -> str:
    """``own`` where ``model`` is a model path whose mesh is none of the paper's scenes', else ``two-beams``."""
    if model is None or model == FEM_NEWTON or not Path(model).exists():
        return "two-beams"
    import numpy as np

    from fem.meshes import beam_mesh, bunny_mesh

    path = Path(model)      # read with numpy alone: JAX must not start before the cores are pinned
    if path.is_dir():
        path = path / "model.npz" if (path / "model.npz").exists() else path / "model" / "model.npz"
    try:
        with np.load(path, allow_pickle=False) as raw:
            params = {"mesh": {"q0": np.asarray(raw["mesh/q0"], np.float64)}}
    except (OSError, KeyError, ValueError):
        raise UsageError(f"--model {model}: not a model file or folder (no {path})") from None
    for mesh, scene in ((beam_mesh, "two-beams"), (bunny_mesh, "bunny")):
        if _model_units(params, np.asarray(mesh()[0], np.float64))[1] > 0:
            return scene
    return "own"


def own_scene(model: str, frames: int, size: tuple = SIZE):
    """The demo scene of a model on its own mesh (module docstring, ``own``).

    Args:
      model: a model folder, run folder or file whose mesh keeps its cells.
      frames: the track's length.
      size: (width, height) of the image in pixels.

    Returns:
      (the `tignn_jax.mr.Scene`, a one-line description of its dynamics).

    Raises:
      ValueError: a model without cells (written before models kept them), or a mesh without free surface nodes.
    """
    import jax.numpy as jnp
    import numpy as np

    from fem.meshes import surface_nodes_and_normals
    from tignn_jax import api, mr

    params, _ = api.load_pretrained(model)
    mesh = params["mesh"]
    if "cells" not in mesh:
        raise ValueError(f"model {model!r} keeps no cells to draw its surface from: retrain it with tignn train")
    q0 = np.asarray(mesh["q0"], np.float64)
    cells = np.asarray(mesh["cells"])
    step_fn, dynamics, q0_model, _ = _dynamics(model, q0.astype(np.float32), "")
    lo, hi = q0.min(axis=0), q0.max(axis=0)
    extent = float(np.max(hi - lo))
    scale = 0.2 / extent                                   # the body is 20 cm across
    up = np.asarray(mr.rotation_matrix([1.0, 0.0, 0.0], -np.pi / 2))   # model z -> world y (up)
    centre = 0.5 * (lo + hi)
    translation = -up @ (scale * np.array([centre[0], centre[1], lo[2]]))   # the bottom centre at the origin
    pose = np.asarray(mr.model_matrix(translation, up, scale))
    world = q0 @ (scale * up).T + translation
    w_lo, w_hi = world.min(axis=0), world.max(axis=0)
    target = 0.5 * (w_lo + w_hi)
    radius = 0.5 * float(np.linalg.norm(w_hi - w_lo))
    width, height = (int(v) for v in size)
    focal = FOCAL * width / SIZE[0]
    half_fov = np.arctan(0.5 * min(width, height) / focal)
    direction = np.array([0.55, 0.6, 0.58]) / np.linalg.norm([0.55, 0.6, 0.58])
    eye = target + direction * 1.15 * radius / np.sin(half_fov)
    view = np.asarray(mr.look_at(eye, target, [0.0, 1.0, 0.0]))
    cam = mr.Camera(fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height,
                    near=0.02 * radius, far=10.0 * (radius + float(np.linalg.norm(eye - target))), view=view)
    nodes, normals = surface_nodes_and_normals(q0, cells)
    free = np.asarray(mesh["node_type"])[nodes] == 0
    nodes, normals = nodes[free], normals[free]
    if not len(nodes):
        raise ValueError(f"model {model!r}: its mesh has no free surface node to press")
    clamped = np.where(np.asarray(mesh["node_type"]) != 0)[0]
    far = (np.min(np.linalg.norm(q0[nodes][:, None] - q0[clamped][None], axis=-1), axis=1) if len(clamped)
           else np.zeros(len(nodes)))
    world_normals = normals @ up.T
    to_eye = eye - world[nodes]
    facing = np.sum(world_normals * to_eye, axis=1) / np.linalg.norm(to_eye, axis=1)   # cosine towards the eye
    score = np.where(facing > 0.3, far, -np.inf)
    pick = int(np.argmax(score)) if np.isfinite(score).any() else int(np.argmax(far))
    edges = np.linalg.norm(q0[mesh["senders"]] - q0[mesh["receivers"]], axis=1)
    tip_radius = 1.5 * float(np.median(edges))
    tip_force = 0.5 * float(np.asarray(params["envelope"]["f_max"]).ravel()[0])
    sigma_scale = float(np.max(np.asarray(params["envelope"]["z_dev_max"])[6:9]))
    triangles = mr.surface_triangles(cells, q0_model)
    z0 = np.concatenate([q0_model, np.zeros((len(q0_model), 9), np.float32)], axis=1)
    body = mr.Body(q0=q0_model, triangles=triangles, model=pose, z=z0, step_fn=step_fn, tip_radius=tip_radius,
                   tip_force=tip_force, vmax=max(sigma_scale, 1e-12), guard=getattr(step_fn, "guard", None),
                   clamped=np.asarray(mesh["node_type"]) != 0)
    point = np.asarray(mr.transform_points(pose, jnp.asarray([q0[nodes[pick]]], jnp.float32)))[0]
    track = mr.press_track(cam, point, world_normals[pick], frames, approach=0.15 * 0.2, press=0.05 * 0.2)
    fallback = getattr(step_fn, "fallback", None)
    scene = mr.Scene(bodies=(body,), camera=cam, background=mr.table_background(cam), track=track,
                     contact_radius=0.0, fallback=(fallback,) if fallback is not None else (),
                     handover="next-frame")
    return scene, dynamics + f" on its own mesh ({len(q0)} nodes)"


def stand_in_step(q0, cells, clamped, stiffness=5.0e4, damping=0.03, dt=0.05, substeps=8, modulus=9.3e5):
    """The STAND-IN dynamics, not a learned model: damped springs between every pair of nodes of each element.

    Each spring has the axial stiffness ``stiffness`` / rest length (a stable truss for hex8 and tet4); clamped
    nodes are fixed; each node's mass is lumped from its springs so that each of the ``substeps`` explicit
    sub-steps of a frame ``dt`` is stable on any mesh (ω_max · dt / substeps <= 1, by Gershgorin's bound); σ gets
    ``modulus`` × the mean absolute spring strain at each node in S11 (something to colour by, not a stress).

    Args:
      q0: [N, 3] rest positions.
      cells: [E, 8] or [E, 4] element node ids.
      clamped: [N] bool, fixed nodes.
      stiffness: spring stiffness × rest length.
      damping: velocity damping per sub-step (fraction).
      dt: the frame's time step.
      substeps: explicit sub-steps per frame.
      modulus: the factor from strain to the coloured S11.

    Returns:
      ``step(z [N, 12], f [N, 3]) -> z_next [N, 12]``, jit-able.
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    k = cells.shape[1]
    local = np.array([(a, b) for a in range(k) for b in range(a + 1, k)])
    pairs = np.unique(np.sort(np.asarray(cells)[:, local].reshape(-1, 2), axis=1), axis=0)
    rest_np = np.linalg.norm(q0[pairs[:, 1]] - q0[pairs[:, 0]], axis=1)
    spring = stiffness / rest_np
    node_k = np.zeros(len(q0))
    np.add.at(node_k, pairs[:, 0], spring)
    np.add.at(node_k, pairs[:, 1], spring)
    h = dt / substeps
    mass = jnp.asarray(4.0 * h ** 2 * np.maximum(node_k, 1e-12), jnp.float32)[:, None]  # Gershgorin bound
    i, j = jnp.asarray(pairs[:, 0]), jnp.asarray(pairs[:, 1])
    rest = jnp.asarray(rest_np, jnp.float32)
    free = jnp.asarray(~np.asarray(clamped), jnp.float32)[:, None]
    degree = jnp.maximum(jnp.zeros(len(q0)).at[i].add(1.0).at[j].add(1.0), 1.0)

    def step(z, f):
        def sub(_, qv):
            q, v = qv
            d = q[j] - q[i]
            length = jnp.linalg.norm(d, axis=1)
            fe = (stiffness * (length - rest) / (rest * length))[:, None] * d
            f_int = jnp.zeros_like(q).at[i].add(fe).at[j].add(-fe)
            v = free * ((1.0 - damping) * v + h * (f_int + f) / mass)
            return q + h * v, v

        q, v = jax.lax.fori_loop(0, substeps, sub, (z[:, :3], z[:, 3:6]))
        length = jnp.linalg.norm(q[j] - q[i], axis=1)
        strain = jnp.abs(length - rest) / rest
        s11 = modulus * jnp.zeros(len(q)).at[i].add(strain).at[j].add(strain) / degree
        sigma = jnp.zeros((len(q), 6)).at[:, 0].set(s11)
        return jnp.concatenate([q, v, sigma], axis=1)

    return step


def _parse_size(text: str) -> tuple:
    """(width, height) from ``--size`` WxH."""
    try:
        width, height = (int(t) for t in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must be WIDTHxHEIGHT in pixels, e.g. 640x480, got {text!r}") from None
    if not (32 <= width <= 4096 and 32 <= height <= 4096):
        raise UsageError(f"--size {text}: width and height must each be 32..4096 pixels")
    return width, height


def _check_model(model: str | None, stand_in: bool) -> None:
    """Refuse an unknown ``--model`` before JAX starts (a shipped name, an existing path or ``FEM_NEWTON``), and a
    model whose file says it is not for interaction (``info["interactive"]`` false: the paper's reproduction
    ``beam-tignn``), since every scene is pushed by a fingertip."""
    if stand_in:
        if model is not None:
            raise UsageError(f"--stand-in runs the placeholder dynamics instead of a model; drop --model {model}")
        return
    if model is None or model == FEM_NEWTON:
        return
    from tignn_jax import api

    shipped = api.shipped_models()
    if model not in shipped and not Path(model).exists():
        raise UsageError(f"--model {model!r}: no such model; shipped models: {', '.join(shipped)} (or a model "
                         f"folder or .npz file, or {FEM_NEWTON!r})")
    if not api.for_interaction(model):
        raise UsageError(f"--model {model}: {api.NOT_INTERACTIVE}; the demo's models: "
                         f"{', '.join(sorted(set(DEFAULT_MODELS.values())))}")


def _dynamics(model_name: str, q0, linear_name: str):
    """A model's step for the scene's bodies.

    A model of a class that is stable by construction (``stable_by_construction``: the linear and the
    corotational GENERIC models, whose steps never create energy) is guarded for finiteness only; any other by its
    training envelope (`tignn_jax.guards.state_guard`), with the scene's rest-linearised model ``linear_name`` as
    the fallback of a flagged body where that is on the model's mesh (`tignn_jax.guards.fallback_step`).

    Returns:
      (step ``(z, forces) -> z`` with the attribute ``guard`` (``Body.guard``) and, where there is one,
      ``fallback``; the description; the model's rest positions [N, 3] float32; model units per mesh unit).

    Raises:
      ValueError: no such model, or a model on another mesh than ``q0`` (up to a scale).
    """
    import numpy as np

    from tignn_jax import api, guards

    params, _ = api.load_pretrained(model_name)
    mesh_q0, units = _model_units(params, q0)
    if units <= 0:
        raise ValueError(f"model {model_name!r} was trained on a mesh of {len(mesh_q0)} nodes, not this scene's "
                         f"mesh of {len(q0)} nodes")
    fn = api.stepper(params)

    def step(z, forces):
        return fn(z, forces)

    step.params = params

    described = f"model {model_name}"
    if getattr(params["model"], "stable_by_construction", False):
        step.guard = _finite_guard
    else:
        step.guard = guards.state_guard(params, tolerance=1.5)
        try:
            linear, _ = api.load_pretrained(linear_name) if linear_name else (None, None)
            if linear is not None:
                step.fallback = guards.fallback_step(params, linear)
                described += f" (fallback {linear_name})"
        except ValueError:   # not on the linear model's mesh: a flagged body is reset to rest
            pass
    return step, described, mesh_q0.astype(np.float32), units


def _model_units(params, q0):
    """(the model's rest positions [N, 3], model units per mesh unit; 0 where the model's mesh is not ``q0``
    scaled)."""
    import numpy as np

    mesh_q0 = np.asarray(params["mesh"]["q0"], np.float64)
    units = float(np.sum(mesh_q0 * q0) / np.sum(q0 * q0)) if mesh_q0.shape == q0.shape else 0.0
    if units > 0 and np.allclose(mesh_q0, units * q0, atol=1e-4 * max(units, 1.0) * np.abs(q0).max()):
        return mesh_q0, units
    return mesh_q0, 0.0


def _finite_guard(z):
    """True where a state is not finite: the guard of a step that is stable by construction."""
    import jax.numpy as jnp

    return ~jnp.all(jnp.isfinite(z))


def _fem_newton(linear_name, q0, iterations: int = 3, newton: int = 2):
    """(step, description, q0 in the model's units, units) of ``--model fem-newton``: the FEM's backward-Euler
    frame step (`tignn_jax.newton.fem_stepper`) on the mesh of the shipped rest-linearised model ``linear_name``.
    Its guard flags a non-finite state only (the body is then reset to rest): the FEM has no training envelope."""
    import numpy as np

    from tignn_jax import api, newton as nw

    linear, _ = api.load_pretrained(linear_name)
    mesh_q0, units = _model_units(linear, q0)
    if units <= 0:
        raise ValueError(f"{linear_name!r} is not on this scene's mesh")
    fn = nw.fem_stepper(linear, iterations=iterations, newton=newton)

    def step(z, forces):
        return fn(z, forces)

    step.guard = _finite_guard
    described = (f"FEM backward Euler, {newton} Newton x {iterations} CG iterations per frame (tignn_jax.newton, "
                 f"on {linear_name}'s mesh; not learned)")
    return step, described, mesh_q0.astype(np.float32), units
