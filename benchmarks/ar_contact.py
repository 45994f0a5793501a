"""Contact forces between two bodies: is the library's pruned all-pairs search the fastest exact choice?

Question: the two-beam scene needs the penalty contact forces between two bodies every frame
(`tignn_jax.mr.contact_forces`); is its pruned all-pairs search faster than a dense all-pairs sum and than
jax-md's neighbour lists, for bodies of the demo's sizes, with the same forces?

How: two bodies side by side with a strip of nodes within the contact radius, as in the two-beam scene:

- ``beams``: two 40×10×10 beams (20×5×5 hex, 756 nodes each), the second 10.5 units to the side (gap 0.5 <
  radius 1);
- ``beam_surfaces``: the same with only the 452 surface nodes of each beam (what the scene passes);
- ``blobs``: two 1352-node bodies (a 13×13×8-node grid, about the bunny's node count) 0.5 apart.

Variants, each jitted, timed after compilation with the calls interleaved so that each sees the same load from
other processes (p50 / p99 / min over ``--repeats`` calls); each one's forces are compared with the dense sum's:

- ``dense``: all pairs in one fused loop (`tignn_jax.mr.forcing._dense_contact`, no bounding-box test);
- ``dense_cond``: ``contact_forces(..., capacity=None)``: the same behind a bounding-box ``lax.cond``;
- ``pruned`` (what the scenes use): ``contact_forces(..., capacity=C)``: only the nodes inside the other body's
  grown bounding box take part (C = 2× their count here); also timed with the bodies far apart
  (``pruned_apart``), the common case in a scene;
- ``jaxmd_cell``: a jax-md sparse neighbour list with its cell list, allocated outside jit, ``update`` and the
  pair forces inside jit every call (positions change every frame);
- ``jaxmd_nocell``: the same with ``disable_cell_list=True`` (its O(N²) builder; slow, so timed with
  ``--repeats`` / 20 calls, at least 5, and skipped for the blobs).

The jax-md variants need the ``bench`` extra (jax-md); without it they are left out and the results say so.
Writes ``ar_contact.{json,md}`` to ``--out`` (default benchmarks/results) with the CPU and its load average at
start and end. ``--quick`` is a smoke test (a few calls), not a measurement.

    python benchmarks/ar_contact.py [--repeats 200]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax import mr
from tignn_jax.mr.forcing import _dense_contact

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, write_results  # noqa: E402

RADIUS, STIFFNESS = 1.0, 1e4
CASES = ("beams", "beam_surfaces", "blobs")


def grid(nx, ny, nz, size):
    ijk = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    node = np.arange(ijk[..., 0].size).reshape(ijk.shape[:3])
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    corners = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))
    cells = np.stack([node[i + a, j + b, k + c] for a, b, c in corners], axis=1)
    return (ijk.reshape(-1, 3) * np.asarray(size) / np.array([nx, ny, nz])).astype(np.float32), cells


def cases():
    beam, cells = grid(20, 5, 5, (40.0, 10.0, 10.0))
    surf = beam[mr.surface_nodes(mr.surface_triangles(cells, beam))]
    blob, _ = grid(12, 12, 7, (36.0, 36.0, 21.0))
    return {
        "beams": (beam, beam + np.array([0.0, 10.5, 0.0], np.float32)),
        "beam_surfaces": (surf, surf + np.array([0.0, 10.5, 0.0], np.float32)),
        "blobs": (blob, blob + np.array([0.0, 36.5, 0.0], np.float32)),
    }


def jaxmd_contact(a, b, cell_list: bool):
    """A jax-md neighbour-list version: returns (allocate-time nbrs, jitted fn(a, b, nbrs) -> (fa, fb, nbrs))."""
    from jax_md import partition, space

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


def bench_case(a, b, repeats: int, slow_repeats: int, jaxmd: bool):
    """Time the variants (module docstring) on bodies ``a`` and ``b``: ``repeats`` calls each (``slow_repeats``
    for ``jaxmd_nocell``), the jax-md ones only with ``jaxmd``. Raises RuntimeError if a jax-md list overflows."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    far = b + jnp.array([0.0, 100.0, 0.0])
    dense = jax.jit(lambda a, b: _dense_contact(a, b, RADIUS, STIFFNESS))
    library = jax.jit(lambda a, b: mr.contact_forces(a, b, RADIUS, STIFFNESS))
    near = lambda x, y: int(jnp.sum(jnp.all((x >= y.min(0) - RADIUS) & (x <= y.max(0) + RADIUS), axis=-1)))
    capacity = 2 * max(near(a, b), near(b, a))
    pruned = jax.jit(lambda a, b: mr.contact_forces(a, b, RADIUS, STIFFNESS, capacity=capacity))
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
    for name, cell in (("jaxmd_cell", True), ("jaxmd_nocell", False))[: (1 if len(a) > 1000 else 2) * jaxmd]:
        nbrs, fn = jaxmd_contact(np.asarray(a), np.asarray(b), cell)
        fa, fb, nbrs2 = fn(a, b, nbrs)
        if bool(nbrs2.did_buffer_overflow):
            raise RuntimeError(f"{name}: the jax-md neighbour list overflowed")
        call = (lambda fn=fn, nbrs=nbrs: jax.block_until_ready(fn(a, b, nbrs)))
        (fns if cell else slow)[name] = call
        out[name] = {"max_abs_diff_vs_dense": float(jnp.max(jnp.abs(fa - ref_a)) + jnp.max(jnp.abs(fb - ref_b))),
                     "capacity": int(nbrs.idx.shape[1])}
    for name, t in {**timings(fns, repeats), **timings(slow, slow_repeats)}.items():
        out.setdefault(name, {}).update(t)
    variants = tuple(k for k in ("dense", "dense_cond", "pruned", "jaxmd_cell", "jaxmd_nocell") if k in out)
    out["fastest"] = min(variants, key=lambda k: out[k]["p50_ms"])
    for k in variants:
        out[f"{k}_over_pruned_p50"] = out[k]["p50_ms"] / out["pruned"]["p50_ms"]
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description="Contact forces between two bodies: the library's pruned all-pairs search against a dense "
                    "sum and jax-md neighbour lists; writes ar_contact.{json,md}.")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed calls per variant and case, at least 3; jax-md without cell list: a 20th of "
                             "them, at least 5 (default: 200; --quick: 5, and 2 without cell list)")
    parser.add_argument("--cases", default=",".join(CASES),
                        help=f"cases, comma-separated, from {list(CASES)} (default: all)")
    parser.add_argument("--quick", action="store_true", help="a smoke test: 5 calls per variant (unless --repeats)")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR,
                        help="folder the results are written to (default: benchmarks/results)")
    args = parser.parse_args(argv)
    repeats = args.repeats if args.repeats is not None else 5 if args.quick else 200
    slow_repeats = 2 if args.quick and args.repeats is None else max(repeats // 20, 5)
    names = [c for c in args.cases.split(",") if c]
    bad = [c for c in names if c not in CASES]
    if bad or not names or repeats < 3:
        raise SystemExit(f"--cases must name some of {list(CASES)} (unknown: {bad}) and --repeats be ≥ 3, got "
                         f"{args.cases!r} and {repeats}")
    jaxmd = importlib.util.find_spec("jax_md") is not None
    machine = describe()
    results = {"machine": machine, "quick": args.quick, "radius": RADIUS, "stiffness": STIFFNESS,
               "repeats": repeats, "jax_md": jaxmd}
    bodies = cases()
    for name in names:
        results[name] = bench_case(*bodies[name], repeats, slow_repeats, jaxmd)
        print(name, json.dumps(results[name]), flush=True)
    machine["load_average_1m_at_end"] = describe()["load_average_1m"]
    lines = ["# Contact forces between two bodies: p50 / p99 ms per call", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']} ({machine['backend']}); "
             f"load average {machine['load_average_1m']} at start, {machine['load_average_1m_at_end']} at end "
             f"({machine['note']}). {repeats} calls per variant after compilation, interleaved; min times and "
             "ratios against the pruned search are in the JSON."
             + ("" if jaxmd else " jax-md is not installed (the `bench` extra): its variants are left out.")
             + (" QUICK RUN (smoke test): not a measurement." if args.quick else ""), "",
             "| case | nodes | pairs in contact | dense | dense + bbox cond | pruned (library, scenes) | pruned, "
             "bodies apart | jax-md cell list | jax-md no cell list | fastest | largest force difference, pruned "
             "vs dense |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in names:
        r = results[name]
        cell = lambda k: f"{r[k]['p50_ms']:.3f} / {r[k]['p99_ms']:.3f}" if "p50_ms" in r.get(k, {}) else "n/a"  # noqa
        lines.append(f"| {name} | {r['nodes'][0]}+{r['nodes'][1]} | {r['pairs_in_contact']} | {cell('dense')} | "
                     f"{cell('dense_cond')} | {cell('pruned')} | {cell('pruned_apart')} | {cell('jaxmd_cell')} | "
                     f"{cell('jaxmd_nocell')} | {r['fastest']} | {r['pruned_max_abs_diff_vs_dense']:.1e} |")
    lines += ["", "jax-md's builder without cell list is skipped for the 1352-node bodies (slow already at 756). "
              "jax-md lists are allocated outside jit (not timed) and updated inside the timed call, as a scene "
              "must do every frame."]
    write_results("ar_contact", results, "\n".join(lines) + "\n", folder=args.out, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
