r"""Run time against error on the held-out beam cases: the learned simulator and the FEM it replaces (issue 6).

On the six test cases of the Abaqus beam data (sims 9, 10, 12, 13, 38, 44) this measures, on this CPU,
  * the learned simulator: step time (median after compilation) over a grid of sizes, hidden width
    {16, 24, 32, 64, 128} × message passes {2, 3, 5, 10} (untrained weights time the same as trained ones), and
    the rollout errors of a subset trained with one equal budget (same recipe, seed and number of epochs; the
    epochs are chosen from a measured per-step training time so that the subset fits ``--train-minutes``);
    the shipped ``beam-abaqus`` model (its own, longer budget) in float32 and with weights and network
    activations in bfloat16 (state and integrator stay float32). Only forward Euler is trained: another
    integrator would need its own training, so it is not a point here;
  * the FEM at decreasing cost: its own stable step on the 20×5×5 reference mesh, mass scaling (density ×4,
    ×16, ×64: fewer sub-steps per frame, dynamics distorted) and coarser hex meshes of the 40×10×10 beam
    (loads moved onto the coarse nodes with trilinear weights, which conserves total force; results
    interpolated back to the reference nodes with the same weights). Its cost is the wall time of one
    0.05 s frame for one case (median after compilation);
  * the FEM's rest linearisation stepped by backward Euler, one or two dense solves per frame, on the reference
    and two coarser meshes (the step of a ``linear_prior`` model with no network: K₀ and S₀ from
    `fem.implicit.rest_linearization`), and the non-linear backward-Euler FEM (`fem.implicit`, one Newton step
    per frame) — the cheap baselines a user could run instead of a network — and that backward-Euler frame by a
    fixed count of Newton iterations of a few CG each (`tignn_jax.newton`).
Errors: per snapshot relative L2 over all 756 nodes, mean over snapshots 1..20 and the six cases, of u = q − q0,
v and σ (``tignn_jax.evaluate.relative_errors``); the FEM's v is numpy.gradient of its q over the frames, the
convention of the reference data. The Pareto front is the set of points not dominated in (step time, u error);
a second front asks for domination in (step time, u, v, σ) at once.
Writes benchmarks/results/pareto.{json,md,png}; trained models and cached errors go to runs/pareto/.

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \
        python benchmarks/pareto.py [--quick] [--times-only] [--train-only] [--train-minutes 65]

--times-only re-measures every time and reuses the cached errors (runs/pareto/, else those in the committed
pareto.json; models and FEM variants at hand without errors are run, as that needs no training); --quick is
a small smoke setting (one case, writes runs/pareto/quick/); --train-only trains the subset (resumable:
finished configurations are skipped) and stops; --train-heun trains the Heun sizes first.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
RUNS = ROOT / "runs" / "pareto"
SHIPPED = "beam-abaqus"
# the demo's beam since session 43: the learned linear GENERIC model (`tignn_jax.linear_generic`) trained on this
# data set's train split, with the FEM's rest linearisation as its prior (`beam-fem` is the same class trained on
# our FEM's reference and fingertip cases)
SHIPPED_LINEAR = "beam"
# session 46: beam-abaqus with one message pass fewer, fine-tuned (its card): below beam-abaqus's errors, 1.3x cheaper
SHIPPED_FAST = "beam-abaqus-64x2"
BUDGET_MS = (9.0, 11.0)   # the real-time step budget of issue 5 (one beam 9 ms; bunny 11 ms)
WIDTHS = (16, 24, 32, 64, 128)
PASSES = (2, 3, 5, 10)
TRAINED = ((16, 3), (24, 2), (24, 3), (24, 5), (32, 3), (64, 3))
HEUN = ((24, 2),)   # trained with the Heun integrator (two rates per step), same recipe, seed and epochs
LEARNED = tuple((c, "euler") for c in TRAINED) + tuple((c, "heun") for c in HEUN)   # ((hidden, passes), integrator)
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
# the FEM's rest linearisation, backward Euler by one dense solve per sub-step (the step of a `linear_prior`
# model with no network): (name, elements along x, y, z, solves per frame)
LINEAR_VARIANTS = (("FEM linearised 20×5×5, 2 solves", (20, 5, 5), 2),
                   ("FEM linearised 20×5×5, 1 solve", (20, 5, 5), 1),
                   ("FEM linearised 14×4×4, 1 solve", (14, 4, 4), 1),
                   ("FEM linearised 10×3×3, 1 solve", (10, 3, 3), 1))
# the non-linear backward-Euler FEM (`fem.implicit`: Newton, CG preconditioned by the rest operator's inverse)
IMPLICIT_VARIANTS = (("FEM implicit 20×5×5, 1 step", (20, 5, 5), 1),)
# backward Euler by a fixed number of Newton iterations of a few CG each, preconditioned with the rest operator
# turned with the body (`tignn_jax.newton`, the fallback step): (name, divisions, (Newton iterations, CG each))
NEWTON_VARIANTS = (("FEM Newton-CG 20×5×5, 2×3 CG", (20, 5, 5), (2, 3)),
                   ("FEM Newton-CG 20×5×5, 1×3 CG", (20, 5, 5), (1, 3)))
BEAM_SIZE = (40.0, 10.0, 10.0)
# XLA:CPU configurations each jitted step is compiled and timed under (per compilation, ``compiler_options``),
# its time the faster of them: YNNPACK's fusions on (XLA's default) or off (the learned loop's option,
# `tignn_jax.scene.REAL_TIME_XLA_FLAG`). Session 38, both cores: the shipped learned step 10.4 → 6.6 ms with them
# off, the Newton-CG FEM step 8.5 → 27.9 ms: timing both under one process-wide setting favours one of them.
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


# ------------------------------------------------------------------------------------------------------------
# learned simulator


def load_data():
    from tignn_jax import data as D

    path = D.reference_path()
    if not path.exists():
        raise SystemExit(f"reference data not found at {path}")
    return D.load(path)


def point_key(hidden: int, passes: int, integrator: str = "euler") -> str:
    """The name of a learned size in the caches and step times: '24x2', or '24x2 heun' for another integrator."""
    return f"{hidden}x{passes}" + ("" if integrator == "euler" else f" {integrator}")


def run_dir(hidden: int, passes: int, integrator: str = "euler") -> Path:
    return RUNS / (f"h{hidden}_p{passes}" + ("" if integrator == "euler" else f"_{integrator}"))


def train_heun(data, epochs: int, log=print) -> None:
    """Train the ``HEUN`` sizes with the Heun integrator: the shipped recipe, seed and ``epochs`` of the
    equal-budget Euler subset (resumable; a finished run has done.json)."""
    from tignn_jax import train as T

    for hidden, passes in HEUN:
        _train_run(data, T.CONFIGS["beam"]._replace(hidden=hidden, passes=passes, epochs=epochs, integrator="heun"),
                   run_dir(hidden, passes, "heun"), log)


def _train_run(data, cfg, rd: Path, log=print) -> None:
    """One equal-budget run of the subset into ``rd`` (skipped when its done.json exists; resumes otherwise)."""
    from tignn_jax import train as T

    if (rd / "done.json").exists():
        return
    t0 = time.time()
    T.train(data, cfg, rd, train_split="train", val_split="val", progress=False, log=log)
    (rd / "done.json").write_text(json.dumps({"epochs": cfg.epochs, "wall_s_last_session": time.time() - t0,
                                              "load_average_1m": round(os.getloadavg()[0], 2)}))


def train_step_seconds(data, configs, repeats: int = 6) -> dict:
    """Median wall time of one optimiser step of the shipped recipe (batch 2) per (hidden, passes)."""
    from tignn_jax import data as D
    from tignn_jax import model as M
    from tignn_jax import train as T

    rows = D.split_rows(data, "train")
    norm = {k: jnp.asarray(v) for k, v in D.normalization(data, rows).items()}
    nt = jnp.asarray(data.node_type, jnp.int32)
    topo = M.topology(data.edges[0], data.edges[1], len(data.node_type), data.q0)
    out = {}
    for hidden, passes in configs:
        cfg = T.CONFIGS["beam"]._replace(hidden=hidden, passes=passes)
        opt = T.make_optimizer(cfg, 1000)
        w = M.init_weights(jax.random.PRNGKey(cfg.seed), cfg.model, norm, jnp.asarray(data.z[rows[0], 0]),
                           jnp.asarray(data.f[rows[0], 0]), nt, topo)
        state = {"step": jnp.zeros((), jnp.int32), "weights": w, "opt_state": opt.init(w)}
        b = cfg.batch_size
        batch = T.Batch(jnp.asarray(data.z[rows[:b], 5]), jnp.asarray(data.f[rows[:b], 5]),
                        jnp.asarray(data.z[rows[:b], 6]))
        step = T.make_train_step(cfg, 1000, norm, nt, topo)
        state, _ = step(state, batch)
        jax.block_until_ready(state)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            state, _ = step(state, batch)
            jax.block_until_ready(state)
            times.append(time.perf_counter() - t0)
        out[f"{hidden}x{passes}"] = float(np.median(times))
    return out


def choose_epochs(step_s: dict, steps_per_epoch: int, minutes: float) -> int:
    """The largest equal number of epochs with which every configuration together trains in ``minutes``."""
    per_epoch = steps_per_epoch * sum(step_s.values())
    return max(1, int(minutes * 60.0 // per_epoch))


def train_subset(data, configs, minutes: float, log=print) -> dict:
    """Train every configuration with the same recipe, seed and number of epochs (resumable: a run whose
    ``done.json`` exists is skipped, an interrupted one resumes from its checkpoint). Returns the plan."""
    from tignn_jax import data as D
    from tignn_jax import train as T

    RUNS.mkdir(parents=True, exist_ok=True)
    plan_path = RUNS / "plan.json"
    if plan_path.exists():
        plan = json.loads(plan_path.read_text())
    else:
        steps_per_epoch = len(D.split_rows(data, "train")) * data.f.shape[1] // T.CONFIGS["beam"].batch_size
        step_s = train_step_seconds(data, configs)
        epochs = choose_epochs(step_s, steps_per_epoch, minutes)
        plan = {"train_step_s": step_s, "steps_per_epoch": steps_per_epoch, "epochs": epochs,
                "budget_minutes": minutes, "configs": [list(c) for c in configs],
                "estimated_minutes": epochs * steps_per_epoch * sum(step_s.values()) / 60.0,
                "load_average_1m": round(os.getloadavg()[0], 2)}
        plan_path.write_text(json.dumps(plan, indent=1))
    log(f"training plan: {plan['epochs']} epochs each, estimated {plan['estimated_minutes']:.0f} min; "
        f"per-step s {plan['train_step_s']}")
    for hidden, passes in plan["configs"]:
        _train_run(data, T.CONFIGS["beam"]._replace(hidden=hidden, passes=passes, epochs=plan["epochs"]),
                   run_dir(hidden, passes), log)
    return plan


def step_mixed(weights, config, norm, z, f, node_type, topo, dtype=jnp.bfloat16):
    """One forward-Euler step (as ``model.step_state``) with the network's weights and activations in ``dtype``.

    The edge and node features, the products with L and M and the state update stay in z's dtype (float32):
    positions of ~40 with edge vectors of ~2 do not survive bfloat16's 8-bit mantissa. With dtype = z.dtype
    this is ``model.step_state``. ``weights`` should already be in ``dtype`` (cast once, outside the loop)."""
    from tignn_jax import model as M

    topo_d = topo._replace(mask=topo.mask.astype(dtype))
    flags = [getattr(config, k) for k in ("edge_velocity", "edge_strain", "node_position") if k in config._fields]

    def potentials(z_):
        x_node, x_edge = M._features(norm, z_, f, node_type, topo, *flags)
        es, heads = M.Network(config).apply({"params": weights}, x_node.astype(dtype), x_edge.astype(dtype),
                                            topo_d)
        es = es.astype(z_.dtype)
        return jnp.stack([es[:, 0].sum(), es[:, 1].sum()]), heads.astype(z_.dtype)

    _, pullback, heads = jax.vjp(potentials, z, has_aux=True)
    (grads,) = jax.vmap(pullback)(jnp.eye(2, dtype=z.dtype))
    scale = M.state_scale(norm)
    l_mat, m_mat = M._matrices(heads)
    dw = M._apply_l(l_mat, grads[0] * scale) + M._apply_m(m_mat, grads[1] * scale)
    clamped = (node_type != 0)[:, None] & (jnp.arange(M.STATE_DIM) < 6)[None, :]
    return z + jnp.where(clamped, 0.0, dw) * scale


def cast_weights(weights, dtype):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), weights)


def weights_fingerprint(params: dict) -> str:
    """SHA-256 of a model's weights and its normalisation entries (leaves in tree order, with their shapes; the
    entries a model derives when it is built left out): cached errors belong to it. The norm entries count
    because a linear GENERIC model's network is zero and its operators are all it learned (session 43: two such
    models with different operators had the same weights' hash, and the new one was given the old one's errors)."""
    from tignn_jax import framesolve as FS

    h = hashlib.sha256()
    norm = {k: v for k, v in params.get("norm", {}).items() if k not in FS.DERIVED}
    for leaf in jax.tree_util.tree_leaves(params["weights"]) + [norm[k] for k in sorted(norm)]:
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def stale(cache: dict, name: str, weights: str) -> bool:
    """Whether ``name``'s cached errors are missing or were measured with other weights than ``weights``. An
    entry without a fingerprint (written before they were kept) counts as stale: session 38 found the committed
    errors of the shipped model were its session-4 weights' (u 0.0488, σ 0.1245 against 0.0453, 0.0944)."""
    return cache.get(name, {}).get("weights_sha256") != weights


