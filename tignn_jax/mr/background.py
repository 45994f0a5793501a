"""The real image a scene is drawn over: a camera's RGB and depth, a synthetic table, and a hand proxy that rests
on the bodies' deformed surface.

Depths are in metres along the camera's optical axis (the depth camera's unit and `tignn_jax.mr.camera`'s
``depth``).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax.mr.camera import Camera


class Background(NamedTuple):
    """The real image.

    Attributes:
      rgb: [H, W, 3] colours in [0, 1].
      depth: [H, W] depth (m; 0 = unknown).
    """
    rgb: np.ndarray
    depth: np.ndarray


def table_background(camera: Camera, table_height: float = 0.0, wall_distance: float = 1.5,
                     tile: float = 0.05) -> Background:
    """A synthetic real image: a grey checkered table and a plain wall where the table is not seen.

    Each pixel's ray from the camera meets the table (the world plane y = ``table_height``, y up) at the ray
    parameter s = (table_height - o_y) / d_y, which with the ray's direction scaled to unit depth is the depth.

    Args:
      camera: the camera whose image it is.
      table_height: the table's world y (m).
      wall_distance: depth of the wall (m), and the farthest table shown.
      tile: edge of the checker's squares (m).

    Returns:
      A `Background` of the camera's size (float32).
    """
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    rays = np.stack([(u - camera.cx) / camera.fx, -(v - camera.cy) / camera.fy, -np.ones_like(u)], -1)  # eye
    to_world = np.linalg.inv(np.asarray(camera.view, np.float64))
    origin = to_world[:3, 3]
    dirs = rays @ to_world[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (table_height - origin[1]) / dirs[..., 1]   # ray parameter = depth along the optical axis
    on_table = (s > 0) & (s < wall_distance)
    depth = np.where(on_table, s, wall_distance)
    hit = origin + np.where(on_table, s, 0.0)[..., None] * dirs
    checker = (np.floor(hit[..., 0] / tile) + np.floor(hit[..., 2] / tile)) % 2
    table = (0.55 + 0.12 * checker)[..., None] * np.array([0.85, 0.8, 0.72])
    wall = np.broadcast_to(np.array([0.78, 0.8, 0.83]), table.shape)
    rgb = np.where(on_table[..., None], table, wall)
    return Background(rgb=rgb.astype(np.float32), depth=depth.astype(np.float32))


def hand_proxy(rgb, depth, tips, camera: Camera, radius: float):
    """Draw a hand proxy into the real image: for each fingertip a finger of 4 shaded spheres from the tip
    towards the camera and down the image, the way a hand reaching in is seen.

    Each sphere is drawn inside a fixed-size window around its centre (sized for spheres at >= 0.1 m), so the
    cost does not depend on the image size. Jit-able (``camera`` and ``radius`` static).

    Args:
      rgb: [H, W, 3] real image.
      depth: [H, W] real depth (m).
      tips: [K, 3] fingertips as (u, v, depth_m) (the track format, `tignn_jax.mr.track`); rows with a
        non-finite value or a depth nearer than ``camera.near`` are not drawn.
      camera: the camera.
      radius: the spheres' radius (m); <= 0 draws nothing.

    Returns:
      (rgb [H, W, 3], depth [H, W]) with the spheres drawn where they are nearer than the image.
    """
    if radius <= 0:
        return rgb, depth
    steps = jnp.linspace(0.0, 1.0, 4)[:, None] * jnp.array([0.0, 0.05, -0.04])  # (down m, down m, depth m)
    d = tips[:, None, 2] + steps[None, :, 2]
    centres = jnp.stack([tips[:, None, 0] + 0.0 * d,
                         tips[:, None, 1] + steps[None, :, 1] * camera.fy / tips[:, None, 2], d], -1)
    win = _window(camera, radius)
    offs = jnp.arange(win, dtype=jnp.float32)
    skin = jnp.array([0.93, 0.72, 0.6], jnp.float32)
    for c in centres.reshape(-1, 3):
        ok = jnp.all(jnp.isfinite(c)) & (c[2] > camera.near)
        i0, j0 = _corner(c, win, camera)
        u = i0 + offs + 0.5
        v = j0 + offs + 0.5
        rho = camera.fx * radius / c[2]
        r2 = ((u[None, :] - c[0]) ** 2 + (v[:, None] - c[1]) ** 2) / rho ** 2
        cos = jnp.sqrt(jnp.maximum(1.0 - r2, 0.0))
        sphere = c[2] - radius * cos
        window = jax.lax.dynamic_slice(depth, (j0, i0), (win, win))
        hit = ok & (r2 < 1.0) & (sphere < window)
        depth = jax.lax.dynamic_update_slice(depth, jnp.where(hit, sphere, window), (j0, i0))
        colour = jax.lax.dynamic_slice(rgb, (j0, i0, 0), (win, win, 3))
        shaded = (0.35 + 0.6 * cos)[..., None] * skin
        rgb = jax.lax.dynamic_update_slice(rgb, jnp.where(hit[..., None], shaded, colour), (j0, i0, 0))
    return rgb, depth


def rest_on_surface(tips, depth, camera: Camera, radius: float, touching=None):
    """Move each fingertip that touches a body towards the camera until its sphere rests on the rendered surface
    instead of sinking into it.

    A fingertip pressing a soft body is tracked into it (the press goes deeper than the body gives way), but a
    finger cannot be inside the body: it touches the deformed surface. Along each pixel p of the sphere's
    footprint (radius ρ = f r / d pixels, ρ(p) its distance from the centre over ρ) the sphere reaches depth
    d + r √(1 − ρ(p)²); it rests on the surface s(p) at

        d* = min_p [s(p) − r √(1 − ρ(p)²)],

    and a touching tip's depth becomes min(d, d*); the image coordinates are kept. A tip that does not touch a body
    and lies behind one stays behind it. Jit-able (``camera`` and ``radius`` static).

    Args:
      tips: [K, 3] fingertips as (u, v, depth_m); rows with a non-finite value are returned unchanged.
      depth: [H, W] rendered depth of the bodies (m; inf where none, `tignn_jax.mr.render.Raster`).
      camera: the camera.
      radius: the proxy spheres' radius (m); <= 0 returns ``tips`` unchanged.
      touching: [K] bool, the fingertips in contact with a body (as the scene's forces see it: a node within the
        body's ``tip_radius``); None: all.

    Returns:
      [K, 3] the fingertips, touching ones moved onto the surface.
    """
    if radius <= 0:
        return tips
    touching = jnp.ones(tips.shape[0], bool) if touching is None else jnp.asarray(touching, bool)
    win = _window(camera, radius)
    offs = jnp.arange(win, dtype=jnp.float32)

    def one(tip, touch):
        ok = jnp.all(jnp.isfinite(tip)) & (tip[2] > camera.near)
        i0, j0 = _corner(tip, win, camera)
        d = jnp.where(ok, tip[2], 1.0)
        rho = camera.fx * radius / d
        r2 = (((i0 + offs + 0.5)[None, :] - tip[0]) ** 2 + ((j0 + offs + 0.5)[:, None] - tip[1]) ** 2) / rho ** 2
        surface = jax.lax.dynamic_slice(depth, (j0, i0), (win, win))
        rest = jnp.min(jnp.where(r2 < 1.0, surface - radius * jnp.sqrt(jnp.maximum(1.0 - r2, 0.0)), jnp.inf))
        return tip.at[2].set(jnp.where(ok & touch & (d > rest), rest, tip[2]))

    return jax.vmap(one)(tips, touching)


def _window(camera: Camera, radius: float) -> int:
    """The side (pixels) of the square window a sphere of ``radius`` is drawn or sampled in, sized for spheres at
    >= 0.1 m from the camera, at most the image."""
    return int(min(camera.height, camera.width, 2 * np.ceil(max(camera.fx, camera.fy) * radius / 0.1) + 4))


def _corner(centre, win: int, camera: Camera):
    """(column, row) int32 of the top-left pixel of the ``win``-pixel window around ``centre`` (u, v, ...), kept
    inside the image (a non-finite centre gives some window: its caller masks it)."""
    i0 = jnp.clip(jnp.nan_to_num(jnp.floor(centre[0]) - win // 2), 0, camera.width - win).astype(jnp.int32)
    j0 = jnp.clip(jnp.nan_to_num(jnp.floor(centre[1]) - win // 2), 0, camera.height - win).astype(jnp.int32)
    return i0, j0
