"""Drawing: colour, Phong shading, a software rasteriser for triangle surfaces, and occlusion by a real depth image.

`rasterize` draws triangles given in pixel coordinates and camera depth (the output of
`tignn_jax.mr.camera.project`) into a ``width × height`` image with a z-buffer, back-face culling and
perspective-correct interpolation of depth and colour. Colours are per vertex (already shaded with `phong`: the
Phong reflection evaluated at the vertices of the deformed surface and interpolated across each triangle). Pixel
(i, j) is drawn by a triangle when its centre (i + 0.5, j + 0.5) lies inside it.

How: every front-facing triangle is cut into pixel rows, and each row into the span of pixels whose centres it
may cover; the spans are laid out as candidate fragments in one flat array of static length ``capacity`` (so the
function compiles once). Each fragment is tested with edge functions, and the nearest fragment per pixel wins
through scatters (min depth, then the winner's index, then the winner writes its colour). Against the same
algorithm in NumPy: see benchmarks/render.py. Choose ``capacity`` with `fragment_capacity` outside jit, like a
jax-md neighbour list; ``Raster.overflow`` says when it was too small (fragments beyond it are dropped) and the
caller should re-size it.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax.mr.camera import _normalise, project
from tignn_jax.mr.surface import _normalise_rows, vertex_normals

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

_MIN_DEPTH = 1e-6


class Raster(NamedTuple):
    """A rasterised image.

    Attributes:
      rgb: [H, W, 3] colours in [0, 1] (0 where empty).
      depth: [H, W] camera depth (scene units; inf where empty).
      triangle: [H, W] int32 id of the visible triangle (-1 where empty).
      overflow: () bool: the fragment capacity was too small and some fragments were dropped.
    """
    rgb: Array
    depth: Array
    triangle: Array
    overflow: Array


def colour_map(values, vmin, vmax) -> Array:
    """Map values to RGB with a fixed colour map (viridis, 9-point piecewise linear).

    Args:
      values: [...] values; clipped to [vmin, vmax].
      vmin: the value shown dark purple.
      vmax: the value shown yellow.

    Returns:
      [..., 3] RGB in [0, 1].
    """
    table = jnp.asarray(_COLOUR_TABLE)
    t = jnp.clip((values - vmin) / (vmax - vmin), 0.0, 1.0) * (len(_COLOUR_TABLE) - 1)
    i = jnp.minimum(jnp.floor(t).astype(jnp.int32), len(_COLOUR_TABLE) - 2)
    w = (t - i)[..., None]
    return (1.0 - w) * table[i] + w * table[i + 1]


def von_mises(sigma) -> Array:
    """The von Mises equivalent stress, what a body is coloured by.

    σ_vM = sqrt(½ [(s11 - s22)² + (s22 - s33)² + (s33 - s11)²] + 3 (s12² + s13² + s23²)).

    Args:
      sigma: [N, 6] Cauchy stress in S11, S22, S33, S12, S13, S23 order.

    Returns:
      [N] equivalent stress (stress units of ``sigma``).
    """
    s11, s22, s33, s12, s13, s23 = (sigma[:, i] for i in range(6))
    return jnp.sqrt(jnp.maximum(0.5 * ((s11 - s22) ** 2 + (s22 - s33) ** 2 + (s33 - s11) ** 2)
                                + 3.0 * (s12 ** 2 + s13 ** 2 + s23 ** 2), 0.0))


def phong(positions, normals, colours, eye, light_dir, ambient=0.25, diffuse=0.65, specular=0.35,
          shininess=32.0) -> Array:
    """The Phong reflection model under a directional light, with a white highlight.

    rgb = ambient · c + diffuse · max(n·l, 0) · c + specular · max(r·e, 0)^shininess (clipped to [0, 1]), where l
    points towards the light, r is l reflected about n and e points towards the eye; no highlight where n·l <= 0.

    Args:
      positions: [N, 3] shaded points.
      normals: [N, 3] unit normals.
      colours: [N, 3] base (ambient and diffuse) colour.
      eye: [3] camera position, in the positions' frame.
      light_dir: [3] direction the light travels, same frame.
      ambient: ambient weight.
      diffuse: diffuse weight.
      specular: specular weight.
      shininess: specular exponent.

    Returns:
      [N, 3] RGB in [0, 1].
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
    """Composite a virtual image over a real one: a virtual pixel is shown only where it is nearer than the real
    depth.

    Args:
      virtual_rgb: [H, W, 3] rendered colours.
      virtual_depth: [H, W] rendered depth (inf where nothing virtual was drawn).
      real_rgb: [H, W, 3] camera image.
      real_depth: [H, W] depth camera image, same units; inf or 0 where unknown, treated as far away (the virtual
        pixel is shown).

    Returns:
      [H, W, 3] composite.
    """
    real = jnp.where(real_depth > 0, real_depth, jnp.inf)
    show = (virtual_depth < real)[..., None]
    return jnp.where(show, virtual_rgb, real_rgb)