def learned_errors(params, data, rows, dtype=None) -> dict:
    """Mean rollout errors (q, v, sigma, u) over snapshots 1..T and the cases ``rows``, all nodes."""
    from tignn_jax import evaluate as EV
    from tignn_jax import model as M

    if dtype is None:
        pred = EV.rollout_cases(params, data, rows)
    else:
        config = M.ModelConfig(**params["config"])
        w = cast_weights(params["weights"], dtype)
        nt = jnp.asarray(data.node_type, jnp.int32)
        topo, norm = params["topo"], params["norm"]

        @jax.jit
        def roll(z0, forces):
            def body(z, f):
                z = step_mixed(w, config, norm, z, f, nt, topo, dtype)
                return z, z
            return jnp.concatenate([z0[None], jax.lax.scan(body, z0, forces)[1]])

        pred = np.stack([np.asarray(roll(jnp.asarray(data.z[r, 0]), jnp.asarray(data.f[r]))) for r in rows])
    return summary(pred, data, rows)


def summary(pred, data, rows) -> dict:
    """Mean errors of predicted states [cases, T+1, N, 12] against the data's cases ``rows`` over snapshots
    1..T and cases, all nodes (NaN when a rollout diverged); σ also over the free nodes; the worst case's u."""
    from tignn_jax import evaluate as EV

    e = EV.relative_errors(pred, data.z[rows], data.q0)[:, 1:]
    e_free = EV.relative_errors(pred, data.z[rows], data.q0, data.node_type == 0)[:, 1:]
    out = {k: float(np.mean(e[..., i])) for i, k in enumerate(("q", "v", "sigma", "u"))}
    out["sigma_free"] = float(np.mean(e_free[..., 2]))
    out["u_worst_case"] = float(np.max(np.mean(e[..., 3], axis=1)))
    return out


