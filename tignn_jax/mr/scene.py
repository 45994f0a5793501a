"""Mixed-reality scenes and their real-time loop: fingertips in a camera image push virtual solids.

A `Scene` is a tuple of `Body` (surface mesh, pose, state z and a ``step_fn(z, forces) -> z``), a
`tignn_jax.mr.camera.Camera`, a `tignn_jax.mr.background.Background` (the real RGB and depth image) and a
fingertip track (`tignn_jax.mr.track`). `run` plays it frame by frame::

    unproject fingertips -> fingertip + contact forces -> step every body -> render -> write frame

timed as the stages ``forces`` (unprojection, fingertip and contact forces), ``step``, ``render`` (shade,
rasterise, hand proxy, occlusion), ``write`` (copy to the host and the caller's writer) and the whole ``frame``.
Each stage is jitted and compiled before the first timed frame; shapes never change afterwards (the track is
padded to a fixed number of fingertips), so nothing is recompiled unless the rasteriser's fragment buffer has to
grow (``Timings.reallocations``). `run` returns per-stage timings (p50/p99).

Units: the world and the camera are in metres (the depth camera's unit). A body's state lives in its model frame
and units (q and forces as the body's model was trained); ``Body.model`` maps model to world (with a scale).
"""
from __future__ import annotations

import gc
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax.mr.background import Background, hand_proxy, rest_on_surface
from tignn_jax.mr.camera import Camera, camera_projection, project, transform_points, unproject
from tignn_jax.mr.forcing import contact_forces, fingertip_forces, fingertip_pads, fingertip_spring_forces
from tignn_jax.mr.render import colour_map, draw_mesh, fragment_capacity, occlude, von_mises
from tignn_jax.mr.surface import surface_nodes, vertex_normals

StepFn = Callable[[jax.Array, jax.Array], jax.Array]


CLAMP_COLOUR = (0.62, 0.24, 0.18)   # the supports' colour (brick red: outside the colour map and the table's greys)


class Body(NamedTuple):
    """A virtual solid.

    Attributes:
      q0: [N, 3] reference positions (model units).
      triangles: [T, 3] outward surface triangles (`tignn_jax.mr.surface.surface_triangles`).
      model: [4, 4] pose, model -> world (`tignn_jax.mr.camera.model_matrix`).
      z: [N, 12] initial state (q, v, σ with σ in S11, S22, S33, S12, S13, S23 order).
      step_fn: ``step_fn(z [N, 12], forces [N, 3]) -> z``, one frame of the body's simulator (a model's
        `tignn_jax.api.stepper`, or anything with that signature), traceable by ``jax.jit`` (no Python-side
        checks on values: `run` jits all bodies' steps together).
      tip_radius: the fingertip's contact radius (model units; `tignn_jax.mr.forcing.fingertip_forces`).
      tip_force: the fingertip's force per node (model force units).
      vmax: the value shown at the top of the colour map (the von Mises stress of σ, or the displacement
        magnitude, see ``Scene.colour_by``), whose bottom is 0.
      guard: optional jit-able ``z -> bool``, True where this body's new state must not be shown (as
        ``Scene.guard``, for one body; with ``Scene.devices`` it runs in the body's own step program on its
        device).
      clamped: optional [N] bool, the nodes held fixed (the model's node_type ≠ 0): drawn in ``CLAMP_COLOUR``
        instead of the colour map, so the supports show.
      tip_stiffness: 0: the fingertip puts ``tip_force`` on every node within ``tip_radius`` (the training loads'
        law, `tignn_jax.mr.forcing.fingertip_forces`); positive: it pushes along ``Scene.press_direction`` as a
        spring of this stiffness (model force units per model length) from the surface under it, spread over a
        pad of radius ``tip_radius`` (`tignn_jax.mr.forcing.fingertip_spring_forces`), so a deep press bends the
        body instead of passing through it.
    """
    q0: np.ndarray
    triangles: np.ndarray
    model: np.ndarray
    z: np.ndarray
    step_fn: StepFn
    tip_radius: float
    tip_force: float
    vmax: float
    guard: Callable | None = None
    clamped: np.ndarray | None = None
    tip_stiffness: float = 0.0


