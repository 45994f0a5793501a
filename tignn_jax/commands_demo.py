"""`tignn demo`: a fingertip in a (synthetic) camera image pushes virtual solids; writes a GIF and timings.

Scenes:
- ``two-beams``: the paper's configuration (``fem.scenes.two_beams_scene``): two copies of the 40x10x10 beam
  (shown 0.2 m long), the lower one A clamped at x = 0, the upper one B turned 90° about the vertical and lying
  across A's free half with a gap of 10 (5 cm). The fingertip presses B's free end down onto A; each body steps
  in its own model frame, and they interact through ``ar.contact_forces``. The demo runs on ``--cores`` cores
  (default 1), the process pinned to them (``scene.pin_cores``). With two or more, each beam steps on its own
  CPU device, concurrently (``Scene.devices``); with one, both bodies' frames run in one program (each body
  its own step, in its own ``lax.cond``: faster than one batched graph of both, see
  ``benchmarks/results/bodies_one_program.md``).
- ``beam``: beam A alone, pressed down at its free end.
- ``bunny``: the Stanford bunny (10 cm tall) standing on the table, base clamped, pushed on its back with about
  the unit point load of the training cases.

Dynamics: the shipped learned model (``--model``, default per scene: ``beam`` for the beams, ``bunny`` for the
bunny, both learned linear GENERIC models stepped by backward Euler; ``--model beam-abaqus`` runs the non-linear
explicit TIGNN trained on the Abaqus data, with its guard and fallback). If no shipped model is found, a clearly
labelled STAND-IN (damped springs between all nodes of each element, not the learned model and not physically
calibrated) runs instead so the pipeline can still be seen; the summary and file names say so.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

BUNNY_PRESS_NODE = 917
# the learned linear GENERIC models (`tignn_jax.linear_generic`): stable without a guard, within every budget;
# ``--model beam-abaqus`` runs the non-linear explicit TIGNN trained on the Abaqus data instead
DEFAULT_MODELS = {"beam": "beam", "two-beams": "beam", "bunny": "bunny"}
# the rest-linearised FEM a learned model's body is handed to when it leaves its training envelope
# (api.fallback_step); models without one are reset to rest instead
FALLBACKS = {"beam-abaqus": "beam-linear", "beam-abaqus-64x2": "beam-linear", "beam-abaqus-small": "beam-linear"}
# ``--model fem-newton``: the FEM's own backward-Euler frame step (`tignn_jax.newton.fem_stepper`, 2 Newton
# iterations of 3 CG each), not learned, on the mesh of the scene's rest-linearised model
FEM_NEWTON = "fem-newton"
LINEAR_OF_SCENE = {"two-beams": "beam-linear", "beam": "beam-linear", "bunny": "bunny-linear"}
SCENES = ("two-beams", "beam", "bunny")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="mixed reality: a fingertip pushes virtual solids (GIF + timings)",
                       description="Mixed reality: a fingertip in a (synthetic) camera image pushes virtual solids "
                                   "simulated by the shipped model; writes a GIF, the fingertip track (JSON lines) "
                                   "and per-stage timings (p50/p99).")
    p.add_argument("--scene", choices=SCENES, default="two-beams",
                   help="two cantilevers pushed into each other, one beam, or the bunny on a table "
                        "(default: %(default)s)")
    p.add_argument("--out", default="out/demo", help="output folder (default: %(default)s)")
    p.add_argument("--frames", type=int, default=120, help="frames to play (default: %(default)s)")
    p.add_argument("--model", default=None,
                   help=f"shipped model name or path (default: per scene, {DEFAULT_MODELS}), or {FEM_NEWTON!r}: the FEM's own "
                        "backward-Euler step by 2 Newton iterations of 3 CG each (tignn_jax.newton; not learned)")
    p.add_argument("--track", default=None, help="fingertip track, JSON lines (default: a synthetic press)")
    p.add_argument("--stand-in", action="store_true", help="use the stand-in dynamics even if a model exists")
    p.add_argument("--cores", type=int, default=1,
                   help="CPU cores the demo runs on: the process is pinned to that many of the CPUs it may use "
                        "(scene.pin_cores), with one CPU device per core and the bodies stepped concurrently, one "
                        "per core; 1: all bodies in one program on one core, the steadiest frame times measured "
                        "(benchmarks/results/pinning.md) (default: %(default)s)")
    p.set_defaults(func=run)


def run(args) -> int:
    import imageio.v2 as imageio

    from tignn_jax import scene as sc

    if args.frames < 2:
        raise SystemExit(f"--frames must be at least 2, got {args.frames}")
    cores = args.cores
    if cores < 1:
        raise SystemExit(f"--cores must be at least 1, got {cores}")
    if args.model != FEM_NEWTON:      # the FEM's step is 3x slower without YNNPACK's fusions (session 38)
        sc.real_time_xla_flags()      # before JAX's first operation: XLA:CPU options of the learned loop
    try:                              # before JAX's first operation: pinned, one CPU device per core
        pinned, devices = sc.real_time_cores(cores)
    except ValueError as e:
        raise SystemExit(f"--cores {cores}: {e}")
    scene, dynamics = build_scene(args.scene, args.frames, args.model, args.stand_in, devices=devices)
    if args.track:
        scene = scene._replace(track=sc.load_track(args.track))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    track_path = out / f"{args.scene}_track.jsonl"
    sc.save_track(track_path, scene.track)  # the fingertip track in the documented format (tignn_jax/scene.py)
    frames = []
    print(f"scene {args.scene}: {sum(len(b.q0) for b in scene.bodies)} nodes, dynamics: {dynamics}; "
          + (f"pinned to CPU {', '.join(map(str, pinned))}" if pinned else f"{cores} core(s), not pinned"))
    _, timings = sc.run(scene, frames=args.frames, write=lambda i, rgb: frames.append(rgb))
    suffix = "_STAND-IN" if dynamics.startswith("STAND-IN") else ""
    gif = out / f"{args.scene}{suffix}.gif"
    t0 = time.perf_counter()
    imageio.mimsave(gif, frames, duration=1 / 30, loop=0)
    summary = {"scene": args.scene, "dynamics": dynamics, "image": [scene.camera.width, scene.camera.height],
               "cores": cores, "pinned_cpus": list(pinned),
               "guard": "fallback" if scene.fallback else "reset",
               **timings.summary(), "gif_encode_s": time.perf_counter() - t0,
               "note": "write = handing the frame to the writer (kept in memory); the GIF is encoded after the loop"}
    (out / f"{args.scene}{suffix}_timings.json").write_text(json.dumps(summary, indent=2))
    print(f"{'stage':8s} {'p50 ms':>8s} {'p99 ms':>8s}")
    for k in ("forces", "step", "render", "write", "frame"):
        print(f"{k:8s} {summary[k]['p50_ms']:8.2f} {summary[k]['p99_ms']:8.2f}")
    if summary.get("fused_frames"):
        print(f"(in {summary['fused_frames']} frames forces, step and guard were dispatched together: the forces "
              "time is inside the step's)")
    print(f"{summary['fps_at_p50']:.1f} frames per second at the median frame time")
    if summary.get("guard_trips"):
        after = (f"handed to the rest-linearised FEM for {scene.fallback_hold} frames each time (api.fallback_step)"
                 if scene.fallback else "reset to rest each time")
        print(f"WARNING: a body's state left the model's training envelope {summary['guard_trips']} times "
              f"(api.state_check); that body was {after}")
    print(f"wrote {gif}, {out / f'{args.scene}{suffix}_timings.json'} and the fingertip track {track_path}")
    if suffix:
        print("NOTE: no shipped model was used: the motion comes from the STAND-IN spring dynamics.")
    return 0


def build_scene(name: str, frames: int, model: str | None = None, stand_in: bool = False, devices: tuple = ()):
    """(Scene, dynamics description) for ``name`` in ``SCENES``. With two or more ``devices`` (``scene.
    cpu_devices``) a scene of several bodies steps each on its own device (``Scene.devices``)."""
    import jax.numpy as jnp
    import numpy as np

    from fem.meshes import beam_mesh, bunny_bottom_nodes, bunny_mesh, clamped_nodes
    from tignn_jax import ar
    from tignn_jax import scene as sc
    from tignn_jax.render import surface_triangles

    width, height = 640, 480
    if name in ("two-beams", "beam"):
        q0, cells, edges = beam_mesh()
        clamped = np.zeros(len(q0), bool)
        clamped[clamped_nodes(q0)] = True
        scale = 0.005
        up = ar.rotation_matrix([1.0, 0.0, 0.0], -np.pi / 2)        # model z (the load axis) -> world y (up)
        turn = ar.rotation_matrix([0.0, 0.0, 1.0], np.pi / 2)       # B: x_B = 36 - y, y_B = x - 25, z_B = z + 20
        offset_b = np.asarray(up) @ np.array([36.0, -25.0, 20.0]) * scale
        base = np.array([0.0, 0.02, 0.0])
        poses = [ar.model_matrix(base, up, scale), ar.model_matrix(base + offset_b, np.asarray(up) @ turn, scale)]
        eye, target = [0.33, 0.27, 0.28], [0.13, 0.06, -0.03]
        press_body, press_at, normal = 1, [38.0, 5.0, 10.0], [0.0, 0.0, 1.0]  # B's free end, top face
        if name == "beam":
            poses = poses[:1]
            press_body = 0
        tip_radius, tip_force, vmax = 3.0, 2.0e4, 6.0e4
    elif name == "bunny":
        q0, cells, edges = bunny_mesh()
        clamped = np.zeros(len(q0), bool)
        clamped[bunny_bottom_nodes(q0)] = True
        scale = 0.01
        poses = [ar.model_matrix([0.1, 0.0, 0.0], ar.rotation_matrix([1.0, 0.0, 0.0], -np.pi / 2), scale)]
        eye, target = [0.17, 0.16, 0.22], [0.1, 0.05, 0.0]
        # the top of the head (node 917), not an ear: a unit load on an ear tip folds it over (|u| up to 37 of
        # the bunny's 49; such cases are left out of the bunny model's training), the head deflects by about 1
        press_body, press_at, normal = 0, q0[BUNNY_PRESS_NODE], [0.0, 0.0, 1.0]
        tip_radius, tip_force, vmax = 0.35, 1.0, 0.5   # about one node at the training loads' unit force
    else:
        raise ValueError(f"scene must be 'two-beams' or 'bunny', got {name!r}")
    q0 = np.asarray(q0, np.float32)
    model = model or DEFAULT_MODELS[name]
    if model == FEM_NEWTON and not stand_in:
        step_fn, dynamics, q0, units = _fem_newton(LINEAR_OF_SCENE[name], q0)
    else:
        step_fn, dynamics, q0, units = _dynamics(model, stand_in, q0, cells, edges, clamped)
    if units != 1.0:   # the model's mesh is this mesh scaled (the bunny data use the scan's scale)
        poses = [np.asarray(m) @ np.diag([1 / units] * 3 + [1.0]) for m in poses]
        press_at, tip_radius = np.asarray(press_at) * units, tip_radius * units
    triangles = surface_triangles(cells, q0)
    view = np.asarray(ar.look_at(eye, target, [0.0, 1.0, 0.0]))
    cam = sc.Camera(fx=540.0, fy=540.0, cx=width / 2, cy=height / 2, width=width, height=height, near=0.05,
                    far=5.0, view=view)
    z0 = np.concatenate([q0, np.zeros((len(q0), 9), np.float32)], axis=1)
    bodies = tuple(sc.Body(q0=q0, triangles=triangles, model=np.asarray(m), z=z0, step_fn=step_fn,
                           tip_radius=tip_radius, tip_force=tip_force, vmax=vmax,
                           guard=getattr(step_fn, "guard", None)) for m in poses)
    world_point = np.asarray(ar.transform_points(poses[press_body], jnp.asarray([press_at], jnp.float32)))[0]
    world_normal = np.asarray(poses[press_body])[:3, :3] @ np.asarray(normal, np.float64)
    world_normal /= np.linalg.norm(world_normal)
    track = sc.press_track(cam, world_point, world_normal, frames, approach=0.03, press=0.012)
    fallback = getattr(step_fn, "fallback", None)
    scene = sc.Scene(bodies=bodies, camera=cam, background=sc.table_background(cam), track=track,
                     contact_radius=0.006, contact_stiffness=5e7,
                     fallback=(fallback,) * len(bodies) if fallback is not None else (),
                     handover="next-frame")   # a trip frame runs one learned step, not that and a fallback step
    if len(devices) > 1 and len(bodies) > 1:
        scene = scene._replace(devices=tuple(devices))
        dynamics += f" (bodies on {min(len(devices), len(bodies))} cores)"
    return scene, dynamics


def _dynamics(model_name, stand_in, q0, cells, edges, clamped):
    """(one body's step (z, forces) -> z, with attributes ``guard`` (``Body.guard``) and ``fallback``
    (``api.fallback_step``) where the model has them; description; q0 in the model's units; model units per
    mesh unit)."""
    import numpy as np

    if not stand_in:
        try:
            from tignn_jax import api
            params, graph = api.load_pretrained(model_name)
        except (ValueError, FileNotFoundError, ImportError, AttributeError) as err:
            print(f"no shipped model {model_name!r} ({err}); using the STAND-IN dynamics")
        else:
            mesh_q0, units = _model_units(params, q0)
            if units > 0:
                fn = api.stepper(params)

                def step(z, forces):
                    return fn(z, forces)

                # each body's own flag (Body.guard); a model whose network is zero steps a linear system with a PSD
                # energy by backward Euler (the learned `bunny`, the rest-linearised FEM): stable by construction,
                # so only a non-finite state is flagged, as for the FEM, not a state beyond the training envelope
                step.guard = _finite_guard if api.network_is_zero(params) else api.state_guard(params)
                if model_name in FALLBACKS:
                    linear, _ = api.load_pretrained(FALLBACKS[model_name])
                    step.fallback = api.fallback_step(params, linear)
                described = f"model {model_name}" + (f" (fallback {FALLBACKS[model_name]})"
                                                     if model_name in FALLBACKS else "")
                return step, described, mesh_q0.astype(np.float32), units
            print(f"model {model_name!r} was trained on another mesh; using the STAND-IN dynamics")
    return stand_in_step(q0, cells, clamped), "STAND-IN spring dynamics (not the learned model)", q0, 1.0


def _model_units(params, q0):
    """(the model's rest positions [N,3], model units per mesh unit; 0 where the model's mesh is not ``q0``
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
    frame step (`newton.fem_stepper`) on the mesh of the shipped rest-linearised model ``linear_name``. Its
    guard flags a non-finite state only (the body is then reset to rest): the FEM has no training envelope."""
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


def stand_in_step(q0, cells, clamped, stiffness=5.0e4, damping=0.03, dt=0.05, substeps=8, modulus=9.3e5):
    """STAND-IN dynamics, not the learned model: damped springs (axial stiffness ``stiffness`` / rest length)
    between every pair of nodes of each element (a stable truss for hex8 and tet4), clamped nodes fixed, each
    node's mass lumped from its springs so that each of the ``substeps`` explicit sub-steps of a frame ``dt`` is
    stable on any mesh (omega_max dt_sub <= 1); sigma gets ``modulus`` x the mean absolute spring strain at each
    node in S11 (a colourable stand-in for stress). (z [N,12], f [N,3]) -> z."""
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
