r"""Run time against error on the held-out beam cases: the shipped models and the FEM they replace.

On the six test cases of the Abaqus beam data (sims 9, 10, 12, 13, 38, 44; ``tignn_jax.data.split_rows(data,
"test")``) this measures, on this machine,
  * the shipped default ``beam-corot`` (the corotational GENERIC model, the FEM's element operators turned with
    each element), ``beam`` (the learned linear GENERIC model trained on the data's train split),
    ``beam-linear`` (the FEM's rest linearisation as a linear model) and ``beam-tignn`` (the paper's network,
    reproduced on the train split): one compiled step of each (its class's
    ``step_state``, what `tignn_jax.stepper` runs), rolled out from each case's first state on its forces
    (`tignn_jax.evaluation.rollout_cases`);
  * the FEM at decreasing cost: its own stable sub-step on the 20×5×5 reference mesh, mass scaling (density ×4,
    ×16, ×64: fewer sub-steps per frame, dynamics distorted) and coarser hex meshes of the 40×10×10 beam (loads
    moved onto the coarse nodes with trilinear weights, which conserves total force; results interpolated back to
    the reference nodes with the same weights), from rest; its cost is the wall time of one 0.05 s frame of one
    case;
  * the FEM's own backward-Euler frame step by a fixed count of Newton iterations of a few conjugate-gradient
    iterations each (`tignn_jax.fem_stepper(beam-linear, iterations, newton)`, `tignn_jax.newton`), from rest;
  * the published TIGNN's test errors (`tignn_jax.evaluation.PUBLISHED_TEST`; its authors' weights, whose run time
    is not measured here) as a reference line.
Errors: per snapshot relative L2 over all 756 nodes, mean over snapshots 1..20 and the cases, of u = q − q0, v and
σ (`tignn_jax.evaluation.relative_errors`); the FEM's v is numpy.gradient of its q over the frames, the convention
of the reference data. Step times: median after compilation; each model step and Newton step is compiled under
two XLA:CPU configurations (YNNPACK's fusions on, XLA's default, and off, the option of the real-time loop,
`tignn_jax.mr.REAL_TIME_XLA_FLAG`), timed interleaved, and the faster counts. The Pareto front is the set of
points not dominated in (time, u error); a second front asks for domination in (time, u, v, σ) at once.
Writes pareto.{json,md,png} to ``--out`` (default benchmarks/results); the FEM's errors, which are deterministic,
are cached in runs/pareto/errors.json (by a full run; delete it after changing the FEM).

    python benchmarks/pareto.py [--repeats 200] [--newton 1x3,2x3,3x5]
    python benchmarks/pareto.py --quick --out /tmp/pareto      # smoke run: one case, cheap variants
    python benchmarks/pareto.py --report-only                   # rewrite .md and .png from the .json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, machine_line  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "runs" / "pareto"
SHIPPED = "beam-corot"        # the default model (`tignn_jax.api.DEFAULT_MODEL`): corotational GENERIC
LEARNED = "beam"              # the learned linear GENERIC model
LINEAR = "beam-linear"        # the FEM's rest linearisation as a linear model
REPRODUCTION = "beam-tignn"   # the paper's network, reproduced (not a model for interaction)
BUDGET_MS = (9.0, 11.0)       # the real-time step budget (one beam 9 ms; bunny 11 ms)
# FEM variants: (name, elements along x, y, z, density factor)
FEM_VARIANTS = (("FEM 20×5×5 (reference mesh)", (20, 5, 5), 1.0),
                ("FEM 20×5×5, mass ×4", (20, 5, 5), 4.0),
                ("FEM 20×5×5, mass ×16", (20, 5, 5), 16.0),
                ("FEM 20×5×5, mass ×64", (20, 5, 5), 64.0),
                ("FEM 14×4×4", (14, 4, 4), 1.0),
                ("FEM 10×3×3", (10, 3, 3), 1.0),
                ("FEM 14×4×4, mass ×16", (14, 4, 4), 16.0),
                ("FEM 10×3×3, mass ×16", (10, 3, 3), 16.0),
                ("FEM 10×3×3, mass ×64", (10, 3, 3), 64.0),
                ("FEM 5×2×2", (5, 2, 2), 1.0),
                ("FEM 5×2×2, mass ×16", (5, 2, 2), 16.0),
                ("FEM 5×2×2, mass ×64", (5, 2, 2), 64.0))
QUICK_FEM = ("FEM 5×2×2, mass ×64",)
NEWTON = "1x3,2x3,3x5"        # (Newton iterations)x(CG iterations each) of the FEM's backward-Euler step
BEAM_SIZE = (40.0, 10.0, 10.0)
# XLA:CPU configurations each model or Newton step is compiled and timed under (``compiler_options``), its time
# the faster of them: YNNPACK's fusions on (XLA's default) or off (the real-time loop's option)
XLA_CONFIGS = {"default": {}, "ynn-off": {"xla_cpu_experimental_ynn_fusion_type": ""}}


# ------------------------------------------------------------------------------------------------------------
# Pareto front and the coarse-mesh transfer (pure functions, tested in tests/test_pareto.py)


def pareto_front(cost, error) -> np.ndarray:
    """Indices of the points not dominated in (cost, error), all minimised, ordered by cost; ``error`` [n] or
    [n, k] (k error measures, e.g. u, v, σ).

    A point is dominated when another is no worse in every measure and better in one. Points with a non-finite
    error (a diverged rollout) are never on the front."""
    cost, error = np.asarray(cost, float), np.asarray(error, float)
    if cost.ndim != 1 or error.ndim not in (1, 2) or error.shape[0] != cost.shape[0]:
        raise ValueError(f"cost must be 1-D and error 1-D or 2-D of one length, got {cost.shape} and {error.shape}")
    obj = np.column_stack([cost, error])
    ok = np.all(np.isfinite(obj), axis=1)
    front = []
    for i in np.flatnonzero(ok):
        no_worse = np.all(obj[ok] <= obj[i], axis=1)
        better = np.any(obj[ok] < obj[i], axis=1)
        if not np.any(no_worse & better):
            front.append(i)
    return np.array(sorted(front, key=lambda i: tuple(obj[i])), dtype=int)


def trilinear_weights(points, divisions, size=BEAM_SIZE, origin=(0.0, 0.0, 0.0)):
    """Interpolation matrix W [P, Nc] from the nodes of ``fem.box_hex_mesh(size, divisions, origin)`` to
    ``points`` [P, 3] inside the box: W @ values_coarse = trilinear interpolation at the points.

    Each row holds the 8 shape functions of the coarse element containing the point (they sum to 1 and
    reproduce any linear field exactly). ``W.T @ f`` moves point forces f [P, 3] onto the coarse nodes with
    the same total force and moment (the consistent load of a point force)."""
    points = np.asarray(points, float)
    div = np.asarray(divisions, int)
    size, origin = np.asarray(size, float), np.asarray(origin, float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [P, 3], got {points.shape}")
    s = (points - origin) / size * div                      # position in element units
    if np.any(s < -1e-9) or np.any(s > div + 1e-9):
        raise ValueError("points must lie inside the box")
    cell = np.clip(np.floor(s).astype(int), 0, div - 1)
    xi = np.clip(s - cell, 0.0, 1.0)
    nx, ny = div[0] + 1, div[1] + 1
    node = lambda i, j, k: (k * ny + j) * nx + i              # box_hex_mesh numbering (x fastest)
    i, j, k = cell.T
    w = np.zeros((len(points), int(np.prod(div + 1))))
    rows = np.arange(len(points))
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                shape = ((xi[:, 0] if a else 1 - xi[:, 0]) * (xi[:, 1] if b else 1 - xi[:, 1])
                         * (xi[:, 2] if c else 1 - xi[:, 2]))
                np.add.at(w, (rows, node(i + a, j + b, k + c)), shape)
    return w


def parse_newton(text: str) -> list:
    """``"1x3,2x3"`` → [(1, 3), (2, 3)]: (Newton iterations, CG iterations each)."""
    out = []
    for item in [s.strip() for s in text.split(",") if s.strip()]:
        try:
            n, cg = (int(x) for x in item.split("x"))
        except ValueError:
            raise ValueError(f"a Newton setting is NEWTONxCG, e.g. 2x3; got {item!r}") from None
        if n < 1 or cg < 1:
            raise ValueError(f"Newton and CG iterations must be positive, got {item!r}")
        out.append((n, cg))
    return out


# ------------------------------------------------------------------------------------------------------------
# timing


def compiled_configs(fn, args) -> dict:
    """{config: the jitted ``fn`` compiled for ``args`` under each of ``XLA_CONFIGS``}."""
    lowered = fn.lower(*args)
    return {c: lowered.compile(compiler_options=opts) if opts else lowered.compile()
            for c, opts in XLA_CONFIGS.items()}


def best_config(times: dict) -> dict:
    """{name: timing} from ``time_round_robin``'s {"name|config": timing}: each name's faster configuration, with
    its name (``xla``) and every configuration's median (``p50_by_xla``)."""
    out = {}
    for key, t in times.items():
        name, config = key.rsplit("|", 1)
        entry = out.setdefault(name, {"p50_by_xla": {}})
        entry["p50_by_xla"][config] = t["p50_ms"]
        if "p50_ms" not in entry or t["p50_ms"] < entry["p50_ms"]:
            entry.update(t, xla=config)
    return out