class Scene(NamedTuple):
    """Bodies, camera, background, fingertip track, and how the loop steps, guards and hands bodies over.

    Attributes:
      bodies: tuple of `Body`.
      camera: the `tignn_jax.mr.camera.Camera`.
      background: the real image, of the camera's size.
      track: [F, K, 3] fingertips as (u, v, depth_m) per frame (`tignn_jax.mr.track`; NaN rows: no fingertip).
      contact_radius: penalty contact distance between every pair of bodies (m, world space;
        `tignn_jax.mr.forcing.contact_forces` on their surface nodes); 0: no contact, nothing computed.
      contact_stiffness: contact stiffness (model force units per metre of overlap).
      hand_radius: radius of the spheres of the hand proxy drawn into the real depth at each fingertip (m; 0 for
        none; `tignn_jax.mr.background.hand_proxy`).
      step: optional ``(zs, forces) -> zs`` over the tuples of all bodies' states and forces, used instead of
        each body's ``step_fn`` (e.g. one batched graph for two copies of a mesh).
      colour_by: ``"stress"`` (von Mises of σ) or ``"displacement"`` (|q - q0|; the stress is then not
        evaluated).
      skip_rest: while no body has been touched (all forces zero since the start, bodies in their initial state)
        the step is skipped.
      guard: optional jit-able ``zs -> bool`` or ``zs -> bool [bodies]``, True where a new state must not be
        shown (e.g. non-finite or outside the model's training envelope, `tignn_jax.guards.state_guard`): the
        flagged bodies (all bodies for a single bool) return to their initial state or, where ``fallback`` gives
        the body one, are handed to it, and each counts as a guard trip. Give the scene this guard or each body
        its own ``Body.guard``, not both.
      fallback: per body, None or a jitted ``(z, forces, restart) -> z`` (`tignn_jax.guards.fallback_step`: a
        linear model, starting from σ = S u where ``restart``) that steps a flagged body from its previous state
        instead, and keeps stepping it for ``fallback_hold`` more frames (the body's learned step and guard
        then ignored), after which the learned step resumes. Empty: every flagged body is reset.
      fallback_hold: frames a handed-over body stays on its fallback.
      handover: when a flagged body's fallback takes over. ``"same-frame"``: in the frame of the trip (that
        frame runs the body's learned step and then its fallback step). ``"next-frame"``: the frame of the trip
        shows the body's previous state again, and the next frame runs the fallback twice, from that state
        under the trip frame's forces (restarted) and then under its own, so the body has taken as many steps
        as with ``"same-frame"`` from then on and every frame runs at most one learned step or two fallback
        steps (the trip frame's forces are those ``"same-frame"`` would use; the next frame's are computed from
        the previous state instead of the state one fallback step on); the hold then lasts
        ``max(fallback_hold, 1)`` frames. A body without a fallback is reset in the frame of its trip either way.
      devices: where the bodies step, body k on ``devices[k % len(devices)]`` (e.g. the CPU devices of a
        process that made one per core, `tignn_jax.mr.runtime.cpu_devices`): each body's ``step_fn`` is then
        jitted on its own and the bodies' steps are dispatched together, so they run concurrently, one core each
        (XLA runs one program's independent parts one after another on a single core); the states return to
        ``devices[0]`` for forces and rendering. Empty: all bodies step in one program on the default device.
      fuse: once a body is touched, forces, step and guard are dispatched together and awaited once per frame:
        one program, or with ``devices`` one per body on its device. Where bodies step on their own (no
        ``Scene.step``, no ``Scene.guard``) each body's part holds its guard and its hand-over, and a body on
        its fallback runs only the fallback step (without devices, several bodies: each body's frame in its own
        ``lax.cond``, which also keeps XLA:CPU from running the bodies' steps together); a scene with devices
        and a ``Scene.guard`` over all bodies runs its guard after the steps. False: each stage is dispatched
        and awaited in turn, so the forces are timed on their own (see benchmarks/realtime.py).
      press_direction: [3] the direction (world space) in which the fingertips of bodies with a ``tip_stiffness``
        push (default: down, −y).
    """
    bodies: tuple
    camera: Camera
    background: Background
    track: np.ndarray
    contact_radius: float = 0.004
    contact_stiffness: float = 1e6
    hand_radius: float = 0.008
    step: Callable | None = None
    colour_by: str = "stress"
    skip_rest: bool = True
    guard: Callable | None = None
    devices: tuple = ()
    fallback: tuple = ()
    fallback_hold: int = 30
    fuse: bool = True
    handover: str = "same-frame"
    press_direction: tuple = (0.0, -1.0, 0.0)


