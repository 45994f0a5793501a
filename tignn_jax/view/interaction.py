"""One viewer's simulation: bodies pushed and pulled by a dragged fingertip, stepped at a fixed rate.

A `Interaction` holds one page's state (the bodies' states z, the grab, the pause flag) and advances it by `step`,
one frame of the model per call. It knows nothing of the browser: `tignn_jax.view.server` calls `grab`, `drag`,
`release` from the page's pointer events and `step` from a physics thread, and tests call them directly.

The fingertip is a spring. `grab(point)` takes the free surface nodes within ``grab_radius`` of the pressed point
(at least the nearest one) as the patch P; while dragging, the pointer's target T (on the camera-facing plane
through the grab point) pulls the patch's grab point, the patch centroid c(q) plus its offset d at the grab::

    F = clip(k · (T - (c(q) + d)), F_cap),    f_i = F / |P| for i in P,

with F_cap = |P| · f_max: no node receives more than the largest nodal force of the model's training data
(``envelope["f_max"]``), so a pointer dragged far away never leaves the training loads. Pressing into the surface
and pulling out are the same gesture. The stiffness is

    k = min(F_cap / u_max, LOOP_GAIN / ‖C‖₂):

a pointer held u_max (the largest training displacement) from the grab point applies the largest force, unless
the body is softer than that. The spring acts on the current patch position, so the body settles where
k (T - x) = K_body x instead of being pushed ever harder by a held pointer; but that makes it an explicit feedback
loop, which oscillates with a period of two steps when k ‖C‖ exceeds about 1, C [3, 3] the patch's one-step
compliance (how far one model step moves its centroid per unit force), which `grab` probes with four model steps
from the current state. F also changes by at most ``RAMP`` x F_cap per step: a sudden yank builds up over a few
steps, which the FEM's truncated Newton step (``fem-newton``, `tignn_jax.newton`) needs to stay finite.

Why a spring on a patch rather than the demo's constant force along the normal
(`tignn_jax.mr.forcing.fingertip_forces`): a mouse has no depth, so "press" and "pull" must come from the
pointer's motion in the view plane, and a spring turns that motion into a bounded, continuous load.

Frames: every body's state lives in its model frame and units; the world (what the page shows, and what `grab`
and `drag` take) is the first body's model frame, z up. Body k maps model to world by x_w = R_k x + t_k.
Two bodies touch through penalty springs between surface nodes: inside their one implicit frame where the
scene has a ``joint`` step (`tignn_jax.contact_stepper`, the corotational models), otherwise as forces taken at
each step's start (`tignn_jax.mr.forcing.contact_forces`).

A body whose new state is flagged by its guard (not finite, or for a model that is not stable by construction
outside its training envelope, see `tignn_jax.cli.demo._dynamics`) is reset to rest and counted in ``resets``.
"""
from __future__ import annotations

import threading
import time
from typing import Callable, NamedTuple

import numpy as np

QUANTITIES = ("von Mises", "σxx", "|u|")
LOOP_GAIN = 0.5   # k · ‖C‖₂ of the spring (module docstring)
RAMP = 0.1        # the spring's force changes by at most this fraction of F_cap per step


class Body(NamedTuple):
    """A solid of the scene.

    Attributes:
      q0: [N, 3] rest positions (model units).
      triangles: [T, 3] int32 outward surface triangles (`tignn_jax.mr.surface_triangles`).
      free: [N] bool, nodes the model moves (``node_type == 0``); only these can be grabbed.
      rotation: [3, 3] model -> world rotation R.
      offset: [3] model -> world translation t (world = R q + t, model units).
    """
    q0: np.ndarray
    triangles: np.ndarray
    free: np.ndarray
    rotation: np.ndarray
    offset: np.ndarray