def time_configs(fns: dict, repeats: int, block: int = 5, configs: bool = True) -> dict:
    """``time_round_robin`` of every jitted function {name: (fn, args)}, compiled under each of ``XLA_CONFIGS``
    (``configs``; else as jitted, under the default only), all interleaved, reduced by ``best_config``."""
    if configs:
        calls = {f"{k}|{c}": (fc, a) for k, (fn, a) in fns.items() for c, fc in compiled_configs(fn, a).items()}
    else:
        calls = {f"{k}|default": (fn, a) for k, (fn, a) in fns.items()}
    return best_config(time_round_robin(calls, repeats, block))


def time_round_robin(calls: dict, repeats: int, block: int = 5) -> dict:
    """Median and p90 wall time [ms] of ``repeats`` calls per function {name: (fn, args)} after a compiling
    call. Functions take turns in blocks of ``block`` timed calls, each block after one untimed call, so that load
    changes on a shared machine hit every variant alike and no variant is timed on caches just evicted by another."""
    for fn, a in calls.values():
        jax.block_until_ready(fn(*a))
    times = {k: [] for k in calls}
    for _ in range(max(1, repeats // block)):
        for k, (fn, a) in calls.items():
            jax.block_until_ready(fn(*a))
            for _ in range(block):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*a))
                times[k].append(1e3 * (time.perf_counter() - t0))
    return {k: {"p50_ms": float(np.median(v)), "p90_ms": float(np.percentile(v, 90)), "repeats": len(v)}
            for k, v in times.items()}