class Timings(NamedTuple):
    """Per-frame timings of `run`'s stages (milliseconds, over the timed frames) and what each frame did.

    Attributes:
      forces: [F] the forces stage (0 in fused frames, whose forces are timed inside ``step``).
      step: [F] the step stage (with guard and hand-over).
      render: [F] the render stage.
      write: [F] copying the frame to the host and the caller's writer.
      frame: [F] the whole frame.
      reallocations: how often the rasteriser's fragment buffer was grown (each a recompilation).
      guard_trips: bodies flagged by a guard, summed over all frames (the warm-up frames too).
      fused_frames: timed frames whose forces, step and guard were dispatched together and awaited once
        (``Scene.fuse``, once a body is touched and, with a ``Scene.step`` or ``Scene.guard`` or a single body,
        not every body is on its fallback); forces + step is the simulation time of every frame.
      learned: [F] bool, the learned step ran in that frame: some body was touched and not on its fallback
        (None: not recorded).
      learned_bodies: [F] int, how many bodies the learned step moved (touched and not on their fallback; with a
        ``Scene.step`` or ``Scene.guard`` a held body's step is still computed and discarded).
      handed: [F] bool, a guard handed some body over in that frame.
    """
    forces: np.ndarray
    step: np.ndarray
    render: np.ndarray
    write: np.ndarray
    frame: np.ndarray
    reallocations: int
    guard_trips: int = 0
    fused_frames: int = 0
    learned: np.ndarray | None = None
    learned_bodies: np.ndarray | None = None
    handed: np.ndarray | None = None

    def summary(self, bodies: int | None = None) -> dict:
        """Statistics of the timings.

        Args:
          bodies: the scene's body count; with it the learned-step frames are also split by class.

        Returns:
          {stage: {"p50_ms", "p99_ms", "mean_ms"}} for the stages and the simulation (forces + step), and
          ``simulation_learned`` over the frames the learned step ran in; ``frames``, ``fps_at_p50`` (frames per
          second at the median frame time), ``reallocations``, ``guard_trips``, ``fused_frames``,
          ``learned_frames``; with ``bodies`` also ``simulation_by_class``: the learned-step frames split into
          those where every body ran its learned step, those where some body was held on its fallback, and
          hand-over frames (each class present: its stats and frame count).
        """
        def stats(v):
            return {"p50_ms": float(np.median(v)), "p99_ms": float(np.percentile(v, 99)), "mean_ms": float(np.mean(v))}

        out = {k: stats(v) for k, v in self._asdict().items()
               if k not in ("reallocations", "guard_trips", "fused_frames", "learned", "learned_bodies", "handed")
               and len(v)}
        if len(self.frame):
            out["simulation"] = stats(self.forces + self.step)
        out["frames"] = int(len(self.frame))
        out["fps_at_p50"] = 1e3 / out["frame"]["p50_ms"] if len(self.frame) else 0.0
        out["reallocations"] = self.reallocations
        out["guard_trips"] = self.guard_trips
        out["fused_frames"] = self.fused_frames
        if self.learned is not None and len(self.learned) == len(self.frame):
            out["learned_frames"] = int(self.learned.sum())
            if self.learned.any():   # the simulation time of the frames the learned model stepped
                out["simulation_learned"] = stats((self.forces + self.step)[self.learned])
        if bodies and self.learned_bodies is not None and self.handed is not None and self.learned is not None:
            sim, handed = self.forces + self.step, np.asarray(self.handed, bool)
            classes = {"every body learned": self.learned & ~handed & (self.learned_bodies == bodies),
                       "a body held": self.learned & ~handed & (self.learned_bodies < bodies),
                       "hand-over": self.learned & handed}
            out["simulation_by_class"] = {k: {**stats(sim[m]), "frames": int(m.sum())}
                                          for k, m in classes.items() if m.any()}
        return out


def run(scene: Scene, frames: int | None = None, write: Callable[[int, np.ndarray], None] | None = None,
        warmup: int = 1, gc_pause: bool = True):
    """Play a scene frame by frame.

    Python's automatic garbage collection is switched off while the loop runs (with ``gc_pause``): a collection
    landing inside a frame's simulation stage would lengthen it, so a cheap young-generation collection runs
    instead at the end of every 32nd frame, inside its ``write`` stage; the previous setting is restored
    afterwards, also after an error.

    Args:
      scene: the scene.
      frames: frames to play (default: the track's length; a shorter track is padded with frames without
        fingertips).
      write: ``write(frame_index, rgb [H, W, 3] uint8)`` receives every rendered frame (e.g. an imageio writer's
        ``append_data``); its time is the ``write`` stage.
      warmup: the first frames, run but not timed (the first frame compiles the render stage).
      gc_pause: pause automatic garbage collection as above.

    Returns:
      (the bodies' final states, a tuple of [N_k, 12]; `Timings` of the frames after ``warmup``).

    Raises:
      ValueError: the scene's arrays do not fit together (`validate`).
    """
    validate(scene)
    was_enabled = gc.isenabled()
    if gc_pause:
        gc.collect()
        gc.disable()
    try:
        return _run(scene, frames, write, warmup, gc_pause)
    finally:
        if was_enabled:
            gc.enable()


