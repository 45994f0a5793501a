"""How the cost grows: step time of the learned simulator and of the FEM against mesh size and batch size.

Meshes: the 40×10×10 beam, clamped at x = 0, refined from the paper's 20×5×5 hex8 (756 nodes) to 92×23×23
(53 568 nodes) by ``fem.box_hex_mesh``; the graph is both directions of every hex edge (``fem.meshes.
mesh_edges``), as for the paper's beam.

Learned simulator: the shipped ``beam-abaqus`` model (hidden 24, 3 passes, its weights and normalisation;
a graph network's weights fit any mesh, and values do not change the time) put on each refined mesh by
``api.make_params``; one jit-compiled step (``api.stepper``: forward, one reverse pass for ∇E and ∇S, the
GENERIC update) is one 0.05 s frame. Median of interleaved calls after compilation (fewer for big meshes).
Batch: ``copies`` = 1…32 beams of 756 nodes stepped in one graph (``api.stepper(params, copies)``).

FEM: ``fem.setup`` / ``fem.simulate`` on the same meshes with the beam scene's material and damping and a tip
load. Its stable sub-step h shrinks with the element size (n_sub = ⌈0.05 / h⌉ sub-steps per frame), so a
frame of a large mesh takes minutes; the time per sub-step is measured instead, as the slope between runs
of k and 2k sub-steps at the stable h (one frame of k·h), which removes the per-run overhead (initial force,
frame outputs: nodal stress and energies). Time per frame = n_sub × sub-step + that overhead; on the
smallest meshes a whole 0.05 s frame is also timed directly to check that estimate. Batch: 1…16 load cases
of the paper's mesh in one ``fem.simulate_batch`` call.

Exponents a of time ∝ nodes^a are least-squares fits in log–log over the meshes from 40×10×10 on (the small
meshes are dominated by fixed per-call costs). Writes benchmarks/results/scaling.{json,md,png}.

    python benchmarks/scaling.py [--quick] [--max-nodes N] [--out DIR]

``--quick`` is a smoke run (three small meshes, few repeats) written to /tmp/tignn_scaling_quick unless
``--out`` is given. Run the full benchmark single-threaded for numbers comparable with the other results:
    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" python benchmarks/scaling.py
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
QUICK_OUT = Path("/tmp/tignn_scaling_quick")
BEAM_SIZE = (40.0, 10.0, 10.0)
REFINEMENTS = ((20, 5, 5), (28, 7, 7), (40, 10, 10), (56, 14, 14), (80, 20, 20), (92, 23, 23))
BATCHES = (1, 2, 4, 8, 16, 32)
FEM_BATCHES = (1, 2, 4, 8, 16)
GPU_EXTRA_BATCHES = (64, 128)  # an accelerator amortises per-call costs much further than one core
FIT_FROM_NODES = 4000          # fit exponents over meshes with at least this many nodes
TIP_FORCE = 3.0e4              # total tip load [force], the size of the reference data's first frame (6 × 5000)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: three small meshes, few repeats")
    parser.add_argument("--max-nodes", type=int, default=60000, help="skip meshes with more nodes")
    parser.add_argument("--model", default="beam-abaqus", help="shipped model whose config/weights are timed")
    parser.add_argument("--seconds", type=float, default=None,
                        help="CPU seconds of timed calls per variant (default 2, quick 0.5)")
    parser.add_argument("--out", default=None, help="output folder (default benchmarks/results; quick: /tmp)")
    parser.add_argument("--render", default=None, metavar="JSON",
                        help="only write the table and plot of a result (or a cut-off run's .partial.json) "
                             "measured elsewhere, e.g. on a GPU machine")
    args = parser.parse_args(argv)
    if args.render:
        return render(Path(args.render), Path(args.out) if args.out else RESULTS)
    if args.max_nodes < 756:
        raise SystemExit(f"--max-nodes must be at least 756 (the paper's mesh), got {args.max_nodes}")
    quick = args.quick
    seconds = args.seconds or (0.5 if quick else 2.0)
    refinements = [d for d in (REFINEMENTS[:3] if quick else REFINEMENTS) if nodes_of(d) <= args.max_nodes]
    batches = BATCHES[:3] if quick else BATCHES if on_cpu() else BATCHES + GPU_EXTRA_BATCHES
    fem_batches = FEM_BATCHES[:2] if quick else FEM_BATCHES if on_cpu() else FEM_BATCHES + GPU_EXTRA_BATCHES
    out = Path(args.out) if args.out else (QUICK_OUT if quick else RESULTS)
    stem = result_stem(jax.default_backend())

    machine = describe()
    machine["load_average_1m_at_start"] = machine.pop("load_average_1m")
    flags = os.environ.get("XLA_FLAGS", "")
    machine["xla_flags"] = flags
    machine["threads"] = "single-threaded XLA: batching can only amortise per-call costs" \
        if "multi_thread_eigen=false" in flags else "XLA's default threading"
    machine["accelerator"] = "none (CPU only; no GPU was available in this session)" \
        if jax.default_backend() == "cpu" else jax.devices()[0].device_kind
    t_start, c_start = time.perf_counter(), time.process_time()
    from tignn_jax import api
    base = api.load_pretrained(args.model)[0]

    out.mkdir(parents=True, exist_ok=True)
    partial = out / f"{stem}.partial.json"     # what is done so far, should a long run be cut off
    done = {"machine": machine, "quick": quick, "model": args.model, "model_config": base["config"]}

    def stage(key, label, fn, *fn_args):
        print(label, flush=True)
        done[key] = fn(*fn_args)
        partial.write_text(json.dumps(done, indent=1))

    stage("learned_vs_nodes", f"learned step on {len(refinements)} meshes ...", learned_mesh_scaling, base,
          refinements, seconds)
    stage("learned_vs_batch", f"learned step, batch {list(batches)} ...", learned_batch_scaling, base, batches,
          seconds)
    stage("fem_vs_nodes", f"FEM on {len(refinements)} meshes ...", fem_mesh_scaling, refinements, quick, seconds)
    stage("fem_vs_batch", f"FEM batch {list(fem_batches)} ...", fem_batch_scaling, fem_batches,
          50 if quick else 200, seconds)
    machine["load_average_1m_at_end"] = describe()["load_average_1m"]
    result = {**done, "wall_seconds": time.perf_counter() - t_start, "cpu_seconds": time.process_time() - c_start,
              "fits": fits(done["learned_vs_nodes"], done["fem_vs_nodes"])}
    write_result(result, out, stem)
    partial.unlink(missing_ok=True)
    return 0


def result_stem(backend: str) -> str:
    """scaling.* for the CPU backend, scaling_<backend>.* (e.g. scaling_gpu) for an accelerator."""
    return "scaling" if backend == "cpu" else f"scaling_{backend}"


def write_result(result: dict, out: Path, stem: str) -> None:
    """``stem``.json, .md and .png in ``out``; prints the table."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1))
    md = format_md(result)
    (out / f"{stem}.md").write_text(md)
    plot(result, out / f"{stem}.png")
    print(md)
    print(f"wrote {out}/{stem}.{{json,md,png}}")


