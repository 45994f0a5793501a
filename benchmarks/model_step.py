"""What the public API's per-call checks cost: `tignn_jax.step` against `tignn_jax.stepper` and `rollout`.

`tignn_jax.step(params, graph, forces)` checks every call (the graph is the model's mesh, the forces have the
right shape and are finite) and then runs the model's compiled frame map; `tignn_jax.stepper(params, copies)`
returns that same compiled program without the checks, for loops that hold the state as an array;
`tignn_jax.rollout(params, graph, forces_seq)` checks once and runs T frames in one ``lax.scan``. The product
requirement: the checks cost at most 10 % of a step, i.e. "checks overhead" = step / stepper − 1 ≤ 0.10.

Rows: the shipped ``beam`` (one body, 756 nodes), two beams (a graph of 2 copies of the beam, 1512 nodes:
`rest_graph(params, 2)`, whose edges `step` knows by identity), the shipped ``bunny`` (1330 nodes) and the
corotational ``beam-corot`` and ``bunny-corot`` (the beam's and the bunny's meshes; their frames iterate, so their
time depends on the state more than the linear models') and the paper's network ``beam-tignn`` (one forward-Euler
step of a 2-pass graph network). For each row the state is the rest state advanced by 10
frames under a load at half the model's largest training force (``envelope["f_max"]``) on the free node farthest
from the clamps; each call steps that state under that load (numpy float32 forces, as a real-time loop hands them
over). Times: milliseconds per call after a
compiling call, ``--repeats`` samples of each variant, the variants called in a new random order each round
(`_machine.interleaved_ms`: a change of the machine's load hits all alike, and no variant always follows the
rollout, whose 20 frames sweep the caches); reported are medians and 90th percentiles, and the median over rounds
of the step and stepper calls' difference and ratio (paired: robust to load changes between rounds); the rollout's
time is per frame (its call over T frames divided by T).

Writes model_step.{json,md} to ``--out`` (default benchmarks/results).

    python benchmarks/model_step.py [--repeats 200] [--rollout-frames 20] \
        [--rows beam:1,beam:2,bunny:1,beam-corot:1,bunny-corot:1,beam-tignn:1]
    python benchmarks/model_step.py --quick --out /tmp/model_step     # smoke run, ~30 s
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, machine_line, interleaved_ms, write_results  # noqa: E402

ROWS = "beam:1,beam:2,bunny:1,beam-corot:1,bunny-corot:1,beam-tignn:1"
CHECKS_BUDGET = 0.10     # the checks may cost at most 10 % of a step
WARM_FRAMES = 10         # frames from rest before the timed state


def parse_rows(text: str) -> list:
    """``"beam:1,beam:2,bunny"`` → [("beam", 1), ("beam", 2), ("bunny", 1)] (a shipped model name and the number
    of bodies in the graph)."""
    rows = []
    for item in [s.strip() for s in text.split(",") if s.strip()]:
        name, _, copies = item.partition(":")
        try:
            k = int(copies or 1)
        except ValueError:
            raise SystemExit(f"--rows: {item!r} is not NAME[:COPIES]") from None
        if k < 1:
            raise SystemExit(f"--rows: the number of copies must be positive, got {item!r}")
        rows.append((name, k))
    if not rows:
        raise SystemExit("--rows names no model")
    return rows


def row_label(name: str, copies: int) -> str:
    return name if copies == 1 else f"{copies} × {name}"


def load_of(params: dict, copies: int) -> np.ndarray:
    """[copies·N, 3] float32: half the largest training force on each body's free node farthest from its clamped
    nodes, pointing down (−z)."""
    q0 = np.asarray(params["mesh"]["q0"], np.float64)
    node_type = np.asarray(params["mesh"]["node_type"])
    clamped = q0[node_type != 0] if np.any(node_type != 0) else q0.mean(0, keepdims=True)
    dist = np.min(np.linalg.norm(q0[:, None] - clamped[None], axis=-1), axis=1)
    dist[node_type != 0] = -1.0
    f = np.zeros_like(q0, np.float32)
    f[int(np.argmax(dist)), 2] = -0.5 * float(np.asarray(params["envelope"]["f_max"]).reshape(-1)[0])
    return np.tile(f, (copies, 1))


def variants(name: str, copies: int, frames: int) -> tuple:
    """({"step", "stepper", "rollout"}: zero-argument calls, info) for one row."""
    import jax.numpy as jnp
    import tignn_jax

    params, _ = tignn_jax.load_pretrained(name)
    graph = tignn_jax.rest_graph(params, copies)
    forces = load_of(params, copies)
    fast = tignn_jax.stepper(params, copies)
    z = graph.nodes["z"]
    for _ in range(WARM_FRAMES):
        z = fast(z, forces)
    graph = graph._replace(nodes={**graph.nodes, "z": z})
    seq = np.repeat(forces[None], frames, axis=0)
    fns = {"step": lambda: tignn_jax.step(params, graph, forces).nodes["z"],
           "stepper": lambda: fast(z, forces),
           "rollout": lambda: tignn_jax.rollout(params, graph, seq)}
    # the three must compute the same frame (the same program)
    a, b = np.asarray(fns["step"]()), np.asarray(fns["stepper"]())
    c = np.asarray(fns["rollout"]()[1])
    info = {"model": name, "copies": copies, "nodes": int(z.shape[0]), "class": params["model"].name,
            "same_frame": bool(np.array_equal(a, b)
                               and np.allclose(a, c, rtol=1e-5, atol=1e-5 * float(jnp.abs(z).max())))}
    return fns, info


def summarise(times: dict, frames: int) -> dict:
    """Medians and 90th percentiles (ms) of one row's samples, the rollout's per frame, and the ratio."""
    out = {}
    for k, v in times.items():
        v = np.asarray(v) / (frames if k == "rollout" else 1)
        out[k] = {"p50_ms": float(np.median(v)), "p90_ms": float(np.percentile(v, 90)), "samples": len(v)}
    ratio = out["step"]["p50_ms"] / out["stepper"]["p50_ms"]
    out["step_over_stepper"] = ratio
    out["checks_overhead"] = ratio - 1.0
    out["checks_within_budget"] = bool(ratio - 1.0 <= CHECKS_BUDGET)
    # paired within a round (the two calls follow each other, so a change of load hits both): more robust
    step, fast = np.asarray(times["step"]), np.asarray(times["stepper"])
    out["checks_ms_paired"] = float(np.median(step - fast))
    out["checks_overhead_paired"] = float(np.median(step / fast) - 1.0)
    out["rollout_over_stepper"] = out["rollout"]["p50_ms"] / out["stepper"]["p50_ms"]
    return out


def report(result: dict) -> str:
    m = result["machine"]
    lines = ["# The public API's cost: `step` (checked) against `stepper` (unchecked) and `rollout`", "",
             machine_line(m) + "; load average "
             f"{m['load_average_1m']} at the start, {result['load_average_1m_end']} at the end (above {m['cores']}: "
             f"other processes shared the CPU). Median (p90) of {result['repeats']} calls per variant after "
             f"compilation, variants interleaved in a new random order each round; rollout: one call over "
             f"{result['rollout_frames']} frames, per frame."
             + (" QUICK run (few repeats): indicative only." if result["quick"] else ""), "",
             "| model | bodies | nodes | step ms | stepper ms | rollout ms / frame | step / stepper | checks overhead "
             f"(≤ {CHECKS_BUDGET:.0%}) | paired: checks ms, overhead |", "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        t = r["timing"]
        cell = lambda k: f"{t[k]['p50_ms']:.3f} ({t[k]['p90_ms']:.3f})"
        verdict = "met" if t["checks_within_budget"] else "**NOT met**"
        lines.append(f"| {r['model']} | {r['copies']} | {r['nodes']} | {cell('step')} | {cell('stepper')} | "
                     f"{cell('rollout')} | {t['step_over_stepper']:.3f} | {100 * t['checks_overhead']:+.1f} % "
                     f"({verdict}) | {t['checks_ms_paired']:+.3f} ms, {100 * t['checks_overhead_paired']:+.1f} % |")
    lines += ["", "checks overhead = step / stepper − 1 (medians). Paired: the median over rounds of the difference "
              "and of the ratio of the step and stepper calls of one round (they follow each other, so a change of "
              "the machine's load hits both). `step` and `stepper` run the same compiled "
              "program on the same state and forces; the difference is `step`'s checks (the graph's edges against the "
              "model's mesh: by identity for `rest_graph`'s graphs and those `step` returns, one body or several, "
              "by value for any other; the forces' "
              "shape and finiteness) and wrapping the result in a graph. All three variants return the same frame: "
              + ", ".join(f"{row_label(r['model'], r['copies'])} {'yes' if r['same_frame'] else 'NO'}"
                          for r in result["rows"]) + "."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=200,
                    help="timed calls per variant and row (default %(default)s; --quick: 20)")
    ap.add_argument("--rollout-frames", type=int, default=20,
                    help="frames of the timed rollout call (default %(default)s; --quick: 10)")
    ap.add_argument("--rows", default=ROWS,
                    help="shipped models and bodies per graph, NAME[:COPIES],... (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 20 repeats, 10-frame rollouts")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="folder of model_step.{json,md} (default %(default)s)")
    args = ap.parse_args(argv)
    repeats = 20 if args.quick else args.repeats
    frames = 10 if args.quick else args.rollout_frames
    if repeats < 1 or frames < 1:
        raise SystemExit("--repeats and --rollout-frames must be positive")
    rows = parse_rows(args.rows)
    machine = describe()
    out_rows = []
    for name, copies in rows:
        print(f"timing {row_label(name, copies)} ...", flush=True)
        fns, info = variants(name, copies, frames)
        out_rows.append({**info, "timing": summarise(interleaved_ms(fns, repeats), frames)})
    result = {"machine": machine, "repeats": repeats, "rollout_frames": frames, "quick": args.quick,
              "checks_budget": CHECKS_BUDGET, "rows": out_rows,
              "load_average_1m_end": describe()["load_average_1m"]}
    write_results("model_step", result, report(result), Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