def _run(scene, frames, write, warmup, gc_pause):
    frames = len(scene.track) if frames is None else int(frames)
    forces_fn, step_fn, render_fn, capacity = build(scene)
    max_capacity = 8 * scene.camera.width * scene.camera.height  # beyond this, drop fragments rather than grow
    # the initial states, placed as the step returns states (committed to devices[0] with Scene.devices), so that
    # neither a guard's reset nor the first step changes the stages' argument placement (that would recompile them)
    initial = tuple(jnp.asarray(b.z, jnp.float32) for b in scene.bodies)
    if scene.devices:
        initial = tuple(jax.device_put(z, scene.devices[0]) for z in initial)
    zs = initial
    track = _pad_frames(scene.track, frames)  # host array: a device index per frame would compile per index
    times = {k: [] for k in ("forces", "step", "render", "write", "frame")}
    reallocations = 0
    guard_trips = 0
    guard = _scene_guard(scene)
    guard_fn = jax.jit(guard) if guard is not None else None
    at_rest = all(np.allclose(np.asarray(b.z)[:, :3], b.q0) and not np.any(np.asarray(b.z)[:, 3:])
                  for b in scene.bodies)
    touched = not (scene.skip_rest and at_rest)
    if not touched:   # compile the step now, so the first touch does not stall a frame
        jax.block_until_ready(step_fn(zs, forces_fn(zs, track[0])))
    fallback = tuple(scene.fallback) + (None,) * (len(zs) - len(scene.fallback))
    left = np.zeros(len(zs), np.int64)   # frames each body still spends on its fallback
    has_fallback = np.array([fb is not None for fb in fallback])
    defer = scene.handover == "next-frame"
    hold = max(scene.fallback_hold, 1) if defer else scene.fallback_hold
    pending = [None] * len(zs)   # next-frame hand-over: the trip frame's forces, per body, until it catches up
    for fb, z, f in zip(fallback, zs, forces_fn(zs, track[0])):   # compiled now, not at the first hand-over
        if fb is not None:
            jax.block_until_ready(fb(z, f, jnp.asarray(True)))
    if guard_fn is not None:   # likewise the guard, before its first touched frame
        jax.block_until_ready(guard_fn(zs))
    sim_fn = None
    resolves = False   # does sim_fn also hand flagged bodies over and step those on their fallback?
    per_body = scene.fuse and scene.guard is None and scene.step is None   # each body's whole frame: learned
    if per_body and scene.devices:                                         # step, guard, hand-over or fallback
        sim_fn, resolves = _fused_concurrent(forces_fn, _concurrent_frame(scene, fallback, initial, defer)), True
    elif per_body and len(scene.bodies) > 1:   # (one body: its held frames skip the step anyway, below)
        sim_fn, resolves = _fused_frames(forces_fn, scene, fallback, initial, defer), True
    elif scene.fuse and not scene.devices:
        sim_fn = _fused_simulation(forces_fn, step_fn, guard)
    if sim_fn is not None:   # compiled now, not at the first touched frame (every program of each body)
        none = [None] * len(zs)
        calls = [(False, none)] + ([(True, none)] + ([(True, list(forces_fn(zs, track[0])))] if defer else [])
                                   if resolves else [])
        for on_all, waiting in calls:
            jax.block_until_ready(sim_fn(zs, track[0], np.full(len(zs), on_all), waiting))
    fused_frames = 0
    learned_bodies, handed = [], []   # per timed frame: how many bodies the learned step moved; was a body handed over
    for i in range(frames):
        tips = track[i]
        t0 = time.perf_counter()
        on = left > 0
        fused = sim_fn is not None and touched and (resolves or not on.all())
        if fused:   # forces, step and guard in one program (the forces stage is then counted in the step's)
            prev = zs
            zs, forces, flags = sim_fn(zs, tips, on, pending)
            flags = np.asarray(flags)   # awaits the program
            t1 = t0
            fused_frames += i >= warmup
        else:
            forces = jax.block_until_ready(forces_fn(zs, tips))
            t1 = time.perf_counter()
        touched = touched or any(bool(jnp.any(f != 0)) for f in forces)
        if touched:   # bodies at rest and untouched stay as they are: no step
            if not fused:
                prev = zs
                zs = prev if on.all() else jax.block_until_ready(step_fn(zs, forces))
                flags = np.asarray(guard_fn(zs)) if guard_fn is not None and not on.all() else False
            flags = np.broadcast_to(np.asarray(flags, bool).reshape(-1), (len(zs),)) & ~on
            guard_trips += int(flags.sum())
            if (flags.any() or on.any()) and not (fused and resolves):
                zs = tuple((_held(fb, p, f) if fp is None else _catch_up(fb, p, fp, f)) if busy
                           else p if bad and defer and fb is not None
                           else _hand_over(fb, p, f, z0, z, bool(bad), _py_cond)
                           for fb, p, f, z0, z, bad, busy, fp
                           in zip(fallback, prev, forces, initial, zs, flags, on, pending))
                zs = jax.block_until_ready(zs)
            pending = [None if busy else f if bad and defer and has else None
                       for f, bad, busy, has in zip(forces, flags, on, has_fallback)]
            left = np.where(flags & has_fallback, hold, np.maximum(left - 1, 0))
        t2 = time.perf_counter()
        image, overflow = jax.block_until_ready(render_fn(zs, tips))
        if bool(overflow) and capacity < max_capacity:  # rare: a body came much nearer the camera
            capacity = min(2 * capacity, max_capacity)
            render_fn = make_render_fn(scene, capacity)      # recompiles, once per doubling
            image, _ = jax.block_until_ready(render_fn(zs, tips))
            reallocations += 1
        t3 = time.perf_counter()
        frame = np.asarray(image)
        if write is not None:
            write(i, frame)
        if gc_pause and i % 32 == 31:
            gc.collect(0)
        t4 = time.perf_counter()
        if i >= warmup:
            for key, dt in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0)):
                times[key].append(1e3 * dt)
            learned_bodies.append(int((~on).sum()) if touched else 0)
            handed.append(bool(touched and np.any(flags)))
    learned_bodies = np.asarray(learned_bodies, np.int64)
    return zs, Timings(**{k: np.asarray(v) for k, v in times.items()}, reallocations=reallocations,
                       guard_trips=guard_trips, fused_frames=fused_frames,
                       learned=learned_bodies > 0, learned_bodies=learned_bodies, handed=np.asarray(handed, bool))