def render(path: Path, out: Path) -> int:
    """Tables and plot of a saved result; the stages a cut-off run did not reach are left empty and named."""
    if not path.exists():
        raise SystemExit(f"--render: no such file {path}")
    result = json.loads(path.read_text())
    missing = [k for k in ("learned_vs_nodes", "learned_vs_batch", "fem_vs_nodes", "fem_vs_batch")
               if k not in result]
    for k in missing:
        result[k] = []
    result.setdefault("not_measured", missing)
    result.setdefault("quick", False)
    if "model_config" not in result:
        from tignn_jax import api
        result["model"] = result.get("model", "beam-abaqus")
        result["model_config"] = api.load_pretrained(result["model"])[0]["config"]
    m = result["machine"]
    m.setdefault("load_average_1m_at_end", m.get("load_average_1m_at_start"))
    result.setdefault("wall_seconds", float("nan"))
    for row in result["learned_vs_nodes"] + result["learned_vs_batch"]:   # results from before the "ms" key
        row.setdefault("ms", row["cpu_ms"] if timed_on_cpu(result) else row["wall_ms"])
    result["fits"] = fits(result["learned_vs_nodes"], result["fem_vs_nodes"])
    write_result(result, out, result_stem(m["backend"]))
    return 0


# ------------------------------------------------------------------------------------------------------------
# meshes


def nodes_of(divisions) -> int:
    return int(np.prod(np.asarray(divisions) + 1))


def beam(divisions):
    """The refined beam: (points [N,3] float64, cells [K,8] int32, edges [2,E] int32, node_type [N] int8)."""
    import fem
    from fem.meshes import beam_node_type, mesh_edges

    points, cells = fem.box_hex_mesh(BEAM_SIZE, divisions)
    return points, cells, mesh_edges(cells), beam_node_type(points)


# ------------------------------------------------------------------------------------------------------------
# learned simulator


def model_on_mesh(base: dict, points, edges, node_type) -> dict:
    """The shipped model's config, normalisation and weights on another mesh."""
    from tignn_jax import api
    from tignn_jax import model as M

    return api.make_params(M.ModelConfig(**base["config"]), base["norm"], base["weights"], points, edges,
                           node_type)


def sample_state(params: dict, copies: int = 1, seed: int = 0):
    """A state near the training distribution (q near the rest mesh; v, σ ~ mean + 0.1 std) and zero forces."""
    q0 = np.tile(params["mesh"]["q0"], (copies, 1))
    mean, std = (np.asarray(params["norm"][k]) for k in ("z_mean", "z_std"))
    rng = np.random.default_rng(seed)
    rest = mean[3:] + 0.1 * std[3:] * rng.normal(size=(len(q0), 9))
    z = np.concatenate([q0 + 0.01 * rng.normal(size=q0.shape), rest], axis=1)
    return jnp.asarray(z, jnp.float32), jnp.zeros((len(q0), 3), jnp.float32)


