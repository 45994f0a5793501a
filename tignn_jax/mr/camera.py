"""Camera maths: projection, view and model matrices, and projecting points to pixels and back.

Every function here is pure and jit-able (arrays in, arrays out, nothing cached), except `camera_projection`,
which returns a NumPy matrix.

Conventions (OpenGL):

* Eye space is right-handed; the camera sits at the origin looking down -z with +y up.
* ``clip = P · V · M · [x, 1]`` (``mvp = P @ V @ M``, [4, 4] matrices acting on column vectors). Normalised
  device coordinates are ``clip[:3] / clip[3]`` and the visible frustum is the cube [-1, 1]³: a point on the near
  plane has z_ndc = -1, one on the far plane z_ndc = +1.
* ``depth`` is the clip coordinate w, which for a perspective ``P`` equals -z_eye: the distance from the camera
  along its optical axis, in scene units (metres in the scenes of `tignn_jax.mr.scene`). It is what a depth
  camera reports, so it is compared directly with a real depth image.
* Pixels are continuous image coordinates (u right, v down, origin at the top-left corner of the image); pixel
  (i, j) covers [i, i+1) × [j, j+1) and its centre is (i + 0.5, j + 0.5). A viewport ``(x0, y0, width, height)``
  maps ``u = x0 + (x_ndc + 1) / 2 · width`` and ``v = y0 + (1 - y_ndc) / 2 · height``. A normalised landmark
  (x, y) in [0, 1]², as MediaPipe gives, is the pixel ``(x · width, y · height)``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


class Camera(NamedTuple):
    """A pinhole camera.

    Attributes:
      fx: horizontal focal length (pixels).
      fy: vertical focal length (pixels).
      cx: principal point's u (pixels, the module's convention).
      cy: principal point's v (pixels, v down).
      width: image width (pixels).
      height: image height (pixels).
      near: distance of the near clipping plane (m).
      far: distance of the far clipping plane (m).
      view: [4, 4] extrinsics, world -> camera (OpenGL: the camera looks down its -z axis).
    """
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float
    far: float
    view: np.ndarray


def camera_projection(camera: Camera) -> np.ndarray:
    """The OpenGL projection matrix of a camera's intrinsics, for a full-image viewport.

    Args:
      camera: the camera.

    Returns:
      [4, 4] NumPy float32 matrix (`projection_from_intrinsics` of the camera's intrinsics).
    """
    return np.asarray(projection_from_intrinsics(camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                                                 camera.height, camera.near, camera.far))


def perspective(fov_y, aspect, near, far) -> Array:
    """The OpenGL perspective projection matrix.

    Maps z_eye = -near to z_ndc = -1 and z_eye = -far to z_ndc = +1, and sets clip w = -z_eye.

    Args:
      fov_y: vertical field of view (radians).
      aspect: width / height.
      near: distance of the near clipping plane along the optical axis (scene units), > 0.
      far: distance of the far clipping plane (scene units), > near.

    Returns:
      [4, 4] float32 matrix.

    Raises:
      ValueError: a concrete argument that is not positive, or ``far <= near``.
    """
    _check_positive_scalars(fov_y=fov_y, aspect=aspect, near=near, far=far)
    if _concrete(near, far) and not float(far) > float(near):
        raise ValueError(f"far must exceed near, got near={near}, far={far}")
    f = 1.0 / jnp.tan(0.5 * jnp.asarray(fov_y, jnp.float32))
    return _projection(f / aspect, f, 0.0, 0.0, near, far)


def projection_from_intrinsics(fx, fy, cx, cy, width, height, near, far) -> Array:
    """The OpenGL projection matrix equivalent to pinhole intrinsics, for a full-image viewport.

    With ``viewport = (0, 0, width, height)``, `project` then gives the pinhole model::

        u = fx · x_e / (-z_e) + cx,   v = -fy · y_e / (-z_e) + cy   (eye y is up, v is down).

    Args:
      fx: horizontal focal length (pixels).
      fy: vertical focal length (pixels).
      cx: principal point's u (pixels).
      cy: principal point's v (pixels, v down).
      width: image width (pixels).
      height: image height (pixels).
      near: near clipping distance (scene units).
      far: far clipping distance (scene units).

    Returns:
      [4, 4] float32 matrix.

    Raises:
      ValueError: a concrete ``fx``, ``fy``, ``width``, ``height``, ``near`` or ``far`` that is not positive.
    """
    _check_positive_scalars(fx=fx, fy=fy, width=width, height=height, near=near, far=far)
    return _projection(2.0 * fx / width, 2.0 * fy / height,
                       1.0 - 2.0 * cx / width, 2.0 * cy / height - 1.0, near, far)


def look_at(eye, target, up) -> Array:
    """The view matrix (world -> eye space) of a camera at ``eye`` looking at ``target``.

    The eye maps to the origin and the target onto the negative z axis, at distance |target - eye|.

    Args:
      eye: [3] camera position (world).
      target: [3] point looked at (world).
      up: [3] the up direction; need not be orthogonal to the viewing direction but must not be parallel to it.

    Returns:
      [4, 4] float32 rigid transform.

    Raises:
      ValueError: an argument that is not of shape [3].
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
    """The rotation by ``angle`` about ``axis`` (right-hand rule), by Rodrigues' formula.

    R = I + sin θ K + (1 - cos θ) K², K the cross-product matrix of the unit axis.

    Args:
      axis: [3] rotation axis (any length > 0).
      angle: rotation angle (radians).

    Returns:
      [3, 3] rotation matrix.
    """
    axis = _normalise(jnp.asarray(axis, jnp.float32))
    k = jnp.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * k + (1.0 - jnp.cos(angle)) * (k @ k)


def model_matrix(translation, rotation, scale) -> Array:
    """The model matrix (model -> world) of a pose with a scale.

    x_world = translation + rotation @ (scale * x_model).

    Args:
      translation: [3] (world units).
      rotation: [3, 3] rotation matrix.
      scale: scalar or [3], world units per model unit (e.g. 0.005 to show the 40-unit beam as a 0.2 m object in a
        scene measured in metres).

    Returns:
      [4, 4] float32 affine matrix.

    Raises:
      ValueError: ``translation`` is not [3] or ``rotation`` not [3, 3].
    """
    translation = jnp.asarray(translation, jnp.float32)
    rotation = jnp.asarray(rotation, jnp.float32)
    _check_shape("translation", translation, (3,))
    _check_shape("rotation", rotation, (3, 3))
    scale = jnp.broadcast_to(jnp.asarray(scale, jnp.float32), (3,))
    return _affine(rotation * scale[None, :], translation)


def mvp_matrix(projection, view, model) -> Array:
    """The product ``P @ V @ M`` [4, 4]: model space -> clip space."""
    return jnp.asarray(projection) @ jnp.asarray(view) @ jnp.asarray(model)


def transform_points(matrix, points) -> Array:
    """Apply an affine ``matrix`` [4, 4] to ``points`` [N, 3] (w = 1, no division); returns [N, 3]."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def clip_coordinates(points, mvp) -> Array:
    """The homogeneous clip coordinates [N, 4] of model-space ``points`` [N, 3] under ``mvp`` [4, 4]."""
    return points @ mvp[:, :3].T + mvp[:, 3]


def project(points, mvp, viewport):
    """Project model-space points to pixels and camera depth.

    Args:
      points: [N, 3] model-space points.
      mvp: [4, 4] model -> clip matrix (`mvp_matrix`).
      viewport: (x0, y0, width, height) in pixels.

    Returns:
      (pixels [N, 2] in the module's convention (u right, v down, continuous), depth [N]: clip w, the distance
      along the optical axis in scene units, negative behind the camera).
    """
    clip = clip_coordinates(points, mvp)
    depth = clip[:, 3]
    ndc = clip[:, :2] / depth[:, None]
    x0, y0, width, height = _viewport(viewport)
    u = x0 + 0.5 * (ndc[:, 0] + 1.0) * width
    v = y0 + 0.5 * (1.0 - ndc[:, 1]) * height
    return jnp.stack([u, v], axis=-1), depth


def unproject(pixels, depth, mvp, viewport) -> Array:
    """The inverse of `project`: model-space points from pixels and camera depth.

    Solves rows x, y and w of ``mvp @ [x, 1] = clip`` for x; the z row is not needed because the depth fixes w.
    Valid for any invertible ``mvp`` whose w row depends on the point (every perspective projection).

    Args:
      pixels: [N, 2] pixel coordinates (module's convention).
      depth: [N] clip w (scene units).
      mvp: [4, 4] model -> clip matrix.
      viewport: (x0, y0, width, height) in pixels.

    Returns:
      [N, 3] model-space points.
    """
    x0, y0, width, height = _viewport(viewport)
    x_ndc = 2.0 * (pixels[:, 0] - x0) / width - 1.0
    y_ndc = 1.0 - 2.0 * (pixels[:, 1] - y0) / height
    rows = mvp[jnp.array([0, 1, 3])]
    rhs = jnp.stack([x_ndc * depth, y_ndc * depth, depth], axis=-1) - rows[:, 3]
    return rhs @ jnp.linalg.inv(rows[:, :3]).T


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


def _concrete(*values) -> bool:
    return all(not isinstance(v, jax.core.Tracer) and np.ndim(v) == 0 for v in values)


def _check_positive_scalars(**values):
    for name, value in values.items():
        if _concrete(value) and not float(value) > 0:
            raise ValueError(f"{name} must be positive, got {name}={value}")


def _check_shape(name, array, shape):
    if tuple(array.shape) != tuple(shape):
        raise ValueError(f"{name} must have shape {shape}, got {tuple(array.shape)}")