def _hand_over(fb, prev, f, z0, nxt, bad, cond):
    """A body's state after its guard's verdict ``bad``: where bad, its fallback restarted from the previous
    state (or its initial state ``z0`` without a fallback), else the learned step's ``nxt``. ``cond`` is
    `jax.lax.cond` inside a program (bad traced) or `_py_cond` in the loop (bad a Python bool): one rule for both."""
    handed = (lambda: fb(prev, f, jnp.asarray(True))) if fb is not None else (lambda: z0)
    return cond(bad, handed, lambda: nxt)


def _held(fb, prev, f):
    """A body held on its fallback steps by the fallback alone, not restarted."""
    return fb(prev, f, jnp.asarray(False))


def _catch_up(fb, prev, f_trip, f):
    """A body in the frame after its next-frame hand-over (``Scene.handover``): its fallback from the state it
    showed at the trip, restarted, under the trip frame's forces ``f_trip``, then one more step under ``f``."""
    return fb(fb(prev, f_trip, jnp.asarray(True)), f, jnp.asarray(False))


def _py_cond(pred, true_fn, false_fn):
    return true_fn() if pred else false_fn()


def _scene_guard(scene: Scene):
    """The loop's guard over all bodies, ``zs -> bool`` or ``bool [bodies]``: ``scene.guard``, or the bodies'
    own guards stacked (False for a body without one), or None when there is none."""
    if scene.guard is not None or all(b.guard is None for b in scene.bodies):
        return scene.guard
    guards = [b.guard for b in scene.bodies]
    return lambda zs: jnp.stack([jnp.asarray(False) if g is None else g(z) for g, z in zip(guards, zs)])


def _fused_concurrent(forces_fn, frame_fn):
    """``(zs, tips, on, pending) -> (zs_next, forces, flags)`` for a scene with ``devices``: the forces on
    ``devices[0]``, then every body's frame as one program on its own device (`_concurrent_frame`), all
    dispatched before anything is awaited; returns once the states are back on ``devices[0]``."""
    def fn(zs, tips, on, pending):
        forces = forces_fn(zs, tips)
        nxt, flags = frame_fn(zs, forces, on, pending)
        return jax.block_until_ready(nxt), forces, jnp.stack(flags)

    return fn


def _body_frames(b: Body, fb, z0, defer: bool = False):
    """(learned, held, catch_up): body ``b``'s simulation frame as ``(z, forces, trip_forces) -> (z_next,
    flag)``. ``learned`` runs its step and its ``Body.guard`` and, where the guard flags the new state, hands the
    body over as the loop would after it (`_hand_over`: its fallback from the previous state with the stress
    restarted, or its initial state ``z0`` without one; with ``defer``, a next-frame hand-over, a body with a
    fallback keeps its previous state instead); ``held`` (None without a fallback) runs only the fallback, for
    a body on it: its learned step, whose result would be discarded, is not computed; ``catch_up`` (None
    without a fallback) is a held body's frame after a next-frame hand-over (`_catch_up`, from ``trip_forces``)."""
    def learned(z, f, f_trip):
        nxt = b.step_fn(z, f)
        if b.guard is None:
            return nxt, jnp.asarray(False)
        bad = jnp.asarray(b.guard(nxt), bool).reshape(())
        if defer and fb is not None:
            return jnp.where(bad, z, nxt), bad
        return _hand_over(fb, z, f, z0, nxt, bad, jax.lax.cond), bad
    if fb is None:
        return learned, None, None
    held = lambda z, f, f_trip: (_held(fb, z, f), jnp.asarray(False))                 # noqa: E731
    catch_up = lambda z, f, f_trip: (_catch_up(fb, z, f_trip, f), jnp.asarray(False))  # noqa: E731
    return learned, held, catch_up


def _branch(on: bool, trip_forces) -> int:
    """Which of `_body_frames`' (learned, held, catch_up) a body runs this frame: its learned frame unless it is
    on its fallback (``on``), then its catch-up where the trip frame's forces are pending (a next-frame
    hand-over), else its held step."""
    return 0 if not on else 1 if trip_forces is None else 2


def _concurrent_frame(scene: Scene, fallback: tuple, initial: tuple, defer: bool = False):
    """``frame_fn(zs, forces, on, pending) -> (zs, flags)``: body k's whole simulation frame (`_body_frames`:
    its learned frame, or where ``on[k]`` its fallback alone, caught up from the trip frame's forces
    ``pending[k]`` where those are not None) as one program on ``scene.devices[k % D]``, every body's
    dispatched before any is awaited."""
    home, places = scene.devices[0], _places(scene)
    progs = []
    for b, fb, z0, d in zip(scene.bodies, fallback, initial, places):
        progs.append(tuple(None if fn is None else jax.jit(fn)
                           for fn in _body_frames(b, fb, jax.device_put(z0, d), defer)))

    def frame_fn(zs, forces, on, pending):
        out = [prog[_branch(on_k and prog[1] is not None, fp)](jax.device_put(z, d), jax.device_put(f, d),
                                                               None if fp is None else jax.device_put(fp, d))
               for prog, z, f, d, on_k, fp in zip(progs, zs, forces, places, on, pending)]
        return tuple(jax.device_put(z, home) for z, _ in out), tuple(jax.device_put(g, home) for _, g in out)

    return frame_fn


