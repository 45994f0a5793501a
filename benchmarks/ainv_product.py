"""The product by A₀⁻¹ that dominates the shipped linear step, and what might shorten its tail: smaller storage,
and the threads the loop runs on.

The demo's `beam` and `bunny` step by one product with the dense inverse A₀⁻¹ (`framesolve.linear_step`): 20.6 MB
for the beam, 63.7 MB for the bunny, in float32. The bunny's simulation p99 misses 1.5 × its p50 in
`realtime.md`; the product is memory-bound, so this script asks whether fewer bytes or fewer threads help.

1. Numerics of smaller storage, per model: A₀⁻¹ symmetrised and scaled by its largest entry, rounded to float16,
   bfloat16 and int16 (scaled to ±32767): the largest entry error (relative to the largest entry), the extreme
   eigenvalues against float32's (a storage that kept them would keep the step stable: the product stays
   symmetric positive definite), and the largest difference of one step from the shipped step (relative to the
   step's largest increment).
2. Time of the product, per storage and formulation, interleaved (each variant in turn, ``--repeats`` calls):
   "hot" back to back, and "cold" after touching 256 MB between calls (what the loop does between steps:
   rendering, and the machine's other tenants, evict the operator from the caches).
3. With ``--loop-rounds N``: the bunny's whole demo loop (`scene.run`, 500 frames after 20) in child processes,
   alternating XLA's default threads, single-threaded XLA, and single-threaded XLA with the process pinned to
   one core (`os.sched_setaffinity`), N rounds each: simulation p50 / p99 and render p50.

Writes benchmarks/results/ainv_product.{json,md}.

    python benchmarks/ainv_product.py [--models beam,bunny] [--repeats 100] [--loop-rounds 3] [--report-only]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
_YNN_OFF = "--xla_cpu_experimental_ynn_fusion_type="
_SINGLE = f"{_YNN_OFF} --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
LOOP_MODES = {"XLA default threads": (_YNN_OFF, False), "single-threaded XLA": (_SINGLE, False),
              "single-threaded XLA, pinned to one core": (_SINGLE, True)}
STORAGES = ("float16", "bfloat16", "int16")


def stored(a: np.ndarray, storage: str):
    """``a`` / scale rounded to ``storage`` (a jax array) and the scale."""
    import jax.numpy as jnp

    scale = float(np.abs(a).max())
    if storage == "int16":
        return jnp.asarray(np.round(a / scale * 32767.0).astype(np.int16)), scale / 32767.0
    return jnp.asarray(a / scale, getattr(jnp, storage)), scale


def numerics(params: dict) -> tuple[dict, np.ndarray]:
    """Entry error, eigenvalue range and one step's difference of each storage of the model's A₀⁻¹."""
    import jax
    import jax.numpy as jnp

    from tignn_jax import framesolve as FS

    nt = np.asarray(params["mesh"]["node_type"])
    norm = FS.with_inverse(params["norm"], nt)
    full = np.asarray(norm["fs_ainv"], np.float64)
    free = np.repeat(nt == 0, 3)   # the step multiplies by the free rows only (clamped rows are the identity)
    a = full[np.ix_(free, free)]
    asym = float(np.abs(a - a.T).max() / np.abs(a).max())
    a = 0.5 * (a + a.T)
    w = np.linalg.eigvalsh(a)
    out = {"dofs": len(a), "mb_float32": 4 * a.size / 2 ** 20, "asymmetry": asym,
           "eig_float32": [float(w[0]), float(w[-1])], "storages": {}}
    node_type, q0 = jnp.asarray(nt, jnp.int32), jnp.asarray(params["mesh"]["q0"], jnp.float32)
    rng = np.random.default_rng(0)
    n = len(nt)
    z = jnp.asarray(np.concatenate([params["mesh"]["q0"] + 0.01 * rng.normal(size=(n, 3)),
                                    0.01 * rng.normal(size=(n, 9))], axis=1), jnp.float32)
    f = jnp.asarray(0.01 * rng.normal(size=(n, 3)), jnp.float32)
    base = {k: jnp.asarray(v) for k, v in norm.items()}
    ref = np.asarray(jax.jit(lambda z, f: FS.linear_step(base, z, f, node_type, q0))(z, f))
    for storage in STORAGES:
        s, scale = stored(a, storage)
        r = np.asarray(s.astype(jnp.float32), np.float64) * scale
        wr = np.linalg.eigvalsh(r)
        rounded = full.copy()
        rounded[np.ix_(free, free)] = r
        step = np.asarray(FS.linear_step({**base, "fs_ainv": jnp.asarray(rounded, jnp.float32)}, z, f, node_type, q0))
        out["storages"][storage] = {
            "mb": s.dtype.itemsize * a.size / 2 ** 20,
            "entry_error": float(np.abs(r - a).max() / np.abs(a).max()),
            "eig": [float(wr[0]), float(wr[-1])],
            "eig_change": float(max(abs(wr[0] / w[0] - 1), abs(wr[-1] / w[-1] - 1))),
            "positive_definite": bool(wr[0] > 0),
            "step_difference": float(np.abs(step - ref).max() / np.abs(ref).max())}
    return out, a.astype(np.float32)


def product_times(a: np.ndarray, repeats: int) -> dict:
    """Hot and cold medians and p99 of the product by ``a`` in each storage and formulation."""
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=len(a)).astype(np.float32))
    a32 = jnp.asarray(a)
    variants = {"float32, dot (shipped)": (jax.jit(lambda m, x: m @ x), a32)}
    for storage in STORAGES:
        s, scale = stored(np.asarray(a, np.float64), storage)
        variants[f"{storage}, converted then dot"] = (
            jax.jit(lambda m, x, c=scale: c * (m.astype(jnp.float32) @ x)), s)
        variants[f"{storage}, multiply and reduce"] = (
            jax.jit(lambda m, x, c=scale: c * jnp.sum(m.astype(jnp.float32) * x[:, None], axis=0)), s)
    for storage in ("float16", "bfloat16"):
        s, scale = stored(np.asarray(a, np.float64), storage)
        variants[f"{storage}, dot in {storage}, float32 result"] = (
            jax.jit(lambda m, x, c=scale, d=getattr(jnp, storage): c * jax.lax.dot(
                m, x.astype(d), preferred_element_type=jnp.float32)), s)
    ref = np.asarray(a32 @ x)
    # each variant's error, from its first call (which also compiles it before the timing)
    out = {k: {"error": float(np.abs(np.asarray(fn(m, x)) - ref).max() / np.abs(ref).max())}
           for k, (fn, m) in variants.items()}
    big = np.ones(256 * 2 ** 18, np.float32)
    for cold in (False, True):
        ms = {k: [] for k in variants}
        for _ in range(repeats):   # the variants in turn; the touch is outside the timed call
            for k, (fn, m) in variants.items():
                if cold:
                    big += 1.0   # 256 MB between calls: the operator leaves the caches
                t0 = time.perf_counter()
                jax.block_until_ready(fn(m, x))
                ms[k].append(1e3 * (time.perf_counter() - t0))
        for k, t in ms.items():
            out[k]["cold" if cold else "hot"] = {"p50_ms": float(np.median(t)), "p99_ms": float(np.percentile(t, 99))}
    return out


def loop_child(mode: str) -> None:
    flags, pin = LOOP_MODES[mode]
    if pin:   # before JAX creates its threads: they all inherit the one core
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    os.environ["XLA_FLAGS"] = flags
    from realtime import run_scene   # after the flags and the affinity: it imports JAX

    s = run_scene("bunny", frames=500, warmup=20)   # every frame steps, as in realtime.md
    sim = s["simulation_learned"]
    print(json.dumps({"simulation_p50_ms": sim["p50_ms"], "simulation_p99_ms": sim["p99_ms"],
                      "render_p50_ms": s["render"]["p50_ms"], "frame_p50_ms": s["frame"]["p50_ms"]}))


def loop_modes(rounds: int) -> dict:
    out = {m: [] for m in LOOP_MODES}
    for _ in range(rounds):
        for mode in LOOP_MODES:
            env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
            res = subprocess.run([sys.executable, __file__, "--loop-child", mode], capture_output=True, text=True,
                                 env=env, check=True)
            out[mode].append(json.loads(res.stdout.strip().splitlines()[-1]))
    return out


def format_md(result: dict) -> str:
    m = result["machine"]
    lines = ["# The product by A₀⁻¹: smaller storage, and the loop's threads", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']}; load average {m['load_average_1m']} at start, "
             f"{result['load_average_end']} at end. Written by `benchmarks/ainv_product.py`.", "",
             "## Smaller storage: numerics", "",
             "A₀⁻¹ on the free DOFs (the step multiplies the clamped rows by zero), symmetrised, scaled by its largest entry and rounded. Eigenvalues: the smallest and largest; "
             "step difference: one `linear_step` from a perturbed rest state with the rounded operator, relative "
             "to the step's largest increment.", "",
             "| model | free DOFs | storage | MB | largest entry error | eigenvalues (float32: min, max) | largest relative eigenvalue change | step difference |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in result["numerics"].items():
        e = r["eig_float32"]
        lines.append(f"| {name} | {r['dofs']} | float32 | {r['mb_float32']:.1f} | 0 | {e[0]:.4g}, {e[1]:.4g} | 0 | 0 |")
        for s, x in r["storages"].items():
            lines.append(f"| {name} | {r['dofs']} | {s} | {x['mb']:.1f} | {x['entry_error']:.1e} | "
                         f"{x['eig'][0]:.4g}, {x['eig'][1]:.4g} | {x['eig_change']:.1e} | {x['step_difference']:.1e} |")
    lines += ["", "## Smaller storage: time of the product (ms)", "",
              f"Interleaved calls, {result['repeats']} per variant; hot: the variants in turn, nothing between "
              "(for the bunny the other variants' 29–59 MB operators and their converted copies pass through the "
              "caches between two calls of one variant, so its hot column is not cache-resident either); cold: "
              "256 MB touched between calls. In brackets: × the shipped float32 product's p50 in the same column.", "",
              "| model | variant | hot p50 / p99 | cold p50 / p99 | largest error vs float32 |", "|---|---|---|---|---|"]
    for name, r in result["times"].items():
        h0, c0 = (r["float32, dot (shipped)"][k]["p50_ms"] for k in ("hot", "cold"))
        for k, x in r.items():
            lines.append(f"| {name} | {k} | {x['hot']['p50_ms']:.2f} / {x['hot']['p99_ms']:.2f} "
                         f"({x['hot']['p50_ms'] / h0:.1f}×) | {x['cold']['p50_ms']:.2f} / {x['cold']['p99_ms']:.2f} "
                         f"({x['cold']['p50_ms'] / c0:.1f}×) | {x['error']:.1e} |")
    if result.get("loop"):
        lines += ["", "## The bunny's demo loop on fewer threads", "",
                  "`scene.run` of the bunny scene, 500 frames after 20, each in its own child process (XLA reads "
                  "its flags once), the modes alternating; simulation p50 / p99 (ratio) and render p50, ms, per round.",
                  "", "| mode | simulation p50 / p99 (p99 / p50), per round | render p50 | median p99 |", "|---|---|---|---|"]
        for mode, rs in result["loop"].items():
            cells = "; ".join(f"{r['simulation_p50_ms']:.2f} / {r['simulation_p99_ms']:.2f} "
                              f"({r['simulation_p99_ms'] / r['simulation_p50_ms']:.2f})" for r in rs)
            lines.append(f"| {mode} | {cells} | {np.median([r['render_p50_ms'] for r in rs]):.2f} | "
                         f"{np.median([r['simulation_p99_ms'] for r in rs]):.2f} |")
    lines += ["", "## Findings", ""] + [f"- {f}" for f in findings(result)]
    return "\n".join(lines) + "\n"


def findings(result: dict) -> list:
    out = []
    for name, r in result["numerics"].items():
        for storage, x in r["storages"].items():
            out.append(f"{name}, {storage}: " + (
                f"A₀⁻¹ stays positive definite (extreme eigenvalues within {100 * x['eig_change']:.2g} % of "
                f"float32's); one step moves by {x['step_difference']:.1e} of its largest increment."
                if x["positive_definite"] else
                f"A₀⁻¹ is no longer positive definite (smallest eigenvalue {x['eig'][0]:.3g}, float32's "
                f"{r['eig_float32'][0]:.3g}): its condition number {r['eig_float32'][1] / r['eig_float32'][0]:.2g} "
                "is beyond this storage's precision, so backward Euler's dissipation is no longer guaranteed."))
    for name, r in result["times"].items():
        c0 = r["float32, dot (shipped)"]["cold"]["p50_ms"]
        best = min((k for k in r if not k.startswith("float32")), key=lambda k: r[k]["cold"]["p50_ms"])
        out.append(f"{name}: the fastest smaller storage ({best}) takes {r[best]['cold']['p50_ms'] / c0:.1f}× the "
                   f"float32 product cold: XLA:CPU converts and reduces element by element, so halving the bytes "
                   "does not pay; the shipped product stays float32.")
    if result.get("loop"):
        med = {m: (np.median([x["simulation_p50_ms"] for x in rs]), np.median([x["simulation_p99_ms"] for x in rs]))
               for m, rs in result["loop"].items()}
        d = med["XLA default threads"]
        for m, (p50, p99) in med.items():
            if m != "XLA default threads":
                out.append(f"{m}: median simulation p50 {p50:.2f} ms and p99 {p99:.2f} ms against the default's "
                           f"{d[0]:.2f} and {d[1]:.2f}; p99 / p50 {p99 / p50:.2f} against {d[1] / d[0]:.2f}. "
                           + ("A lower ratio from a higher p50 and a p99 no better is not a shorter tail."
                              if p99 >= d[1] and p50 > d[0] else ""))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="beam,bunny", help="shipped models (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=100, help="calls per variant and cache state")
    ap.add_argument("--loop-rounds", type=int, default=0, help="rounds of the bunny loop per thread mode (0: none)")
    ap.add_argument("--loop-child", choices=tuple(LOOP_MODES), help=argparse.SUPPRESS)
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite ainv_product.md from benchmarks/results/ainv_product.json (no timing)")
    args = ap.parse_args(argv)
    if args.loop_child:
        loop_child(args.loop_child)
        return 0
    if args.report_only:
        md = format_md(json.loads((RESULTS / "ainv_product.json").read_text()))
        (RESULTS / "ainv_product.md").write_text(md)
        print(md)
        return 0
    if args.repeats < 1:
        ap.error(f"--repeats must be at least 1, got {args.repeats}")
    os.environ.setdefault("XLA_FLAGS", _YNN_OFF)
    from tignn_jax import api

    result = {"machine": describe(), "repeats": args.repeats, "numerics": {}, "times": {}}
    for name in [m for m in args.models.split(",") if m]:
        params, _ = api.load_pretrained(name)
        if not api.network_is_zero(params) or "fs_k" not in params["norm"]:
            ap.error(f"--models: {name!r} is not a model stepped by a product with A₀⁻¹")
        result["numerics"][name], a = numerics(params)
        result["times"][name] = product_times(a, args.repeats)
    if args.loop_rounds:
        result["loop"] = loop_modes(args.loop_rounds)
    result["load_average_end"] = round(os.getloadavg()[0], 2)
    write_results("ainv_product", result, format_md(result), RESULTS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