def learned_step_fns(data, sizes, shipped_params, linear_params=None, fast_params=None):
    """{name: jitted (z, f) → z_next} for untrained models of each size, the shipped model (float32, as
    ``api.stepper``), the shipped model in bfloat16, the shipped linear GENERIC model (``linear_params``,
    as ``api.stepper``) and the shipped two-pass network (``fast_params``, as ``api.stepper``); and example
    arguments."""
    from tignn_jax import api
    from tignn_jax import data as D
    from tignn_jax import model as M

    rows = D.split_rows(data, "train")
    norm = {k: jnp.asarray(v) for k, v in D.normalization(data, rows).items()}
    nt = jnp.asarray(data.node_type, jnp.int32)
    topo = M.topology(data.edges[0], data.edges[1], len(data.node_type), data.q0)
    test = D.split_rows(data, "test")[0]
    z, f = jnp.asarray(data.z[test, 10]), jnp.asarray(data.f[test, 10])
    fns = {}
    for hidden, passes, integrator in [(h, p, "euler") for h, p in sizes] + [(h, p, "heun") for h, p in HEUN]:
        cfg = M.ModelConfig(hidden=hidden, passes=passes, integrator=integrator)
        w = M.init_weights(jax.random.PRNGKey(0), cfg, norm, z, f, nt, topo)
        fns[point_key(hidden, passes, integrator)] = jax.jit(lambda z, f, w=w, cfg=cfg: M.step_state(w, cfg, norm, z, f, nt, topo))
    fns[SHIPPED] = api.stepper(shipped_params)
    cfg = api._config(shipped_params)
    w16 = cast_weights(shipped_params["weights"], jnp.bfloat16)
    sn, stopo = shipped_params["norm"], shipped_params["topo"]
    fns[SHIPPED + " bf16"] = jax.jit(lambda z, f: step_mixed(w16, cfg, sn, z, f, nt, stopo, jnp.bfloat16))
    if linear_params is not None:
        fns[SHIPPED_LINEAR] = api.stepper(linear_params)
    if fast_params is not None:
        fns[SHIPPED_FAST] = api.stepper(fast_params)
    return fns, (z, f)


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


def time_configs(fns: dict, args, repeats: int, block: int = 5) -> dict:
    """``time_round_robin`` of every jitted function compiled under each of ``XLA_CONFIGS`` (all interleaved),
    reduced by ``best_config``."""
    compiled = {f"{k}|{c}": fn_c for k, fn in fns.items() for c, fn_c in compiled_configs(fn, args).items()}
    return best_config(time_round_robin(compiled, args, repeats, block))


def time_round_robin(fns: dict, args, repeats: int, block: int = 5) -> dict:
    """Median and p90 wall time [ms] of ``repeats`` calls per function after a compiling call. Functions take
    turns in blocks of ``block`` timed calls, each block after one untimed call, so that load changes on the
    shared machine hit every variant alike and no variant is timed on caches just evicted by a larger one."""
    for fn in fns.values():
        jax.block_until_ready(fn(*args))
    times = {k: [] for k in fns}
    for _ in range(max(1, repeats // block)):
        for k, fn in fns.items():
            jax.block_until_ready(fn(*args))
            for _ in range(block):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*args))
                times[k].append(1e3 * (time.perf_counter() - t0))
    return {k: {"p50_ms": float(np.median(v)), "p90_ms": float(np.percentile(v, 90)), "repeats": len(v)}
            for k, v in times.items()}


# ------------------------------------------------------------------------------------------------------------
# FEM


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


_LINEAR = {}
_LINEAR_FRAMES = {}


def linear_frame(divisions, n_solves: int):
    """(frame, scene, W): a jitted (z [Nc,12], f_prev, f [Nc,3]) → z after one 0.05 s frame of the rest-linearised
    backward-Euler FEM on the ``divisions`` mesh, in ``n_solves`` sub-steps (the load ramped linearly from f_prev
    to f within the frame, as the FEM's reference runs; each sub-step at its end's load); one
    `fem.implicit.rest_linearization` per mesh and one dense inverse per (mesh, sub-steps), both cached (the
    errors and the timing share them; the linearisation takes ~1 min on the reference mesh)."""
    key = (tuple(divisions), int(n_solves))
    if key not in _LINEAR_FRAMES:
        _LINEAR_FRAMES[key] = _build_linear_frame(divisions, n_solves)
    return _LINEAR_FRAMES[key]


def _rest_operators(divisions, n_solves: int):
    """(scene, problem, W, norm): the ``divisions`` mesh and its rest linearisation (cached per mesh) as
    ``framesolve`` entries with the dense inverse for a step of frame_dt / n_solves."""
    from fem import implicit
    from tignn_jax import framesolve as FS

    scene, problem, w = fem_problem(divisions, 1.0)
    key = tuple(divisions)
    if key not in _LINEAR:
        _LINEAR[key] = implicit.rest_linearization(problem, scene.material)
    norm = {k: np.asarray(v, np.float32) for k, v in FS.norm_entries(_LINEAR[key]).items()}
    norm["dt"] = np.array([problem.config.frame_dt / n_solves], np.float32)
    return scene, problem, w, {k: jnp.asarray(v) for k, v in FS.with_inverse(norm, scene.node_type).items()}


def _build_linear_frame(divisions, n_solves: int):
    from tignn_jax import framesolve as FS

    scene, _, w, norm = _rest_operators(divisions, n_solves)
    node_type, x0 = jnp.asarray(scene.node_type), jnp.asarray(scene.points, jnp.float32)

    @jax.jit
    def frame(z, f_prev, f):
        for j in range(1, n_solves + 1):
            load = f_prev + (f - f_prev) * (j / n_solves) if scene.load_interp == "linear" else f
            z = z + FS.linear_step(norm, z, load, node_type, x0)   # prior_step with no network, no K₀ product
        return z

    return frame, scene, w


def newton_frame(divisions, n):
    """(step, scene, w): the jitted frame step (z [Nc,12], f [Nc,3]) → z of `tignn_jax.newton.newton_cg` with
    ``n`` = (Newton iterations, CG iterations each) on the ``divisions`` mesh (backward Euler with the frame's end
    load, as `fem.implicit` with one step per frame); the rest linearisation is shared with `linear_frame`."""
    key = ("newton", tuple(divisions), tuple(n))
    if key not in _LINEAR_FRAMES:
        from fem import implicit
        from tignn_jax import newton

        scene, problem, w, norm = _rest_operators(divisions, 1)
        force, stress = implicit.force_and_stress(problem, scene.material)
        rotation = newton.rotations(scene.points, scene.edges[0], scene.edges[1])
        step = jax.jit(newton.newton_cg(norm, scene.node_type, scene.points, force, stress, rotation,
                                        iterations=int(n[1]), newton=int(n[0])))
        _LINEAR_FRAMES[key] = (step, scene, w)
    return _LINEAR_FRAMES[key]