def _fused_frames(forces_fn, scene: Scene, fallback: tuple, initial: tuple, defer: bool = False):
    """``(zs, tips, on, pending) -> (zs_next, forces, flags)`` for a scene without devices whose bodies step
    on their own (no ``Scene.step``, no ``Scene.guard``): the forces and every body's whole frame
    (`_body_frames`; a body on its fallback, ``on[k]``, runs only the fallback, caught up from the trip frame's
    forces ``pending[k]`` where those are not None, chosen by ``lax.switch`` inside the program) as one
    program, one dispatch and one wait per frame, with no second dispatch for a hand-over. A body without a
    fallback (never on one) gets the switch too: it keeps XLA:CPU from compiling the bodies' steps together."""
    keep = lambda z, f, f_trip: (z, jnp.asarray(False))   # noqa: E731 (never taken: such a body is never held)
    frames = [_body_frames(b, fb, z0, defer) for b, fb, z0 in zip(scene.bodies, fallback, initial)]
    idle = [jnp.zeros((len(b.q0), 3), jnp.float32) for b in scene.bodies]

    @jax.jit
    def fn(zs, tips, branch, trip_forces):
        forces = forces_fn(zs, tips)
        out = [jax.lax.switch(branch[k], [learned, keep if held is None else held,
                                          keep if catch_up is None else catch_up], z, f, fp)
               for k, ((learned, held, catch_up), z, f, fp) in enumerate(zip(frames, zs, forces, trip_forces))]
        return tuple(z for z, _ in out), forces, jnp.stack([g for _, g in out])

    def call(zs, tips, on, pending):
        branch = [_branch(on_k, fp) for on_k, fp in zip(on, pending)]
        return fn(zs, tips, jnp.asarray(branch, jnp.int32),
                  tuple(z if fp is None else fp for z, fp in zip(idle, pending)))

    return call


def _fused_simulation(forces_fn, step_fn, guard):
    """``(zs, tips, on) -> (zs_next, forces, flags)`` for a scene with a ``Scene.step`` over all bodies or a
    ``Scene.guard``: the loop's simulation stages (forces, step, guard) as one program, one dispatch and one wait
    per frame instead of three (every body is stepped, so ``on``, the bodies on their fallback, is not used: the
    loop hands bodies over after it). ``flags`` is what the guard returns (one bool, or one per body), False
    without a guard."""
    @jax.jit
    def fn(zs, tips):
        forces = forces_fn(zs, tips)
        nxt = step_fn(zs, forces)
        return nxt, forces, jnp.asarray(False) if guard is None else guard(nxt)

    return lambda zs, tips, on, pending: fn(zs, tips)