def time_interleaved(fns: dict, seconds: float, min_repeats: int = 3, max_repeats: int = 50) -> dict:
    """Compile each fn(), then time the calls round-robin until each has its quota (≈ ``seconds`` of CPU
    time, between min and max repeats). Returns {name: {"cpu_ms", "wall_ms", "wall_p90_ms", "repeats",
    "compile_s", "ms"}}: medians of the process's CPU time and of the wall-clock time per call; "ms" is the
    primary clock (CPU time on the CPU backend, wall time on an accelerator, whose work the process's CPU time
    does not count). With single-threaded
    XLA the CPU time is the cost of the work itself, which other jobs on a shared machine inflate only through
    the caches and memory bandwidth they share; the wall time also counts the time the process waited for
    a core."""
    compile_s, quota = {}, {}
    cpu, wall = ({k: [] for k in fns} for _ in range(2))
    for k, fn in fns.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        compile_s[k] = time.perf_counter() - t0
        c0 = time.process_time()
        jax.block_until_ready(fn())
        first = time.process_time() - c0
        quota[k] = int(min(max_repeats, max(min_repeats, seconds / max(first, 1e-6))))
    while any(len(cpu[k]) < quota[k] for k in fns):
        for k, fn in fns.items():
            if len(cpu[k]) < quota[k]:
                t0, c0 = time.perf_counter(), time.process_time()
                jax.block_until_ready(fn())
                cpu[k].append(time.process_time() - c0)
                wall[k].append(time.perf_counter() - t0)
    primary = cpu if on_cpu() else wall
    return {k: {"ms": 1e3 * float(np.median(primary[k])),
                "cpu_ms": 1e3 * float(np.median(cpu[k])), "wall_ms": 1e3 * float(np.median(wall[k])),
                "wall_p90_ms": 1e3 * float(np.percentile(wall[k], 90)), "repeats": len(cpu[k]),
                "compile_s": compile_s[k]} for k in fns}


def on_cpu() -> bool:
    return jax.default_backend() == "cpu"


def timed_on_cpu(result: dict) -> bool:
    """Whether a result was measured on the CPU backend (formatting may run on another machine)."""
    return result["machine"]["backend"] == "cpu"


def clocks(result: dict) -> tuple:
    """(primary, secondary) clock names for the table headers."""
    return ("CPU", "wall") if timed_on_cpu(result) else ("wall", "CPU")


def second(r: dict, result: dict) -> float:
    return r["wall_ms"] if timed_on_cpu(result) else r["cpu_ms"]


def learned_mesh_scaling(base: dict, refinements, seconds: float) -> list:
    from tignn_jax import api

    fns, rows = {}, []
    for d in refinements:
        points, cells, edges, node_type = beam(d)
        t0 = time.perf_counter()
        params = model_on_mesh(base, points, edges, node_type)
        setup_s = time.perf_counter() - t0
        step = api.stepper(params)
        z, f = sample_state(params)
        name = "x".join(map(str, d))
        fns[name] = lambda step=step, z=z, f=f: step(z, f)
        rows.append({"elements": list(d), "cells": int(len(cells)), "nodes": int(len(points)),
                     "edges": int(edges.shape[1]), "slots": list(params["topo"].nbr.shape),
                     "topology_setup_s": setup_s})
        print(f"  {name}: {len(points)} nodes, {edges.shape[1]} edges", flush=True)
    timed = time_interleaved(fns, seconds)
    for row, (name, t) in zip(rows, timed.items()):
        row.update(t)
        row["us_per_node"] = 1e3 * t["ms"] / row["nodes"]
        row["ns_per_edge"] = 1e6 * t["ms"] / row["edges"]
    return rows


def learned_batch_scaling(base: dict, batches, seconds: float) -> list:
    from tignn_jax import api

    points, _, edges, node_type = beam(REFINEMENTS[0])
    params = model_on_mesh(base, points, edges, node_type)
    fns = {}
    for b in batches:
        step = api.stepper(params, b, one_graph=True)   # one graph (CPU default: one by one)
        z, f = sample_state(params, b)
        fns[b] = lambda step=step, z=z, f=f: step(z, f)
    timed = time_interleaved(fns, seconds)
    rows = []
    for b, t in timed.items():
        rows.append({"copies": b, "nodes": b * len(points), **t, "ms_per_body_step": t["ms"] / b,
                     "wall_ms_per_body_step": t["wall_ms"] / b})
    for r in rows:
        r["speedup_per_body_vs_1"] = rows[0]["ms_per_body_step"] / r["ms_per_body_step"]
    return rows


# ------------------------------------------------------------------------------------------------------------
# FEM


