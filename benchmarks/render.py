"""Render time per frame at 640×480: does the render stage fit its share of the frame, and does the JAX
rasteriser beat the same algorithm in NumPy?

Question: the loop's render stage (`tignn_jax.mr.render`) should take ≤ 10 ms at 640×480, so that the simulation
keeps ≥ 23 ms of a 33 ms frame; the library keeps the JAX rasteriser only if it is faster than the same row/span
algorithm in NumPy.

How: three meshes, each shown about 0.2 m across, 0.45 m in front of the camera, and deformed differently every
frame (a travelling bend) so that nothing is cached between frames: the beam (a 40×10×10 box meshed 20×5×5 hex8:
450 boundary quads, 900 triangles), a 1352-node tet4 blob (a 13×13×8-node block, each hex split into 6 tets)
and, where fem/data/bunny.npz is present, the 1330-node bunny (2000 surface triangles). Timed per frame after
compilation, the variants interleaved frame by frame so that each sees the same load from other processes
(p50 / p99 / min over ``--repeats`` frames):

- ``raster_jax``: `tignn_jax.mr.rasterize` alone (projected vertices in, image out), jitted;
- ``raster_numpy``: the same row/span fragment algorithm in NumPy (rows and fragments generated with
  ``np.repeat``, the z-buffer with ``np.minimum.at``; no fragment capacity needed); its image is compared with
  the JAX one;
- ``draw_jax``: the render stage as the loop (`tignn_jax.mr.scene`) runs it, one jitted program:
  `tignn_jax.mr.draw_mesh` (normals, Phong, projection, rasterise), `tignn_jax.mr.occlude` against a real depth
  image, uint8.

Writes ``render.{json,md}`` to ``--out`` (default benchmarks/results) with the CPU and its load average at start
and end (a load above the core count means other processes shared the CPU). ``--quick`` is a smoke test (a few
frames), not a measurement.

    python benchmarks/render.py [--repeats 200]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax import mr
from tignn_jax.mr import draw_mesh, fragment_capacity, rasterize, surface_triangles

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, write_results  # noqa: E402

W, H = 640, 480
MESHES = ("beam_hex8", "blob_tet4", "bunny_tet4")


def box_hex(nx, ny, nz, size):
    ijk = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    node = np.arange(ijk[..., 0].size).reshape(ijk.shape[:3])
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    corners = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))
    cells = np.stack([node[i + a, j + b, k + c] for a, b, c in corners], axis=1)
    return ijk.reshape(-1, 3) * np.asarray(size) / np.array([nx, ny, nz]), cells


def beam():
    return box_hex(20, 5, 5, (40.0, 10.0, 10.0))


def tet_blob():
    points, hexes = box_hex(12, 12, 7, (40.0, 40.0, 25.0))
    split = np.array([[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]])
    c = points - points.mean(0)
    r = np.linalg.norm(c / np.array([20.0, 20.0, 12.5]), axis=1, keepdims=True)
    points = points.mean(0) + c * (0.6 + 0.4 / (1.0 + r))  # round the block into a blob
    return points, hexes[:, split].reshape(-1, 4)


def rasterize_numpy(pixels, depth, colours, triangles, width, height):
    """NumPy version of `tignn_jax.mr.rasterize` (same rows/spans, rules and z-buffer), returning
    (rgb, depth); fragments are generated with ``np.repeat`` (exact sizes, no capacity)."""
    p = pixels[triangles]
    w = depth[triangles]
    x, y = p[..., 0], p[..., 1]
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    visible = (area < 0) & np.all(w > 1e-6, axis=1)
    j0 = np.clip(np.ceil(y.min(1) - 0.5), 0, height).astype(np.int64)
    j1 = np.clip(np.floor(y.max(1) - 0.5) + 1, 0, height).astype(np.int64)
    count = np.where(visible, np.maximum(j1 - j0, 0), 0)
    t = np.repeat(np.arange(len(triangles)), count)                        # one entry per row
    j = j0[t] + np.arange(len(t)) - np.repeat(np.cumsum(count) - count, count)
    yc = (j + 0.5)[:, None]
    ya, yb = y[t], np.roll(y[t], -1, axis=1)
    xa, xb = x[t], np.roll(x[t], -1, axis=1)
    crosses = ((ya <= yc) != (yb <= yc)) | ((ya == yc) & (yb == yc))
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = np.where(yb != ya, xa + (yc - ya) / (yb - ya) * (xb - xa), xa)
    lo = np.where(crosses, np.minimum(xc, np.where(ya == yb, np.minimum(xa, xb), xc)), np.inf).min(1)
    hi = np.where(crosses, np.maximum(xc, np.where(ya == yb, np.maximum(xa, xb), xc)), -np.inf).max(1)
    lo, hi = np.where(np.isfinite(lo), lo, 0.0), np.where(np.isfinite(hi), hi, -1.0)
    i_start = np.clip(np.ceil(lo - 0.5 - 1e-3), 0, width).astype(np.int64)
    span = np.maximum(np.clip(np.floor(hi - 0.5 + 1e-3) + 1, 0, width).astype(np.int64) - i_start, 0)
    row = np.repeat(np.arange(len(t)), span)                                 # one entry per fragment
    px = i_start[row] + np.arange(len(row)) - np.repeat(np.cumsum(span) - span, span)
    py = j[row]
    t = t[row]
    cx, cy = px + 0.5, py + 0.5
    xt, yt = x[t], y[t]
    inv_area = 1.0 / area[t]
    l0 = ((xt[:, 1] - cx) * (yt[:, 2] - cy) - (xt[:, 2] - cx) * (yt[:, 1] - cy)) * inv_area
    l1 = ((xt[:, 2] - cx) * (yt[:, 0] - cy) - (xt[:, 0] - cx) * (yt[:, 2] - cy)) * inv_area
    l2 = 1.0 - l0 - l1
    inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
    t, px, py = t[inside], px[inside], py[inside]
    wt = w[t]
    b = np.stack([l0[inside] / wt[:, 0], l1[inside] / wt[:, 1], l2[inside] / wt[:, 2]], axis=1)
    inv_w = b.sum(1)
    frag_depth = (1.0 / inv_w).astype(np.float32)
    pixel = py * width + px
    zbuf = np.full(width * height, np.inf, np.float32)
    np.minimum.at(zbuf, pixel, frag_depth)
    winner = np.flatnonzero(frag_depth <= zbuf[pixel])
    owner = np.full(width * height, -1, np.int64)
    owner[pixel[winner]] = winner
    drawn = np.flatnonzero(owner >= 0)
    f = owner[drawn]
    rgb = np.zeros((width * height, 3), np.float32)
    weights = b[f] / inv_w[f][:, None]
    rgb[drawn] = np.einsum("pk,pkc->pc", weights, colours[triangles[t[f]]])
    return rgb.reshape(height, width, 3), zbuf.reshape(height, width)


def camera():
    view = mr.look_at([0.05, 0.25, 0.45], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    projection = mr.perspective(np.deg2rad(55.0), W / H, 0.05, 5.0)
    return projection @ view, jnp.array([0.05, 0.25, 0.45])


def deformed(points, frame):
    """A travelling bend, different every frame (model units)."""
    x = points[:, 0] / max(points[:, 0].max(), 1e-9)
    bend = 3.0 * np.sin(0.1 * frame) * x ** 2
    out = points.copy()
    out[:, 1] += bend
    return out


def timings(fns, repeats):
    """Per-call ms of each function in ``fns`` ({name: fn(frame)}), interleaved frame by frame so that every
    variant sees the same background load; {name: {p50_ms, p99_ms, min_ms}}."""
    out = {name: [] for name in fns}
    for i in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn(i)
            out[name].append((time.perf_counter() - t0) * 1e3)
    return {name: {"p50_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)), "min_ms": float(np.min(a))}
            for name, a in out.items()}


def bunny():
    from fem.meshes import BUNNY_FILE, bunny_mesh
    if not BUNNY_FILE.exists():
        return None
    q0, cells, _ = bunny_mesh()
    return q0[:, [0, 2, 1]] * np.array([1.0, 1.0, -1.0]), cells  # z-up -> y-up (a proper rotation)


def bench_mesh(name, points, cells, repeats):
    tris = surface_triangles(cells, points)
    centre = points.mean(0)
    scale = 0.2 / np.ptp(points[:, 0])
    model = mr.model_matrix(-scale * centre, np.eye(3), scale)
    vp, eye = camera()
    frames = [np.asarray(mr.transform_points(model, jnp.asarray(deformed(points, i), jnp.float32)))
              for i in range(16)]
    values = np.linalg.norm(points - centre, axis=1)
    colours = mr.colour_map(jnp.asarray(values), values.min(), values.max())
    light = jnp.array([-0.3, -1.0, -0.5])
    real_depth = jnp.full((H, W), 0.5).at[:, : W // 3].set(0.3)  # a real object covering the left third
    real_rgb = jnp.full((H, W, 3), 0.4)

    proj = [mr.project(jnp.asarray(f), vp, (0.0, 0.0, W, H)) for f in frames]
    pix_np = [(np.asarray(p), np.asarray(d)) for p, d in proj]
    first = jnp.asarray(frames[0])
    shaded = np.asarray(mr.phong(first, mr.vertex_normals(first, jnp.asarray(tris)), colours, eye, light))
    capacity = fragment_capacity(*pix_np[0], tris, W, H, headroom=1.5)
    tris_j = jnp.asarray(tris)
    frames_j = [jnp.asarray(f) for f in frames]

    def raster_jax(i):
        p, d = proj[i % 16]
        rasterize(p, d, shaded, tris_j, width=W, height=H, capacity=capacity).rgb.block_until_ready()

    def raster_np(i):
        p, d = pix_np[i % 16]
        rasterize_numpy(p, d, shaded, tris, W, H)

    @jax.jit
    def render_stage(q, real_rgb, real_depth):
        r = draw_mesh(q, tris_j, colours, vp, eye, light, width=W, height=H, capacity=capacity)
        rgb = mr.occlude(r.rgb, r.depth, real_rgb, real_depth)
        return (jnp.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(jnp.uint8), r.overflow

    def render(q):
        return render_stage(q, real_rgb, real_depth)

    def draw_jax(i):
        render(frames_j[i % 16])[0].block_until_ready()

    for fn in (raster_jax, raster_np, draw_jax):
        fn(0)  # compile / warm up
    ref_rgb, _ = rasterize_numpy(*pix_np[3], shaded, tris, W, H)
    jax_rgb = np.asarray(rasterize(*proj[3], shaded, tris_j, width=W, height=H, capacity=capacity).rgb)
    drawn = int((np.asarray(rasterize(*proj[3], shaded, tris_j, width=W, height=H, capacity=capacity).triangle)
                 >= 0).sum())
    result = {
        "nodes": int(len(points)), "surface_triangles": int(len(tris)), "drawn_pixels": drawn,
        "fragment_capacity": int(capacity),
        "max_abs_diff_jax_vs_numpy": float(np.abs(ref_rgb - jax_rgb).max()),
        "overflow": bool(render(frames_j[0])[1]),
        **timings({"raster_jax": raster_jax, "raster_numpy": raster_np, "draw_jax": draw_jax}, repeats),
    }
    result["numpy_over_jax_p50"] = result["raster_numpy"]["p50_ms"] / result["raster_jax"]["p50_ms"]
    print(name, json.dumps(result), flush=True)
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description="Render time per frame at 640x480: the JAX rasteriser and render stage against the same "
                    "algorithm in NumPy; writes render.{json,md}.")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed frames per mesh and variant, at least 3 (default: 200; --quick: 5)")
    parser.add_argument("--meshes", default=",".join(MESHES),
                        help=f"meshes, comma-separated, from {list(MESHES)}; the bunny only where "
                             "fem/data/bunny.npz is present (default: all)")
    parser.add_argument("--quick", action="store_true", help="a smoke test: 5 frames per mesh (unless --repeats)")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR,
                        help="folder the results are written to (default: benchmarks/results)")
    args = parser.parse_args(argv)
    repeats = args.repeats if args.repeats is not None else 5 if args.quick else 200
    meshes = [m for m in args.meshes.split(",") if m]
    bad = [m for m in meshes if m not in MESHES]
    if bad or not meshes or repeats < 3:
        raise SystemExit(f"--meshes must name some of {list(MESHES)} (unknown: {bad}) and --repeats be ≥ 3, got "
                         f"{args.meshes!r} and {repeats}")
    machine = {**describe(), "numpy": np.__version__}
    makers = {"beam_hex8": beam, "blob_tet4": tet_blob, "bunny_tet4": bunny}
    results = {"machine": machine, "quick": args.quick, "image": [W, H], "repeats": repeats}
    for key in meshes:
        mesh = makers[key]()
        if mesh is not None:   # the bunny without fem/data/bunny.npz
            results[key] = bench_mesh(key, *mesh, repeats)
    machine["load_average_1m_at_end"] = describe()["load_average_1m"]
    lines = ["# Render time per frame, 640×480", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']} ({machine['backend']}), "
             f"numpy {np.__version__}; load average {machine['load_average_1m']} at start, "
             f"{machine['load_average_1m_at_end']} at end ({machine['note']}). {repeats} frames per mesh after "
             "compilation, the variants interleaved frame by frame; min is the least contended frame."
             + (" QUICK RUN (smoke test): not a measurement." if args.quick else ""), "",
             "| mesh | nodes | triangles | pixels drawn | raster JAX p50 / p99 (ms) | raster NumPy p50 / p99 (ms) "
             "| NumPy / JAX (p50) | largest colour difference, JAX vs NumPy | render stage p50 / p99 / min (ms) "
             "| render stage ≤ 10 ms (p50) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for key in (k for k in MESHES if k in results):
        r = results[key]
        d = r["draw_jax"]
        lines.append(f"| {key} | {r['nodes']} | {r['surface_triangles']} | {r['drawn_pixels']} | "
                     f"{r['raster_jax']['p50_ms']:.2f} / {r['raster_jax']['p99_ms']:.2f} | "
                     f"{r['raster_numpy']['p50_ms']:.2f} / {r['raster_numpy']['p99_ms']:.2f} | "
                     f"{r['numpy_over_jax_p50']:.2f} | {r['max_abs_diff_jax_vs_numpy']:.1e} | "
                     f"{d['p50_ms']:.2f} / {d['p99_ms']:.2f} / {d['min_ms']:.2f} | "
                     f"{'yes' if d['p50_ms'] <= 10.0 else 'no'} |")
    lines += ["", "Render stage = vertex normals + Phong + projection + rasterise, then occlusion against a real "
              "depth image + uint8 (one jitted program, as in `tignn_jax.mr.scene`). Target: ≤ 10 ms, so that the "
              "simulation keeps ≥ 23 ms of the 33 ms frame. The NumPy rasteriser is the same algorithm."]
    write_results("render", results, "\n".join(lines) + "\n", folder=args.out, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
