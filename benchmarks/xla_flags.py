"""XLA:CPU options for the real-time loop: the shipped beam step under each option, in alternating processes.

XLA reads ``XLA_FLAGS`` once per process, so each option is timed in its own child process (the shipped
`beam-abaqus` stepper of `api.stepper`, median of 300 calls after 20 untimed), the options alternating over
``--rounds`` rounds so that a slow spell of the machine falls on all of them. Each child also saves its output
for one fixed state, so the options are compared on the states they compute too. The loop's default
(`scene.real_time_xla_flags`) is chosen from this. Writes benchmarks/results/xla_flags.{json,md}.

    python benchmarks/xla_flags.py [--rounds 3]
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

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
_YNN_OFF = "--xla_cpu_experimental_ynn_fusion_type="
OPTIONS = {"default": "", "YNNPACK fusions off": _YNN_OFF,
           "XNNPACK off": "--xla_cpu_use_xnnpack=false",
           "YNNPACK fusions off + XNNPACK fusions off": f"{_YNN_OFF} --xla_cpu_experimental_xnn_fusion_type=",
           "YNNPACK fusions off + fast math": f"{_YNN_OFF} --xla_cpu_enable_fast_math=true",
           "YNNPACK fusions off + concurrency-optimised scheduler":
               f"{_YNN_OFF} --xla_cpu_enable_concurrency_optimized_scheduler=true",
           "YNNPACK fusions off, single-threaded": f"{_YNN_OFF} --xla_cpu_multi_thread_eigen=false "
                                                  "intra_op_parallelism_threads=1",
           "YNNPACK fusions off + oneDNN dot fusion": f"{_YNN_OFF} --xla_cpu_experimental_onednn_fusion_type=dot",
           "YNNPACK fusions off + 512-bit vectors": f"{_YNN_OFF} --xla_cpu_prefer_vector_width=512",
           "YNNPACK fusions off, pinned to one core": _YNN_OFF}
PINNED = {"YNNPACK fusions off, pinned to one core"}


def child(model: str, out: str, pin: bool = False) -> None:
    if pin:   # before JAX creates its threads: they all inherit the one core
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    import jax.numpy as jnp

    from tignn_jax import api

    params, _ = api.load_pretrained(model)
    fn = api.stepper(params)
    q0 = params["mesh"]["q0"]
    rng = np.random.default_rng(0)
    z = jnp.asarray(np.concatenate([q0 + 0.01 * rng.normal(size=q0.shape), 0.01 * rng.normal(size=(len(q0), 9))],
                                   1), jnp.float32)
    f = jnp.asarray(0.01 * rng.normal(size=(len(q0), 3)), jnp.float32)
    np.save(out, np.asarray(fn(z, f)))
    for _ in range(20):
        fn(z, f).block_until_ready()
    ts = []
    for _ in range(300):
        t = time.perf_counter()
        fn(z, f).block_until_ready()
        ts.append(time.perf_counter() - t)
    print(json.dumps({"p50_ms": 1e3 * float(np.median(ts)), "p99_ms": 1e3 * float(np.percentile(ts, 99))}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--model", default="beam-abaqus")
    ap.add_argument("--child", nargs=2, metavar=("MODEL", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--pin", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child, pin=args.pin)
        return 0
    if args.rounds < 1:
        raise SystemExit(f"--rounds must be positive, got {args.rounds}")
    machine = describe()
    runs = {k: [] for k in OPTIONS}
    outputs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for i, (name, flags) in enumerate(OPTIONS.items()):
                out = str(Path(tmp) / f"{r}_{i}.npy")
                env = dict(os.environ, XLA_FLAGS=flags)
                pin = ["--pin"] if name in PINNED else []
                done = subprocess.run([sys.executable, __file__, "--child", args.model, out, *pin], env=env,
                                      capture_output=True, text=True, check=True, timeout=600)
                runs[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
                outputs.setdefault(name, np.load(out))
                print(name, runs[name][-1], flush=True)
    base = outputs["default"]
    scale = np.abs(base).max(axis=0)
    rows = {}
    for name, rs in runs.items():
        p50 = [r["p50_ms"] for r in rs]
        rows[name] = {"flags": OPTIONS[name], "p50_ms_per_round": p50, "p50_ms": float(np.median(p50)),
                      "p99_ms": float(np.median([r["p99_ms"] for r in rs])),
                      "largest_difference_relative": float((np.abs(outputs[name] - base).max(axis=0) / scale).max())}
    for r in rows.values():
        r["speedup_vs_default"] = rows["default"]["p50_ms"] / r["p50_ms"]
    machine["load_average_1m_at_end"] = describe()["load_average_1m"]
    lines = [f"# XLA:CPU options for the real-time loop ({args.model} step, api.stepper)", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']}; load average "
             f"{machine['load_average_1m']} at start, {machine['load_average_1m_at_end']} at end. Each option in its "
             f"own process (XLA reads XLA_FLAGS once), {args.rounds} rounds alternating the options; per process "
             "the median of 300 calls after 20 untimed; \"pinned to one core\": the child process and all its "
             "threads on one core (`os.sched_setaffinity`).", "",
             "| option | XLA_FLAGS | step p50 per round (ms) | p50 (median of rounds) | p99 | × default | "
             "largest state difference vs default (relative) |", "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | `{r['flags'] or '(none)'}` | {', '.join(f'{x:.2f}' for x in r['p50_ms_per_round'])} "
                     f"| {r['p50_ms']:.2f} | {r['p99_ms']:.2f} | {r['speedup_vs_default']:.2f}× | "
                     f"{r['largest_difference_relative']:.1e} |")
    write_results("xla_flags", {"machine": machine, "model": args.model, "rows": rows}, "\n".join(lines) + "\n",
                  RESULTS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