def _median_frame_ms(fn, min_repeats: int = 5, min_seconds: float = 3.0, max_repeats: int = 200) -> dict:
    """Wall time [ms] of ``fn()`` after a compiling call: at least ``min_repeats`` calls and ``min_seconds``,
    at most ``max_repeats``; median, 90th percentile and the load average."""
    jax.block_until_ready(fn())
    times, start = [], time.perf_counter()
    while len(times) < max_repeats and (len(times) < min_repeats or time.perf_counter() - start < min_seconds):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(1e3 * (time.perf_counter() - t0))
    return {"p50_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90)), "repeats": len(times),
            "load_average_1m": round(os.getloadavg()[0], 2)}


# ------------------------------------------------------------------------------------------------------------
# errors


def load_data(path=None):
    from tignn_jax import data as D

    path = Path(path) if path else D.reference_path()
    if not path.exists():
        raise SystemExit(f"reference data not found at {path}")
    return D.load(path)


def summary(pred, data, rows) -> dict:
    """Mean errors of predicted states [cases, T+1, N, 12] against the data's cases ``rows`` over snapshots
    1..T and cases, all nodes (NaN when a rollout diverged); σ also over the free nodes; the worst case's u."""
    from tignn_jax import evaluation as EV

    e = EV.relative_errors(pred, data.z[rows], data.q0)[:, 1:]
    e_free = EV.relative_errors(pred, data.z[rows], data.q0, data.node_type == 0)[:, 1:]
    out = {k: float(np.mean(e[..., i])) for i, k in enumerate(EV.VARIABLES)}
    out["sigma_free"] = float(np.mean(e_free[..., 2]))
    out["u_worst_case"] = float(np.max(np.mean(e[..., 3], axis=1)))
    return out


def model_errors(params, data, rows) -> dict:
    """A model's errors over the cases ``rows``, rolled out from each case's first state on its forces."""
    from tignn_jax import evaluation as EV

    return summary(EV.rollout_cases(params, data, rows), data, rows)


def model_step(params):
    """(jitted fn(arrays, z, f) -> z_next, arrays): one body's step of the model's class, the program
    `tignn_jax.stepper` runs, with the arrays as an argument (compiled under each XLA configuration)."""
    model = params["model"]
    return jax.jit(lambda arrays, z, f: model.step_state(arrays, z, f.astype(z.dtype))), params["arrays"]


def fem_problem(divisions, density_factor: float, n_frames: int = 20):
    """(scene, problem, W) of the beam on a hex mesh of ``divisions`` elements with density × factor; W [756, Nc]
    maps coarse-node values to the reference nodes (None on the reference mesh itself)."""
    from fem import box_hex_mesh
    from fem import meshes as fm
    from fem import scenes as fs

    base = fs.beam_scene()
    mat = base.material._replace(density=base.material.density * density_factor)
    if tuple(divisions) == fm.BEAM_SHAPE:
        scene, w = base._replace(material=mat, n_frames=n_frames), None
    else:
        points, cells = box_hex_mesh(BEAM_SIZE, divisions)
        scene = base._replace(name=f"beam {divisions}", points=points, cells=cells, edges=fm.mesh_edges(cells),
                              node_type=fm.beam_node_type(points), material=mat, n_frames=n_frames)
        w = trilinear_weights(base.points, divisions)
    return scene, fs.setup_scene(scene), w


