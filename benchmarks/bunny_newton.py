"""The bunny's FEM step by a fixed count of Newton–CG iterations (`tignn_jax.newton`) against the shipped
rest-linearised step `bunny-linear`, on the held-out load positions of the bunny data: rollout errors and time.

The data (`tignn generate bunny --integrator implicit --density 1e-3 --load-radius 5 --rise-frames 10 --seed 0`,
`data/bunny.npz`; or its test rows alone, made on a GPU machine in 37 s and brought back under a transfer limit by
`scripts/bunny_heldout_subset.py`, as in session 38: `--data data/bunny_test.npz`) are the converged backward-Euler FEM at one step per frame, which the Newton–CG step
approximates by 1 or 2 Newton iterations of a few preconditioned CG iterations each (`newton.fem_stepper` on
`bunny-linear`'s mesh, density and damping). Errors: 20-step rollouts from each test case's first state with its
forces, relative L2 per snapshot (`tignn_jax.evaluate.relative_errors`, all nodes, clamped stress predicted), mean
over snapshots 1..20 and cases: the measure of the model cards. Time: median of one step from the first test
case's state at frame 10, every step compiled under both XLA:CPU configurations of `pareto.XLA_CONFIGS` and timed
interleaved (the faster reported, both recorded).
Writes benchmarks/results/bunny_newton.{json,md}.

    python benchmarks/bunny_newton.py [--data data/bunny.npz] [--split test] [--repeats 40]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402
from pareto import time_configs, xla_fields  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
VARIANTS = ((1, 3), (2, 3), (2, 5))   # (Newton iterations, CG iterations each)


def rollout(step, z0, forces):
    """[T+1, N, 12]: ``step`` (z, f) -> z from ``z0`` under ``forces`` [T, N, 3]."""
    zs = [jnp.asarray(z0)]
    for f in forces:
        zs.append(step(zs[-1], jnp.asarray(f)))
    return np.asarray(jnp.stack(zs))


def errors(step, data, rows) -> dict:
    """Mean errors of ``step``'s rollouts of the cases ``rows`` of ``data`` (`tignn_jax.data.Dataset`)."""
    from tignn_jax.evaluate import relative_errors

    e = np.stack([relative_errors(rollout(step, data.z[c, 0], data.f[c]), data.z[c], data.q0)[1:]
                  for c in rows])                                   # [cases, T, (q, v, σ, u)]
    mean = e.mean(axis=(0, 1))
    return {"u": float(mean[3]), "v": float(mean[1]), "sigma": float(mean[2]), "q": float(mean[0]),
            "finite": bool(np.isfinite(e).all()), "u_worst_case": float(e[..., 3].mean(axis=1).max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/bunny.npz")
    ap.add_argument("--split", default="test")
    ap.add_argument("--repeats", type=int, default=40, help="timed calls per step and configuration")
    args = ap.parse_args(argv)
    if not Path(args.data).exists():
        raise SystemExit(f"no data file {args.data}: generate it with the command in this script's docstring")
    from tignn_jax import api, newton
    from tignn_jax import data as D

    data = D.load(args.data)
    rows = D.split_rows(data, args.split)
    linear, _ = api.load_pretrained("bunny-linear")
    steps = {"bunny-linear (rest-linearised, 1 solve)": api.stepper(linear)}
    for n, k in VARIANTS:
        steps[f"FEM Newton-CG {n}×{k}"] = newton.fem_stepper(linear, iterations=k, newton=n)
    points = {}
    for name, step in steps.items():
        print(f"errors: {name}", flush=True)
        points[name] = errors(step, data, rows)
    args_t = (jnp.asarray(data.z[rows[0], 10]), jnp.asarray(data.f[rows[0], 10]))
    print("timing", flush=True)
    times = time_configs(steps, args_t, args.repeats)
    for name in points:
        points[name].update(ms=times[name]["p50_ms"], **xla_fields(times[name]))
    result = {"machine": describe(), "data": args.data, "split": args.split,
              "sims": data.sim_id[rows].tolist(), "points": points}
    write_results("bunny_newton", result, report(result), RESULTS)
    return 0


def report(result: dict) -> str:
    m = result["machine"]
    lines = ["# The bunny: the FEM's Newton–CG step against the rest-linearised step", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']} ({m['backend']}); load average "
             f"{m['load_average_1m']} at start. Data `{result['data']}`, {result['split']} sims "
             f"{', '.join(map(str, result['sims']))}: rollouts of 20 steps from each case's first state, errors "
             "relative to each snapshot, mean over snapshots 1..20 and cases (all nodes). Time: median of one step "
             "(ms), the faster of two XLA:CPU configurations (YNNPACK fusions on, the default, or off).", "",
             "| step | ms / step | XLA (both, ms) | u | v | σ | worst-case u | finite |", "|---|---|---|---|---|---|---|---|"]
    for name, p in sorted(result["points"].items(), key=lambda kv: kv[1]["ms"]):
        both = ", ".join(f"{c} {t:.2f}" for c, t in p["p50_by_xla"].items())
        lines.append(f"| {name} | {p['ms']:.2f} | {both} | {p['u']:.4f} | {p['v']:.4f} | {p['sigma']:.4f} | "
                     f"{p['u_worst_case']:.4f} | {'yes' if p['finite'] else 'NO'} |")
    return "\n".join(lines + [""])


if __name__ == "__main__":
    sys.exit(main())