def fem_problem(points, cells, node_type, n_sub: int, batch: int | None = None):
    """(problem, material, loads): one frame of ``n_sub`` sub-steps at the stable sub-step h, tip load ramped
    over the frame (loads [batch, 1, N, 3] when batched, each case a different direction)."""
    import fem
    from fem import scenes

    scene = scenes.beam_scene()
    h = fem.stable_time_step(points, cells, scene.material, "hexahedron")
    problem = fem.setup(points, cells, material=scene.material, frame_dt=n_sub * h * (1 - 1e-6), n_frames=1,
                        clamped=np.flatnonzero(node_type == 1), cell_type="hexahedron", damping=scene.damping,
                        load_interp=scene.load_interp)
    nodal = tip_loads(points, batch or 1)
    return problem, scene.material, fem.Loads(nodal=jnp.asarray(nodal if batch else nodal[0])), h


def tip_loads(points, cases: int) -> np.ndarray:
    """[cases, 1, N, 3]: TIP_FORCE spread over the free end's nodes, case c pointing at angle 2πc/cases in
    the y–z plane (case 0 along −y)."""
    tip = np.flatnonzero(np.abs(points[:, 0] - points[:, 0].max()) < 1e-9)
    nodal = np.zeros((cases, 1, len(points), 3))
    for c, a in enumerate(np.linspace(0.0, 2 * np.pi, cases, endpoint=False)):
        nodal[c, 0, tip] = TIP_FORCE / len(tip) * np.array([0.0, -np.cos(a), -np.sin(a)])
    return nodal


def fem_runner(problem, material, loads, batched: bool):
    import fem

    if batched:
        return lambda: fem.simulate_batch(problem, material, loads).q
    return lambda: fem.simulate(problem, material, loads, on_inversion="ignore").q


def fem_substep_fns(points, cells, node_type, k: int, batch: int | None = None) -> tuple:
    """Runs of one frame of k and of 2k sub-steps at the stable sub-step h: ({k: fn, 2k: fn}, h)."""
    fns = {}
    for n_sub in (k, 2 * k):
        problem, material, loads, h = fem_problem(points, cells, node_type, n_sub, batch)
        assert problem.config.n_sub == n_sub, (problem.config.n_sub, n_sub)
        fns[n_sub] = fem_runner(problem, material, loads, batch is not None)
    return fns, h


def substep_slope(timed: dict, k: int) -> dict:
    """ms per sub-step (slope between k and 2k sub-steps; the primary clock, and wall time) and the per-run
    overhead (intercept: initial force, frame outputs; the primary clock)."""
    per = max(timed[2 * k]["ms"] - timed[k]["ms"], 0.0) / k
    per_wall = max(timed[2 * k]["wall_ms"] - timed[k]["wall_ms"], 0.0) / k
    return {"ms_per_substep": per, "ms_per_substep_wall": per_wall,
            "overhead_ms": max(timed[k]["ms"] - k * per, 0.0), "substeps_timed": [k, 2 * k],
            "repeats": timed[k]["repeats"], "compile_s": timed[k]["compile_s"] + timed[2 * k]["compile_s"]}


def fem_mesh_scaling(refinements, quick: bool, seconds: float) -> list:
    import fem
    from fem import scenes

    scene = scenes.beam_scene()
    rows = []
    for d in refinements:
        points, cells, _, node_type = beam(d)
        h = fem.stable_time_step(points, cells, scene.material, "hexahedron")
        n_sub = int(math.ceil(0.05 / h - 1e-9))
        k = int(np.clip((5e4 if quick else 2e5) / len(cells), 8, 200))
        fns, _ = fem_substep_fns(points, cells, node_type, k)
        row = {"elements": list(d), "cells": int(len(cells)), "nodes": int(len(points)), "substep_dt": h,
               "substeps_per_frame": n_sub,
               **substep_slope(time_interleaved(fns, seconds, min_repeats=3, max_repeats=20), k)}
        row["ns_per_element_substep"] = 1e6 * row["ms_per_substep"] / len(cells)
        row["ms_per_frame"] = n_sub * row["ms_per_substep"] + row["overhead_ms"]
        row["ms_per_frame_wall"] = n_sub * row["ms_per_substep_wall"] + row["overhead_ms"]
        if row["ms_per_frame"] < (500 if quick else 3000):   # cheap enough to time a whole 0.05 s frame
            problem = fem.setup(points, cells, material=scene.material, frame_dt=0.05, n_frames=1,
                                clamped=np.flatnonzero(node_type == 1), cell_type="hexahedron",
                                damping=scene.damping, load_interp=scene.load_interp)
            loads = fem.Loads(nodal=jnp.asarray(tip_loads(points, 1)[0]))
            frame = time_interleaved({"frame": fem_runner(problem, scene.material, loads, False)}, 0.0,
                                     min_repeats=3)["frame"]
            row["ms_per_frame_measured"] = frame["ms"]
            row["ms_per_frame_measured_wall"] = frame["wall_ms"]
        rows.append(row)
        print(f"  FEM {'x'.join(map(str, d))}: {row['ms_per_substep']:.3f} ms/sub-step × {n_sub} = "
              f"{row['ms_per_frame']:.0f} ms/frame", flush=True)
    return rows