def newton_errors(divisions, n, data, rows) -> dict:
    """Roll `newton_frame` out from rest over the cases ``rows`` and compare with the reference."""
    step, scene, w = newton_frame(divisions, n)
    forces = jnp.asarray(_coarse_forces(data, rows, w), jnp.float32)
    z0 = jnp.concatenate([jnp.asarray(scene.points, jnp.float32), jnp.zeros((len(scene.points), 9))], 1)
    case = lambda f: jnp.concatenate([z0[None], jax.lax.scan(lambda z, f_: (step(z, f_),) * 2, z0, f)[1]])
    zs = np.asarray(jax.vmap(case)(forces))
    pred = _as_prediction(zs[..., :3], zs[..., 6:], w, data.dt)
    return dict(summary(pred, data, rows), n_sub=1, newton=list(n), nodes=len(scene.points),
                elements=len(scene.cells), inverted=[-1] * len(rows))


def newton_frame_time(divisions, n, data, row, min_seconds: float = 3.0) -> dict:
    """Median wall time [ms] of one `newton_frame` step from the case's state after 9 frames, under its 10th load."""
    step, scene, w = newton_frame(divisions, n)
    f = jnp.asarray(_coarse_forces(data, [row], w)[0], jnp.float32)
    z = jnp.concatenate([jnp.asarray(scene.points, jnp.float32), jnp.zeros((len(scene.points), 9))], 1)
    for k in range(9):
        z = step(z, f[k])
    return {**_frame_ms_configs(step, (z, f[9]), min_seconds), "n_sub": 1, "newton": list(n)}


def _frame_ms_configs(step, args, min_seconds: float) -> dict:
    """``time_configs`` of one jitted frame step: about ``min_seconds`` of calls per configuration."""
    one = _median_frame_ms(lambda: step(*args), min_repeats=3, min_seconds=0.0, max_repeats=3)["p50_ms"]
    repeats = int(np.clip(1e3 * min_seconds / max(one, 1e-3), 20, 200)) // 5 * 5
    return {**time_configs({"frame": step}, args, repeats)["frame"], "load_average_1m": round(os.getloadavg()[0], 2)}


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


def linear_errors(divisions, n_solves, data, rows) -> dict:
    """Roll the rest-linearised FEM out from rest over the cases ``rows`` and compare with the reference."""
    frame, scene, w = linear_frame(divisions, n_solves)
    forces = jnp.asarray(_coarse_forces(data, rows, w), jnp.float32)
    z0 = jnp.concatenate([jnp.asarray(scene.points, jnp.float32), jnp.zeros((len(scene.points), 9))], 1)

    def case(f):
        prev = jnp.concatenate([jnp.zeros_like(f[:1]), f[:-1]])
        _, zs = jax.lax.scan(lambda z, fs_: (frame(z, *fs_),) * 2, z0, (prev, f))
        return jnp.concatenate([z0[None], zs])

    zs = np.asarray(jax.vmap(case)(forces))
    pred = _as_prediction(zs[..., :3], zs[..., 6:], w, data.dt)
    return dict(summary(pred, data, rows), n_sub=n_solves, nodes=len(scene.points), elements=len(scene.cells),
                inverted=[-1] * len(rows))


def implicit_errors(divisions, n_sub, data, rows) -> dict:
    """The non-linear backward-Euler FEM (`fem.implicit`) over the cases ``rows`` against the reference."""
    from fem import Loads, implicit

    scene, problem, w = fem_problem(divisions, 1.0)
    forces = jnp.asarray(_coarse_forces(data, rows, w), jnp.float32)
    res, diag = implicit.simulate_implicit_batch(problem, scene.material, Loads(nodal=forces), n_sub=n_sub)
    pred = _as_prediction(res.q, res.sigma, w, data.dt)
    return dict(summary(pred, data, rows), n_sub=n_sub, nodes=len(scene.points), elements=len(scene.cells),
                inverted=np.asarray(res.inverted).tolist(), newton_residual_max=float(np.max(diag.residual)),
                newton_iterations_max=int(np.max(diag.newton_iterations)))


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


def linear_frame_time(divisions, n_solves, data, row, min_seconds: float = 3.0) -> dict:
    """Median wall time [ms] of one frame of the rest-linearised FEM (its solves), at the case's 10th frame."""
    frame, scene, w = linear_frame(divisions, n_solves)
    f = jnp.asarray(_coarse_forces(data, [row], w)[0], jnp.float32)
    z = jnp.concatenate([jnp.asarray(scene.points, jnp.float32), jnp.zeros((len(scene.points), 9))], 1)
    return {**_frame_ms_configs(frame, (z, f[8], f[9]), min_seconds), "n_sub": n_solves}


def implicit_frame_time(divisions, n_sub, data, row, min_seconds: float = 3.0) -> dict:
    """Median wall time [ms] per frame of the non-linear backward-Euler FEM: a whole case's run over its frames
    (Newton iterations vary along a case)."""
    from fem import Loads, implicit

    scene, problem, w = fem_problem(divisions, 1.0)
    pinv = implicit.preconditioner(problem, scene.material, n_sub)
    loads = Loads(nodal=jnp.asarray(_coarse_forces(data, [row], w)[0], jnp.float32))
    frames = loads.nodal.shape[0]
    run = lambda: implicit.simulate_implicit(problem, scene.material, loads, pinv, n_sub=n_sub)[0].q
    t = _median_frame_ms(run, min_repeats=3, min_seconds=min_seconds)
    return {**{k: (v / frames if k.endswith("_ms") else v) for k, v in t.items()}, "n_sub": n_sub,
            "timed": f"whole {frames}-frame case / {frames}"}