def fem_errors(divisions, density_factor, data, rows) -> dict:
    """Run the FEM variant on the cases ``rows`` (loads moved to its nodes) and compare with the reference."""
    from fem import Loads, check, simulate_batch

    scene, problem, w = fem_problem(divisions, density_factor)
    forces = _coarse_forces(data, rows, w)
    t0 = time.perf_counter()
    res = simulate_batch(problem, scene.material, Loads(nodal=jnp.asarray(forces, jnp.float32)))
    jax.block_until_ready(res.q)
    wall = time.perf_counter() - t0
    check(res, "warn")
    pred = _as_prediction(res.q, res.sigma, w, data.dt)
    return dict(summary(pred, data, rows), n_sub=problem.config.n_sub, nodes=len(scene.points),
                elements=len(scene.cells), inverted=np.asarray(res.inverted).tolist(), batch_wall_s=wall)


def fem_frame_time(divisions, density_factor, sim_id: int, min_repeats: int = 5, min_seconds: float = 3.0,
                   max_repeats: int = 200) -> dict:
    """Median wall time [ms] of one 0.05 s frame (all its sub-steps, the stress recovery) for one case,
    jit-compiled, after a compiling call."""
    from fem import Loads, simulate
    from fem import scenes as fs

    scene, problem, w = fem_problem(divisions, density_factor, n_frames=1)
    f = fs.beam_reference_forces(fs.beam_scene(), [sim_id])[0, :1]
    if w is not None:
        f = np.einsum("pn,tpd->tnd", w, f)
    loads = Loads(nodal=jnp.asarray(f, jnp.float32))
    run = lambda: simulate(problem, scene.material, loads, on_inversion="ignore").q
    return {**_median_frame_ms(run, min_repeats, min_seconds, max_repeats), "n_sub": problem.config.n_sub}


def newton_errors(step, data, rows) -> dict:
    """The FEM's backward-Euler step ``step`` (z, f) -> z rolled out from rest over the cases ``rows`` (one
    compiled step called frame by frame) against the reference."""
    from tignn_jax import graph as G

    forces = _coarse_forces(data, rows, None)
    z0 = jnp.asarray(G.rest_state(data.q0))
    preds = []
    for case in forces:
        z, out = z0, [np.asarray(z0)]
        for f in case:
            z = step(z, jnp.asarray(f, jnp.float32))
            out.append(np.asarray(z))
        preds.append(np.stack(out))
    preds = np.stack(preds)
    return dict(summary(_as_prediction(preds[..., :3], preds[..., 6:], None, data.dt), data, rows),
                nodes=int(data.q0.shape[0]), elements=500)


def _coarse_forces(data, rows, w):
    from fem import scenes as fs

    forces = fs.beam_reference_forces(fs.beam_scene(), data.sim_id[rows])          # [C, T, 756, 3]
    if not np.allclose(fs.beam_scene().points, data.q0, atol=1e-5):
        raise SystemExit("the FEM reference mesh and the data's q0 differ")
    return forces if w is None else np.einsum("pn,ctpd->ctnd", w, forces)


def _as_prediction(q, sig, w, dt):
    q, sig = np.asarray(q, np.float64), np.asarray(sig, np.float64)
    if w is not None:
        q, sig = np.einsum("pn,ctnd->ctpd", w, q), np.einsum("pn,ctnd->ctpd", w, sig)
    v = np.gradient(q, float(dt), axis=1, edge_order=2)   # the reference data's velocity convention
    return np.concatenate([q, v, sig], -1)


