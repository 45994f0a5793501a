"""Does work on one core of this machine slow a step on the other? (why the two-beams scene has a slow tail)

The two-beams scene steps one body per core (`Scene.devices`). Its per-frame simulation time has a tail
(p99 about 1.5–1.6 × p50 in `realtime.md`) that a body's step alone does not have. This benchmark separates the
loop from the machine: one process pinned to core 0 steps one body of the shipped beam model (``beam-abaqus``)
``--calls`` times, while core 1

  * is idle;
  * runs a pinned pure-Python integer loop (no memory traffic, no JAX, nothing shared with core 0's process);
  * runs a pinned NumPy matrix product (vector units and memory);
  * runs the same step in a second pinned process (what the two-beams scene does, without its shared thread
    pool: each process has its own).

and, as the control, the same process unpinned with the other core idle. If a step pinned to core 0 slows down
or gains a tail when core 1 runs anything, that interference is the machine's (on a virtual machine: two vCPUs
that share a host core, or host scheduling), and no arrangement of the loop removes it; if the pinned step has
its tail whatever core 1 does, the tail comes from sharing one core among XLA's threads or from the host. Writes benchmarks/results/core_interference.{json,md}. Linux only (it pins
with ``os.sched_setaffinity``); needs two cores.

    python benchmarks/core_interference.py [--calls 150] [--rounds 4] [--model beam-abaqus]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]

STEP = """
import gc, json, os, sys, time
os.sched_setaffinity(0, {{{core}}})
sys.path.insert(0, {root!r})
import numpy as np, jax, jax.numpy as jnp
from tignn_jax import api
params, graph = api.load_pretrained({model!r})
one = api.stepper(params)
z = jnp.asarray(graph.nodes["z"]); n = z.shape[0]
rng = np.random.default_rng(0)
z = z.at[:, 3:].set(jnp.asarray(0.01 * rng.normal(size=(n, 9)), jnp.float32))
f = jnp.asarray(0.01 * rng.normal(size=(n, 3)), jnp.float32)
for _ in range(5): jax.block_until_ready(one(z, f))
gc.disable(); ms = []
t_end = time.perf_counter() + {seconds}
while len(ms) < {calls} or time.perf_counter() < t_end:
    t = time.perf_counter(); jax.block_until_ready(one(z, f)); ms.append(1e3 * (time.perf_counter() - t))
print(json.dumps(ms[:{calls}]))
"""
SPIN = "import os, time\nos.sched_setaffinity(0, {1})\nt = time.time(); x = 0\nwhile time.time() - t < %f: x += 1\n"
MATMUL = ("import os, time\nos.sched_setaffinity(0, {1})\nimport numpy as np\n"
          "a = np.random.rand(1500, 1500).astype(np.float32); t = time.time()\n"
          "while time.time() - t < %f: a @ a\n")


def measure(model: str, calls: int, other: str) -> list:
    """Step times (ms) on core 0 while core 1 runs ``other`` (idle / spin / matmul / step), or on either core
    with the other idle (``unpinned``)."""
    env = {**os.environ, "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    step0 = STEP.format(core="0, 1" if other == "unpinned" else 0, root=str(ROOT), model=model, calls=calls,
                        seconds=0)
    background = None
    if other in ("spin", "matmul"):
        background = subprocess.Popen([sys.executable, "-c", (SPIN if other == "spin" else MATMUL) % 600.0])
    elif other == "step":   # the second body: keeps stepping until the first process has its samples
        background = subprocess.Popen([sys.executable, "-c", STEP.format(core=1, root=str(ROOT), model=model,
                                                                        calls=1, seconds=600)],
                                      stdout=subprocess.DEVNULL, env=env)
        time.sleep(15.0)    # let it load and compile before core 0 starts timing
    try:
        out = subprocess.run([sys.executable, "-c", step0], capture_output=True, text=True, env=env, check=True)
    finally:
        if background is not None:
            background.kill()
            background.wait()
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    import numpy as np

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=150, help="timed steps per condition (default: %(default)s)")
    parser.add_argument("--model", default="beam-abaqus")
    parser.add_argument("--rounds", type=int, default=4, help="times each condition is run, in turn")
    args = parser.parse_args(argv)
    if args.calls < 50:
        raise SystemExit(f"--calls must be at least 50, got {args.calls}")
    if not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2:
        raise SystemExit("needs Linux and two cores (it pins one process per core)")
    conditions = ("unpinned", "idle", "spin", "matmul", "step")
    samples = {c: [] for c in conditions}
    for r in range(args.rounds):
        for c in conditions:
            print(f"round {r + 1}/{args.rounds}: core 1 {c} ...", flush=True)
            samples[c].append(measure(args.model, args.calls, c))
    stats = {}
    for c, runs in samples.items():
        per_run = [{"p50_ms": float(np.median(v)), "p99_ms": float(np.percentile(v, 99)),
                    "p99_over_p50": float(np.percentile(v, 99) / np.median(v)),
                    "slow_share": float(np.mean(np.asarray(v) > 1.5 * np.median(v)))} for v in runs]
        stats[c] = {"runs": per_run}
    result = {"machine": describe(), "model": args.model, "calls": args.calls, "rounds": args.rounds,
              "conditions": stats}
    m = result["machine"]
    what = {"unpinned": "idle, and the step's process may use both cores (not pinned)", "idle": "idle", "spin": "a pinned Python integer loop", "matmul": "a pinned NumPy matrix product",
            "step": "the same step (second pinned process)"}
    lines = ["# One body's step on core 0 against what core 1 does", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']}; load average {m['load_average_1m']} at end "
             f"({m['note']}). Model `{args.model}`, {args.calls} timed steps per run after 5 untimed, each process "
             f"pinned with sched_setaffinity; {args.rounds} rounds of the conditions in turn.", "",
             "| core 1 runs | step p50 (ms), per round | p99 | p99 / p50 | steps > 1.5 × p50 |", "|---|---|---|---|---|"]
    for c, s in stats.items():
        runs = s["runs"]
        lines.append(f"| {what[c]} | " + ", ".join(f"{r['p50_ms']:.2f}" for r in runs) + " | " +
                     ", ".join(f"{r['p99_ms']:.2f}" for r in runs) + " | " +
                     ", ".join(f"{r['p99_over_p50']:.2f}" for r in runs) + " | " +
                     ", ".join(f"{100 * r['slow_share']:.1f} %" for r in runs) + " |")
    write_results("core_interference", result, "\n".join(lines) + "\n", RESULTS, echo=False)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