# ------------------------------------------------------------------------------------------------------------
# driver


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small smoke setting (writes runs/pareto/quick/)")
    ap.add_argument("--times-only", action="store_true", help="re-measure times, reuse cached errors")
    ap.add_argument("--train-only", action="store_true", help="train the equal-budget subset and stop")
    ap.add_argument("--train-minutes", type=float, default=65.0, help="budget of the subset (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=200, help="timed calls per learned variant")
    ap.add_argument("--train-heun", action="store_true",
                    help="train the Heun-integrator sizes first (the subset's epochs; resumable)")
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite pareto.md and pareto.png from the stored pareto.json (benchmarks/results/, "
                         "or runs/pareto/quick/ with --quick; no timing)")
    args = ap.parse_args(argv)
    from tignn_jax import api
    from tignn_jax import data as D

    stem = "pareto_quick" if args.quick else "pareto"
    out = RUNS / "quick" if args.quick else RESULTS
    widths, passes = ((16, 24), (2, 3)) if args.quick else (WIDTHS, PASSES)
    if args.report_only:
        if not (out / f"{stem}.json").exists():
            ap.error(f"--report-only: no stored result at {out / f'{stem}.json'} (run without it first)")
        result = json.loads((out / f"{stem}.json").read_text())
        points = result["points"]
        front = [i for i, p in enumerate(points) if p["name"] in result["front"]]
        plot(out / f"{stem}.png", points, np.asarray(front), result)
        md = report(result, widths, passes)
        (out / f"{stem}.md").write_text(md)
        print(md)
        return 0

    data = load_data()
    if args.train_only:
        train_subset(data, TRAINED, args.train_minutes)
        return 0
    rows = D.split_rows(data, "test")
    variants = FEM_VARIANTS[7:9] if args.quick else FEM_VARIANTS
    linear = LINEAR_VARIANTS[-1:] if args.quick else LINEAR_VARIANTS
    implicit_variants = () if args.quick else IMPLICIT_VARIANTS
    newton_variants = NEWTON_VARIANTS[:1] if args.quick else NEWTON_VARIANTS
    repeats = 20 if args.quick else args.repeats
    if args.quick:
        rows = rows[:1]
    cache_path = RUNS / f"{stem}_errors.json"
    cache_path.parent.mkdir(parents=True, exist_ok=True)
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    plan = json.loads((RUNS / "plan.json").read_text()) if (RUNS / "plan.json").exists() else None
    previous = (RUNS / "quick" if args.quick else RESULTS) / f"{stem}.json"
    if args.times_only and not cache and previous.exists():   # a checkout without runs/: the committed errors
        old = json.loads(previous.read_text())
        cache, plan = old["errors"], old.get("train_plan")
    if not args.quick and not args.times_only:
        plan = train_subset(data, TRAINED, args.train_minutes)

    if args.train_heun and not args.quick:   # the same number of epochs as the Euler subset
        epochs = (plan or {}).get("epochs") or cache.get("24x2", {}).get("train_info", {}).get(
            "train_config", {}).get("epochs")
        if not epochs:
            raise SystemExit("--train-heun: the Euler subset's epochs are unknown (no plan and no cached 24x2)")
        train_heun(data, int(epochs))

    # errors (cached)
    shipped, _ = api.load_pretrained(SHIPPED)
    shipped_linear, _ = api.load_pretrained(SHIPPED_LINEAR)
    shipped_fast, _ = api.load_pretrained(SHIPPED_FAST)
    learned = {SHIPPED: (shipped, None), SHIPPED + " bf16": (shipped, jnp.bfloat16),
               SHIPPED_LINEAR: (shipped_linear, None), SHIPPED_FAST: (shipped_fast, None)}
    for (h, p), integrator in LEARNED:
        key = point_key(h, p, integrator)
        path = run_dir(h, p, integrator) / "best" / "model.npz"
        if key not in cache and (run_dir(h, p, integrator) / "done.json").exists() and path.exists():
            learned[key] = (api.load_model(path), None)
    for name, (params, dtype) in learned.items():
        weights = weights_fingerprint(params)
        if stale(cache, name, weights):   # a model at hand: its rollouts are cheap (--times-only too)
            print(f"errors: {name}", flush=True)
            cache[name] = {**learned_errors(params, data, rows, dtype), "weights_sha256": weights}
            if name not in (SHIPPED, SHIPPED + " bf16", SHIPPED_LINEAR, SHIPPED_FAST):
                cache[name]["train_info"] = params.get("info", {})
            cache_path.write_text(json.dumps(cache, indent=1))
    # the FEM variants' errors are deterministic and need no training: computed where missing, --times-only too
    solvers = [(name, div, n, linear_errors, linear_frame_time) for name, div, n in linear]
    solvers += [(name, div, n, implicit_errors, implicit_frame_time) for name, div, n in implicit_variants]
    solvers += [(name, div, n, newton_errors, newton_frame_time) for name, div, n in newton_variants]
    for name, div, factor in variants:
        if name not in cache:
            print(f"errors: {name}", flush=True)
            cache[name] = fem_errors(div, factor, data, rows)
            cache_path.write_text(json.dumps(cache, indent=1))
    for name, div, n, errors_fn, _ in solvers:
        if name not in cache:
            print(f"errors: {name}", flush=True)
            cache[name] = errors_fn(div, n, data, rows)
            cache_path.write_text(json.dumps(cache, indent=1))

    # times (always measured, now)
    load_start = os.getloadavg()
    print("timing the learned steps", flush=True)
    sizes = [(h, p) for h in widths for p in passes]
    fns, fargs = learned_step_fns(data, sizes, shipped, shipped_linear, shipped_fast)
    step_times = time_configs(fns, fargs, repeats)
    load_learned = os.getloadavg()
    fem_times = {}
    for name, div, factor in variants:
        print(f"timing {name}", flush=True)
        fem_times[name] = fem_frame_time(div, factor, int(data.sim_id[rows[0]]),
                                         min_seconds=1.0 if args.quick else 3.0)
    for name, div, n, _, time_fn in solvers:
        print(f"timing {name}", flush=True)
        fem_times[name] = time_fn(div, n, data, rows[0], min_seconds=1.0 if args.quick else 3.0)
    load_end = os.getloadavg()

    points = build_points(cache, step_times, fem_times, variants, shipped, solvers, shipped_fast)
    front = pareto_front([p["ms"] for p in points], [p["u"] for p in points])
    front_all = pareto_front([p["ms"] for p in points], [[p["u"], p["v"], p["sigma"]] for p in points])
    for i, p in enumerate(points):
        p["on_front"] = bool(i in set(front.tolist()))
        p["on_front_uvs"] = bool(i in set(front_all.tolist()))
    result = {"machine": describe(), "load_average_start": [round(x, 2) for x in load_start],
              "load_average_end": [round(x, 2) for x in load_end],
              "load_average_after_learned": [round(x, 2) for x in load_learned],
              "test_sims": data.sim_id[rows].tolist(),
              "budget_ms": BUDGET_MS, "points": points, "front": [points[i]["name"] for i in front],
              "front_uvs": [points[i]["name"] for i in front_all],
              "grid_step_ms": {k: v for k, v in step_times.items() if "x" in k and " " not in k
                               and not k.startswith(SHIPPED) and k not in (SHIPPED_LINEAR, SHIPPED_FAST)},
              "step_times": step_times, "fem_times": fem_times, "errors": cache, "train_plan": plan,
              "repeats": repeats, "quick": args.quick, "xla_flags": os.environ.get("XLA_FLAGS", "")}
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1))
    plot(out / f"{stem}.png", points, front, result)
    md = report(result, widths, passes)
    (out / f"{stem}.md").write_text(md)
    print(md)
    return 0