class Scene(NamedTuple):
    """What a `Interaction` simulates.

    Attributes:
      name: the scene's name as shown on the page.
      bodies: tuple of `Body` (all of one model's mesh).
      step: ``step(z [N, 12], forces [N, 3]) -> z [N, 12]``, one frame of the model (jitted).
      guard: ``guard(z [N, 12]) -> bool``, True where a new state must be replaced by the rest state.
      dynamics: a one-line description of the model.
      f_max: the largest nodal force of the model's training data (model force units).
      u_max: the largest nodal displacement of the training data (model length units).
      ranges: {quantity: (vmin, vmax)} of the colour legend, for each of ``QUANTITIES``.
      contact: (radius, stiffness) of penalty contact between bodies (model length, force per length), or None.
      joint: ``joint(zs, forces) -> zs`` over all bodies' states and forces, one frame with the contact inside it
        (`tignn_jax.contact_stepper`), used instead of ``step`` and the explicit contact; or None.
    """
    name: str
    bodies: tuple
    step: Callable
    guard: Callable
    dynamics: str
    f_max: float
    u_max: float
    ranges: dict
    contact: tuple | None = None
    joint: Callable | None = None


class Frame(NamedTuple):
    """A snapshot to draw: per body the world positions [N, 3] and the three colour quantities [N]."""
    positions: tuple
    values: dict
    index: int