def fem_batch_scaling(batches, k: int, seconds: float) -> list:
    points, cells, _, node_type = beam(REFINEMENTS[0])
    fns = {}
    for b in batches:
        pair, _ = fem_substep_fns(points, cells, node_type, k, batch=b)
        fns.update({(b, n): fn for n, fn in pair.items()})
    timed = time_interleaved(fns, seconds, min_repeats=3, max_repeats=30)
    rows = []
    for b in batches:
        row = {"batch": b, **substep_slope({n: timed[(b, n)] for n in (k, 2 * k)}, k)}
        row["ms_per_body_substep"] = row["ms_per_substep"] / b
        row["element_substeps_per_s"] = b * len(cells) / (1e-3 * row["ms_per_substep"]) \
            if row["ms_per_substep"] > 0 else float("nan")
        rows.append(row)
        print(f"  FEM batch {b}: {row['ms_per_substep']:.3f} ms/sub-step", flush=True)
    for r in rows:
        r["speedup_per_body_vs_1"] = rows[0]["ms_per_body_substep"] / r["ms_per_body_substep"] \
            if r["ms_per_body_substep"] > 0 else float("nan")   # 0: the k and 2k runs did not separate
    return rows


# ------------------------------------------------------------------------------------------------------------
# fits and output


def power_fit(nodes, ms) -> dict | None:
    """Least-squares fit of log(ms) = log(c) + a log(nodes) over the points with nodes ≥ FIT_FROM_NODES."""
    nodes, ms = np.asarray(nodes, float), np.asarray(ms, float)
    keep = (nodes >= FIT_FROM_NODES) & (ms > 0)
    if keep.sum() < 2:
        return None
    a, logc = np.polyfit(np.log(nodes[keep]), np.log(ms[keep]), 1)
    return {"exponent": float(a), "coefficient_ms": float(np.exp(logc)), "meshes": int(keep.sum()),
            "from_nodes": int(nodes[keep].min()), "to_nodes": int(nodes[keep].max())}


def fits(learned: list, fem_rows: list) -> dict:
    col = lambda rows, k: [r[k] for r in rows]
    return {"learned_step": power_fit(col(learned, "nodes"), col(learned, "ms")),
            "fem_substep": power_fit(col(fem_rows, "nodes"), col(fem_rows, "ms_per_substep")),
            "fem_frame": power_fit(col(fem_rows, "nodes"), col(fem_rows, "ms_per_frame")),
            "learned_step_wall": power_fit(col(learned, "nodes"), col(learned, "wall_ms")),
            "fem_substep_wall": power_fit(col(fem_rows, "nodes"), col(fem_rows, "ms_per_substep_wall")),
            "fem_frame_wall": power_fit(col(fem_rows, "nodes"), col(fem_rows, "ms_per_frame_wall"))}


def _exp(fit) -> str:
    return f"{fit['exponent']:.2f}" if fit else "n/a (fewer than 2 meshes ≥ %d nodes)" % FIT_FROM_NODES


