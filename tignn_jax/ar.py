"""The mixed-reality layer: camera maths, fingertip and contact forcing, colouring, shading and occlusion.

Every function here is pure and jit-able; arrays in, arrays out, nothing cached.

Conventions (OpenGL):
- Eye space is right-handed; the camera sits at the origin looking down -z with +y up.
- ``clip = P · V · M · [x, 1]`` (``mvp = P @ V @ M``, matrices act on column vectors, shape [4,4]).
  Normalised device coordinates are ``clip[:3] / clip[3]`` and the visible frustum is the cube [-1, 1]^3:
  a point on the near plane has z_ndc = -1, one on the far plane z_ndc = +1.
- ``depth`` is the clip coordinate w, which for a perspective ``P`` equals -z_eye: the distance from the
  camera along its optical axis, in scene units (metres in our scenes). It is what a depth camera reports,
  so it is compared directly with a real depth image.
- Pixels are continuous image coordinates (u right, v down, origin at the top-left corner of the image);
  pixel (i, j) covers [i, i+1) x [j, j+1) and its centre is (i + 0.5, j + 0.5). A viewport
  ``(x0, y0, width, height)`` maps ``u = x0 + (x_ndc + 1) / 2 · width`` and ``v = y0 + (1 - y_ndc) / 2 · height``.
  A normalised landmark (x, y) in [0, 1]^2, as MediaPipe gives, is the pixel ``(x · width, y · height)``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

# viridis sampled at 9 equally spaced points (perceptually uniform, readable in grey scale).
_COLOUR_TABLE = np.array([
    [0.2670, 0.0049, 0.3294],
    [0.2788, 0.1755, 0.4834],
    [0.2297, 0.3224, 0.5457],
    [0.1727, 0.4488, 0.5579],
    [0.1276, 0.5669, 0.5506],
    [0.1579, 0.6838, 0.5017],
    [0.3692, 0.7889, 0.3829],
    [0.6785, 0.8637, 0.1895],
    [0.9932, 0.9062, 0.1439],
], dtype=np.float32)


# ----------------------------------------------------------------------------------------------- camera


def perspective(fov_y, aspect, near, far) -> Array:
    """OpenGL perspective projection matrix [4,4].

    fov_y: vertical field of view in radians; aspect: width / height; near, far: distances of the clipping
    planes along the optical axis (scene units, 0 < near < far). Maps z_eye = -near to z_ndc = -1 and
    z_eye = -far to z_ndc = +1, and sets clip w = -z_eye.
    """
    _check_positive_scalars(fov_y=fov_y, aspect=aspect, near=near, far=far)
    if _concrete(near, far) and not float(far) > float(near):
        raise ValueError(f"far must exceed near, got near={near}, far={far}")
    f = 1.0 / jnp.tan(0.5 * jnp.asarray(fov_y, jnp.float32))
    return _projection(f / aspect, f, 0.0, 0.0, near, far)


def projection_from_intrinsics(fx, fy, cx, cy, width, height, near, far) -> Array:
    """OpenGL projection matrix [4,4] equivalent to pinhole intrinsics (pixels), for a full-image viewport.

    fx, fy: focal lengths in pixels; (cx, cy): principal point in the pixel convention of this module (v
    down); width, height: image size in pixels. With ``viewport = (0, 0, width, height)``, ``project``
    then gives ``u = fx · x_e / (-z_e) + cx`` and ``v = -fy · y_e / (-z_e) + cy`` (eye y is up, v is down).
    """
    _check_positive_scalars(fx=fx, fy=fy, width=width, height=height, near=near, far=far)
    return _projection(2.0 * fx / width, 2.0 * fy / height,
                       1.0 - 2.0 * cx / width, 2.0 * cy / height - 1.0, near, far)


def look_at(eye, target, up) -> Array:
    """View matrix [4,4] (world -> eye space) of a camera at ``eye`` [3] looking at ``target`` [3].

    ``up`` [3] need not be orthogonal to the viewing direction but must not be parallel to it. The eye maps
    to the origin and the target onto the negative z axis, at distance |target - eye|.
    """
    eye, target, up = (jnp.asarray(a, jnp.float32) for a in (eye, target, up))
    for name, a in (("eye", eye), ("target", target), ("up", up)):
        _check_shape(name, a, (3,))
    forward = _normalise(target - eye)
    right = _normalise(jnp.cross(forward, up))
    true_up = jnp.cross(right, forward)
    rotation = jnp.stack([right, true_up, -forward])
    return _affine(rotation, -rotation @ eye)


def rotation_matrix(axis, angle) -> Array:
    """Rotation matrix [3,3] of ``angle`` radians about ``axis`` [3] (right-hand rule, Rodrigues' formula)."""
    axis = _normalise(jnp.asarray(axis, jnp.float32))
    k = jnp.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * k + (1.0 - jnp.cos(angle)) * (k @ k)


def model_matrix(translation, rotation, scale) -> Array:
    """Model matrix [4,4] (model -> world): ``x_world = translation + rotation @ (scale * x_model)``.

    translation: [3] (world units); rotation: [3,3] rotation matrix; scale: scalar or [3] (world units per
    model unit, e.g. 0.005 to show the 40-unit beam as a 0.2 m object in a scene measured in metres).
    """
    translation = jnp.asarray(translation, jnp.float32)
    rotation = jnp.asarray(rotation, jnp.float32)
    _check_shape("translation", translation, (3,))
    _check_shape("rotation", rotation, (3, 3))
    scale = jnp.broadcast_to(jnp.asarray(scale, jnp.float32), (3,))
    return _affine(rotation * scale[None, :], translation)


def mvp_matrix(projection, view, model) -> Array:
    """The product ``P @ V @ M`` [4,4]: model space -> clip space."""
    return jnp.asarray(projection) @ jnp.asarray(view) @ jnp.asarray(model)


def transform_points(matrix, points) -> Array:
    """Apply an affine [4,4] ``matrix`` to ``points`` [N,3] (w = 1), returning [N,3] (no division)."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def clip_coordinates(points, mvp) -> Array:
    """Homogeneous clip coordinates [N,4] of model-space ``points`` [N,3]."""
    return points @ mvp[:, :3].T + mvp[:, 3]


def project(points, mvp, viewport):
    """Model-space ``points`` [N,3] -> (``pixels`` [N,2], ``depth`` [N]).

    pixels follow the module's convention (u right, v down, continuous); depth is clip w (distance along the
    optical axis, scene units; negative behind the camera). viewport: (x0, y0, width, height) in pixels.
    """
    clip = clip_coordinates(points, mvp)
    depth = clip[:, 3]
    ndc = clip[:, :2] / depth[:, None]
    x0, y0, width, height = _viewport(viewport)
    u = x0 + 0.5 * (ndc[:, 0] + 1.0) * width
    v = y0 + 0.5 * (1.0 - ndc[:, 1]) * height
    return jnp.stack([u, v], axis=-1), depth


def unproject(pixels, depth, mvp, viewport) -> Array:
    """Inverse of ``project``: ``pixels`` [N,2] and ``depth`` [N] (clip w) -> model-space points [N,3].

    Solves rows x, y and w of ``mvp @ [x, 1] = clip`` for x; the z row is not needed because depth fixes w.
    Valid for any invertible ``mvp`` whose w row depends on the point (every perspective projection).
    """
    x0, y0, width, height = _viewport(viewport)
    x_ndc = 2.0 * (pixels[:, 0] - x0) / width - 1.0
    y_ndc = 1.0 - 2.0 * (pixels[:, 1] - y0) / height
    rows = mvp[jnp.array([0, 1, 3])]
    rhs = jnp.stack([x_ndc * depth, y_ndc * depth, depth], axis=-1) - rows[:, 3]
    return rhs @ jnp.linalg.inv(rows[:, :3]).T


# --------------------------------------------------------------------------------------------- forcing


def fingertip_forces(tips, positions, normals, radius, magnitude) -> Array:
    """External nodal forces [N,3] from fingertips pushing on a body.

    tips: [K,3] fingertip positions in the body's model frame (a missing fingertip is a row of NaN and
    contributes nothing); positions: [N,3] current nodal positions; normals: [N,3] outward unit normals (zero
    for interior nodes, as ``vertex_normals`` gives); radius: contact radius (model units); magnitude: force
    per node (model force units).

    The rule: every node within ``radius`` of a fingertip receives a force of constant ``magnitude`` along its
    inward normal ``-n_i`` (the finger pushes into the surface, like the training data's loads: a fixed force
    per node on a patch of the surface, into the body); there is no falloff inside the radius and the force is
    exactly zero outside it. (The mixed-reality paper prescribes a load at the tracked fingertip but does not
    spell out a falloff; this choice keeps the loads inside the distribution the model was trained on.) A node touched by
    several fingertips receives one such force per fingertip. Interior nodes have n = 0 and receive nothing.
    """
    distance = jnp.linalg.norm(positions[None, :, :] - tips[:, None, :], axis=-1)  # [K,N]
    touched = jnp.sum(jnp.where(distance < radius, 1.0, 0.0), axis=0)  # NaN compares false
    return -magnitude * touched[:, None] * normals


def contact_forces(positions_a, positions_b, radius, stiffness, capacity: int | None = None):
    """Penalty contact between two bodies: (``forces_a`` [Na,3], ``forces_b`` [Nb,3]).

    Every pair of nodes (i in a, j in b) closer than ``radius`` repels with a linear spring
    ``stiffness · (radius - r_ij)`` along the line between them; this is minus the gradient of the energy
    ``E = Σ_ij ½ · stiffness · max(radius - r_ij, 0)²`` (``contact_energy``). Each pair force acts equally and
    oppositely on its two nodes, so the forces on the two bodies sum to zero, and they are exactly zero when no
    pair is within ``radius``. Positions must be in one common frame (world space); forces come out in that
    frame, in units of stiffness x length. Passing only surface nodes is enough for contact.

    Implementation (exact in every case, no state to carry):
    - bodies whose bounding boxes, grown by ``radius``, are disjoint get zeros at once (``lax.cond``);
    - with a static ``capacity``, only the nodes of each body inside the other's grown box take part (at most
      ``capacity`` per body, gathered with ``jnp.nonzero(size=capacity)``), then all pairs among them; if
      more nodes than ``capacity`` are inside, it falls back to all pairs of the full bodies;
    - with ``capacity=None``, all pairs of the full bodies.
    benchmarks/ar_contact.py measured this against a jax-md neighbour list (allocated outside jit, updated
    every frame) for two touching beams: the pruned version was the fastest there (see results/ar_contact.md).
    """
    lo_a, hi_a = positions_a.min(0) - radius, positions_a.max(0) + radius
    lo_b, hi_b = positions_b.min(0) - radius, positions_b.max(0) + radius
    apart = jnp.any((lo_a > hi_b) | (lo_b > hi_a))
    zeros = (jnp.zeros_like(positions_a), jnp.zeros_like(positions_b))
    full = lambda: _dense_contact(positions_a, positions_b, radius, stiffness)
    if capacity is None:
        return jax.lax.cond(apart, lambda: zeros, full)
    near_a = jnp.all((positions_a >= lo_b) & (positions_a <= hi_b), axis=-1)
    near_b = jnp.all((positions_b >= lo_a) & (positions_b <= hi_a), axis=-1)
    fits = (near_a.sum() <= capacity) & (near_b.sum() <= capacity)
    pruned = lambda: _pruned_contact(positions_a, positions_b, near_a, near_b, radius, stiffness, capacity)
    return jax.lax.cond(apart, lambda: zeros, lambda: jax.lax.cond(fits, pruned, full))


def contact_energy(positions_a, positions_b, radius, stiffness) -> Array:
    """The penalty energy whose negative gradient ``contact_forces`` returns (scalar)."""
    r = jnp.linalg.norm(positions_a[:, None, :] - positions_b[None, :, :], axis=-1)
    return 0.5 * stiffness * jnp.sum(jnp.maximum(radius - r, 0.0) ** 2)


def _dense_contact(positions_a, positions_b, radius, stiffness):
    d = positions_a[:, None, :] - positions_b[None, :, :]
    r = jnp.sqrt(jnp.maximum(jnp.sum(d * d, axis=-1), 1e-30))
    scale = stiffness * jnp.maximum(radius - r, 0.0) / r
    pair = scale[:, :, None] * d
    return pair.sum(1), -pair.sum(0)


def _pruned_contact(positions_a, positions_b, near_a, near_b, radius, stiffness, capacity):
    n_a, n_b = positions_a.shape[0], positions_b.shape[0]
    ia = jnp.nonzero(near_a, size=capacity, fill_value=n_a)[0]
    ib = jnp.nonzero(near_b, size=capacity, fill_value=n_b)[0]
    far = 1e6 * (1.0 + jnp.abs(positions_a).max() + jnp.abs(positions_b).max() + radius)
    xa = jnp.where((ia < n_a)[:, None], positions_a[jnp.minimum(ia, n_a - 1)], far)
    xb = jnp.where((ib < n_b)[:, None], positions_b[jnp.minimum(ib, n_b - 1)], -far)
    fa, fb = _dense_contact(xa, xb, radius, stiffness)
    return (jnp.zeros((n_a + 1, 3), fa.dtype).at[ia].add(fa)[:n_a],
            jnp.zeros((n_b + 1, 3), fb.dtype).at[ib].add(fb)[:n_b])


# ---------------------------------------------------------------------------------- colour and shading


def colour_map(values, vmin, vmax) -> Array:
    """Map ``values`` [...] to RGB [..., 3] in [0, 1] with a fixed colour map (viridis, 9-point linear).

    Values are clipped to [vmin, vmax]; vmin maps to dark purple, vmax to yellow.
    """
    table = jnp.asarray(_COLOUR_TABLE)
    t = jnp.clip((values - vmin) / (vmax - vmin), 0.0, 1.0) * (len(_COLOUR_TABLE) - 1)
    i = jnp.minimum(jnp.floor(t).astype(jnp.int32), len(_COLOUR_TABLE) - 2)
    w = (t - i)[..., None]
    return (1.0 - w) * table[i] + w * table[i + 1]


def vertex_normals(positions, triangles) -> Array:
    """Unit outward vertex normals [N,3] of the (deformed) surface ``triangles`` [T,3] over ``positions`` [N,3].

    Each vertex averages the unit normals of its triangles weighted by the triangle's angle at that vertex,
    which makes the result independent of how faces were split into triangles (a cube corner gets the
    diagonal). Triangles are counter-clockwise seen from outside. Nodes on no triangle get the zero vector.
    """
    p = positions[triangles]                                                 # [T,3,3]
    face = _normalise_rows(jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    e_next = _normalise_rows(jnp.roll(p, -1, axis=1) - p)
    e_prev = _normalise_rows(jnp.roll(p, 1, axis=1) - p)
    angle = jnp.arccos(jnp.clip(jnp.sum(e_next * e_prev, axis=-1), -1.0, 1.0))  # [T,3]
    contrib = angle[:, :, None] * face[:, None, :]
    summed = jnp.zeros_like(positions).at[triangles.reshape(-1)].add(contrib.reshape(-1, 3))
    norm = jnp.linalg.norm(summed, axis=-1, keepdims=True)
    return jnp.where(norm > 0, summed / jnp.maximum(norm, 1e-30), 0.0)


def phong(positions, normals, colours, eye, light_dir, ambient=0.25, diffuse=0.65, specular=0.35,
          shininess=32.0) -> Array:
    """Phong reflection model: RGB [N,3] in [0, 1] at points ``positions`` [N,3] with unit ``normals`` [N,3].

    colours: [N,3] base (ambient and diffuse) colour; eye: [3] camera position; light_dir: [3] direction
    the light travels (a directional light), all in one frame. The result is
    ``ambient·c + diffuse·max(n·l, 0)·c + specular·max(r·e, 0)^shininess`` (white highlight), where l points
    towards the light, r is l reflected about n and e points towards the eye.
    """
    to_light = -_normalise(jnp.asarray(light_dir, jnp.float32))
    to_eye = _normalise_rows(jnp.asarray(eye, jnp.float32) - positions)
    n_dot_l = jnp.sum(normals * to_light, axis=-1, keepdims=True)
    reflected = 2.0 * n_dot_l * normals - to_light
    lit = (n_dot_l > 0).astype(positions.dtype)
    highlight = lit * jnp.maximum(jnp.sum(reflected * to_eye, axis=-1, keepdims=True), 0.0) ** shininess
    rgb = ambient * colours + diffuse * jnp.maximum(n_dot_l, 0.0) * colours + specular * highlight
    return jnp.clip(rgb, 0.0, 1.0)


def occlude(virtual_rgb, virtual_depth, real_rgb, real_depth) -> Array:
    """Composite [H,W,3]: a virtual pixel is shown only where it is nearer than the real depth.

    virtual_depth: [H,W] (inf where nothing virtual was drawn); real_depth: [H,W] from the depth camera
    (same units; inf or 0 where unknown is treated as far away, so the virtual pixel is shown).
    """
    real = jnp.where(real_depth > 0, real_depth, jnp.inf)
    show = (virtual_depth < real)[..., None]
    return jnp.where(show, virtual_rgb, real_rgb)


# -------------------------------------------------------------------------------------------- helpers


def _projection(sx, sy, ox, oy, near, far) -> Array:
    a = (far + near) / (near - far)
    b = 2.0 * far * near / (near - far)
    return jnp.array([
        [sx, 0.0, ox, 0.0],
        [0.0, sy, oy, 0.0],
        [0.0, 0.0, a, b],
        [0.0, 0.0, -1.0, 0.0],
    ], dtype=jnp.float32)


def _affine(linear, translation) -> Array:
    top = jnp.concatenate([linear, translation[:, None]], axis=1)
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype)], axis=0)


def _viewport(viewport):
    x0, y0, width, height = (viewport[i] for i in range(4))
    return x0, y0, width, height


def _normalise(v):
    return v / jnp.linalg.norm(v)


def _normalise_rows(v):
    return v / jnp.maximum(jnp.linalg.norm(v, axis=-1, keepdims=True), 1e-30)


def _concrete(*values) -> bool:
    return all(not isinstance(v, jax.core.Tracer) and np.ndim(v) == 0 for v in values)


def _check_positive_scalars(**values):
    for name, value in values.items():
        if _concrete(value) and not float(value) > 0:
            raise ValueError(f"{name} must be positive, got {name}={value}")


def _check_shape(name, array, shape):
    if tuple(array.shape) != tuple(shape):
        raise ValueError(f"{name} must have shape {shape}, got {tuple(array.shape)}")