def build(scene: Scene):
    """The jitted stages of `run`.

    Args:
      scene: the scene (not validated here).

    Returns:
      (forces_fn(zs, tips [K, 3]) -> forces, a tuple of [N_k, 3] in each body's model frame;
      step_fn(zs, forces) -> zs; render_fn(zs, tips) -> (rgb [H, W, 3] uint8, overflow bool);
      the rasteriser's fragment capacity, sized on the bodies' initial states).
    """
    cam = scene.camera
    vp = jnp.asarray(camera_projection(cam) @ cam.view)
    viewport = (0.0, 0.0, float(cam.width), float(cam.height))
    models = [jnp.asarray(b.model, jnp.float32) for b in scene.bodies]
    inverses = [jnp.linalg.inv(m) for m in models]
    tris = [jnp.asarray(b.triangles, jnp.int32) for b in scene.bodies]
    surfaces = [jnp.asarray(surface_nodes(b.triangles)) for b in scene.bodies]
    capacities = [max(64, len(s) // 2) for s in surfaces]
    rotations = [m[:3, :3] / jnp.linalg.norm(m[:3, :3], axis=0, keepdims=True) for m in models]
    masks, presses = _press_frames(scene)
    n = len(scene.bodies)

    @jax.jit
    def forces_fn(zs, tips):
        world_tips = _world_tips(tips, vp, viewport)
        out = []
        for b, z, inv, tri, mask, press in zip(scene.bodies, zs, inverses, tris, masks, presses):
            q = z[:, :3]
            if b.tip_stiffness > 0:
                out.append(fingertip_spring_forces(transform_points(inv, world_tips), q, mask, press, b.tip_radius,
                                                   b.tip_stiffness))
            else:
                out.append(fingertip_forces(transform_points(inv, world_tips), q, vertex_normals(q, tri),
                                            b.tip_radius, b.tip_force))
        world = [transform_points(m, z[:, :3])[s] for m, z, s in zip(models, zs, surfaces)]
        for i in range(n if scene.contact_radius > 0 else 0):   # no contact: no neighbour search at all
            for j in range(i + 1, n):
                fi, fj = contact_forces(world[i], world[j], scene.contact_radius, scene.contact_stiffness,
                                           capacity=max(capacities[i], capacities[j]))
                out[i] = out[i].at[surfaces[i]].add(fi @ rotations[i])  # world -> model directions
                out[j] = out[j].at[surfaces[j]].add(fj @ rotations[j])
        return tuple(out)

    @jax.jit
    def one_program(zs, forces):
        if scene.step is not None:
            return tuple(scene.step(zs, forces))
        return tuple(b.step_fn(z, f) for b, z, f in zip(scene.bodies, zs, forces))

    step_fn = _concurrent_step(scene) if scene.devices else one_program

    positions, _ = _world_mesh(scene, tuple(jnp.asarray(b.z, jnp.float32) for b in scene.bodies))
    pixels, depth = project(positions, vp, viewport)
    capacity = fragment_capacity(pixels, depth, _all_triangles(scene), cam.width, cam.height, headroom=1.5)
    return forces_fn, step_fn, make_render_fn(scene, capacity), capacity


def _concurrent_step(scene: Scene):
    """``step_fn(zs, forces) -> zs`` that steps body k on ``scene.devices[k % D]``: every body's step is
    dispatched before any is awaited (JAX dispatch is asynchronous), then each state is moved back to
    ``devices[0]`` (the staged loop's step; `_concurrent_frame` is the fused loop's)."""
    fns = [jax.jit(b.step_fn) for b in scene.bodies]
    places = _places(scene)

    def step_fn(zs, forces):
        out = [fn(jax.device_put(z, d), jax.device_put(f, d)) for fn, z, f, d in zip(fns, zs, forces, places)]
        return tuple(jax.device_put(z, scene.devices[0]) for z in out)

    return step_fn


def _press_frames(scene: Scene):
    """Per body: its surface-node mask [N] and ``Scene.press_direction`` in its model frame (unit [3])."""
    masks, presses = [], []
    world = np.asarray(scene.press_direction, np.float64)
    for b in scene.bodies:
        mask = np.zeros(len(b.q0), bool)
        mask[surface_nodes(b.triangles)] = True
        d = np.linalg.solve(np.asarray(b.model, np.float64)[:3, :3], world)
        masks.append(jnp.asarray(mask))
        presses.append(jnp.asarray(d / np.linalg.norm(d), jnp.float32))
    return masks, presses


def _world_tips(tips, vp, viewport):
    """[K, 3] world points of the fingertips (u, v, depth_m) [K, 3]; NaN rows for missing ones (a non-finite or
    non-positive depth)."""
    world = unproject(tips[:, :2], tips[:, 2], vp, viewport)
    return jnp.where(jnp.isfinite(tips[:, 2:3]) & (tips[:, 2:3] > 0), world, jnp.nan)


def _places(scene: Scene) -> list:
    """The device of each body: body k on ``scene.devices[k % D]``."""
    return [scene.devices[k % len(scene.devices)] for k in range(len(scene.bodies))]


def make_render_fn(scene: Scene, capacity: int):
    """The jitted render stage: bodies shaded, rasterised and occluded by the real depth (the background with the
    hand proxy drawn at the fingertips, those pressing a body resting on its deformed surface: `rest_on_surface`).

    Args:
      scene: the scene.
      capacity: the rasteriser's fragment capacity (`tignn_jax.mr.render.fragment_capacity`).

    Returns:
      ``render_fn(zs, tips [K, 3]) -> (rgb [H, W, 3] uint8, overflow bool)``.
    """
    cam = scene.camera
    vp = jnp.asarray(camera_projection(cam) @ cam.view)
    eye = jnp.asarray(np.linalg.inv(cam.view)[:3, 3], jnp.float32)
    light = jnp.array([0.3, -1.0, -0.4], jnp.float32)
    triangles = jnp.asarray(_all_triangles(scene))
    background = (jnp.asarray(scene.background.rgb, jnp.float32), jnp.asarray(scene.background.depth, jnp.float32))
    viewport = (0.0, 0.0, float(cam.width), float(cam.height))
    inverses = [jnp.linalg.inv(jnp.asarray(b.model, jnp.float32)) for b in scene.bodies]

    masks, presses = _press_frames(scene)

    def touching(zs, tips):   # as the forces see it: a node within tip_radius, or a spring fingertip past the surface
        world = _world_tips(tips, vp, viewport)
        near = jnp.zeros(tips.shape[0], bool)
        for b, z, inv, mask, press in zip(scene.bodies, zs, inverses, masks, presses):
            local = transform_points(inv, world)
            if b.tip_stiffness > 0:
                pad, depth = fingertip_pads(local, z[:, :3], mask, press, b.tip_radius)
                near = near | (jnp.any(pad, axis=1) & (depth > 0))
            else:
                distance = jnp.linalg.norm(z[None, :, :3] - local[:, None, :], axis=-1)    # [K, N]
                near = near | jnp.any(distance < b.tip_radius, axis=1)
        return near

    @jax.jit
    def render(zs, tips, background):  # the image-sized background is an argument, not a baked-in constant
        positions, colours = _world_mesh(scene, zs)
        raster = draw_mesh(positions, triangles, colours, vp, eye, light, width=cam.width, height=cam.height,
                           capacity=capacity)
        tips = rest_on_surface(tips, raster.depth, cam, scene.hand_radius, touching(zs, tips))
        real_rgb, real_depth = hand_proxy(*background, tips, cam, scene.hand_radius)
        rgb = occlude(raster.rgb, raster.depth, real_rgb, real_depth)
        return (jnp.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(jnp.uint8), raster.overflow

    return lambda zs, tips: render(zs, tips, background)


def validate(scene: Scene) -> None:
    """Check that a scene's parts fit together.

    Raises:
      ValueError: naming the first field of ``scene`` with a wrong shape or value.
    """
    cam = scene.camera
    if scene.colour_by not in ("stress", "displacement"):
        raise ValueError(f"colour_by must be 'stress' or 'displacement', got {scene.colour_by!r}")
    if np.asarray(cam.view).shape != (4, 4):
        raise ValueError(f"camera.view must be [4,4], got {np.asarray(cam.view).shape}")
    if not 0 < cam.near < cam.far:
        raise ValueError(f"camera needs 0 < near < far, got near={cam.near}, far={cam.far}")
    shape = (cam.height, cam.width)
    if scene.background.rgb.shape != shape + (3,) or scene.background.depth.shape != shape:
        raise ValueError(f"background must be [{cam.height},{cam.width},3] + [{cam.height},{cam.width}], got "
                         f"{scene.background.rgb.shape} + {scene.background.depth.shape}")
    track = np.asarray(scene.track)
    if track.ndim != 3 or track.shape[2] != 3:
        raise ValueError(f"track must be [frames, tips, 3] (u, v, depth_m), got shape {track.shape}")
    if not scene.bodies:
        raise ValueError("scene has no bodies")
    if scene.guard is not None and any(b.guard is not None for b in scene.bodies):
        raise ValueError("give the scene one guard over all bodies (scene.guard) or each body its own "
                         "(Body.guard), not both")
    if scene.devices and scene.step is not None:
        raise ValueError("a scene with devices steps each body's step_fn on its device; it cannot also have a "
                         "step over all bodies (scene.step)")
    if len(scene.fallback) > len(scene.bodies) or not all(fb is None or callable(fb) for fb in scene.fallback):
        raise ValueError(f"fallback must give each of the {len(scene.bodies)} bodies None or a callable, got "
                         f"{scene.fallback!r}")
    if not isinstance(scene.fallback_hold, (int, np.integer)) or scene.fallback_hold < 0:
        raise ValueError(f"fallback_hold must be a non-negative integer, got {scene.fallback_hold!r}")
    if scene.handover not in ("same-frame", "next-frame"):
        raise ValueError(f"handover must be 'same-frame' or 'next-frame', got {scene.handover!r}")
    press = np.asarray(scene.press_direction, np.float64)
    if press.shape != (3,) or not np.all(np.isfinite(press)) or not np.linalg.norm(press) > 0:
        raise ValueError(f"press_direction must be a finite, non-zero [3] vector, got {scene.press_direction!r}")
    for k, b in enumerate(scene.bodies):
        n = len(b.q0)
        if np.asarray(b.z).shape != (n, 12):
            raise ValueError(f"bodies[{k}].z must be [{n},12] (q, v, sigma), got {np.asarray(b.z).shape}")
        if np.asarray(b.model).shape != (4, 4):
            raise ValueError(f"bodies[{k}].model must be [4,4], got {np.asarray(b.model).shape}")
        tri = np.asarray(b.triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.min() < 0 or tri.max() >= n:
            raise ValueError(f"bodies[{k}].triangles must be [T,3] indices below {n}")
        if (scene.step is None or scene.devices) and not callable(b.step_fn):
            raise ValueError(f"bodies[{k}].step_fn must be callable (or give the scene a step), got {b.step_fn!r}")
        if not (b.tip_radius > 0 and b.vmax > 0):
            raise ValueError(f"bodies[{k}] needs tip_radius > 0 and vmax > 0, got {b.tip_radius}, {b.vmax}")
        if not b.tip_stiffness >= 0:
            raise ValueError(f"bodies[{k}].tip_stiffness must be >= 0, got {b.tip_stiffness}")
        if b.clamped is not None and np.asarray(b.clamped).shape != (n,):
            raise ValueError(f"bodies[{k}].clamped must be [{n}] (one flag per node), got "
                             f"{np.asarray(b.clamped).shape}")


def _world_mesh(scene: Scene, zs):
    positions, colours = [], []
    for b, z in zip(scene.bodies, zs):
        positions.append(transform_points(jnp.asarray(b.model, jnp.float32), z[:, :3]))
        value = (von_mises(z[:, 6:12]) if scene.colour_by == "stress"
                 else jnp.linalg.norm(z[:, :3] - jnp.asarray(b.q0, z.dtype), axis=1))
        colour = colour_map(value, 0.0, b.vmax)
        if b.clamped is not None:
            colour = jnp.where(jnp.asarray(b.clamped)[:, None], jnp.asarray(CLAMP_COLOUR, colour.dtype), colour)
        colours.append(colour)
    return jnp.concatenate(positions), jnp.concatenate(colours)


def _all_triangles(scene: Scene) -> np.ndarray:
    offsets = np.cumsum([0] + [len(b.q0) for b in scene.bodies])
    return np.concatenate([np.asarray(b.triangles) + o for b, o in zip(scene.bodies, offsets)]).astype(np.int32)


def _pad_frames(track, frames):
    track = np.asarray(track, np.float32)
    if len(track) >= frames:
        return track[:frames]
    return np.concatenate([track, np.full((frames - len(track),) + track.shape[1:], np.nan, np.float32)])