def format_md(result: dict) -> str:
    m, f = result["machine"], result["fits"]
    cfg = result["model_config"]
    one, two = clocks(result)
    timing = (f"of the process's CPU time (the cost of the work; other jobs inflate it only through shared caches "
              f"and memory bandwidth), with the wall-clock median (which also counts waiting for a core) in "
              f"brackets; the fits and ratios use the CPU time." if timed_on_cpu(result) else
              f"of the wall-clock time (the device works asynchronously: the process's CPU time, in brackets, "
              f"counts only the host side); the fits and ratios use the wall-clock time.")
    lines = [
        "# Scaling: step time against mesh size and batch size" + (" (QUICK smoke run)" if result["quick"] else ""),
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']} ({m['backend']}); accelerator: "
        f"{m['accelerator']}. " + (
            f"Shared machine: load average {m['load_average_1m_at_start']} at start, "
            f"{m['load_average_1m_at_end']} at end (other jobs ran alongside; absolute times are inflated and noisy, "
            f"ratios within a table less so). " if timed_on_cpu(result) else
            f"Load average {m['load_average_1m_at_start']} at start (the host was otherwise idle). ")
        + f"{m['threads'].split(':')[0]} (XLA_FLAGS=\"{m['xla_flags']}\"). "
        + (f"Whole run {result['wall_seconds'] / 60:.1f} min. " if math.isfinite(result["wall_seconds"]) else
           "Whole run: cut off (see the caveats). ")
        + f"Times are medians of interleaved calls after "
        f"compilation, {timing}",
        "",
        f"## Mesh size (the 40×10×10 beam refined; learned step: `{result['model']}`, hidden {cfg['hidden']}, "
        f"{cfg['passes']} passes; one step = one 0.05 s frame)",
        "",
        f"| elements | nodes | edges | learned step {one} ({two}) ms | µs / node | ns / edge | FEM sub-step "
        + ("CPU (wall) ms | " if timed_on_cpu(result) else "wall ms | ")
        + "sub-steps / frame | FEM frame (ms) | FEM frame / learned step |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    fem_by = {r["nodes"]: r for r in result["fem_vs_nodes"]}
    for r in result["learned_vs_nodes"]:
        e = fem_by.get(r["nodes"])
        fem_cells = "| – | – | – | – |" if e is None else (
            f"| {e['ms_per_substep']:.3f}" + (f" ({e['ms_per_substep_wall']:.3f})" if timed_on_cpu(result) else "")
            + f" | {e['substeps_per_frame']} | "
            f"{e['ms_per_frame']:.0f}"
            + (f" (measured {e['ms_per_frame_measured']:.0f})" if "ms_per_frame_measured" in e else "")
            + f" | {e['ms_per_frame'] / r['ms']:.0f}× |")
        lines.append(f"| {'×'.join(map(str, r['elements']))} | {r['nodes']} | {r['edges']} | {r['ms']:.2f} "
                     f"({second(r, result):.2f}), {r['repeats']} calls | {r['us_per_node']:.2f} | {r['ns_per_edge']:.0f} "
                     + fem_cells)
    lines += ["",
              f"Fitted exponents a of time ∝ nodes^a (log–log least squares over the meshes with ≥ {FIT_FROM_NODES} "
              f"nodes): learned step a = {_exp(f['learned_step'])}; FEM sub-step a = {_exp(f['fem_substep'])}; "
              f"FEM frame a = {_exp(f['fem_frame'])}. From the wall-clock medians: learned "
              f"{_exp(f['learned_step_wall'])}, FEM sub-step {_exp(f['fem_substep_wall'])}, FEM frame "
              f"{_exp(f['fem_frame_wall'])}.",
              "",
              "FEM sub-step: slope of the run time between k and 2k sub-steps at the mesh's stable sub-step "
              "(fem.simulate, one frame, beam material and damping, tip load); FEM frame = sub-steps per frame × "
              "sub-step + the per-run overhead (initial force, frame outputs); where a whole 0.05 s frame was cheap "
              "enough it was also timed directly (measured)."]
    lines += ["", "## Batch size (the paper's beam, 756 nodes / 500 hex8)", "",
              f"| bodies | learned step {one} ({two}) ms | ms / body-step | per-body speed-up vs 1 | FEM sub-step "
              f"{one} ms | "
              "ms / body-sub-step | FEM element-sub-steps / s | per-body speed-up vs 1 |",
              "|---|---|---|---|---|---|---|---|"]
    fb = {r["batch"]: r for r in result["fem_vs_batch"]}
    for r in result["learned_vs_batch"]:
        e = fb.get(r["copies"])
        fem_cells = "| – | – | – | – |" if e is None else (
            f"| {e['ms_per_substep']:.3f} | {e['ms_per_body_substep']:.4f} | "
            f"{e['element_substeps_per_s'] / 1e6:.2f} M | {e['speedup_per_body_vs_1']:.2f}× |")
        lines.append(f"| {r['copies']} | {r['ms']:.2f} ({second(r, result):.2f}) | {r['ms_per_body_step']:.2f} | "
                     f"{r['speedup_per_body_vs_1']:.2f}× " + fem_cells)
    lines += ["", "## How the cost grows", "", summary(result), "", "## Caveats", ""] + caveats(result)
    cpu = f"; {result['cpu_seconds'] / 60:.1f} min of CPU time in this run" if "cpu_seconds" in result else ""
    if not timed_on_cpu(result):
        lines += ["", f"Re-run on a GPU machine (jax with CUDA): `python benchmarks/scaling.py` (writes "
                      f"benchmarks/results/scaling_gpu.*){cpu}.", ""]
        return "\n".join(lines)
    lines += ["", f"Re-run on a quiet machine (same settings{cpu}):", "",
              "    XLA_FLAGS=\"--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1\" "
              "python benchmarks/scaling.py", "",
              "and on a GPU machine (jax with CUDA) with `python benchmarks/scaling.py` (without XLA_FLAGS; it writes "
              "scaling_gpu.* and times by the wall clock there).", ""]
    return "\n".join(lines)


def caveats(result: dict) -> list:
    """Limits of the measurement, with the numbers that bound them."""
    ln, lb = result["learned_vs_nodes"], result["learned_vs_batch"]
    out = ["- No GPU measurement: no GPU was available in this session; all times are for this CPU."] \
        if result["machine"]["backend"] == "cpu" else []
    out += [f"- {note}" for note in result.get("notes", [])]
    if result.get("not_measured"):
        out.append(f"- Not measured: {', '.join(result['not_measured'])} (the run was cut off at its time limit "
                   f"before these stages; the tables leave them empty).")
    if ln and lb and ln[0]["nodes"] == lb[0]["nodes"]:
        a, b = ln[0]["ms"], lb[0]["ms"]
        out.append(f"- Reproducibility: the same 756-node step timed in the mesh table "
                   f"and in the batch table gives {a:.2f} and {b:.2f} ms {clocks(result)[0]} ({100 * abs(a - b) / min(a, b):.0f} % "
                   f"apart); differences smaller than that are not resolved.")
    big = [r for r in ln if r["nodes"] >= FIT_FROM_NODES]
    if big and len(ln) > len(big) and timed_on_cpu(result):
        per = [r["us_per_node"] for r in big]
        small = [r for r in ln if r["nodes"] < FIT_FROM_NODES]
        small_per = ", ".join(f"{r['us_per_node']:.1f}" for r in small)
        out.append(f"- The learned step's cost per node is {small_per} µs "
                   f"below {FIT_FROM_NODES} nodes and {min(per):.1f}–{max(per):.1f} µs from "
                   f"{big[0]['nodes']} nodes on: a step, then flat (the fit starts above the step). The batch "
                   f"table shows the same step (4 bodies = {4 * ln[0]['nodes']} nodes). This is consistent with the "
                   f"per-call working set (arrays of nodes × {ln[0]['slots'][1]} slots × hidden floats, forward and "
                   f"reverse) outgrowing the core's caches; it was not profiled.")
    out.append("- The learned step on the refined meshes uses the weights trained on the paper's mesh: this times "
               "it, it does not claim it is accurate there (its edges are shorter than any it was trained on). "
               f"The architecture is fixed ({result['model_config']['passes']} message passes reach "
               f"{result['model_config']['passes']} edges, a physical radius that shrinks with the element size); a "
               "model that keeps the same radius in length units on a finer mesh needs passes ∝ 1/h ∝ "
               "nodes^(1/3), which would add about 1/3 to its exponent, as the shrinking sub-step does for the FEM.")
    checked = [r for r in result["fem_vs_nodes"] if "ms_per_frame_measured" in r]
    check = "; ".join(f"{r['nodes']} nodes: a whole frame measured {r['ms_per_frame_measured']:.0f} ms against "
                      f"{r['ms_per_frame']:.0f} ms estimated ({100 * (r['ms_per_frame'] / r['ms_per_frame_measured'] - 1):+.0f} %)"
                      for r in checked)
    if checked and len(checked) == len(result["fem_vs_nodes"]):
        out.append("- FEM frame = sub-steps per frame × the measured sub-step + the per-run overhead; every mesh's "
                   f"whole frame was also timed: {check}.")
    else:
        out.append("- FEM frames of the large meshes are not run whole (minutes each): a frame is sub-steps per "
                   "frame × the measured sub-step + the per-run overhead"
                   + (f"; check on the small mesh: {check}." if checked else " (no mesh was cheap enough to check)."))
    if not timed_on_cpu(result) and len(ln) > 1:
        out.append(f"- On the accelerator the learned step costs {ln[0]['ms']:.2f} ms at {ln[0]['nodes']} nodes and "
                   f"{ln[1]['ms']:.2f} ms at {ln[1]['nodes']}: below a few thousand nodes the time is a fixed cost "
                   f"per call (launching the step's kernels), not work, which is why the fitted exponent is below 1 "
                   f"and why batching bodies pays.")
        cpu_path = RESULTS / "scaling.json"
        if cpu_path.exists():
            cpu_res = json.loads(cpu_path.read_text())
            by = {r["nodes"]: r for r in cpu_res.get("learned_vs_nodes", [])}
            fby = {r["nodes"]: r for r in cpu_res.get("fem_vs_nodes", [])}
            pairs = [(r, by[r["nodes"]]) for r in ln if r["nodes"] in by]
            fem_pairs = [(r, fby[r["nodes"]]) for r in result["fem_vs_nodes"] if r["nodes"] in fby]
            if pairs:
                cpu_key = "ms" if "ms" in pairs[0][1] else "cpu_ms"
                out.append("- Against this project's CPU result (`scaling.md`, "
                           f"{cpu_res['machine']['cpu']}, single core; another run on another machine): learned step "
                           + ", ".join(f"{c[cpu_key] / g['ms']:.0f}×" for g, c in pairs)
                           + " faster here" + (", FEM frame " + ", ".join(
                               f"{c['ms_per_frame'] / g['ms_per_frame']:.0f}×" for g, c in fem_pairs) + " faster"
                               if fem_pairs else "")
                           + f" (meshes of {', '.join(str(g['nodes']) for g, _ in pairs)} nodes).")
    return out


def growth(a: float) -> str:
    return "about linearly" if 0.9 <= a <= 1.1 else "faster than linearly" if a > 1.1 else "slower than linearly"


def summary(result: dict) -> str:
    """The measured growth in plain sentences (every qualitative word follows from the numbers)."""
    f = result["fits"]
    ln, fn = result["learned_vs_nodes"], result["fem_vs_nodes"]
    lb, fb = result["learned_vs_batch"], result["fem_vs_batch"]
    parts = []
    if f["learned_step"]:
        a = f["learned_step"]["exponent"]
        parts.append(f"The learned step's time grows {growth(a)} with the number of nodes (nodes^{a:.2f}; from "
                     f"the wall-clock medians nodes^{f['learned_step_wall']['exponent']:.2f}): "
                     f"{ln[0]['us_per_node']:.1f} µs per node on the paper's 756-node beam, "
                     f"{ln[-1]['us_per_node']:.1f} µs per node at {ln[-1]['nodes']} nodes.")
    if f["fem_substep"] and f["fem_frame"]:
        a = f["fem_substep"]["exponent"]
        parts.append(f"An FEM sub-step grows {growth(a)} (nodes^{a:.2f}), but the stable sub-step shrinks with "
                     f"the element size (∝ nodes^(-1/3) under uniform refinement), so the sub-steps per 0.05 s "
                     f"frame grow from {fn[0]['substeps_per_frame']} to {fn[-1]['substeps_per_frame']} and the FEM "
                     f"frame grows as nodes^{f['fem_frame']['exponent']:.2f}.")
    if ln and fn and ln[-1]["nodes"] == fn[-1]["nodes"] and len(ln) > 1:
        first, last = fn[0]["ms_per_frame"] / ln[0]["ms"], fn[-1]["ms_per_frame"] / ln[-1]["ms"]
        trend = "widens" if last > 1.2 * first else "narrows" if last < first / 1.2 else "stays about the same"
        parts.append(f"Per 0.05 s frame the learned step's advantage over the FEM {trend} with refinement: "
                     f"{first:.0f}× on the paper's mesh, {last:.0f}× at {ln[-1]['nodes']} nodes.")
    if lb:
        parts.append(f"Stepping beams together in one graph costs {lb[-1]['ms_per_body_step']:.2f} ms per "
                     f"body-step at {lb[-1]['copies']} bodies against {lb[0]['ms_per_body_step']:.2f} ms for one "
                     f"({lb[-1]['speedup_per_body_vs_1']:.2f}× per body)")
        if fb:
            parts[-1] += (f"; the FEM batch of {fb[-1]['batch']} load cases gives "
                          f"{fb[-1]['speedup_per_body_vs_1']:.2f}× per body-sub-step")
        parts[-1] += (f" on this CPU ({result['machine']['threads']})." if timed_on_cpu(result) else
                      f" on this {result['machine']['accelerator']}.")
    return " ".join(parts)


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ln, fn = result["learned_vs_nodes"], result["fem_vs_nodes"]
    series = ((ln, "ms", "learned step (= one 0.05 s frame)", "learned_step", "C0"),
              (fn, "ms_per_frame", "FEM, one 0.05 s frame", "fem_frame", "C3"),
              (fn, "ms_per_substep", "FEM, one sub-step", "fem_substep", "C1"))
    for rows, key, label, fit_key, colour in series:
        x = np.array([r["nodes"] for r in rows], float)
        y = np.array([r[key] for r in rows], float)
        fit = result["fits"][fit_key]
        ax1.loglog(x, y, "o-", color=colour, label=label + (f" (a = {fit['exponent']:.2f})" if fit else ""))
        if fit:
            xs = np.geomspace(fit["from_nodes"], fit["to_nodes"], 20)
            ax1.loglog(xs, fit["coefficient_ms"] * xs ** fit["exponent"], ":", color=colour)
    ax1.set_xlabel("nodes (beam refined from 20×5×5 elements)")
    ax1.set_ylabel(f"{clocks(result)[0]} time per call (ms)")
    ax1.set_title("time ∝ nodes^a (fit dotted)")
    ax1.grid(True, which="both", alpha=0.3)
    ax1.legend(fontsize=8, loc="upper left")
    lb, fb = result["learned_vs_batch"], result["fem_vs_batch"]
    ax2.loglog([r["copies"] for r in lb], [r["ms_per_body_step"] for r in lb], "o-", color="C0",
               label="learned: ms per body-step")
    ax2.loglog([r["batch"] for r in fb], [r["ms_per_body_substep"] for r in fb], "s-", color="C1",
               label="FEM: ms per body-sub-step")
    ax2.set_xticks([r["copies"] for r in lb])
    ax2.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax2.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax2.set_xlabel("bodies in one call (756-node beam)")
    ax2.set_ylabel(f"{clocks(result)[0]} time per body (ms)")
    ax2.set_title("per-body cost against batch size")
    ax2.grid(True, which="both", alpha=0.3)
    ax2.legend(fontsize=8, loc="upper left")
    m = result["machine"]
    where = (f"{m['cpu']}, {m['cores']} cores, {m['backend']} (shared: load {m['load_average_1m_at_start']}"
             f"→{m['load_average_1m_at_end']})" if timed_on_cpu(result) else
             f"{m['accelerator']} ({m['backend']}, jax {m['jax']}), host {m['cpu']}")
    fig.suptitle(where + (" — QUICK" if result["quick"] else ""), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sys.exit(main())