class Interaction:
    """One viewer's bodies, grab and clock.

    Thread-safe: `grab`, `drag`, `release`, `reset` and `pause` may be called from one thread while another
    calls `step`. Input from the page is checked here and a bad value is refused (the method returns False),
    never raised, so a malformed event cannot stop the page's physics.

    Args:
      scene: the `Scene`.
      grab_radius: radius of the grabbed patch around the pressed point (model length units; default 1.5 x
        the median surface edge length).
      reach: points farther than ``reach`` x the scene's size from its centre are refused.
    """

    def __init__(self, scene: Scene, grab_radius: float | None = None, reach: float = 20.0):
        self.scene = scene
        self._lock = threading.Lock()
        self._rest = tuple(np.concatenate([b.q0, np.zeros((len(b.q0), 9), np.float32)], 1).astype(np.float32)
                           for b in scene.bodies)
        self.zs = self._rest
        self._surface = tuple(np.unique(b.triangles) for b in scene.bodies)
        world = np.concatenate([_to_world(b, b.q0) for b in scene.bodies])
        self.centre = 0.5 * (world.min(0) + world.max(0))
        self.size = float(np.linalg.norm(world.max(0) - world.min(0)))
        self._reach = reach * self.size
        self.grab_radius = float(grab_radius) if grab_radius else 1.5 * _median_edge(scene.bodies[0])
        self._grab = None          # (body, patch node ids, offset d [3] model units) while grabbing
        self._target = None        # [3] world
        self._pull = np.zeros(3)   # the spring's total force in the last step (model frame)
        self.paused = False
        self.index = 0             # steps taken since the last reset
        self.resets = 0            # bodies reset by their guard
        self.step_ms = 0.0         # the last step's wall time (model step, forces, guard)
        explicit = scene.contact and len(scene.bodies) > 1 and scene.joint is None
        self._contact = _contact_fn(scene) if explicit else None

    def grab(self, point) -> bool:
        """Start a drag at the world point ``point`` [3] (e.g. where the pointer pressed the surface).

        Grabs the free surface nodes of the nearest body within ``grab_radius`` of the point (at least the
        nearest free surface node, which must lie within 3 ``grab_radius``).

        Returns:
          True if a patch was grabbed; False for a malformed point or one not on a body (nothing changes).
        """
        p = self._point(point)
        if p is None:
            return False
        best = None
        for k, (b, z, surf) in enumerate(zip(self.scene.bodies, self.zs, self._surface)):
            nodes = surf[b.free[surf]]
            if not len(nodes):
                continue
            local = (p - b.offset) @ b.rotation          # world -> model: R^T (p - t)
            dist = np.linalg.norm(z[nodes, :3] - local, axis=1)
            if best is None or dist.min() < best[0]:
                best = (float(dist.min()), k, nodes, dist, local)
        if best is None or best[0] > 3.0 * self.grab_radius:
            return False
        _, k, nodes, dist, local = best
        patch = nodes[dist <= max(self.grab_radius, best[0])]
        z = self.zs[k]
        offset = local - z[patch, :3].mean(0)
        stiffness = self._stiffness(z, patch)
        with self._lock:
            self._grab = (k, patch, offset, stiffness)
            self._target = p
            self._pull = np.zeros(3)
        return True

    def drag(self, target) -> bool:
        """Move the pointer's target to the world point ``target`` [3] while a patch is grabbed.

        Returns:
          True if taken; False when nothing is grabbed or the point is malformed (the previous target stays).
        """
        p = self._point(target)
        with self._lock:
            if p is None or self._grab is None:
                return False
            self._target = p
        return True

    def release(self) -> None:
        """End the drag: the body is free again and springs back."""
        with self._lock:
            self._grab, self._target = None, None

    def reset(self) -> None:
        """Put every body back to rest (q = q0, v = 0, σ = 0) and end any drag."""
        with self._lock:
            self.zs = self._rest
            self._grab, self._target = None, None
            self.index = 0

    def pause(self, paused: bool) -> None:
        """Stop (True) or resume (False) `step`'s advance of the bodies."""
        self.paused = bool(paused)

    @property
    def grabbed(self) -> bool:
        """Whether a patch is held."""
        return self._grab is not None

    @property
    def target(self):
        """The pointer's target [3] (world) while a patch is grabbed, else None."""
        with self._lock:
            return None if self._grab is None else self._target

    def spring(self):
        """(grab point, target), each [3] in the world, while a patch is grabbed, else None: the spring's ends,
        the grab point moving with the patch (c(q) + d)."""
        with self._lock:
            grab, target, zs = self._grab, self._target, self.zs
        if grab is None:
            return None
        k, patch, offset, _ = grab
        return _to_world(self.scene.bodies[k], zs[k][patch, :3].mean(0) + offset), target

    def forces(self) -> tuple:
        """The fingertip spring's nodal forces per body that the next `step` applies, ([N, 3] float32, ...),
        model units (module docstring)."""
        return self._forces()[0]

    def step(self) -> bool:
        """Advance every body by one frame of the model under the spring's (and contact) forces.

        Returns:
          False when paused (nothing changes), True otherwise.
        """
        if self.paused:
            return False
        t0 = time.perf_counter()
        zs = self.zs
        forces, grab, pull = self._forces()
        forces = list(forces)
        if self._contact is not None:
            for k, f in enumerate(self._contact(zs)):
                forces[k] = forces[k] + f
        if self.scene.joint is not None:
            stepped = [np.asarray(z) for z in self.scene.joint(zs, tuple(forces))]
        else:
            stepped = [np.asarray(self.scene.step(z, f)) for z, f in zip(zs, forces)]
        new = []
        for nxt, rest in zip(stepped, self._rest):
            if bool(self.scene.guard(nxt)):
                nxt = rest
                self.resets += 1
            new.append(nxt)
        with self._lock:
            if self.zs is zs:            # not reset meanwhile
                self.zs = tuple(new)
                self.index += 1
            if self._grab is grab:       # not grabbed anew or released meanwhile
                self._pull = pull
        self.step_ms = 1e3 * (time.perf_counter() - t0)
        return True

    def frame(self) -> Frame:
        """The current state to draw: world positions and the colour quantities (`QUANTITIES`) per body."""
        from fem.mesh import von_mises

        zs, index = self.zs, self.index
        positions = tuple(_to_world(b, z[:, :3]) for b, z in zip(self.scene.bodies, zs))
        values = {"von Mises": tuple(von_mises(z[:, 6:12]) for z in zs),
                  "σxx": tuple(z[:, 6] for z in zs),
                  "|u|": tuple(np.linalg.norm(z[:, :3] - b.q0, axis=1) for b, z in zip(self.scene.bodies, zs))}
        return Frame(positions, values, index)

    def displacement(self) -> tuple:
        """Per body the nodal displacements |q - q0| [N] (model units)."""
        return tuple(np.linalg.norm(z[:, :3] - b.q0, axis=1) for b, z in zip(self.scene.bodies, self.zs))

    def _stiffness(self, z, patch) -> float:
        """The spring's k for a patch: F_cap / u_max, at most ``LOOP_GAIN`` / ‖C‖₂, C [3, 3] the patch's one-step
        compliance (how far one model step moves its centroid per unit total force, probed from ``z``)."""
        cap = len(patch) * self.scene.f_max
        probe = 0.1 * cap
        f = np.zeros((len(z), 3), np.float32)
        base = np.asarray(self.scene.step(z, f))[patch, :3].mean(0)
        compliance = np.zeros((3, 3))
        for axis in range(3):
            f[:] = 0.0
            f[patch, axis] = probe / len(patch)
            compliance[:, axis] = (np.asarray(self.scene.step(z, f))[patch, :3].mean(0) - base) / probe
        norm = float(np.linalg.norm(compliance, 2))
        k = cap / self.scene.u_max
        return min(k, LOOP_GAIN / norm) if np.isfinite(norm) and norm > 0 else k

    def _forces(self):
        """(nodal forces per body, the grab they belong to, the total pull F [3]): F is the spring's force,
        clipped to F_cap, its change since the last step limited to ``RAMP`` x F_cap."""
        with self._lock:
            grab, target, zs, last = self._grab, self._target, self.zs, self._pull
        out = [np.zeros((len(b.q0), 3), np.float32) for b in self.scene.bodies]
        if grab is None:
            return tuple(out), grab, np.zeros(3)
        k, patch, offset, stiffness = grab
        b = self.scene.bodies[k]
        cap = len(patch) * self.scene.f_max
        pull = _clip(((target - b.offset) @ b.rotation - (zs[k][patch, :3].mean(0) + offset)) * stiffness, cap)
        pull = last + _clip(pull - last, RAMP * cap)
        out[k][patch] = pull / len(patch)
        return tuple(out), grab, pull

    def _point(self, point):
        """A finite world point [3] within reach of the scene, as float64, or None."""
        try:
            p = np.asarray(point, np.float64).reshape(3)
        except (TypeError, ValueError):
            return None
        if not np.all(np.isfinite(p)) or np.linalg.norm(p - self.centre) > self._reach:
            return None
        return p


