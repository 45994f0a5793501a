r"""FEM throughput: time per sub-step and element-sub-steps per second, single and batched, after compilation.

Meshes: the paper's beam (500 hex8, 756 nodes) and the bunny (tet4, 1330 nodes / 4698 tets). Each variant runs
a fixed number of sub-steps in one `lax.scan` (the solver's own sub-step: Verlet update, internal forces,
viscous update) for 1…52 load cases. Variants, all in the same run:

* "trailing batch (solver)": what `fem.simulate_batch` runs — the cases are the last, contiguous axis of the
  state ([N, 3, B]); per-element data broadcast against it (hex8; tet4 falls back to `jax.vmap` over that axis);
* "vmap (cases first)": `jax.vmap` of the single-case sub-step, which puts the case axis first — the
  straightforward batched version the speed-up is measured against;
* "naive jax.grad + scatter": the internal force as `jax.grad` of the element energy with a scatter-add
  assembly — what one writes first.

Single-process rows use one core (XLA's intra-op threads pinned to 1, the process to one CPU). The
"2 processes" rows run two copies of the trailing-batch variant at the same time, one per core, each with half
of the cases (how `tignn generate --worker K/2` uses this machine), and report the sum of their throughputs,
measured while both run.

    python benchmarks/fem_throughput.py [--substeps 200] [--repeats 5] [--batches 1,4,16,52]
    python benchmarks/fem_throughput.py --scenes beam --substeps 5 --repeats 1 --batches 2 --naive-batches 1 \
        --two-process-batches "" --out /tmp/fem_throughput          # smoke run, ~30 s

Writes benchmarks/results/fem_throughput.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SINGLE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
os.environ.setdefault("XLA_FLAGS", SINGLE_THREAD)   # before JAX starts

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fem  # noqa: E402
from fem import scenes, solver  # noqa: E402
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


VARIANTS = {"trailing": "trailing batch (solver)", "vmap": "vmap (cases first)", "naive": "naive jax.grad + scatter"}


def substep_runner(problem, material, n_steps, variant="trailing"):
    """A jitted function of initial displacements running n_steps explicit sub-steps for a batch of cases.

    Input: initial displacements u = x − X, [N, 3, B] for "trailing", [B, N, 3] otherwise.
    """
    arr, cfg = problem.arrays, problem.config
    hg = solver._hourglass_for(arr, material, cfg)
    mass = fem.lumped_mass(problem, material)[:, None]
    inv_m = arr.free / mass
    h = cfg.frame_dt / cfg.n_sub
    energy = lambda u: fem.internal_energy(problem, material, arr.points + u)   # the state is u = x − X

    def scan(u0, force, visco0, inv_m, free):
        def step(c, _):
            u, v, a, visco = c
            v = v + 0.5 * h * a
            u = u + h * v
            f, visco = force(u, visco)
            a = -f * inv_m
            return (u, v + 0.5 * h * a, a, visco), None
        v0 = jnp.zeros_like(u0).at[:, 1].set(1.0) * free
        c, _ = jax.lax.scan(step, (u0, v0, jnp.zeros_like(u0), visco0), None, length=n_steps)
        return c[0]

    if variant == "trailing":
        internal = solver._internal_fn(arr, material, hg, cfg, h, batched=True)

        def run(u0):
            visco0 = solver._zero_visco(arr, cfg, u0.shape[-1:])
            return scan(u0, lambda u, vis: internal(u, vis)[:2], visco0, inv_m[..., None], arr.free[..., None])
        return jax.jit(run)

    def force(u, visco):
        if variant == "naive":
            return jax.grad(energy)(u), visco
        f, visco, *_ = solver._internal(arr, material, hg, u, visco, cfg, h)
        return f, visco

    return jax.jit(jax.vmap(lambda u0: scan(u0, force, solver._zero_visco(arr, cfg), inv_m, arr.free)))


def initial(scene, b, variant):
    """Zero initial displacements for b cases in the variant's layout."""
    n = len(scene.points)
    return jnp.zeros((n, 3, b) if variant == "trailing" else (b, n, 3), jnp.float32)


def measure(fn, x, repeats):
    jax.block_until_ready(fn(x))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def scene_by_name(name):
    return scenes.beam_scene() if name == "beam" else scenes.bunny_scene()


def child(args):
    """One of the "2 processes" copies: pinned to a core, waits for its sibling after compiling, then measures."""
    os.sched_setaffinity(0, {args.core})
    scene = scene_by_name(args.scene)
    problem = scenes.setup_scene(scene._replace(n_frames=1))
    fn = substep_runner(problem, scene.material, args.substeps, "trailing")
    x = initial(scene, args.batch, "trailing")
    jax.block_until_ready(fn(x))
    sync = Path(args.sync)
    (sync / f"ready{args.core}").touch()
    while len(list(sync.glob("ready*"))) < 2:
        time.sleep(0.01)
    t = measure(fn, x, args.repeats)
    print(json.dumps({"seconds_per_substep": t / args.substeps}), flush=True)