def build_points(cache, step_times, fem_times, variants, shipped, solvers=(), fast=None) -> list:
    """One record per point with both a time and errors: name, kind, ms (step or frame), errors, params."""
    from tignn_jax import model as M

    points = []
    cfg = shipped["config"]
    n_shipped = M.count_params(shipped["weights"])
    for name in (SHIPPED, SHIPPED + " bf16"):
        if name in cache and name in step_times:
            points.append({"name": name, "kind": "shipped" if name == SHIPPED else "shipped-bf16",
                           "hidden": cfg["hidden"], "passes": cfg["passes"], "params": n_shipped,
                           "epochs": shipped.get("info", {}).get("train_config", {}).get("epochs"),
                           "ms": step_times[name]["p50_ms"], **xla_fields(step_times[name]), **cache[name]})
    if fast is not None and SHIPPED_FAST in cache and SHIPPED_FAST in step_times:
        fcfg = fast["config"]
        points.append({"name": SHIPPED_FAST, "kind": "shipped-fast", "hidden": fcfg["hidden"],
                       "passes": fcfg["passes"], "params": M.count_params(fast["weights"]),
                       "ms": step_times[SHIPPED_FAST]["p50_ms"], **xla_fields(step_times[SHIPPED_FAST]),
                       **cache[SHIPPED_FAST]})
    if SHIPPED_LINEAR in cache and SHIPPED_LINEAR in step_times:
        points.append({"name": SHIPPED_LINEAR, "kind": "shipped-linear", "ms": step_times[SHIPPED_LINEAR]["p50_ms"],
                       **xla_fields(step_times[SHIPPED_LINEAR]), **cache[SHIPPED_LINEAR]})
    for (h, p), integrator in LEARNED:
        key = point_key(h, p, integrator)
        if key in cache and key in step_times:
            info = cache[key].get("train_info", {})
            points.append({"name": f"learned {key}", "kind": "learned", "hidden": h, "passes": p,
                           "integrator": integrator,
                           "epochs": info.get("train_config", {}).get("epochs"),
                           "best_epoch": info.get("best", {}).get("epoch"),
                           "ms": step_times[key]["p50_ms"], **xla_fields(step_times[key]),
                           **{k: v for k, v in cache[key].items() if k != "train_info"}})
    for name, _, factor in variants:
        if name in cache and name in fem_times:
            points.append({"name": name, "kind": "fem", "density_factor": factor,
                           "ms": fem_times[name]["p50_ms"], **cache[name]})
    for name, _, _, errors_fn, _ in solvers:
        if name in cache and name in fem_times:
            kind = {linear_errors: "fem-linear", newton_errors: "fem-newton"}.get(errors_fn, "fem-implicit")
            points.append({"name": name, "kind": kind, "density_factor": 1.0, "ms": fem_times[name]["p50_ms"],
                           **xla_fields(fem_times[name]), **cache[name]})
    return points


def xla_fields(timing: dict) -> dict:
    """The XLA:CPU configuration a point's time was taken under and every configuration's median, where timed
    under several (`time_configs`)."""
    return {k: timing[k] for k in ("xla", "p50_by_xla") if k in timing}


def plot(path, points, front, result) -> None:
    """Two panels against step time, u and σ errors, each with its own (time, error) front; labels are nudged
    apart (`spread_labels`) where points crowd, e.g. around the shipped model and the 9 ms budget."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(15, 6.2))
    style = {"learned": ("o", "C0", "learned, equal budget"),
             "shipped": ("*", "C3", "shipped non-linear TIGNN, beam-abaqus (float32)"),
             "shipped-bf16": ("D", "C1", "beam-abaqus, bfloat16"),
             "shipped-fast": ("*", "C9", "shipped two-pass TIGNN, beam-abaqus-64x2 (float32)"),
             "shipped-linear": ("*", "C2", "shipped default: learned linear GENERIC beam (the demo's)"),
             "fem": ("s", "C7", "FEM (per 0.05 s frame)"),
             "fem-linear": ("P", "C4", "FEM rest-linearised, backward Euler"),
             "fem-implicit": ("X", "C5", "FEM non-linear backward Euler"),
             "fem-newton": ("v", "C6", "FEM backward Euler, fixed Newton-CG (tignn_jax.newton)")}
    shown = [p for p in points if np.isfinite(p["u"]) and np.isfinite(p["sigma"])]
    for ax, key, name in ((axes[0], "u", "u = q − q0"), (axes[1], "sigma", "σ")):
        ax.axvspan(*BUDGET_MS, color="C2", alpha=0.15, label=f"real-time budget {BUDGET_MS[0]:g}–{BUDGET_MS[1]:g} ms")
        seen = set()
        for p in shown:
            m, c, label = style[p["kind"]]
            ax.scatter(p["ms"], p[key], marker=m, color=c, s=160 if p["kind"].startswith("shipped") else 50, zorder=3,
                       edgecolor="k", linewidth=0.5, label=None if p["kind"] in seen else label)
            seen.add(p["kind"])
        idx = front if key == "u" else pareto_front([p["ms"] for p in points], [p[key] for p in points])
        idx = sorted(idx, key=lambda i: points[i]["ms"])
        fx, fy = [points[i]["ms"] for i in idx], [points[i][key] for i in idx]
        if fx:
            ax.step(fx, fy, where="post", color="k", lw=1, ls="--", label=f"Pareto front (time, {name.split()[0]})")
        ax.set(xscale="log", yscale="log", xlabel="wall time per step / per 0.05 s frame (ms, median, this CPU)",
               ylabel=f"{name} relative L2 error (test, mean over 20 snapshots)")
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xlim(right=4 * max(p["ms"] for p in shown))   # room for the slowest points' labels
    grid = result["grid_step_ms"]
    if grid:
        ymin = min([p["u"] for p in shown] + [1.0])
        axes[0].scatter([v["p50_ms"] for v in grid.values()], [ymin * 0.6] * len(grid), marker="|", color="C0",
                        s=80, label="size grid, time only")
    fig.suptitle(f"Beam, {len(result['test_sims'])} test cases: run time against error")
    handles, labels = axes[0].get_legend_handles_labels()
    h2, l2 = axes[1].get_legend_handles_labels()
    handles += [h for h, l in zip(h2, l2) if l not in labels]
    labels += [l for l in l2 if l not in labels]
    fig.legend(handles, labels, fontsize=8, loc="lower center", ncol=4)
    fig.tight_layout(rect=(0, 0.12, 0.97, 1), w_pad=3)
    fig.canvas.draw()   # labels placed in the final layout's coordinates
    for ax, key in ((axes[0], "u"), (axes[1], "sigma")):
        xy = ax.transData.transform([(p["ms"], p[key]) for p in shown]) * 72.0 / fig.dpi   # points
        for p, (dx, dy) in zip(shown, spread_labels(xy)):
            ax.annotate(p["name"].replace("learned ", "").replace("FEM ", ""), (p["ms"], p[key]), fontsize=6.5,
                        xytext=(dx, dy), textcoords="offset points", ha="left",
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


def findings(pts, shipped) -> list:
    """Sentences computed from the points: what the FEM costs at beam-abaqus's accuracy and in budget."""
    if shipped is None:
        return []
    fem = [p for p in pts if p["kind"].startswith("fem") and np.isfinite(p["u"])]
    out = []
    as_good = [p for p in fem if p["u"] <= shipped["u"]]
    if as_good:
        best = min(as_good, key=lambda p: p["ms"])
        out.append(f"- The cheapest FEM variant at least as accurate in u as beam-abaqus is {best['name']}: "
                   f"{best['ms']:.2f} ms per frame, {best['ms'] / shipped['ms']:.2f}× beam-abaqus's step "
                   f"(u {best['u']:.4f}, σ {best['sigma']:.4f} against {shipped['u']:.4f}, {shipped['sigma']:.4f}).")
    dominating = [p for p in fem if p["ms"] <= shipped["ms"] and all(p[k] < shipped[k] for k in ("u", "v", "sigma"))]
    for p in sorted(dominating, key=lambda p: p["ms"]):
        out.append(f"- {p['name']} beats beam-abaqus in every error at no more time: {p['ms']:.2f} ms per "
                   f"frame ({p['ms'] / shipped['ms']:.2f}× beam-abaqus's step), u {p['u']:.4f}, v {p['v']:.4f}, "
                   f"σ {p['sigma']:.4f} against {shipped['u']:.4f}, {shipped['v']:.4f}, {shipped['sigma']:.4f}.")
    in_budget = [p for p in fem if p["ms"] <= BUDGET_MS[0]]
    if in_budget:
        best = min(in_budget, key=lambda p: p["u"])
        out.append(f"- Within the {BUDGET_MS[0]:g} ms budget the most accurate FEM variant is {best['name']} "
                   f"({best['ms']:.1f} ms): u {best['u']:.4f}, {best['u'] / shipped['u']:.1f}× beam-abaqus's.")
    linear = [p for p in pts if p["kind"] == "fem-linear" and np.isfinite(p["u"])]
    if linear:
        best = min(linear, key=lambda p: p["u"])
        out.append(f"- The FEM's rest linearisation stepped by backward Euler ({best['name']}, {best['ms']:.2f} ms per "
                   f"frame, {shipped['ms'] / best['ms']:.1f}× cheaper than beam-abaqus's step): u {best['u']:.4f}, "
                   f"v {best['v']:.4f}, σ {best['sigma']:.4f} against beam-abaqus's {shipped['u']:.4f}, "
                   f"{shipped['v']:.4f}, {shipped['sigma']:.4f}: beam-abaqus's error is "
                   + ", ".join(f"{shipped[k] / best[k]:.2f}× its {n}" for k, n in (("u", "u"), ("v", "v"),
                                                                                  ("sigma", "σ")))
                   + ". It is the cheapest baseline here (its v suffers from backward Euler at the frame step "
                   "and the frozen rest tangent).")
    demo = next((p for p in pts if p["kind"] == "shipped-linear"), None)
    start = next((p for p in pts if p["name"] == "FEM linearised 20×5×5, 1 solve"), None)
    if demo is not None and start is not None:
        out.append(f"- The demo's beam ({demo['name']}) against the FEM's rest linearisation it was trained from "
                   f"({start['name']}): {demo['ms']:.2f} against {start['ms']:.2f} ms per step (its learned stress "
                   f"map has more blocks), u {demo['u']:.4f} / {start['u']:.4f}, v {demo['v']:.4f} / "
                   f"{start['v']:.4f}, σ {demo['sigma']:.4f} / {start['sigma']:.4f}; against beam-abaqus "
                   f"{shipped['ms'] / demo['ms']:.1f}× faster, u {demo['u'] / shipped['u']:.2f}×, v "
                   f"{demo['v'] / shipped['v']:.1f}×, σ {demo['sigma'] / shipped['sigma']:.2f}× its errors.")
    for p in [shipped] + [q for q in fem if q["kind"] == "fem-newton"]:
        by = p.get("p50_by_xla") or {}
        if len(by) == 2:
            (c1, t1), (c2, t2) = by.items()
            out.append(f"- XLA:CPU configuration, {p['name']}: {c1} {t1:.2f} ms, {c2} {t2:.2f} ms "
                       f"({max(t1, t2) / min(t1, t2):.2f}× in favour of {p['xla']}).")
    bf16 = next((p for p in pts if p["kind"] == "shipped-bf16"), None)
    if bf16 is not None:
        out.append(f"- bfloat16 (weights and activations) on this CPU: {bf16['ms']:.2f} ms against "
                   f"{shipped['ms']:.2f} ms in float32 ({bf16['ms'] / shipped['ms']:.2f}×), u {bf16['u']:.4f} "
                   f"against {shipped['u']:.4f}: no speed gain; the error is unchanged to "
                   f"{abs(bf16['u'] / shipped['u'] - 1) * 100:.1f} %, so it sits on the front only by that margin.")
    return out + [""]


