"""One pinned core against all cores: which ``tignn demo --cores N`` meets the real-time budget on this machine?

Question: with the shipped models, does the demo's loop meet its budget (simulation p50 ≤ 9 / 18 / 11 ms for the
beam, the two beams and the bunny, p99 ≤ 1.5 × p50, whole frame p50 ≤ 33 ms) more reliably pinned to one core
(the demo's default) or spread over all the cores it may use?

How: ``tignn demo --cores N`` pins its process to N of the CPUs it may use and makes one CPU device per core, a
body per device (`tignn_jax.mr.runtime.real_time_cores`). Pinning and the device count act only before JAX's
first operation, so each configuration runs in its own process; the configurations alternate for ``--rounds``
rounds, so a change of the machine's load hits both alike. Each process plays every row's loop once
(``realtime.run_scene``: the demo's scene with its shipped model, ``--frames`` frames after ``--warmup``), then
times the loop's step program alone (the same input every call). Reported per row and configuration: every
round's simulation p50 / p99 over the learned-step frames, the medians over the rounds, how many rounds meet the
budget, the whole frame's p50, and the step program alone.

Writes ``pinning.{json,md}`` (``pinning_TAG.*`` with ``--tag``) to ``--out`` (default benchmarks/results), with the
CPU and its load average. ``--quick`` is a smoke test (10 frames, one round), not a measurement. Linux only
(``os.sched_setaffinity``).

    python benchmarks/pinning.py [--rounds 3] [--frames 500] [--configs 1,2] [--rows beam,two-beams,bunny]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ROWS = ("beam", "two-beams", "bunny")   # the demo's scenes, each with its shipped model
QUICK = {"rounds": 1, "frames": 10, "warmup": 2}


def child(cores: int, rows: list, frames: int, warmup: int) -> dict:
    """One configuration in this (fresh) process: pinned to ``cores`` CPUs with as many CPU devices, every row's
    loop played once. {row: {simulation p50/p99 (learned-step frames), frame p50/p99, step alone, budget}}."""
    from tignn_jax import mr

    mr.real_time_xla_flags()
    pinned, devices = mr.real_time_cores(cores)
    import realtime as rt

    rt.share_loaded_models()
    out = {"pinned_cpus": list(pinned), "cpu_devices": len(devices), "machine": describe(), "rows": {}}
    for name in rows:
        s = rt.run_scene(name, frames, warmup, devices, rounds=1, public=False)
        learned = s["simulation_learned"]
        out["rows"][name] = {"dynamics": s["dynamics"], "simulation_p50_ms": learned["p50_ms"],
                             "simulation_p99_ms": learned["p99_ms"], "learned_frames": s["learned_frames"],
                             "frame_p50_ms": s["frame"]["p50_ms"], "frame_p99_ms": s["frame"]["p99_ms"],
                             "step_alone": s["step_programs"][0][rt.LOOP_STEP], "guard_trips": s["guard_trips"],
                             "budget_ms": rt.BUDGET_MS[name], "meets": bool(s["valid"] and all(
                                 s["budget"][k] for k in ("simulation_p50_ok", "p99_ok", "frame_p50_ok")))}
    out["machine"]["load_average_1m_at_end"] = describe()["load_average_1m"]
    return out


def run_child(cores: int, rows: list, frames: int, warmup: int) -> dict:
    cmd = [sys.executable, __file__, "--child", str(cores), "--rows", ",".join(rows), "--frames", str(frames),
           "--warmup", str(warmup)]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=1800)
    if done.returncode != 0:
        raise RuntimeError(f"configuration --cores {cores} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def summarise(runs: dict, rows: list) -> dict:
    """{row: {config: {rounds: [...], median p50 / p99 / ratio, rounds meeting the budget}}}."""
    out = {}
    for row in rows:
        out[row] = {}
        for cfg, played in runs.items():
            r = [p["rows"][row] for p in played]
            ratio = [x["simulation_p99_ms"] / x["simulation_p50_ms"] for x in r]
            out[row][cfg] = {
                "rounds": [{"p50_ms": x["simulation_p50_ms"], "p99_ms": x["simulation_p99_ms"], "p99_over_p50": q,
                            "frame_p50_ms": x["frame_p50_ms"], "step_alone_p50_ms": x["step_alone"]["p50_ms"],
                            "step_alone_p99_over_p50": x["step_alone"]["p99_over_p50"],
                            "guard_trips": x["guard_trips"], "meets": x["meets"]} for x, q in zip(r, ratio)],
                "p50_ms": float(np.median([x["simulation_p50_ms"] for x in r])),
                "p99_ms": float(np.median([x["simulation_p99_ms"] for x in r])),
                "p99_over_p50_median": float(np.median(ratio)), "p99_over_p50_max": float(np.max(ratio)),
                "frame_p50_ms": float(np.median([x["frame_p50_ms"] for x in r])),
                "rounds_meeting": int(sum(x["meets"] for x in r)), "budget_ms": r[0]["budget_ms"],
                "dynamics": r[0]["dynamics"]}
    return out


def format_md(result: dict) -> str:
    m = result["machine"]
    cfgs = list(result["configs"])
    lines = ["# The demo's loop on one pinned core against all cores", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']}; load average {m['load_average_1m']} at the "
             f"start ({m['note']}). Each configuration in its own process (`tignn demo --cores N`: pinned to N CPUs, "
             f"N CPU devices, a body per device), the configurations alternating for {result['rounds']} rounds; "
             f"each round plays every row's loop once, {result['frames']} frames after {result['warmup']} warm-up "
             "frames, then its step program alone (the same input every call). Simulation p50 / p99 over the "
             "learned-step frames, median over the rounds; the budget: simulation p50 ≤ the row's, p99 ≤ 1.5 × "
             "p50, whole frame p50 ≤ 33 ms." + (" QUICK RUN (smoke test): not a measurement."
                                                 if result.get("quick") else ""), "",
             "| row | budget p50 | " + " | ".join(
                 f"{c}: simulation p50 / p99 (median p99/p50; worst round) | {c}: frame p50 | {c}: rounds meeting "
                 "the budget" for c in cfgs) + " | p99, " + f"{cfgs[0]} / {cfgs[-1]} |",
             "|---|---|" + "---|---|---|" * len(cfgs) + "---|"]
    for row, by in result["summary"].items():
        cells = []
        for c in cfgs:
            s = by[c]
            cells.append(f"{s['p50_ms']:.2f} / {s['p99_ms']:.2f} ({s['p99_over_p50_median']:.2f}×; "
                         f"{s['p99_over_p50_max']:.2f}×) | {s['frame_p50_ms']:.2f} | {s['rounds_meeting']} of "
                         f"{len(s['rounds'])}")
        lines.append(f"| {row} | {by[cfgs[0]]['budget_ms']:.0f} ms | " + " | ".join(cells) +
                     f" | {by[cfgs[0]]['p99_ms'] / by[cfgs[-1]]['p99_ms']:.2f} |")
    lines += ["", "Every round, simulation p50 / p99 (p99/p50) and, in brackets, the step program alone (p50, "
              "p99/p50):", ""]
    for row, by in result["summary"].items():
        for c in cfgs:
            lines.append(f"- {row}, {c}: " + "; ".join(
                f"{r['p50_ms']:.2f} / {r['p99_ms']:.2f} ({r['p99_over_p50']:.2f}×) [{r['step_alone_p50_ms']:.2f}, "
                f"{r['step_alone_p99_over_p50']:.2f}×]" for r in by[c]["rounds"]))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description="The demo's loop pinned to one core against all cores, in alternating processes, with the "
                    "shipped models; writes pinning.{json,md}.")
    parser.add_argument("--rounds", type=int, default=None,
                        help="alternations of the configurations (default: 3; --quick: 1)")
    parser.add_argument("--frames", type=int, default=None,
                        help="timed frames per row and round, at least 10 (default: 500; --quick: 10)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="untimed first frames, at least 1 (default: 20; --quick: 2)")
    parser.add_argument("--configs", default=None,
                        help="core counts to compare, comma-separated (default: 1 and all the CPUs the process "
                             "may use)")
    parser.add_argument("--rows", default=",".join(ROWS), help=f"rows, comma-separated, from {list(ROWS)} "
                                                                 "(default: all)")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke test: one round of 10 frames after 2 (each unless given)")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR,
                        help="folder the results are written to (default: benchmarks/results)")
    parser.add_argument("--tag", default="", help="write pinning_TAG.{json,md} instead of pinning.*")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    for key, value in (QUICK if args.quick else {"rounds": 3, "frames": 500, "warmup": 20}).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    rows = [r for r in args.rows.split(",") if r]
    bad = [r for r in rows if r not in ROWS]
    if bad or not rows:
        raise SystemExit(f"unknown row(s) {bad}; choose from {list(ROWS)}")
    if args.rounds < 1 or args.frames < 10 or args.warmup < 1:
        raise SystemExit(f"--rounds must be ≥ 1, --frames ≥ 10 and --warmup ≥ 1, got {args.rounds}, "
                         f"{args.frames} and {args.warmup}")
    if args.child is not None:
        print(json.dumps(child(args.child, rows, args.frames, args.warmup)))
        return 0
    if not hasattr(os, "sched_setaffinity"):
        raise SystemExit("needs Linux (it pins processes with os.sched_setaffinity)")
    cpus = len(os.sched_getaffinity(0))
    try:
        configs = sorted({1, cpus}) if args.configs is None else [int(c) for c in args.configs.split(",") if c]
    except ValueError:
        raise SystemExit(f"--configs must be comma-separated integers, got {args.configs!r}")
    if not configs or any(c < 1 or c > cpus for c in configs):
        raise SystemExit(f"--configs must be core counts from 1 to {cpus}, got {args.configs!r}")
    names = {c: f"{c} core{'s' if c > 1 else ''}{', pinned' if c < cpus else ''}" for c in configs}
    runs = {names[c]: [] for c in configs}
    machine = None
    for k in range(args.rounds):
        for c in configs:
            print(f"round {k + 1}/{args.rounds}: --cores {c} ...", flush=True)
            played = run_child(c, rows, args.frames, args.warmup)
            machine = machine or played["machine"]
            runs[names[c]].append(played)
    result = {"machine": machine, "quick": args.quick, "rounds": args.rounds, "frames": args.frames,
              "warmup": args.warmup, "configs": {names[c]: c for c in configs}, "rows": rows, "runs": runs,
              "summary": summarise(runs, rows)}
    write_results(f"pinning_{args.tag}" if args.tag else "pinning", result, format_md(result), folder=args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
