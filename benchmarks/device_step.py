"""Step time of learned models on whatever device jax runs on (CPU here; a GPU machine where one is lent), for
comparing devices on the same models: the paper's 9 ms (beam) and 11 ms (bunny) per step on a desktop GPU.

For each model (a shipped name or a model file): ``api.stepper`` (one body, jit-compiled, static graph data
closed over) from the rest state with zero forces; the median and 99th percentile of ``--repeats`` calls
after compilation, each synchronised (``block_until_ready``), by the wall clock. Writes
benchmarks/results/device_step_<backend>[_TAG].{json,md} (``--out`` for another folder, ``--tag`` for a suffix).

    python benchmarks/device_step.py beam-abaqus beam [path/to/model.npz ...] [--repeats 300]
    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" python benchmarks/device_step.py ...
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def time_model(name: str, repeats: int) -> dict:
    from tignn_jax import api

    params, graph = api.load_pretrained(name)
    step = api.stepper(params)
    z = jnp.asarray(graph.nodes["z"], jnp.float32)
    f = jnp.zeros((z.shape[0], 3), jnp.float32)
    t0 = time.perf_counter()
    jax.block_until_ready(step(z, f))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(step(z, f))
        times.append(time.perf_counter() - t0)
    cfg = params["config"]
    return {"model": name, "nodes": int(z.shape[0]), "edges": int(len(params["mesh"]["senders"])),
            "hidden": int(cfg["hidden"]), "passes": int(cfg["passes"]), "compile_s": compile_s,
            "integrator": integrator_text(cfg),
            "median_ms": 1e3 * float(np.median(times)), "p99_ms": 1e3 * float(np.percentile(times, 99)),
            "repeats": repeats}


def integrator_text(cfg: dict) -> str:
    """The step's integrator in words: e.g. "rk4 × 2 sub-steps, relaxation"."""
    if cfg.get("frame_solve"):
        return "W-method"
    text = cfg.get("integrator", "euler")
    if cfg.get("substeps", 1) > 1:
        text += f" × {cfg['substeps']} sub-steps"
    return text + (", relaxation" if cfg.get("relaxation") else "")


def model_label(model: str) -> str:
    """A model's name for the table: the shipped name, or the file's folder for a ``model.npz``."""
    path = Path(model)
    if not model.endswith(".npz"):
        return model
    if path.stem != "model":
        return path.stem
    return f"{path.parent.parent.name}/best" if path.parent.name == "best" else path.parent.name


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+", help="shipped model names or model files")
    ap.add_argument("--repeats", type=int, default=300)
    ap.add_argument("--out", default=None, help="output folder (default benchmarks/results)")
    ap.add_argument("--tag", default="", help="write device_step_<backend>_TAG.* instead of device_step_<backend>.*")
    args = ap.parse_args(argv)
    if args.repeats < 10:
        raise SystemExit(f"--repeats must be at least 10, got {args.repeats}")
    machine = describe()
    machine["device"] = jax.devices()[0].device_kind
    machine["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    rows = [time_model(m, args.repeats) for m in args.models]
    backend = machine["backend"]
    out = Path(args.out) if args.out else RESULTS
    name = f"device_step_{backend}" + (f"_{args.tag}" if args.tag else "")
    lines = [f"# Learned step time on {machine['device']} ({backend})", "",
             f"Host {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']}, load average "
             f"{machine['load_average_1m']} at start, XLA_FLAGS=\"{machine['xla_flags']}\". One body, "
             f"`api.stepper`, rest state, zero forces; wall clock per synchronised call after compilation.", "",
             "| model | nodes | edges | hidden × passes | integrator | median ms | p99 ms | compile s |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {model_label(r['model'])} | {r['nodes']} | {r['edges']} | {r['hidden']} × {r['passes']} | "
                     f"{r['integrator']} | {r['median_ms']:.3f} | {r['p99_ms']:.3f} | {r['compile_s']:.1f} |")
    write_results(name, {"machine": machine, "rows": rows}, "\n".join(lines) + "\n", out, echo=False)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