# ------------------------------------------------------------------------------------------------------------
# driver


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help=f"smoke run: one test case, the FEM variant {QUICK_FEM[0]!r} only, no Newton step, 20 "
                         "timed calls, the default XLA configuration only")
    ap.add_argument("--repeats", type=int, default=200, help="timed calls per model and Newton step "
                                                             "(default %(default)s)")
    ap.add_argument("--newton", default=None, help="Newton settings NEWTONxCG,... of the FEM's backward-Euler step "
                                                   f"(default {NEWTON}; --quick: none)")
    ap.add_argument("--data", default=None, help="the Abaqus beam data (default ../shared/data/abaqus_beam.npz)")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="folder of pareto.{json,md,png} (default %(default)s)")
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite pareto.md and pareto.png from the pareto.json in --out (no runs)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    if args.report_only:
        if not (out / "pareto.json").exists():
            ap.error(f"--report-only: no stored result at {out / 'pareto.json'} (run without it first)")
        result = json.loads((out / "pareto.json").read_text())
        write(result, out)
        return 0
    try:
        newton = parse_newton(args.newton if args.newton is not None else ("" if args.quick else NEWTON))
    except ValueError as err:
        ap.error(str(err))
    import tignn_jax
    from tignn_jax import data as D
    from tignn_jax import graph as G

    data = load_data(args.data)
    rows = D.split_rows(data, "test")[:1 if args.quick else None]
    variants = [v for v in FEM_VARIANTS if v[0] in QUICK_FEM] if args.quick else list(FEM_VARIANTS)
    repeats = 20 if args.quick else args.repeats
    min_seconds = 0.5 if args.quick else 3.0
    cache_path = None if args.quick else RUNS / "errors.json"      # a quick run neither reads nor writes it
    cache = json.loads(cache_path.read_text()) if cache_path is not None and cache_path.exists() else {}
    test_sims = data.sim_id[rows].tolist()
    if cache.get("test_sims") != test_sims:
        cache = {"test_sims": test_sims}
    load_start = os.getloadavg()
    points = []

    # the shipped models
    calls, models = {}, {}
    z, f = jnp.asarray(data.z[rows[0], 10]), jnp.asarray(data.f[rows[0], 10])
    for name, kind in ((SHIPPED, "shipped"), (LEARNED, "shipped-learned"), (LINEAR, "shipped-linear"),
                       (REPRODUCTION, "shipped-reproduction")):
        print(f"errors: {name}", flush=True)
        params, _ = tignn_jax.load_pretrained(name)
        models[name] = params
        errors = model_errors(params, data, rows)
        fn, arrays = model_step(params)
        calls[name] = (fn, (arrays, z, f))
        points.append({"name": name, "kind": kind, **errors, "info": params["info"].get("kind", "")})
    # the FEM's backward-Euler step by fixed Newton-CG iterations (on beam-linear's scene)
    for n, cg in newton:
        name = f"FEM Newton-CG {n}×{cg}"
        print(f"errors: {name}", flush=True)
        step = tignn_jax.fem_stepper(models[LINEAR], iterations=cg, newton=n)
        points.append({"name": name, "kind": "fem-newton", "newton": [n, cg], **newton_errors(step, data, rows)})
        case = jnp.asarray(_coarse_forces(data, rows[:1], None)[0], jnp.float32)
        z_mid = jnp.asarray(G.rest_state(data.q0))
        for k in range(9):   # timed from the case's state after 9 frames, under its 10th load
            z_mid = step(z_mid, case[k])
        calls[name] = (step, (z_mid, case[9]))
    print("timing the model and Newton steps", flush=True)
    step_times = time_configs(calls, repeats, configs=not args.quick)
    for p in points:
        p.update(ms=step_times[p["name"]]["p50_ms"], **{k: step_times[p["name"]][k]
                                                       for k in ("p90_ms", "xla", "p50_by_xla")})
    load_steps = os.getloadavg()
    # the explicit FEM at decreasing cost (errors cached: deterministic)
    for name, div, factor in variants:
        if name not in cache:
            print(f"errors: {name}", flush=True)
            cache[name] = fem_errors(div, factor, data, rows)
            if cache_path is not None:
                cache_path.parent.mkdir(parents=True, exist_ok=True)
                cache_path.write_text(json.dumps(cache, indent=1))
        print(f"timing {name}", flush=True)
        t = fem_frame_time(div, factor, int(data.sim_id[rows[0]]), min_seconds=min_seconds)
        points.append({"name": name, "kind": "fem", "density_factor": factor, **cache[name], "ms": t["p50_ms"],
                       "p90_ms": t["p90_ms"], "load_average_1m": t["load_average_1m"]})
    load_end = os.getloadavg()
    front = pareto_front([p["ms"] for p in points], [p["u"] for p in points])
    front_all = pareto_front([p["ms"] for p in points], [[p["u"], p["v"], p["sigma"]] for p in points])
    for i, p in enumerate(points):
        p["on_front"] = bool(i in set(front.tolist()))
        p["on_front_uvs"] = bool(i in set(front_all.tolist()))
    from tignn_jax.evaluation import PUBLISHED_TEST

    result = {"machine": describe(), "load_average_start": [round(x, 2) for x in load_start],
              "load_average_after_steps": [round(x, 2) for x in load_steps],
              "load_average_end": [round(x, 2) for x in load_end], "test_sims": test_sims,
              "budget_ms": BUDGET_MS, "points": points, "front": [points[i]["name"] for i in front],
              "front_uvs": [points[i]["name"] for i in front_all], "published_test": PUBLISHED_TEST,
              "repeats": repeats, "quick": args.quick, "xla_configs": list(XLA_CONFIGS) if not args.quick
              else ["default"], "xla_flags": os.environ.get("XLA_FLAGS", "")}
    write(result, out)
    return 0