def shipped_verdict(shipped: dict) -> str:
    """Where the shipped default stands on the two fronts, in words."""
    on_u, on_uvs = shipped["on_front"], bool(shipped.get("on_front_uvs"))
    u = "lies on the (time, u) front" if on_u else "does NOT lie on the (time, u) front"
    if on_u == on_uvs:
        return u + (" and on" if on_uvs else " nor on") + " the (time, u, v, σ) front"
    return u + (" but lies on" if on_uvs else " but not on") + " the (time, u, v, σ) front"


def report(result, widths, passes) -> str:
    pts, m = result["points"], result["machine"]
    shipped = next((p for p in pts if p["kind"] == "shipped"), None)
    lines = [
        "# Run time against error: the learned simulator and the FEM (beam, test sims "
        f"{', '.join(map(str, result['test_sims']))})", "",
        f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']} ({m['backend']}), "
        f"XLA_FLAGS=`{result['xla_flags'] or '(unset: multi-threaded)'}`; load average 1/5/15 min at the start "
        f"of the timings {result['load_average_start']}, after the learned steps "
        f"{result.get('load_average_after_learned')}, at the end {result['load_average_end']} (shared machine: "
        "times are upper bounds for an idle one; the load at each FEM timing is in pareto.json). "
        f"Learned steps: median of {result['repeats']} calls after compilation, variants interleaved in blocks of "
        "5 calls (each after an untimed call). "
        "FEM: median wall time of one 0.05 s frame (all sub-steps and the stress recovery) for one case. "
        "Every learned step and every linearised and Newton-CG FEM frame is compiled under two XLA:CPU "
        "configurations, YNNPACK's fusions on (XLA's default) and off (the option the learned real-time loop "
        "runs with), timed interleaved, and its time is the faster (both medians in its notes, ms); the explicit "
        "and the converged implicit FEM runs are timed under the default only.", "",
        "Errors: relative L2 over all 756 nodes per snapshot, mean over snapshots 1..20 and the test cases; "
        "u = q − q0, σ all nodes (clamped face included), the FEM's v = numpy.gradient of its q (the data's "
        "convention).", "",
        "| point | ms / step | × faster than FEM reference | u | v | σ | σ (free nodes) | worst-case u | on front "
        "(time, u) | on front (time, u, v, σ) | notes |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    ref = next((p["ms"] for p in pts if p["kind"] == "fem" and p.get("density_factor") == 1.0
                and p["elements"] == 500), float("nan"))
    for p in sorted(pts, key=lambda p: p["ms"]):
        note = ""
        if p["kind"] == "shipped":
            note = f"{p['hidden']}×{p['passes']}, {p['params']} params, its own {p.get('epochs') or '?'}-epoch budget"
        elif p["kind"] == "shipped-bf16":
            note = "shipped weights + activations bfloat16, state/integrator float32"
        elif p["kind"] == "shipped-fast":
            note = (f"{p['hidden']}×{p['passes']}, {p['params']} params: beam-abaqus with one pass removed "
                    "(scripts/drop_pass.py) and fine-tuned (its card)")
        elif p["kind"] == "shipped-linear":
            note = ("learned linear GENERIC (`tignn_jax.linear_generic`), backward Euler; trained on these data's "
                    "train split from the FEM's rest linearisation; the demo's beam")
        elif p["kind"] == "learned":
            note = f"{p['epochs']} epochs (best val epoch {p['best_epoch']})"
            if p.get("integrator", "euler") != "euler":
                note += f", {p['integrator']} integrator (trained with it; two network evaluations per step)"
        elif p["kind"] == "fem-linear":
            note = f"{p['elements']} hex8, {p['n_sub']} dense solve(s)/frame with the rest tangent"
        elif p["kind"] == "fem-implicit":
            note = (f"{p['elements']} hex8, {p['n_sub']} Newton step(s)/frame, ≤ {p['newton_iterations_max']} "
                    f"iterations, residual ≤ {p['newton_residual_max']:.1e}")
        elif p["kind"] == "fem-newton":
            note = (f"{p['elements']} hex8, backward Euler by {p['newton'][0]} Newton iteration(s) of "
                    f"{p['newton'][1]} CG each, preconditioned with the rest operator turned with the body")
        else:
            note = f"{p['elements']} hex8, {p['n_sub']} sub-steps/frame"
        if p["kind"].startswith("fem"):
            if any(i >= 0 for i in p["inverted"]):
                note += ", element inversion"
        if not np.isfinite(p["u"]):
            note += "; rollout diverged (NaN) on a test case"
        if p.get("p50_by_xla"):
            note += "; XLA " + ", ".join(f"{c} {ms:.2f}" for c, ms in p["p50_by_xla"].items())
        lines.append(f"| {p['name']} | {p['ms']:.2f} | {ref / p['ms']:.0f} | {p['u']:.4f} | {p['v']:.4f} | "
                     f"{p['sigma']:.4f} | {p['sigma_free']:.4f} | {p['u_worst_case']:.4f} | "
                     f"{'**yes**' if p['on_front'] else 'no'} | "
                     f"{'**yes**' if p.get('on_front_uvs') else 'no'} | {note} |")
    lines += ["", "Pareto front in (time, u error; a diverged rollout is never on it): "
              + " → ".join(result["front"]) + ".", ""]
    if result.get("front_uvs"):
        lines += ["Pareto front in (time, u, v, σ errors: not dominated in all four at once): "
                  + " → ".join(result["front_uvs"]) + ".", ""]
    lines += findings(pts, shipped)
    if shipped is not None:
        verdict = shipped_verdict(shipped)
        within = "within" if shipped["ms"] <= BUDGET_MS[0] else "above"
        lines.append(f"The shipped non-linear TIGNN ({SHIPPED}, the demo's `--model {SHIPPED}`, {shipped['ms']:.2f} ms, "
                     f"u {shipped['u']:.4f}) {verdict}; its step is {within} the {BUDGET_MS[0]:g} ms budget of one beam.")
        lines.append("")
    fast = next((p for p in pts if p["kind"] == "shipped-fast"), None)
    if fast is not None:
        within = "within" if fast["ms"] <= BUDGET_MS[0] else "above"
        ratio = f", {shipped['ms'] / fast['ms']:.2f}× faster than {SHIPPED}'s step in this run" if shipped else ""
        lines += [f"The shipped two-pass TIGNN ({SHIPPED_FAST}, {fast['ms']:.2f} ms{ratio}; u {fast['u']:.4f}, "
                  f"v {fast['v']:.4f}, σ {fast['sigma']:.4f}) {shipped_verdict(fast)}; its step is {within} the "
                  f"{BUDGET_MS[0]:g} ms budget of one beam.", ""]
    linear = next((p for p in pts if p["kind"] == "shipped-linear"), None)
    if linear is not None:
        within = "within" if linear["ms"] <= BUDGET_MS[0] else "above"
        lines += [f"The shipped default, the demo's beam ({SHIPPED_LINEAR}, learned linear GENERIC, {linear['ms']:.2f} ms, u "
                  f"{linear['u']:.4f}, v {linear['v']:.4f}, σ {linear['sigma']:.4f}) {shipped_verdict(linear)}; "
                  f"its step is {within} the {BUDGET_MS[0]:g} ms budget of one beam.", ""]
    lines += ["## Step time of the size grid (ms, median; untrained weights time the same as trained ones)", "",
              "| hidden \\ passes | " + " | ".join(map(str, passes)) + " |", "|---" * (len(passes) + 1) + "|"]
    grid = result["grid_step_ms"]
    for h in widths:
        cells = [f"{grid[f'{h}x{p}']['p50_ms']:.2f}" + ("*" if (h, p) in TRAINED else "") for p in passes]
        lines.append(f"| {h} | " + " | ".join(cells) + " |")
    plan = result.get("train_plan")
    shipped_epochs = next((p.get("epochs") for p in result["points"] if p["name"] == SHIPPED), None)
    lines += ["", "\\* trained (errors in the table above); the other grid points have a time only."]
    if plan:
        lines += ["", f"Equal training budget: every trained size ran {plan['epochs']} epochs of the shipped recipe "
                  f"(`train.CONFIGS['beam']`, batch 2, {plan['steps_per_epoch']} steps per epoch, seed 0, cosine "
                  f"schedule over those epochs, best val epoch kept), chosen from the measured per-step training "
                  f"time (s: {json.dumps(plan['train_step_s'])}, load average {plan['load_average_1m']}) to fit "
                  f"{plan['budget_minutes']:g} minutes on one core. The shipped model had {shipped_epochs} epochs: "
                  "a longer budget than the grid, so its advantage in error is partly budget, not size."]
    heun = [p for p in pts if p.get("integrator") == "heun"]
    for p in heun:
        base = next((q for q in pts if q["kind"] == "learned" and q.get("integrator", "euler") == "euler"
                     and (q["hidden"], q["passes"]) == (p["hidden"], p["passes"])), None)
        if base is not None:
            lines += ["", f"Integrator (same size, recipe, seed and epochs; a model is rolled out with the integrator "
                      f"it was trained with): {p['hidden']}×{p['passes']} Heun {p['ms']:.2f} ms per step "
                      f"({p['ms'] / base['ms']:.2f}× forward Euler's {base['ms']:.2f} ms), u {p['u']:.4f}, "
                      f"v {p['v']:.4f}, σ {p['sigma']:.4f} against Euler's {base['u']:.4f}, {base['v']:.4f}, "
                      f"{base['sigma']:.4f}."]
    lines += ["", "Integrators: forward Euler (the paper's) for the size grid, Heun (explicit trapezoidal) for the "
              "sizes in `HEUN`; the W-method of `frame_solve` is measured on the beam only as the rest-linearised "
              "FEM above (with a network on top it is not trained on this data set).", "",
              "FEM variants: mass scaling multiplies the density (the stable sub-step grows with √factor, the "
              "inertia and the damping force α·M·v grow with it, so the dynamics are distorted); coarse meshes are "
              "structured hex8 meshes of the 40×10×10 beam, loads moved to their nodes by trilinear weights "
              "(total force conserved) and results interpolated back to the reference nodes with the same weights. "
              "The rest-linearised FEM (`fem.implicit.rest_linearization`: K₀ and the nodal-stress map S₀ by "
              "`jax.jvp`) steps M Δv/h + αM(v + Δv) + K₀(u + h(v + Δv)) = f with the dense inverse of its matrix, σ "
              "carried by S₀ — the step of a `linear_prior` model with no network; the non-linear backward-Euler FEM "
              "is `fem.implicit` (Newton, CG preconditioned by that inverse), timed as a whole case divided by its "
              "frames; `FEM Newton-CG` is the same backward-Euler frame by a fixed count of Newton iterations from "
              "v' = 0, each by a few CG iterations preconditioned with R A₀⁻¹ Rᵀ (per-node rotations R; "
              "`tignn_jax.newton`, the learned models' fallback step), timed as one step from a mid-case state."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