@partial(jax.jit, static_argnames=("width", "height", "capacity"))
def rasterize(pixels, depth, colours, triangles, *, width: int, height: int, capacity: int) -> Raster:
    """Draw triangles with a z-buffer, back-face culling and perspective-correct interpolation.

    Triangles with a vertex at depth <= 0 (behind the camera) or a non-finite vertex are not drawn, nor are back
    faces.

    Args:
      pixels: [N, 2] vertex pixel coordinates (`tignn_jax.mr.camera.project`).
      depth: [N] vertex camera depth.
      colours: [N, 3] vertex RGB.
      triangles: [T, 3] int vertex ids, counter-clockwise seen from the camera's side (front-facing).
      width: image width (pixels), static.
      height: image height (pixels), static.
      capacity: fragment buffer length, static (the row buffer is ``capacity // 2`` long; `fragment_capacity`).

    Returns:
      A `Raster` of ``height × width`` pixels.
    """
    x, y, w, area, visible = _setup(pixels, depth, triangles)
    rows = _row_spans(x, y, visible, width, height, capacity // 2)
    span_end = jnp.cumsum(rows.span)
    total = span_end[-1]

    k = jnp.arange(capacity, dtype=jnp.int32)
    r = _owner_of(span_end, capacity)            # row of fragment k
    t = rows.triangle[r]
    px = rows.i_start[r] + k - (span_end[r] - rows.span[r])
    py = rows.j[r]
    cx, cy = px + 0.5, py + 0.5
    xt, yt = x[t], y[t]
    inv_area = 1.0 / area[t]
    l0 = ((xt[:, 1] - cx) * (yt[:, 2] - cy) - (xt[:, 2] - cx) * (yt[:, 1] - cy)) * inv_area
    l1 = ((xt[:, 2] - cx) * (yt[:, 0] - cy) - (xt[:, 0] - cx) * (yt[:, 2] - cy)) * inv_area
    l2 = 1.0 - l0 - l1
    inside = (k < total) & (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
    wt = w[t]
    b = jnp.stack([l0 / wt[:, 0], l1 / wt[:, 1], l2 / wt[:, 2]], axis=1)   # perspective-correct weights
    inv_w = b.sum(1)
    frag_depth = jnp.where(inside, 1.0 / inv_w, jnp.inf)
    pixel = jnp.where(inside, py * width + px, width * height)

    n_pix = width * height
    zbuf = jnp.full((n_pix,), jnp.inf, frag_depth.dtype).at[pixel].min(frag_depth, mode="drop")
    winner = inside & (frag_depth <= zbuf[jnp.minimum(pixel, n_pix - 1)])
    owner = jnp.full((n_pix,), -1, jnp.int32).at[jnp.where(winner, pixel, n_pix)].max(k, mode="drop")

    # Each pixel's winning fragment writes its colour and triangle id (a scatter computes every fragment's
    # colour once; gathering per pixel instead makes XLA recompute the shading for every pixel and corner).
    first = winner & (owner[jnp.minimum(pixel, n_pix - 1)] == k)
    target = jnp.where(first, pixel, n_pix)
    corner = triangles[t]                                                       # [C,3]
    frag_rgb = (b[:, 0:1] * colours[corner[:, 0]] + b[:, 1:2] * colours[corner[:, 1]]
                + b[:, 2:3] * colours[corner[:, 2]]) / inv_w[:, None]
    rgb = jnp.zeros((n_pix, 3), frag_rgb.dtype).at[target].set(frag_rgb, mode="drop").reshape(height, width, 3)
    triangle = jnp.full((n_pix,), -1, jnp.int32).at[target].set(t, mode="drop").reshape(height, width)
    overflow = (total > capacity) | (rows.total > capacity // 2)
    return Raster(rgb=rgb, depth=zbuf.reshape(height, width), triangle=triangle, overflow=overflow)


@partial(jax.jit, static_argnames=("width", "height", "capacity"))
def draw_mesh(positions, triangles, colours, view_projection, eye, light_dir, *, width: int, height: int,
              capacity: int) -> Raster:
    """Shade and rasterise a deformed surface.

    Vertex normals of the deformed surface (`tignn_jax.mr.surface.vertex_normals`) -> `phong` at the vertices ->
    projection onto a full-image viewport -> `rasterize`. Nodes on no triangle are ignored.

    Args:
      positions: [N, 3] world positions.
      triangles: [T, 3] outward (counter-clockwise) triangles.
      colours: [N, 3] base RGB (e.g. `colour_map` of a state variable).
      view_projection: [4, 4] P @ V.
      eye: [3] camera position (world).
      light_dir: [3] direction a directional light travels (world).
      width: image width (pixels), static.
      height: image height (pixels), static.
      capacity: fragment buffer length, static.

    Returns:
      A `Raster`.
    """
    normals = vertex_normals(positions, triangles)
    shaded = phong(positions, normals, colours, eye, light_dir)
    pixels, depth = project(positions, view_projection, (0.0, 0.0, float(width), float(height)))
    return rasterize(pixels, depth, shaded, triangles, width=width, height=height, capacity=capacity)


def fragment_capacity(pixels, depth, triangles, width: int, height: int, headroom: float = 1.5,
                      minimum: int = 4096) -> int:
    """The fragment buffer length for `rasterize`: ``headroom`` × what one frame needs. Not jit-able.

    Call once on a representative frame (e.g. the first), like allocating a neighbour list; a deforming mesh seen
    from a fixed camera needs little headroom. Covers the row buffer (``capacity // 2``) too.

    Args:
      pixels: [N, 2] vertex pixel coordinates of the frame.
      depth: [N] vertex camera depth.
      triangles: [T, 3] triangles.
      width: image width (pixels).
      height: image height (pixels).
      headroom: factor over the frame's need, >= 1.
      minimum: the smallest capacity returned.

    Returns:
      The capacity (int).

    Raises:
      ValueError: ``headroom`` < 1.
    """
    if headroom < 1.0:
        raise ValueError(f"headroom must be >= 1, got headroom={headroom}")
    x, y, _, _, visible = _setup(jnp.asarray(pixels, jnp.float32), jnp.asarray(depth, jnp.float32),
                                 jnp.asarray(triangles, jnp.int32))
    j0 = np.clip(np.ceil(np.asarray(y).min(1) - 0.5), 0, height)
    j1 = np.clip(np.floor(np.asarray(y).max(1) - 0.5) + 1, 0, height)
    n_rows = int(np.sum(np.where(np.asarray(visible), np.maximum(j1 - j0, 0), 0)))
    rows = jax.jit(_row_spans, static_argnums=(3, 4, 5))(x, y, visible, width, height, max(n_rows, 1))
    needed = max(int(rows.span.sum()), 2 * n_rows)
    return max(int(np.ceil(headroom * needed)), minimum)


class _Rows(NamedTuple):
    triangle: Array   # [R] triangle of each row
    j: Array          # [R] pixel row
    i_start: Array    # [R] first pixel column of the span
    span: Array       # [R] pixels in the span (0 for padding rows)
    total: Array      # () rows needed (may exceed R)


def _setup(pixels, depth, triangles):
    p = pixels[triangles]                  # [T,3,2]
    w = depth[triangles]                   # [T,3]
    x, y = p[..., 0], p[..., 1]
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    # counter-clockwise in a y-up frame is clockwise in pixels (v down): front faces have area < 0
    finite = jnp.all(jnp.isfinite(p), axis=(1, 2)) & jnp.all(jnp.isfinite(w), axis=1)
    visible = (area < 0) & jnp.all(w > _MIN_DEPTH, axis=1) & finite
    return x, y, w, area, visible


def _row_spans(x, y, visible, width, height, n_rows) -> _Rows:
    """The pixel rows each visible triangle crosses and, on each, the columns whose centres it may cover
    (its exact extent on the row's centre line, widened by 1e-3 pixel; the edge test decides)."""
    j0 = jnp.clip(jnp.ceil(y.min(1) - 0.5), 0, height).astype(jnp.int32)
    j1 = jnp.clip(jnp.floor(y.max(1) - 0.5) + 1, 0, height).astype(jnp.int32)
    count = jnp.where(visible, jnp.maximum(j1 - j0, 0), 0)
    end = jnp.cumsum(count)
    r = jnp.arange(n_rows, dtype=jnp.int32)
    t = _owner_of(end, n_rows)
    j = j0[t] + r - (end[t] - count[t])
    yc = j + 0.5
    xt, yt = x[t], y[t]
    xa, ya = xt, yt
    xb, yb = jnp.roll(xt, -1, axis=1), jnp.roll(yt, -1, axis=1)
    crosses = ((ya <= yc[:, None]) != (yb <= yc[:, None])) | ((ya == yc[:, None]) & (yb == yc[:, None]))
    s = jnp.where(yb != ya, (yc[:, None] - ya) / jnp.where(yb != ya, yb - ya, 1.0), 0.0)
    xc = xa + s * (xb - xa)
    lo = jnp.where(crosses, jnp.minimum(xc, jnp.where(ya == yb, jnp.minimum(xa, xb), xc)), jnp.inf).min(1)
    hi = jnp.where(crosses, jnp.maximum(xc, jnp.where(ya == yb, jnp.maximum(xa, xb), xc)), -jnp.inf).max(1)
    lo = jnp.where(jnp.isfinite(lo), lo, 0.0)
    hi = jnp.where(jnp.isfinite(hi), hi, -1.0)
    i_start = jnp.clip(jnp.ceil(lo - 0.5 - 1e-3), 0, width).astype(jnp.int32)
    i_end = jnp.clip(jnp.floor(hi - 0.5 + 1e-3) + 1, 0, width).astype(jnp.int32)
    span = jnp.where(r < end[-1], jnp.maximum(i_end - i_start, 0), 0)
    return _Rows(triangle=t, j=j, i_start=i_start, span=span, total=end[-1])


def _owner_of(end, size):
    """For k in 0..size-1, the index of the segment containing k, given segment ends ``end`` (a cumsum):
    the number of segments ending at or before k (a searchsorted, as a scatter and a cumsum)."""
    owner = jnp.cumsum(jnp.zeros((size,), jnp.int32).at[end].add(1, mode="drop"))
    return jnp.minimum(owner, end.shape[0] - 1)