def _clip(v, bound: float):
    """``v`` [3] shortened to length ``bound`` where longer."""
    norm = float(np.linalg.norm(v))
    return v * (bound / norm) if norm > bound else v


def _to_world(body: Body, q) -> np.ndarray:
    return np.asarray(q, np.float64) @ body.rotation.T + body.offset


def _median_edge(body: Body) -> float:
    t = body.triangles
    q = body.q0
    edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    return float(np.median(np.linalg.norm(q[edges[:, 0]] - q[edges[:, 1]], axis=1)))


def _contact_fn(scene: Scene):
    """``zs -> forces per body`` (model frames) of penalty contact between the first two bodies' surfaces."""
    import jax
    import jax.numpy as jnp

    from tignn_jax.mr.forcing import contact_forces

    (a, b), radius, stiffness = scene.bodies[:2], *scene.contact
    sa, sb = np.unique(a.triangles), np.unique(b.triangles)
    ra, rb = jnp.asarray(a.rotation, jnp.float32), jnp.asarray(b.rotation, jnp.float32)
    ta, tb = jnp.asarray(a.offset, jnp.float32), jnp.asarray(b.offset, jnp.float32)
    capacity = max(len(sa), len(sb))

    @jax.jit
    def fn(za, zb):
        fa, fb = contact_forces(za[sa, :3] @ ra.T + ta, zb[sb, :3] @ rb.T + tb, radius, stiffness, capacity)
        return (jnp.zeros((za.shape[0], 3)).at[sa].set(fa @ ra), jnp.zeros((zb.shape[0], 3)).at[sb].set(fb @ rb))

    def forces(zs):
        fa, fb = fn(zs[0], zs[1])
        return (np.asarray(fa), np.asarray(fb)) + tuple(np.zeros((len(z), 3), np.float32) for z in zs[2:])

    return forces
