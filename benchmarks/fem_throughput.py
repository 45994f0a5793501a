"""FEM throughput: time per sub-step and element-sub-steps per second, single and batched, after compilation.

Meshes: the paper's beam (500 hex8, 756 nodes) and the bunny (tet4, 1330 nodes / 4698 tets). Each variant runs
a fixed number of sub-steps in one `lax.scan` (the solver's own sub-step: Verlet update, internal forces,
viscous update) for 1…52 load cases vmapped. The naive baseline computes the internal force as `jax.grad` of the
element energy with a scatter-add assembly — what one writes first — in the same scan, same run.

    python benchmarks/fem_throughput.py [--substeps 200] [--repeats 5] [--batches 1,4,16,52]

Writes benchmarks/results/fem_throughput.{json,md}.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fem  # noqa: E402
from fem import scenes, solver  # noqa: E402
from _machine import describe  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def substep_runner(problem, material, n_steps, naive=False):
    """A jitted function of a batch of initial positions running n_steps explicit sub-steps."""
    arr, cfg = problem.arrays, problem.config
    hg = solver._hourglass_stiffness(arr.geo, material) if cfg.cell_type == "hexahedron" else None
    mass = fem.lumped_mass(problem, material)[:, None]
    inv_m = arr.free / mass
    h = cfg.frame_dt / cfg.n_sub
    visco0 = solver._zero_visco(arr, cfg)
    energy = lambda x: fem.internal_energy(problem, material, x)

    def force(x, visco):
        if naive:
            return jax.grad(energy)(x), visco
        f, visco, *_ = solver._internal(arr, material, hg, x, visco, cfg, h)
        return f, visco

    def run(x0):
        def step(c, _):
            x, v, a, visco = c
            v = v + 0.5 * h * a
            x = x + h * v
            f, visco = force(x, visco)
            a = -f * inv_m
            return (x, v + 0.5 * h * a, a, visco), None
        v0 = jnp.zeros_like(x0).at[:, 1].set(1.0) * arr.free
        c, _ = jax.lax.scan(step, (x0, v0, jnp.zeros_like(x0), visco0), None, length=n_steps)
        return c[0]

    return jax.jit(jax.vmap(run))


def measure(fn, x, repeats):
    jax.block_until_ready(fn(x))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--substeps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batches", default="1,4,16,52")
    ap.add_argument("--naive-batches", default="1,16")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    batches = [int(b) for b in args.batches.split(",")]
    naive_batches = [int(b) for b in args.naive_batches.split(",")]
    rows = []
    for scene in (scenes.beam_scene(), scenes.bunny_scene()):
        problem = scenes.setup_scene(scene._replace(n_frames=1))
        n_el = len(scene.cells)
        h = problem.config.frame_dt / problem.config.n_sub
        for naive in (False, True):
            fn = substep_runner(problem, scene.material, args.substeps, naive=naive)
            for b in (naive_batches if naive else batches):
                x = jnp.broadcast_to(jnp.asarray(scene.points, jnp.float32), (b,) + scene.points.shape)
                t = measure(fn, x, args.repeats)
                per_sub = t / args.substeps
                row = {"scene": scene.name, "elements": n_el, "cell_type": scene.cell_type,
                       "variant": "naive jax.grad + scatter" if naive else "hand-derived + gather",
                       "batch": b, "seconds_per_substep": per_sub, "substep_dt": h,
                       "seconds_per_simulated_second": per_sub / h,
                       "element_substeps_per_second": b * n_el / per_sub}
                rows.append(row)
                print(json.dumps(row), flush=True)
    for r in rows:
        base = [q for q in rows if q["scene"] == r["scene"] and q["batch"] == r["batch"] and q["variant"].startswith("naive")]
        if base and not r["variant"].startswith("naive"):
            r["speedup_vs_naive"] = r["element_substeps_per_second"] / base[0]["element_substeps_per_second"]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    payload = {"machine": describe(), "substeps": args.substeps, "repeats": args.repeats, "rows": rows}
    (out / "fem_throughput.json").write_text(json.dumps(payload, indent=1))
    lines = ["# FEM throughput (median of %d repeats after compilation, %d sub-steps per run)" % (args.repeats, args.substeps),
             "", "Machine: " + json.dumps(payload["machine"]), "",
             "| scene | elements | variant | batch | µs / sub-step | s / simulated s | element-sub-steps / s | × naive |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['elements']} {r['cell_type']} | {r['variant']} | {r['batch']} | "
                     f"{r['seconds_per_substep'] * 1e6:.1f} | {r['seconds_per_simulated_second']:.1f} | "
                     f"{r['element_substeps_per_second'] / 1e6:.2f} M | {r.get('speedup_vs_naive', float('nan')):.1f} |")
    (out / "fem_throughput.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
