"""Object-object contact forces: dense all-pairs (tignn_jax.ar.contact_forces) against jax-md neighbour lists.

Two bodies side by side with a strip of nodes within the contact radius, as in the two-beam scene:
- ``beams``: two 40x10x10 beams (20x5x5 hex, 756 nodes each), the second 10.5 units to the side (gap 0.5 < radius 1);
- ``beam_surfaces``: the same with only the 452 surface nodes of each beam (what the scene passes);
- ``blobs``: two 1352-node bodies (a 13x13x8-node grid, like the bunny's node count) 0.5 apart.

Variants (each jitted; medians / p99 / min over repeats after compilation, interleaved call by call so each
sees the same load from other jobs; all give the same forces):
- ``dense``: all pairs in one fused loop (no bounding-box test);
- ``dense_cond``: ``contact_forces(..., capacity=None)``: the same behind a bounding-box ``lax.cond``;
- ``pruned`` (what the scenes use): ``contact_forces(..., capacity=C)``: only nodes inside the other body's grown
  bounding box take part (C = 2x their count here); also timed with the bodies far apart (``pruned_apart``), the
  common case in a scene;
- ``jaxmd_cell``: jax-md sparse neighbour list with its cell list, allocated outside jit, ``update`` + pair
  forces inside jit every call (positions change every frame);
- ``jaxmd_nocell``: the same with ``disable_cell_list=True`` (its O(N^2) builder; seconds per call, so timed
  separately with repeats / 20).

Run: ``python benchmarks/ar_contact.py [--repeats 200]``; writes benchmarks/results/ar_contact.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax_md import partition, space

from tignn_jax import ar
from tignn_jax.render import surface_nodes, surface_triangles

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
RADIUS, STIFFNESS = 1.0, 1e4


def grid(nx, ny, nz, size):
    ijk = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    node = np.arange(ijk[..., 0].size).reshape(ijk.shape[:3])
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    corners = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))
    cells = np.stack([node[i + a, j + b, k + c] for a, b, c in corners], axis=1)
    return (ijk.reshape(-1, 3) * np.asarray(size) / np.array([nx, ny, nz])).astype(np.float32), cells


def cases():
    beam, cells = grid(20, 5, 5, (40.0, 10.0, 10.0))
    surf = beam[surface_nodes(surface_triangles(cells, beam))]
    blob, _ = grid(12, 12, 7, (36.0, 36.0, 21.0))
    return {
        "beams": (beam, beam + np.array([0.0, 10.5, 0.0], np.float32)),
        "beam_surfaces": (surf, surf + np.array([0.0, 10.5, 0.0], np.float32)),
        "blobs": (blob, blob + np.array([0.0, 36.5, 0.0], np.float32)),
    }


def jaxmd_contact(a, b, cell_list: bool):
    """A jax-md neighbour-list version: returns (allocate-time nbrs, jitted fn(a, b, nbrs) -> (fa, fb, nbrs))."""
    na = len(a)
    both = np.concatenate([a, b])
    lo = both.min(0) - 5.0
    box = (both.max(0) - lo + 10.0).astype(np.float32)
    displacement, _ = space.free()
    neighbor_fn = partition.neighbor_list(displacement, jnp.asarray(box), RADIUS, dr_threshold=0.0,
                                          capacity_multiplier=1.5, disable_cell_list=not cell_list,
                                          format=partition.NeighborListFormat.Sparse)
    nbrs = neighbor_fn.allocate(jnp.asarray(both - lo))

    @jax.jit
    def forces(a, b, nbrs):
        x = jnp.concatenate([a, b]) - lo
        nbrs = nbrs.update(x)
        i, j = nbrs.idx
        valid = (i < na) & (j >= na) & (j < len(x))
        d = x[jnp.minimum(i, len(x) - 1)] - x[jnp.minimum(j, len(x) - 1)]
        r = jnp.sqrt(jnp.maximum(jnp.sum(d * d, -1), 1e-30))
        pair = jnp.where(valid, STIFFNESS * jnp.maximum(RADIUS - r, 0.0) / r, 0.0)[:, None] * d
        fa = jax.ops.segment_sum(pair, jnp.where(valid, i, len(x)), num_segments=len(x) + 1)[:na]
        fb = -jax.ops.segment_sum(pair, jnp.where(valid, j, len(x)), num_segments=len(x) + 1)[na:len(x)]
        return fa, fb, nbrs

    return nbrs, forces


def timings(fns, repeats):
    """Per-call ms of each zero-argument function in ``fns``, interleaved call by call so that every variant
    sees the same background load; {name: {p50_ms, p99_ms, min_ms}}."""
    for fn in fns.values():
        fn()
    out = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            out[name].append((time.perf_counter() - t0) * 1e3)
    return {name: {"p50_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)), "min_ms": float(np.min(a))}
            for name, a in out.items()}


def bench_case(a, b, repeats):
    a, b = jnp.asarray(a), jnp.asarray(b)
    far = b + jnp.array([0.0, 100.0, 0.0])
    dense = jax.jit(lambda a, b: ar._dense_contact(a, b, RADIUS, STIFFNESS))
    library = jax.jit(lambda a, b: ar.contact_forces(a, b, RADIUS, STIFFNESS))
    near = lambda x, y: int(jnp.sum(jnp.all((x >= y.min(0) - RADIUS) & (x <= y.max(0) + RADIUS), axis=-1)))
    capacity = 2 * max(near(a, b), near(b, a))
    pruned = jax.jit(lambda a, b: ar.contact_forces(a, b, RADIUS, STIFFNESS, capacity=capacity))
    ref_a, ref_b = dense(a, b)
    pa, pb = pruned(a, b)
    out = {"nodes": [int(a.shape[0]), int(b.shape[0])],
           "pairs_in_contact": int(jnp.sum(jnp.linalg.norm(a[:, None] - b[None], axis=-1) < RADIUS)),
           "pruned_capacity": capacity,
           "pruned_max_abs_diff_vs_dense": float(jnp.max(jnp.abs(pa - ref_a)) + jnp.max(jnp.abs(pb - ref_b)))}
    fns = {"dense": lambda: jax.block_until_ready(dense(a, b)),
           "dense_cond": lambda: jax.block_until_ready(library(a, b)),
           "pruned": lambda: jax.block_until_ready(pruned(a, b)),
           "pruned_apart": lambda: jax.block_until_ready(pruned(a, far))}
    slow = {}
    for name, cell in (("jaxmd_cell", True), ("jaxmd_nocell", False))[: 1 if len(a) > 1000 else 2]:
        nbrs, fn = jaxmd_contact(np.asarray(a), np.asarray(b), cell)
        fa, fb, nbrs2 = fn(a, b, nbrs)
        assert not bool(nbrs2.did_buffer_overflow)
        call = (lambda fn=fn, nbrs=nbrs: jax.block_until_ready(fn(a, b, nbrs)))
        (fns if cell else slow)[name] = call
        out[name] = {"max_abs_diff_vs_dense": float(jnp.max(jnp.abs(fa - ref_a)) + jnp.max(jnp.abs(fb - ref_b))),
                     "capacity": int(nbrs.idx.shape[1])}
    for name, t in {**timings(fns, repeats), **timings(slow, max(repeats // 20, 5))}.items():
        out.setdefault(name, {}).update(t)
    variants = tuple(k for k in ("dense", "dense_cond", "pruned", "jaxmd_cell", "jaxmd_nocell") if k in out)
    out["fastest"] = min(variants, key=lambda k: out[k]["p50_ms"])
    for k in variants:
        out[f"{k}_over_pruned_p50"] = out[k]["p50_ms"] / out["pruned"]["p50_ms"]
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    results = {"machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "jax": jax.__version__,
                           "backend": jax.default_backend(), "load_average_at_start": os.getloadavg()},
               "radius": RADIUS, "stiffness": STIFFNESS, "repeats": args.repeats}
    for name, (a, b) in cases().items():
        results[name] = bench_case(a, b, args.repeats)
        print(name, json.dumps(results[name], indent=1))
    results["machine"]["load_average_at_end"] = os.getloadavg()
    lines = ["# Contact forces between two bodies: p50 / p99 ms per call", "",
             f"Machine: {results['machine']['platform']}, {results['machine']['cpu_count']} CPUs, jax {jax.__version__} "
             f"({jax.default_backend()}); {args.repeats} calls after compilation. The 2 CPUs were shared with other jobs "
             f"(load average {results['machine']['load_average_at_start'][0]:.1f} at start, "
             f"{results['machine']['load_average_at_end'][0]:.1f} at end): p99 is mostly other jobs; min times "
             "are in the JSON.", "",
             "| case | nodes | pairs in contact | dense | dense + bbox cond | pruned (library, scenes) | pruned, bodies "
             "apart | jax-md cell list | jax-md no cell list | fastest |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name in cases():
        r = results[name]
        cell = lambda k: f"{r[k]['p50_ms']:.3f} / {r[k]['p99_ms']:.3f}" if k in r else "n/a"
        lines.append(f"| {name} | {r['nodes'][0]}+{r['nodes'][1]} | {r['pairs_in_contact']} | {cell('dense')} | "
                     f"{cell('dense_cond')} | {cell('pruned')} | {cell('pruned_apart')} | {cell('jaxmd_cell')} | "
                     f"{cell('jaxmd_nocell')} | {r['fastest']} |")
    lines += ["", "jax-md's no-cell-list builder is skipped for the 1352-node case (0.2 s per call already at 756). "
              "jax-md lists are allocated outside jit (not timed) and updated inside the timed call, as a "
              "scene must do every frame; ratios against the library version are in the JSON."]
    write_results("ar_contact", results, "\n".join(lines) + "\n", RESULTS, indent=2, echo=False)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