def write(result: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "pareto.json").write_text(json.dumps(result, indent=1))
    plot(out / "pareto.png", result)
    md = report(result)
    (out / "pareto.md").write_text(md)
    print(md)


STYLE = {"shipped": ("*", "C3", "shipped default `beam-corot`: corotational GENERIC"),
         "shipped-learned": ("D", "C0", "shipped `beam`: learned linear GENERIC"),
         "shipped-linear": ("P", "C2", "shipped `beam-linear`: the FEM's rest linearisation"),
         "shipped-reproduction": ("X", "C1", "shipped `beam-tignn`: the paper's network, reproduced"),
         "fem": ("s", "C7", "FEM explicit (per 0.05 s frame)"),
         "fem-newton": ("v", "C4", "FEM backward Euler by Newton–CG (`fem_stepper`)")}


def plot(path, result) -> None:
    """Two panels against step time, u and σ errors, each with its (time, error) front, the real-time budget and
    the published TIGNN's test error; labels are nudged apart (`spread_labels`) where points crowd."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points, published = result["points"], result["published_test"]
    fig, axes = plt.subplots(1, 2, figsize=(15, 6.2))
    shown = [p for p in points if np.isfinite(p["u"]) and np.isfinite(p["sigma"])]
    for ax, key, name in ((axes[0], "u", "u = q − q0"), (axes[1], "sigma", "σ")):
        ax.axvspan(*BUDGET_MS, color="C2", alpha=0.15, label=f"real-time budget {BUDGET_MS[0]:g}–{BUDGET_MS[1]:g} ms")
        ax.axhline(published[key], color="C1", ls="-.", lw=1.2,
                   label="published TIGNN, test error (run time not measured)")
        seen = set()
        for p in shown:
            m, c, label = STYLE[p["kind"]]
            ax.scatter(p["ms"], p[key], marker=m, color=c, s=160 if p["kind"].startswith("shipped") else 50,
                       zorder=3, edgecolor="k", linewidth=0.5, label=None if p["kind"] in seen else label)
            seen.add(p["kind"])
        idx = pareto_front([p["ms"] for p in points], [p[key] for p in points])
        idx = sorted(idx, key=lambda i: points[i]["ms"])
        fx, fy = [points[i]["ms"] for i in idx], [points[i][key] for i in idx]
        if fx:
            ax.step(fx, fy, where="post", color="k", lw=1, ls="--", label=f"Pareto front (time, {name.split()[0]})")
        ax.set(xscale="log", yscale="log", xlabel="wall time per step / per 0.05 s frame (ms, median, this machine)",
               ylabel=f"{name} relative L2 error (test, mean over 20 snapshots)")
        ax.grid(True, which="both", alpha=0.3)
        if shown:
            ax.set_xlim(right=4 * max(p["ms"] for p in shown))   # room for the slowest points' labels
    fig.suptitle(f"Beam, {len(result['test_sims'])} test case(s): run time against error"
                 + (" (QUICK run)" if result["quick"] else ""))
    handles, labels = axes[0].get_legend_handles_labels()
    h2, l2 = axes[1].get_legend_handles_labels()
    handles += [h for h, lab in zip(h2, l2) if lab not in labels]
    labels += [lab for lab in l2 if lab not in labels]
    fig.legend(handles, labels, fontsize=8, loc="lower center", ncol=3)
    fig.tight_layout(rect=(0, 0.12, 0.97, 1), w_pad=3)
    fig.canvas.draw()   # labels placed in the final layout's coordinates
    for ax, key in ((axes[0], "u"), (axes[1], "sigma")):
        if not shown:
            continue
        xy = ax.transData.transform([(p["ms"], p[key]) for p in shown]) * 72.0 / fig.dpi   # points
        for p, (dx, dy) in zip(shown, spread_labels(xy)):
            ax.annotate(p["name"].replace("FEM ", ""), (p["ms"], p[key]), fontsize=6.5, xytext=(dx, dy),
                        textcoords="offset points", ha="left",
                        arrowprops=dict(arrowstyle="-", lw=0.4, color="0.5") if abs(dy) > 6 else None)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def spread_labels(xy, height: float = 9.0, width: float = 70.0) -> list:
    """Label offsets (points) for markers at display positions ``xy`` [n, 2]: each label sits up and right of its
    marker, moved down in steps of ``height`` while it would overlap an earlier label (by this box size)."""
    placed, out = [], []
    for i in np.lexsort((-xy[:, 1], xy[:, 0])):
        x, y = xy[i, 0] + 4, xy[i, 1] + 3
        while any(abs(x - px) < width and abs(y - py) < height for px, py in placed):
            y -= height
        placed.append((x, y))
        out.append((i, (4, y - xy[i, 1])))
    return [o for _, o in sorted(out)]


def shipped_verdict(point: dict) -> str:
    """Where a point stands on the two fronts, in words."""
    on_u, on_uvs = point["on_front"], bool(point.get("on_front_uvs"))
    u = "lies on the (time, u) front" if on_u else "does NOT lie on the (time, u) front"
    if on_u == on_uvs:
        return u + (" and on" if on_uvs else " nor on") + " the (time, u, v, σ) front"
    return u + (" but lies on" if on_uvs else " but not on") + " the (time, u, v, σ) front"


def findings(result: dict) -> list:
    """Sentences computed from the points: where the shipped default stands against the FEM and the published
    network."""
    pts, published = result["points"], result["published_test"]
    shipped = next((p for p in pts if p["kind"] == "shipped"), None)
    if shipped is None:
        return []
    out = []
    within = "within" if shipped["ms"] <= BUDGET_MS[0] else "above"
    out.append(f"- The shipped default `{SHIPPED}` ({shipped['ms']:.2f} ms per step, u {shipped['u']:.4f}, "
               f"v {shipped['v']:.4f}, σ {shipped['sigma']:.4f}) {shipped_verdict(shipped)}; its step is {within} "
               f"the {BUDGET_MS[0]:g} ms budget of one beam.")
    out.append(f"- Against the published TIGNN's test errors (u {published['u']:.4f}, v {published['v']:.4f}, "
               f"σ {published['sigma']:.4f}): " + ", ".join(
                   f"{n} {shipped[k] / published[k]:.2f}×" for k, n in (("u", "u"), ("v", "v"), ("sigma", "σ")))
               + " (below 1: more accurate than the published network).")
    linear = next((p for p in pts if p["kind"] == "shipped-linear"), None)
    if linear is not None:
        out.append(f"- Against `{LINEAR}`, the FEM's rest linearisation: {shipped['ms']:.2f} against "
                   f"{linear['ms']:.2f} ms per step, u {shipped['u']:.4f} / {linear['u']:.4f}, v {shipped['v']:.4f} / "
                   f"{linear['v']:.4f}, σ {shipped['sigma']:.4f} / {linear['sigma']:.4f}.")
    learned = next((p for p in pts if p["kind"] == "shipped-learned"), None)
    if learned is not None:
        out.append(f"- Against `{LEARNED}`, the learned linear GENERIC model: {shipped['ms']:.2f} against "
                   f"{learned['ms']:.2f} ms per step ({shipped['ms'] / learned['ms']:.2f}×), u {shipped['u']:.4f} / "
                   f"{learned['u']:.4f}, v {shipped['v']:.4f} / {learned['v']:.4f}, σ {shipped['sigma']:.4f} / "
                   f"{learned['sigma']:.4f}.")
    reproduction = next((p for p in pts if p["kind"] == "shipped-reproduction"), None)
    if reproduction is not None:
        out.append(f"- `{REPRODUCTION}`, the paper's network reproduced: {reproduction['ms']:.2f} ms per step, u "
                   f"{reproduction['u']:.4f}, v {reproduction['v']:.4f}, σ {reproduction['sigma']:.4f} (the published "
                   f"network's u {published['u']:.4f}, v {published['v']:.4f}, σ {published['sigma']:.4f}).")
    fem = [p for p in pts if p["kind"].startswith("fem") and np.isfinite(p["u"])]
    as_good = [p for p in fem if p["u"] <= shipped["u"]]
    if as_good:
        best = min(as_good, key=lambda p: p["ms"])
        out.append(f"- The cheapest FEM point at least as accurate in u as `{SHIPPED}` is {best['name']}: "
                   f"{best['ms']:.2f} ms per frame, {best['ms'] / shipped['ms']:.1f}× `{SHIPPED}`'s step.")
    else:
        out.append(f"- No FEM point measured here is as accurate in u as `{SHIPPED}`.")
    in_budget = [p for p in fem if p["ms"] <= BUDGET_MS[0]]
    if in_budget:
        best = min(in_budget, key=lambda p: p["u"])
        out.append(f"- Within the {BUDGET_MS[0]:g} ms budget the most accurate FEM point is {best['name']} "
                   f"({best['ms']:.2f} ms): u {best['u']:.4f}, {best['u'] / shipped['u']:.2f}× `{SHIPPED}`'s.")
    return out + [""]


def report(result: dict) -> str:
    pts, m, published = result["points"], result["machine"], result["published_test"]
    lines = [
        "# Run time against error: the shipped models and the FEM (beam, test sims "
        f"{', '.join(map(str, result['test_sims']))})", "",
        machine_line(m) + ", XLA_FLAGS="
        f"`{result['xla_flags'] or '(unset)'}`; load average 1/5/15 min at the start {result['load_average_start']}, "
        f"after the model steps {result['load_average_after_steps']}, at the end {result['load_average_end']} "
        "(above the core count: other processes shared the CPU; times are upper bounds for an idle machine). "
        f"Model and Newton steps: median of {result['repeats']} calls after compilation, interleaved in blocks of 5 "
        f"(each after an untimed call), under the XLA:CPU configurations {', '.join(result['xla_configs'])}, the "
        "faster counting. FEM: median wall time of one 0.05 s frame (all sub-steps and the stress recovery) of one "
        "case." + (" QUICK run: one case, cheap variants." if result["quick"] else ""), "",
        "Errors: relative L2 over all 756 nodes per snapshot, mean over snapshots 1..20 and the test cases; "
        "u = q − q0, σ all nodes (clamped face included), the FEM's v = numpy.gradient of its q (the data's "
        "convention). The models start from each case's first state, the FEM from rest.", "",
        "| point | ms / step | u | v | σ | σ (free nodes) | worst-case u | on front (time, u) | "
        "on front (time, u, v, σ) | notes |", "|---|---|---|---|---|---|---|---|---|---|"]
    for p in sorted(pts, key=lambda p: p["ms"]):
        if p["kind"] == "shipped":
            note = ("corotational GENERIC: the FEM's element stiffness turned with each element, exact volumetric "
                    "energy, linearised backward Euler by preconditioned CG (not learned)")
        elif p["kind"] == "shipped-learned":
            note = "learned linear GENERIC, backward Euler; trained on the data's train split"
        elif p["kind"] == "shipped-linear":
            note = "the FEM's rest linearisation, backward Euler (not learned)"
        elif p["kind"] == "shipped-reproduction":
            note = ("the paper's graph network, reproduced on the data's train split; explicit GENERIC step "
                    "(not a model for interaction)")
        elif p["kind"] == "fem-newton":
            note = (f"500 hex8, backward Euler by {p['newton'][0]} Newton iteration(s) of {p['newton'][1]} CG each, "
                    "preconditioned with the rest operator turned with the body")
        else:
            note = f"{p['elements']} hex8, {p['n_sub']} sub-steps/frame"
            if any(i >= 0 for i in p["inverted"]):
                note += ", element inversion"
        if not np.isfinite(p["u"]):
            note += "; rollout diverged (NaN) on a test case"
        if p.get("p50_by_xla") and len(p["p50_by_xla"]) > 1:
            note += "; XLA " + ", ".join(f"{c} {ms:.2f}" for c, ms in p["p50_by_xla"].items())
        lines.append(f"| {p['name']} | {p['ms']:.2f} | {p['u']:.4f} | {p['v']:.4f} | {p['sigma']:.4f} | "
                     f"{p['sigma_free']:.4f} | {p['u_worst_case']:.4f} | {'**yes**' if p['on_front'] else 'no'} | "
                     f"{'**yes**' if p.get('on_front_uvs') else 'no'} | {note} |")
    lines.append(f"| published TIGNN (reference line) | — | {published['u']:.4f} | {published['v']:.4f} | "
                 f"{published['sigma']:.4f} | — | — | — | — | the paper's network on the test split "
                 "(`tignn_jax.evaluation.PUBLISHED_TEST`), its authors' weights: run time not measured here |")
    lines += ["", "Pareto front in (time, u error; a diverged rollout is never on it): "
              + " → ".join(result["front"]) + ".", "",
              "Pareto front in (time, u, v, σ errors: not dominated in all four at once): "
              + " → ".join(result["front_uvs"]) + ".", ""]
    lines += findings(result)
    lines += ["FEM variants: mass scaling multiplies the density (the stable sub-step grows with √factor, the inertia "
              "and the damping force α·M·v grow with it, so the dynamics are distorted); coarse meshes are structured "
              "hex8 meshes of the 40×10×10 beam, loads moved to their nodes by trilinear weights (total force "
              "conserved) and results interpolated back to the reference nodes with the same weights. `FEM Newton-CG "
              "n×k` is the FEM's backward-Euler frame by n Newton iterations from v' = 0, each by k CG iterations "
              "preconditioned with R A₀⁻¹ Rᵀ (per-node rotations R; `tignn_jax.newton`), timed as one step from a "
              "mid-case state."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