def two_processes(scene_name, batch, substeps, repeats):
    """Sum of the throughputs of two concurrent single-core copies with batch/2 cases each."""
    env = dict(os.environ, XLA_FLAGS=SINGLE_THREAD)
    with tempfile.TemporaryDirectory() as sync:
        procs = [subprocess.Popen([sys.executable, __file__, "--child", scene_name, str(batch // 2), str(core),
                                   "--sync", sync, "--substeps", str(substeps), "--repeats", str(repeats)],
                                  stdout=subprocess.PIPE, env=env, text=True) for core in (0, 1)]
        outs = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in procs]
    return [o["seconds_per_substep"] for o in outs]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--substeps", type=int, default=200, help="sub-steps per timed run (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per row (default %(default)s)")
    ap.add_argument("--batches", default="1,16,32,52", help="load cases per run, beam (default %(default)s)")
    ap.add_argument("--naive-batches", default="1,16", help="batches of the naive variant (default %(default)s)")
    ap.add_argument("--two-process-batches", default="32,64",
                    help="batches of the two-process rows, beam; '' for none (default %(default)s)")
    ap.add_argument("--scenes", default="beam,bunny", help="scenes, of beam,bunny (default %(default)s)")
    ap.add_argument("--bunny-batches", default="1,16",
                    help="batches for the bunny (its vmap rows at 32+ cases take minutes each; default %(default)s)")
    ap.add_argument("--bunny-two-process-batches", default="32",
                    help="batches of the two-process rows, bunny; '' for none (default %(default)s)")
    ap.add_argument("--out", default=str(RESULTS), help="folder of fem_throughput.{json,md} (default %(default)s)")
    ap.add_argument("--child", nargs=3, metavar=("SCENE", "BATCH", "CORE"), help=argparse.SUPPRESS)
    ap.add_argument("--sync", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        args.scene, args.batch, args.core = args.child[0], int(args.child[1]), int(args.child[2])
        return child(args)
    os.sched_setaffinity(0, {1})   # single-process rows: one core (XLA threads pinned to 1 at import)
    batches = [int(b) for b in args.batches.split(",")]
    naive_batches = [int(b) for b in args.naive_batches.split(",")]
    rows = []

    def add(scene, n_el, variant, b, per_sub, h, processes=1):
        row = {"scene": scene.name, "elements": n_el, "cell_type": scene.cell_type, "variant": VARIANTS[variant],
               "processes": processes, "batch": b, "seconds_per_substep": per_sub, "substep_dt": h,
               "seconds_per_simulated_second": per_sub / h, "element_substeps_per_second": b * n_el / per_sub}
        rows.append(row)
        print(json.dumps(row), flush=True)

    for name in args.scenes.split(","):
        scene = scene_by_name(name)
        problem = scenes.setup_scene(scene._replace(n_frames=1))
        n_el = len(scene.cells)
        h = problem.config.frame_dt / problem.config.n_sub
        for variant in ("trailing", "vmap", "naive"):
            fn = substep_runner(problem, scene.material, args.substeps, variant)
            scene_batches = batches if name == "beam" else [int(b) for b in args.bunny_batches.split(",")]
            for b in (naive_batches if variant == "naive" else scene_batches):
                if variant == "trailing" and b == 1:
                    continue   # one case runs the unbatched solver, the "vmap" row at batch 1
                add(scene, n_el, variant, b, measure(fn, initial(scene, b, variant), args.repeats) / args.substeps, h)
        two = args.two_process_batches if name == "beam" else args.bunny_two_process_batches
        for b in [int(b) for b in two.split(",") if b]:
            per = two_processes(name, b, args.substeps, args.repeats)
            # throughput of the pair = sum of each copy's throughput; report it as an equivalent time per sub-step
            rate = sum((b // 2) * n_el / t for t in per)
            add(scene, n_el, "trailing", b, b * n_el / rate, h, processes=2)
    for r in rows:
        same = [q for q in rows if q["scene"] == r["scene"] and q["batch"] == r["batch"] and q["processes"] == 1]
        for key, base in (("speedup_vs_vmap", "vmap"), ("speedup_vs_naive", "naive")):
            ref = [q for q in same if q["variant"] == VARIANTS[base]]
            if ref and r["variant"] != VARIANTS[base]:
                r[key] = r["element_substeps_per_second"] / ref[0]["element_substeps_per_second"]
    out = Path(args.out)
    payload = {"machine": describe(), "substeps": args.substeps, "repeats": args.repeats, "rows": rows}
    lines = ["# FEM throughput (median of %d repeats after compilation, %d sub-steps per run)"
             % (args.repeats, args.substeps),
             "", "Machine: " + json.dumps(payload["machine"]), "",
             "Single-process rows: one core, XLA intra-op threads 1. '2 processes': two concurrent single-core copies,",
             "half of the cases each, throughputs summed (how `tignn generate --worker K/2` runs). × columns: ratio",
             "against the named variant at the same batch, measured in this run.", "",
             "Two cores in one process: splitting the cases over two host devices with `jax.shard_map`",
             "(`XLA_FLAGS=--xla_force_host_platform_device_count=2`) hung in the XLA CPU runtime (jax 0.10.2; a",
             "trivial shard_map ran, the solver's nested checkpointed scans did not return within 120 s at 5",
             "sub-steps), so the second core is used by a second process.", "",
             "| scene | elements | variant | processes | batch | µs / sub-step | s / simulated s | "
             "element-sub-steps / s | × vmap | × naive |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    fmt = lambda v: "" if v is None else f"{v:.1f}"
    for r in rows:
        lines.append(f"| {r['scene']} | {r['elements']} {r['cell_type']} | {r['variant']} | {r['processes']} | "
                     f"{r['batch']} | "
                     f"{r['seconds_per_substep'] * 1e6:.1f} | {r['seconds_per_simulated_second']:.1f} | "
                     f"{r['element_substeps_per_second'] / 1e6:.2f} M | {fmt(r.get('speedup_vs_vmap'))} | "
                     f"{fmt(r.get('speedup_vs_naive'))} |")
    write_results("fem_throughput", payload, "\n".join(lines) + "\n", out, echo=False)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
