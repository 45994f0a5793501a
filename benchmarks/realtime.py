"""The real-time budget: the mixed-reality loop of `tignn demo` over many frames, per stage, on this CPU.

For each scene (one beam, the paper's two beams, the bunny) the loop of ``tignn_jax.scene.run`` plays a
fingertip press track for ``--frames`` frames after ``--warmup`` frames of compilation, with the shipped model
of the scene, rendering at 640x480, in a process set up as ``tignn demo``'s: pinned to ``--cores`` cores
(default 1; ``scene.real_time_cores``; one core against two: ``benchmarks/pinning.py``). Per frame it times:
forces (fingertip unprojection + object contact), step
(the learned simulator for all bodies), render (rasterise + shade + occlude) and the whole frame. The
simulation time per frame is forces + step (once touched, the loop dispatches forces, step and guard together
and awaits them once, `scene.Timings.fused_frames`: the forces time is then inside the step's; the fused loop is
also compared with the stages awaited one by one, `loop_fusion`). Budgets (issue
5): simulation p50 ≤ 9 ms (one beam), ≤ 11 ms (bunny), ≤ 18 ms (two beams), p99 ≤ 1.5 × p50, judged on the
frames the learned step ran in; whole frame p50 ≤ 33 ms (≥ 30 frames per second). Each scene's loop runs
``--rounds`` times (default 3) and the round with the median p99 / p50 is the one judged; every round is
reported beside it. The machine's own tail is measured in the same run on fixed programs of the same duration
(`platform_jitter`) and, after each round, on that round's own step programs called back to back with the same
input (`step_alone`): a loop cannot have a smaller tail than the program it runs. For the scenes whose bodies
have a fallback, a guard trip's hand-over in the same frame and in the next (``Scene.handover``) are compared in
alternating rounds (`handover_modes`). Without ``--model`` the beam scenes run a second time with the shipped network that meets
every accuracy target of the model issue (``ACCURATE_MODELS``: `beam-abaqus-64x2`), as rows "scene (model)":
the demo's default beam (the learned linear `beam`) is the stable one, not the most accurate.

Speed-ups are measured in the same run, as ratios of the step time of each scene's model on its mesh:
  * straightforward: edge list (one row per edge), edge MLP on the concatenated [x_ij, h_j, h_i], scatter-add
    aggregation, two reverse passes for ∇E and ∇S, L and M assembled with 0/1 matmuls (the plain features,
    no edge strain, no coarse level: for a model with more features it is the cheaper reference);
  * max-degree slots: the shipped gather-only layout but with one row of K = max degree slots per node;
  * assembled edge features: the shipped layout, but the edge features assembled per slot (from the factored
    ``model.EdgeInputs``, by a gather and a column add) and multiplied by the first edge layer there;
  * shipped: rows of K slots near the mean degree (`model.topology`), fused first edge layer, one reverse pass,
    features linear in q and v multiplied at node level (``model.EdgeInputs``);
  * as stepped: ``api.stepper``, what the loop runs: the shipped step, except that a model whose network has
    every weight zero (the rest-linearised `bunny-linear`) runs its linearised solve alone.
The three slot variants carry the model's coarse level (``coarse_nodes``) when it has one. A model whose network
is zero (the learned linear GENERIC `beam` and `bunny`) has no network to write differently: its backward-Euler
velocity solve is timed seven ways instead (`linear_variants`: a dense LU solve per step, a Cholesky factor once
with two triangular solves per step, conjugate gradients on the sparse K per step, a product by A⁻¹ computed
once, that product without the one by K (`framesolve.linear_step`) with S as a block list, the same with S row by
row (`framesolve.s_rows_layout`), and the shipped step: the same with A⁻¹ as its upper-triangular blocks,
`framesolve.ainv_blocks`).
A scene whose model is not shipped runs with the labelled stand-in dynamics and is reported as not valid.
Writes benchmarks/results/realtime.{json,md}.

    python benchmarks/realtime.py [--frames 500] [--warmup 20] [--rounds 3] [--scenes beam,two-beams,bunny]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, interleaved_ms  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
BUDGET_MS = {"beam": 9.0, "bunny": 11.0, "two-beams": 18.0}
FRAME_BUDGET_MS = 1e3 / 30


def percentiles(ms) -> dict:
    ms = np.asarray(ms, float)
    return {"p50_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "mean_ms": float(ms.mean())}


def run_scene(name: str, frames: int, warmup: int, devices: tuple = (), model: str | None = None,
              rounds: int = 1) -> dict:
    """The scene's loop, ``rounds`` times ``frames`` frames after ``warmup`` (each round compiles afresh in its
    warm-up). Reported: the round whose simulation p99 / p50 over the learned-step frames is the median of the
    rounds' (the lower median for an even count), with every round's p50 / p99 under "rounds"."""
    from tignn_jax import scene as sc

    scene, dynamics = moving_scene(name, frames + warmup, devices, model)
    played, alone = [], []
    for _ in range(rounds):
        _, t = sc.run(scene, frames=frames + warmup, warmup=warmup)
        summary = t.summary(bodies=len(scene.bodies))
        learned = summary.get("simulation_learned", summary["simulation"])
        played.append((learned["p99_ms"], learned["p50_ms"], t, summary))
        alone.append(step_alone(scene, frames))
    order = sorted(range(rounds), key=lambda i: played[i][0] / played[i][1])   # by p99 / p50, the rule's quantity
    _, _, t, summary = played[order[(rounds - 1) // 2]]
    out = {"dynamics": dynamics, "valid": not dynamics.startswith("STAND-IN"), "frames": summary["frames"],
           "nodes": int(sum(len(b.q0) for b in scene.bodies)),
           "image": [scene.camera.width, scene.camera.height], "reallocations": t.reallocations, "guard_trips": t.guard_trips,
           "fused_frames": t.fused_frames, "learned_frames": summary["learned_frames"],
           "rounds": [{"p50_ms": p50, "p99_ms": p99} for p99, p50, _, _ in played],
           "step_alone": alone, "judged_round": order[(rounds - 1) // 2],
           **{k: summary[k] for k in ("forces", "step", "simulation", "render", "frame")}}
    # the budget is judged on the frames the learned model stepped: frames on the (cheaper) rest-linearised
    # fallback after a guard trip would flatter the median
    out["simulation_learned"] = summary.get("simulation_learned", out["simulation"])
    out["simulation_by_class"] = summary.get("simulation_by_class", {})
    p50, p99 = out["simulation_learned"]["p50_ms"], out["simulation_learned"]["p99_ms"]
    out["budget"] = {"simulation_p50_ms": BUDGET_MS[name], "simulation_p50_ok": p50 <= BUDGET_MS[name],
                     "p99_over_p50": p99 / p50, "p99_ok": p99 <= 1.5 * p50,
                     "frame_p50_ok": out["frame"]["p50_ms"] <= FRAME_BUDGET_MS,
                     "fps_at_p50": 1e3 / out["frame"]["p50_ms"]}
    return out


def step_alone(scene, calls: int) -> dict:
    """The loop's step programs on their own, right after a round: every body's learned step (as the loop
    dispatches it, on its device with ``Scene.devices``; no guard, no render between calls) from the initial
    states under the forces of the track's middle frame (the fingertip pressing), ``calls`` calls back to back,
    each awaited. The same work every call: the tail this machine gives that program, in the same minutes."""
    from tignn_jax import scene as sc

    forces_fn, step_fn, _, _ = sc.build(scene)
    zs = tuple(jnp.asarray(b.z, jnp.float32) for b in scene.bodies)
    if scene.devices:
        zs = tuple(jax.device_put(z, scene.devices[0]) for z in zs)
    forces = jax.block_until_ready(forces_fn(zs, jnp.asarray(scene.track[len(scene.track) // 2])))
    for _ in range(4):   # and interleaved_ms' own first call: 5 untimed
        jax.block_until_ready(step_fn(zs, forces))
    out = percentiles(interleaved_ms({"step": lambda: step_fn(zs, forces)}, calls)["step"])
    out["p99_over_p50"] = out["p99_ms"] / out["p50_ms"]
    return out


def moving_scene(name: str, frames: int, devices: tuple = (), model: str | None = None):
    """(scene, dynamics) of ``tignn demo``'s scene ``name`` for ``frames`` frames, every frame stepped (no rest
    skip): the budget is for a body in motion."""
    from tignn_jax.commands_demo import build_scene

    scene, dynamics = build_scene(name, frames, model, devices=devices)
    return scene._replace(skip_rest=False), dynamics


def alternating_rounds(name: str, frames: int, warmup: int, devices: tuple, rounds: int, model: str | None,
                       variants: dict) -> dict:
    """{label: [(Timings, summary)] per round}: the scene's loop with each of ``variants`` ({label: Scene fields
    to replace}), alternating for ``rounds`` rounds of ``frames`` frames after ``warmup`` in this process, so a
    change of the machine's load hits every variant alike (summaries split by body count)."""
    from tignn_jax import scene as sc

    scene, _ = moving_scene(name, frames + warmup, devices, model)
    played = {k: [] for k in variants}
    for _ in range(rounds):
        for label, fields in variants.items():
            _, t = sc.run(scene._replace(**fields), frames=frames + warmup, warmup=warmup)
            played[label].append((t, t.summary(bodies=len(scene.bodies))))
    return played


def loop_fusion(name: str, frames: int, warmup: int, devices: tuple, rounds: int, model: str | None = None) -> dict:
    """The scene's loop with its simulation stages fused (``Scene.fuse``: forces, step and guard dispatched
    together and awaited once; with ``devices`` each body's guard and hand-over in its step's program, and a body
    on its fallback stepped by the fallback alone) against the stages
    dispatched and awaited one by one, alternating for ``rounds`` rounds of ``frames`` frames each. Simulation
    p50 / p99 over the learned-step frames per run, and the ratio of the two variants' medians over the rounds."""
    played = alternating_rounds(name, frames, warmup, devices, rounds, model,
                                {"staged": {"fuse": False}, "fused": {"fuse": True}})
    runs = {k: [summary.get("simulation_learned", summary["simulation"]) for _, summary in v]
            for k, v in played.items()}
    p50 = {k: float(np.median([r["p50_ms"] for r in v])) for k, v in runs.items()}
    return {"frames": frames, "rounds": rounds, "runs": runs, "p50_ms": p50,
            "p99_ms": {k: float(np.median([r["p99_ms"] for r in v])) for k, v in runs.items()},
            "speedup_fused_vs_staged": p50["staged"] / p50["fused"]}


def handover_modes(name: str, frames: int, warmup: int, devices: tuple, rounds: int, model: str) -> dict:
    """The scene's loop with a guard trip's hand-over in the frame of the trip (``Scene.handover="same-frame"``:
    that frame runs the learned step and the fallback step) against the next frame (``"next-frame"``, the demo's:
    the trip frame shows the previous state, the next runs the fallback twice), alternating for ``rounds`` rounds
    in the same process. Per mode, the median over the rounds of the simulation p50 / p99 over the learned-step
    frames and of the hand-over frames'."""
    played = alternating_rounds(name, frames, warmup, devices, rounds, model,
                                {mode: {"handover": mode} for mode in ("same-frame", "next-frame")})
    runs = {mode: [{"learned": summary.get("simulation_learned", summary["simulation"]),
                    "hand-over": summary.get("simulation_by_class", {}).get("hand-over"),
                    "guard_trips": t.guard_trips} for t, summary in v] for mode, v in played.items()}

    def median(mode, part, key):
        values = [r[part][key] for r in runs[mode] if r[part] is not None]
        return float(np.median(values)) if values else None

    out = {"frames": frames, "rounds": rounds, "runs": runs}
    for part in ("learned", "hand-over"):
        out[part] = {mode: {k: median(mode, part, k) for k in ("p50_ms", "p99_ms")} for mode in runs}
    return out


def step_variants(name: str, repeats: int, model: str | None = None) -> dict:
    """Median step time of the scene's model (``model``, default the scene's shipped one) written four ways (see
    the module docstring); for a model whose network is zero, its backward-Euler step written seven ways
    (`linear_variants`)."""
    from model_step import EdgeListNetwork, assembled_step, edge_list_features, edge_list_rates

    from tignn_jax import api
    from tignn_jax import model as M
    from tignn_jax.commands_demo import DEFAULT_MODELS

    model = model or DEFAULT_MODELS[name]
    params, graph = api.load_pretrained(model)
    if api.network_is_zero(params):
        return linear_variants(params, model, repeats)
    copies = 2 if name == "two-beams" else 1
    cfg, norm, w = api._config(params), params["norm"], params["weights"]
    mesh = params["mesh"]
    n = len(mesh["node_type"])
    s = np.concatenate([mesh["senders"] + i * n for i in range(copies)])
    r = np.concatenate([mesh["receivers"] + i * n for i in range(copies)])
    q0 = np.tile(mesh["q0"], (copies, 1))
    nt = jnp.tile(jnp.asarray(mesh["node_type"], jnp.int32), copies)
    rng = np.random.default_rng(0)
    z = jnp.asarray(np.concatenate([q0 + 0.01 * rng.normal(size=q0.shape), 0.01 * rng.normal(size=(len(q0), 9))],
                                   axis=1), jnp.float32)
    f = jnp.asarray(0.01 * rng.normal(size=(len(q0), 3)), jnp.float32)
    coarse = M.tile_topology(params["topo"], copies).coarse   # a coarse level's clusters, per body (or None)
    rows = M.topology(s, r, len(q0), q0)._replace(coarse=coarse)
    slots = M.topology(s, r, len(q0), q0, slots=int(np.bincount(r).max()))._replace(coarse=coarse)
    x_node, x_edge = edge_list_features(norm, z, f, nt, jnp.asarray(s), jnp.asarray(r))
    plain_cfg = cfg._replace(edge_strain=False)
    w_edge = EdgeListNetwork(plain_cfg).init(jax.random.PRNGKey(0), x_node, x_edge, s, r)["params"]
    fns = {
        # (M.increment: dw · s, or the frame_solve step with the model's solve and prior, the same in all four)
        "straightforward (edge list)": jax.jit(lambda z, f: z + M.increment(cfg, norm, edge_list_rates(
            w_edge, plain_cfg, norm, z, f, nt, jnp.asarray(s), jnp.asarray(r))[0], z, f, nt, rows)),
        "max-degree slots": jax.jit(lambda z, f: M.step_state(w, cfg, norm, z, f, nt, slots)),
        "assembled edge features": assembled_step(w, cfg, norm, nt, rows),
        "shipped (rows)": jax.jit(lambda z, f: M.step_state(w, cfg, norm, z, f, nt, rows)),
        # what the loop runs: the shipped step, or for a model whose network is all zero its solve alone
        "as stepped (api.stepper)": api.stepper(params, copies),
    }
    times = interleaved_ms({k: (lambda fn=fn: fn(z, f)) for k, fn in fns.items()}, repeats)
    out = {k: float(np.median(v)) for k, v in times.items()}
    base = out["straightforward (edge list)"]
    return {"step_p50_ms": out, "speedup_vs_straightforward": {k: base / v for k, v in out.items()},
            "slots": {"max-degree": list(slots.nbr.shape), "rows": list(rows.nbr.shape), "edges": int(len(s))},
            "model": model, "hidden": cfg.hidden, "passes": cfg.passes}


# the beam scenes again with the shipped network that meets every accuracy target of the model issue (the demo's
# default beam, the learned linear `beam`, is stable without a guard but misses the published q and v errors)
ACCURATE_MODELS = {"beam": "beam-abaqus-64x2", "two-beams": "beam-abaqus-64x2"}
LINEAR_VARIANTS = ("dense LU solve per step (straightforward)", "Cholesky factor once, two triangular solves",
                   "conjugate gradients per step (sparse K, Jacobi, tol 1e-6)", "A⁻¹ once, one product, K product",
                   "A⁻¹ once, one product, K eliminated, S as a block list",
                   "A⁻¹ once, one product, K eliminated, S row by row",
                   "shipped: K eliminated, S row by row, A⁻¹ as symmetric blocks where ≥ 32 MB (the bunny's)")


def linear_variants(params: dict, model: str, repeats: int) -> dict:
    """One body's step of a model whose network is zero (the learned linear GENERIC `beam` and `bunny`, the
    rest-linearised FEM): the backward-Euler step (M(1 + αΔt)/Δt² + K) Δv = r solved seven ways, everything else
    the same (`framesolve.prior_step`, with a product by K for the right-hand side): a dense LU factorisation
    and solve every step (what a plain ``jnp.linalg.solve`` does); the Cholesky factor computed once, two
    triangular solves per step; conjugate gradients on the sparse K per step (Jacobi preconditioner, relative
    tolerance 1e-6); one product by A⁻¹ computed once; and the shipped ``api.stepper``, which also multiplies by
    A⁻¹ but needs no product by K (`framesolve.linear_step`: A⁻¹K = I − c A⁻¹M) and applies S row by row
    (`framesolve.s_rows_layout`), and the same step with S as its block list (gather, product, segment sum);
    the shipped step multiplies by A⁻¹'s upper-triangular blocks where A⁻¹ has at least
    `framesolve.AINV_BLOCK_MIN_BYTES` (`framesolve.ainv_blocks`: the bunny's, not the beam's), so its dense-product
    twin is timed beside it. Raises RuntimeError if a
    variant's state differs from the shipped step's by more than 1e-2 of its largest increment (float32)."""
    from jax.scipy.linalg import cho_solve
    from jax.scipy.sparse.linalg import cg

    from tignn_jax import api
    from tignn_jax import framesolve as FS

    mesh = params["mesh"]
    nt = np.asarray(mesh["node_type"], np.int32)
    n = len(nt)
    A = FS.operator(params["norm"], nt)
    norm = {k: jnp.asarray(v) for k, v in FS.with_inverse(params["norm"], nt).items()}
    q0, node_type = jnp.asarray(mesh["q0"], jnp.float32), jnp.asarray(nt)
    free = jnp.asarray(np.repeat(nt == 0, 3), jnp.float32)
    a32 = jnp.asarray(A, jnp.float32)
    chol = jnp.asarray(np.linalg.cholesky(A), jnp.float32)
    diag = jnp.asarray(np.diag(A), jnp.float32)
    h, alpha = float(np.asarray(norm["dt"]).reshape(-1)[0]), float(np.asarray(norm["fs_alpha"]).reshape(-1)[0])
    mass = jnp.repeat(jnp.asarray(norm["fs_mass"], jnp.float32), 3) * (1.0 + alpha * h) / h ** 2

    def apply_a(x):   # A x without forming A: K on the free nodes, the identity on the clamped ones
        kx = FS.apply_k(norm, (x * free).reshape(-1, 3)).reshape(-1)
        return (kx + mass * x) * free + x * (1.0 - free)

    solves = {
        LINEAR_VARIANTS[0]: lambda r: jnp.linalg.solve(a32, r),
        LINEAR_VARIANTS[1]: lambda r: cho_solve((chol, True), r),
        LINEAR_VARIANTS[2]: lambda r: cg(apply_a, r, tol=1e-6, M=lambda x: x / diag)[0],
        LINEAR_VARIANTS[3]: lambda r: norm["fs_ainv"] @ r,   # one dense product
    }
    fns = {k: jax.jit(lambda z, f, solve=solve: z + FS.prior_step(norm, z, f, jnp.zeros_like(z), node_type, q0,
                                                                solve_a=solve))
           for k, solve in solves.items()}
    dense = {k: v for k, v in norm.items() if k not in FS.AINV_BLOCK_KEYS}   # one dense product by A⁻¹
    listed = {k: v for k, v in dense.items() if k not in FS.S_ROW_KEYS}     # and S₀ by segment sum
    fns[LINEAR_VARIANTS[4]] = jax.jit(lambda z, f: z + FS.linear_step(listed, z, f, node_type, q0))
    fns[LINEAR_VARIANTS[5]] = jax.jit(lambda z, f: z + FS.linear_step(dense, z, f, node_type, q0))
    fns[LINEAR_VARIANTS[6]] = api.stepper(params)
    rng = np.random.default_rng(0)
    z = jnp.asarray(np.concatenate([np.asarray(mesh["q0"]) + 0.01 * rng.normal(size=(n, 3)),
                                    0.01 * rng.normal(size=(n, 9))], axis=1), jnp.float32)
    f = jnp.asarray(0.01 * rng.normal(size=(n, 3)), jnp.float32)
    ref = np.asarray(fns[LINEAR_VARIANTS[6]](z, f))
    diffs = {}
    for k, fn in fns.items():
        diffs[k] = float(np.abs(np.asarray(fn(z, f)) - ref).max() / np.abs(ref - np.asarray(z)).max())
        if not diffs[k] <= 1e-2:
            raise RuntimeError(f"{k}: the step differs from the shipped one by {diffs[k]:.2e} of the increment")
    times = interleaved_ms({k: (lambda fn=fn: fn(z, f)) for k, fn in fns.items()}, repeats)
    out = {k: float(np.median(v)) for k, v in times.items()}
    base = out[LINEAR_VARIANTS[0]]
    return {"kind": "linear", "model": model, "dofs": 3 * n, "step_p50_ms": out, "max_difference": diffs,
            "speedup_vs_straightforward": {k: base / v for k, v in out.items()}}


def concurrency(name: str, repeats: int, devices: tuple, model: str | None = None) -> dict:
    """Step time of the scene's bodies (two copies of its model's mesh), interleaved: the layouts of
    `bodies_one_program.two_bodies` (one body alone; two plain steps in one program; each in its own ``lax.cond``,
    what the loop runs without devices; one graph of both; one after another, ``stepper(params, 2)``'s CPU
    default) and each body on its own CPU device, dispatched together (``Scene.devices``: concurrent, one core
    each)."""
    from bodies_one_program import two_bodies

    from tignn_jax import api
    from tignn_jax.commands_demo import DEFAULT_MODELS

    model = model or DEFAULT_MODELS[name]
    params, _ = api.load_pretrained(model)
    if api._config(params).frame_solve:   # one body per stepper (its A₀⁻¹ is one body's): no graph of both
        z, f, fns = _two_solve_bodies(params)
        base = "two plain steps in one program"
    else:
        z, f, fns = two_bodies(params)
        base = "one graph of both"
    if len(devices) > 1:
        one = api.stepper(params)
        placed = [(jax.device_put(z, d), jax.device_put(f, d)) for d in devices[:2]]
        fns["two bodies on two devices (concurrent)"] = lambda: [one(a, b) for a, b in placed]
    times = interleaved_ms(fns, repeats)
    p50 = {k: float(np.median(v)) for k, v in times.items()}
    return {"model": model, "devices": len(devices), "step_p50_ms": p50, "base": base,
            "step_p99_ms": {k: float(np.percentile(v, 99)) for k, v in times.items()},
            "speedup_vs_batched": {k: p50[base] / v for k, v in p50.items()}}


def _two_solve_bodies(params):
    """(z, f, layouts) as `bodies_one_program.two_bodies` for a model that steps one body per call: one body, two
    plain steps in one program, each in its own ``lax.cond`` (what the loop runs without devices)."""
    from tignn_jax import api

    rng = np.random.default_rng(0)
    n = len(params["mesh"]["node_type"])
    z = jnp.asarray(np.concatenate([np.asarray(params["mesh"]["q0"]), 0.01 * rng.normal(size=(n, 9))], 1),
                    jnp.float32)
    f = jnp.asarray(0.01 * rng.normal(size=(n, 3)), jnp.float32)
    one = api.stepper(params)
    keep = lambda z_, f_: z_   # noqa: E731 (the branch not taken)
    plain = jax.jit(lambda za, zb, fa, fb: (one(za, fa), one(zb, fb)))
    in_cond = jax.jit(lambda za, zb, fa, fb, on: (jax.lax.cond(on, keep, one, za, fa),
                                                  jax.lax.cond(on, keep, one, zb, fb)))
    return z, f, {"one body": lambda: one(z, f), "two plain steps in one program": lambda: plain(z, z, f, f),
                  "two steps, each in a lax.cond": lambda: in_cond(z, z, f, f, False)}


# the bunny runs of session 10: traction, port and load-context features, 16 clusters with dense mixing, rest shift
SESSION10_BUNNY = dict(edge_traction=True, force_port=True, load_context=True, coarse_nodes=16, coarse_passes=1,
                       coarse_mixing=True, rest_equilibrium=True)


def unit_statistics(*extra: str) -> dict:
    """Normalisation statistics of an untrained model for timing (every scale 1): the keys a model needs, plus
    ``extra`` one-element keys (e.g. "port_gain", "spring_k" for the port options)."""
    sizes = (("z_mean", 12), ("z_std", 12), ("dz_std", 12), ("f_std", 3), ("dq_std", 3), ("dv_std", 3),
             ("du_std", 3), ("u_std", 3), ("x0_mean", 3), ("x0_std", 3), ("dqn_mean", 1), ("dqn_std", 1))
    return {k: jnp.ones(d, jnp.float32) for k, d in sizes + tuple((k, 1) for k in extra)}


def untrained_step(name: str, repeats: int, sizes=((16, 3), (24, 3))) -> dict:
    """Step time of untrained models of the given sizes on a scene's mesh, for scenes without a shipped model
    (the cost a trained model of that size would have; its weights do not change the time), with the features
    of the scene's training config, written the shipped way and with assembled edge features (interleaved)."""
    from fem import scenes as fs
    from model_step import assembled_step

    from tignn_jax import model as M
    from tignn_jax import train as T

    scene = fs.bunny_scene() if name == "bunny" else fs.beam_scene()
    q0 = np.asarray(scene.points, np.float32)
    n = len(q0)
    s, r = scene.edges
    rng = np.random.default_rng(0)
    z = jnp.asarray(np.concatenate([q0, 0.01 * rng.normal(size=(n, 9))], 1), jnp.float32)
    f = jnp.zeros((n, 3), jnp.float32)
    norm = unit_statistics()
    nt = jnp.asarray(scene.node_type, jnp.int32)
    topo = M.topology(s, r, n, q0)
    base = T.CONFIGS.get(name, T.CONFIGS["beam"]).model._replace(edge_strain=True)
    fns = {}
    for hid, passes in sizes:
        cfg = base._replace(hidden=hid, passes=passes)
        w = M.init_weights(jax.random.PRNGKey(0), cfg, norm, z, f, nt, topo)
        fns[f"{hid}x{passes}"] = jax.jit(lambda z, f, w=w, cfg=cfg: M.step_state(w, cfg, norm, z, f, nt, topo))
        fns[f"{hid}x{passes} assembled"] = assembled_step(w, cfg, norm, nt, topo)
    if name == "bunny":   # the architecture of the session-10 bunny runs (README): 16x3 + coarse level
        cfg = base._replace(hidden=16, passes=3, **SESSION10_BUNNY)
        topo_c = M.model_topology(cfg, s, r, n, q0)
        w = M.init_weights(jax.random.PRNGKey(0), cfg, norm, z, f, nt, topo_c)
        norm_c = M.with_rest(w, cfg, norm, nt, topo_c)
        fns["16x3 coarse (session 10)"] = jax.jit(lambda z, f: M.step_state(w, cfg, norm_c, z, f, nt, topo_c))
    times = interleaved_ms({k: (lambda fn=fn: fn(z, f)) for k, fn in fns.items()}, repeats)
    features = {k: getattr(base, k) for k in ("edge_velocity", "edge_strain", "node_position")}
    return {"nodes": n, "slots": list(topo.nbr.shape), "features": features,
            "step_p50_ms": {k: float(np.median(v)) for k, v in times.items()}}


def platform_jitter(target_ms: float, calls: int = 500) -> dict:
    """p50, p99 and their ratio for fixed programs of about ``target_ms`` that do the same work every call, timed
    like the loop's stages: a jitted XLA program (dense 420×420 products and tanh in a loop, XLA's threads on
    all cores; its data fit in the cores' caches), an element-wise numpy loop (tanh over 420×420, which numpy
    runs on one thread) and a jitted XLA loop of products of a 3000×3000 float32 matrix (36 MB) with a vector,
    bound by memory traffic like a linear model's product with A⁻¹ (the beam's is 21 MB, the bunny's 64 MB).
    Their p99/p50 is the tail the machine itself gives a program of that duration and kind."""
    import time

    a = np.random.default_rng(0).normal(size=(420, 420)).astype(np.float32)

    def xla_program(n):
        fn = jax.jit(lambda x: jax.lax.fori_loop(0, n, lambda i, y: jnp.tanh(y @ x * 1e-3), x))
        xa = jnp.asarray(a)
        return lambda: fn(xa).block_until_ready()

    big = jnp.asarray(np.random.default_rng(1).normal(size=(3000, 3000)).astype(np.float32) / 3000 ** 0.5)

    def xla_matvec_program(n):   # products with a 36 MB matrix: memory-bound, like a linear model's A⁻¹ product
        fn = jax.jit(lambda m, y: jax.lax.fori_loop(0, n, lambda i, y: jnp.tanh(m @ y), y))
        y0 = jnp.ones(3000, jnp.float32)
        return lambda: fn(big, y0).block_until_ready()

    def numpy_program(n):   # element-wise only: no BLAS call, so no thread pool
        def fn():
            x = a
            for _ in range(n):
                x = np.tanh(x * 0.999 + 1e-3)
            return x
        return fn

    out = {}
    for name, make in (("XLA, all cores", xla_program), ("numpy element-wise, one thread", numpy_program),
                       ("XLA matrix-vector products over 36 MB, memory-bound", xla_matvec_program)):
        probe = make(4)
        probe()
        t0 = time.perf_counter()
        for _ in range(5):
            probe()
        per_iteration = 1e3 * (time.perf_counter() - t0) / 20
        n = max(1, round(target_ms / per_iteration))
        fn = make(n)
        fn()
        ms = []
        for _ in range(calls):
            t0 = time.perf_counter()
            fn()
            ms.append(1e3 * (time.perf_counter() - t0))
        p = percentiles(ms)
        out[name] = {**p, "iterations": n, "p99_over_p50": p["p99_ms"] / p["p50_ms"]}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=500, help="timed frames per scene (default: %(default)s)")
    parser.add_argument("--warmup", type=int, default=20, help="untimed first frames (default: %(default)s)")
    parser.add_argument("--scenes", default="beam,two-beams,bunny")
    parser.add_argument("--rounds", type=int, default=3,
                        help="runs of each scene's loop; the one with the median simulation p99 / p50 is reported, every "
                             "round's p50 / p99 beside it (default: %(default)s)")
    parser.add_argument("--variant-repeats", type=int, default=60, help="calls per step variant")
    parser.add_argument("--fusion-rounds", type=int, default=2,
                        help="rounds of the fused-against-staged loop comparison per scene (0: skip it)")
    parser.add_argument("--fusion-frames", type=int, default=200, help="timed frames per run of that comparison")
    parser.add_argument("--handover-rounds", type=int, default=2,
                        help="rounds of the same-frame against next-frame hand-over comparison, for the scenes "
                             "with a fallback (the ACCURATE_MODELS rows; 0: skip it)")
    parser.add_argument("--cores", type=int, default=1,
                        help="cores the process runs on, as `tignn demo --cores`: pinned to that many of the CPUs it "
                             "may use (scene.pin_cores), one CPU device per core, one body per device "
                             "(default: %(default)s, the demo's)")
    parser.add_argument("--model", default=None,
                        help="the dynamics of every scene, as `tignn demo --model` (default: each scene's shipped "
                             "model); 'fem-newton' runs the FEM's Newton-CG step (not learned), without the "
                             "learned loop's XLA:CPU option, and skips the learned step's variants")
    parser.add_argument("--tag", default="", help="results go to realtime_TAG.{json,md} (default: realtime.*)")
    parser.add_argument("--accurate", action=argparse.BooleanOptionalAction, default=True,
                        help="without --model, also run the beam scenes with the shipped network that meets every "
                             "accuracy target (ACCURATE_MODELS), as rows 'scene (model)' (default: on)")
    args = parser.parse_args(argv)
    if args.frames < 10 or args.warmup < 1 or args.rounds < 1:
        raise SystemExit(f"--frames must be ≥ 10, --warmup ≥ 1 and --rounds ≥ 1, got {args.frames}, {args.warmup} "
                         f"and {args.rounds}")
    from tignn_jax import scene as sc
    from tignn_jax.commands_demo import FEM_NEWTON
    fem = args.model == FEM_NEWTON
    if args.cores < 1:
        raise SystemExit(f"--cores must be at least 1, got {args.cores}")
    flagged = False if fem else sc.real_time_xla_flags()   # before JAX's first operation, as `tignn demo` does
    try:
        pinned, devices = sc.real_time_cores(args.cores)   # likewise: pinned, one CPU device per core
    except ValueError as e:
        raise SystemExit(f"--cores {args.cores}: {e}")
    machine = describe()
    machine["cpu_devices"] = len(devices)
    machine["pinned_cpus"] = list(pinned)
    machine["xla_flags"] = os.environ.get("XLA_FLAGS", "") + (
        " (fem-newton: the learned loop's YNNPACK option left unset)" if fem else "" if flagged else " (set by the user)")
    scenes, variants, parallel, fusion, handovers = {}, {}, {}, {}, {}
    requested = [s for s in args.scenes.split(",") if s]
    for name in requested:
        if name not in BUDGET_MS:
            raise SystemExit(f"unknown scene {name!r}; choose from {sorted(BUDGET_MS)}")
        print(f"scene {name}: {args.frames} frames after {args.warmup} warm-up frames ...", flush=True)
        scenes[name] = run_scene(name, args.frames, args.warmup, devices, args.model, args.rounds)
        if scenes[name]["valid"] and not fem:
            variants[name] = step_variants(name, args.variant_repeats, args.model)
            if name == "two-beams":
                parallel[name] = concurrency(name, args.variant_repeats, devices, args.model)
            if args.fusion_rounds > 0:
                print(f"scene {name}: fused against staged loop, {args.fusion_rounds} rounds ...", flush=True)
                fusion[name] = loop_fusion(name, args.fusion_frames, args.warmup, devices, args.fusion_rounds,
                                           args.model)
        elif not scenes[name]["valid"]:
            scenes[name]["untrained_model_step"] = untrained_step(name, args.variant_repeats)
    if args.accurate and args.model is None:
        for name in [s for s in requested if s in ACCURATE_MODELS]:
            model = ACCURATE_MODELS[name]
            print(f"scene {name} with {model}: {args.frames} frames after {args.warmup} warm-up frames ...", flush=True)
            scenes[f"{name} ({model})"] = run_scene(name, args.frames, args.warmup, devices, model, args.rounds)
            if args.handover_rounds > 0 and scenes[f"{name} ({model})"]["guard_trips"]:
                print(f"scene {name} with {model}: hand-over modes, {args.handover_rounds} rounds ...", flush=True)
                handovers[f"{name} ({model})"] = handover_modes(name, args.frames, args.warmup, devices,
                                                                args.handover_rounds, model)
    target = float(np.median([s["simulation_learned"]["p50_ms"] for s in scenes.values()])) if scenes else 8.0
    print(f"platform tail: fixed programs of about {target:.1f} ms ...", flush=True)
    jitter = platform_jitter(target, calls=args.frames)
    machine["load_average_1m_at_end"] = describe()["load_average_1m"]
    result = {"platform_jitter": jitter, "machine": machine, "frames": args.frames, "warmup": args.warmup,
              "rounds": args.rounds, "scenes": scenes,
              "step_variants": variants, "concurrency": parallel, "loop_fusion": fusion, "handover_modes": handovers, "budgets_ms": {"simulation_p50": BUDGET_MS, "frame_p50": FRAME_BUDGET_MS}}
    RESULTS.mkdir(parents=True, exist_ok=True)
    result["model"] = args.model
    stem = f"realtime_{args.tag}" if args.tag else "realtime"
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=1))
    md = format_md(result)
    (RESULTS / f"{stem}.md").write_text(md)
    print(md)
    return 0


def forces_cell(s: dict) -> str:
    """The forces stage's p50, or where most frames ran forces, step and guard fused (``Timings.fused_frames``)
    a note that it is inside the step's time."""
    fused = s.get("fused_frames", 0)
    if 2 * fused > s["frames"]:
        return f"in step ({fused}/{s['frames']} frames fused)"
    return f"{s['forces']['p50_ms']:.2f}"


def format_md(result: dict) -> str:
    m = result["machine"]
    lines = ["# Real-time budget: the mixed-reality loop per frame", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']} ({m['backend']}); load average "
             f"{m['load_average_1m']} at start, {m['load_average_1m_at_end']} at end ({m['note']}). "
             f"{result['frames']} timed frames per scene and round after {result['warmup']} warm-up frames, "
             f"{result.get('rounds', 1)} round(s); 640×480; "
             f"XLA_FLAGS `{m.get('xla_flags', '(not recorded)')}` (`scene.real_time_xla_flags`, as `tignn demo`); "
             + (f"the process pinned to CPU {', '.join(map(str, m['pinned_cpus']))} of {m['cores']} with "
                f"{m['cpu_devices']} CPU device(s) (`scene.pin_cores`, as `tignn demo --cores "
                f"{len(m['pinned_cpus'])}`; one core against two: `pinning.md`)."
                if m.get("pinned_cpus") else f"not pinned, {m.get('cpu_devices', '?')} CPU device(s)."), "",
             "Simulation = forces + step per frame. The budget is judged on the frames the learned model stepped "
             "(after a guard trip a body spends `fallback_hold` frames on the cheaper rest-linearised fallback; "
             "all frames are in the next column)." + (
                 " Rows 'scene (model)' run that scene with the shipped network that meets every accuracy target of "
                 "the model issue (`ACCURATE_MODELS`); the demo's default beam, the learned linear `beam`, is stable "
                 "without a guard but misses the published q and v errors." if any("(" in n for n in result["scenes"])
                 else ""), "",
             "| scene | dynamics | nodes | forces p50 | step p50 | simulation p50 / p99, learned-step frames "
             "(budget) | simulation p50 / p99, all frames | render p50 | frame p50 / p99 | fps | guard trips | "
             "verdict |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in result["scenes"].items():
        b = s["budget"]
        ok = s["valid"] and b["simulation_p50_ok"] and b["p99_ok"] and b["frame_p50_ok"]
        why = [w for w, c in (("sim p50", b["simulation_p50_ok"]), ("p99 > 1.5·p50", b["p99_ok"]),
                              ("frame", b["frame_p50_ok"])) if not c]
        learned = s.get("simulation_learned", s["simulation"])
        verdict = "meets" if ok else ("STAND-IN, not valid" if not s["valid"] else "misses: " + ", ".join(why))
        if s["valid"] and not b["p99_ok"] and s.get("step_alone") and s.get("judged_round") is not None:
            verdict += f" (its step alone, same round: {s['step_alone'][s['judged_round']]['p99_over_p50']:.2f}×)"
        lines.append(
            f"| {name} | {s['dynamics']} | {s['nodes']} | {forces_cell(s)} | {s['step']['p50_ms']:.2f} | "
            f"{learned['p50_ms']:.2f} / {learned['p99_ms']:.2f} ({b['simulation_p50_ms']:.0f}; "
            f"{s.get('learned_frames', s['frames'])} frames) | "
            f"{s['simulation']['p50_ms']:.2f} / {s['simulation']['p99_ms']:.2f} | "
            f"{s['render']['p50_ms']:.2f} | {s['frame']['p50_ms']:.2f} / {s['frame']['p99_ms']:.2f} | "
            f"{b['fps_at_p50']:.1f} | {s.get('guard_trips', '—')} | {verdict} |")
    if any(len(s.get("rounds", [])) > 1 for s in result["scenes"].values()):
        lines += ["", "Each scene's loop ran several rounds of the same frames (each compiled afresh); the table shows "
                  "the round with the median simulation p99 / p50 over the learned-step frames. Every round, simulation "
                  "p50 / p99 (ms, learned-step frames):", ""] + [
            f"- {n}: " + "; ".join(f"{r['p50_ms']:.2f} / {r['p99_ms']:.2f} ({r['p99_ms'] / r['p50_ms']:.2f}×)"
                                  for r in s["rounds"]) for n, s in result["scenes"].items() if s.get("rounds")]
    split = {n: s["simulation_by_class"] for n, s in result["scenes"].items() if len(s.get("simulation_by_class", {})) > 1}
    if split:
        lines += ["", "The learned-step frames by what the bodies did in them (simulation p50 / p99, frames): the "
                  "verdict above is on all of them together; this shows what their mix is made of."] + [""] + [
            f"- {n}: " + "; ".join(f"{k} {v['p50_ms']:.2f} / {v['p99_ms']:.2f} ms ({v['frames']})" for k, v in c.items())
            for n, c in split.items()]
    alone = {n: s for n, s in result["scenes"].items() if s.get("step_alone")}
    if alone:
        lines += ["", "Each round's step programs alone, timed right after it (`step_alone`: the bodies' learned steps as "
                  "the loop dispatches them, the same input every call, no guard or render between calls, as many calls "
                  "as frames), p50 / p99 ms; the judged round in bold:", ""] + [
            f"- {n}: " + "; ".join(("**{}**" if i == s.get("judged_round") else "{}").format(
                f"{a['p50_ms']:.2f} / {a['p99_ms']:.2f} ({a['p99_over_p50']:.2f}×)")
                for i, a in enumerate(s["step_alone"])) for n, s in alone.items()]
    if "platform_jitter" in result:
        lines += ["", "The machine's own tail, same run: fixed programs that do the same work every call, timed "
                  f"{result['frames']} times like the loop's stages (`platform_jitter`): " +
                  ", ".join(f"{k} p50 {v['p50_ms']:.2f} ms, p99 {v['p99_ms']:.2f} ms (p99/p50 "
                            f"{v['p99_over_p50']:.2f})" for k, v in result["platform_jitter"].items()) +
                  ". That is the tail this machine gives a program whose work does not vary at all; the 1.5 × p50 "
                  "rule cannot be judged finer than it."]
    for name, sc_ in result["scenes"].items():
        if "untrained_model_step" in sc_:
            u = sc_["untrained_model_step"]
            lines += ["", f"{name}: no shipped model; step time of untrained models on its mesh "
                      f"({u['nodes']} nodes, rows × slots {u['slots']}, features {u.get('features', {})}; "
                      "'assembled' = the edge features assembled per slot from the factored ones, then the dense first layer): " +
                      ", ".join(f"{k} {v:.2f} ms" for k, v in u["step_p50_ms"].items()) +
                      f" (budget {result['budgets_ms']['simulation_p50'][name]:.0f} ms)."]
    linear = {k: v for k, v in result["step_variants"].items() if v.get("kind") == "linear"}
    if linear:
        lines += ["", "Step time of each scene's model whose network is zero (a linear GENERIC model stepped by "
                  "backward Euler), its step written seven ways, one body (median of interleaved calls, "
                  "same run; `linear_variants`; in brackets the speed-up over the first; every variant's step checked "
                  "against the shipped one's: the largest difference, relative to the step's largest increment, is "
                  "in the last column, float32 rounding):", "",
                  "| scene | model | DOFs | " + " | ".join(LINEAR_VARIANTS) + " | speed-up, shipped vs straightforward "
                  "| largest difference from the shipped step |",
                  "|---|---|---|" + "---|" * (len(LINEAR_VARIANTS) + 2)]
        for name, v in linear.items():
            t, r = v["step_p50_ms"], v["speedup_vs_straightforward"]
            lines.append(f"| {name} | {v['model']} | {v['dofs']} | " +
                         " | ".join(f"{t[k]:.2f} ms ({r[k]:.1f}×)" for k in LINEAR_VARIANTS) +
                         f" | {r[LINEAR_VARIANTS[-1]]:.1f}× | {max(v['max_difference'].values()):.1e} |")
    network = {k: v for k, v in result["step_variants"].items() if v.get("kind") != "linear"}
    if network:
        lines += ["", "Step time of each scene's model written four ways (median of interleaved calls, same run):",
                  "", "| scene | model | slots (max-degree → rows) | straightforward | max-degree slots | "
                  "assembled edge features | shipped | speed-up vs straightforward | vs assembled | "
                  "as stepped by the loop (api.stepper) |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for name, v in network.items():
            t = v["step_p50_ms"]
            lines.append(
                f"| {name} | {v['model']} {v['hidden']}×{v['passes']} | {v['slots']['max-degree']} → "
                f"{v['slots']['rows']} ({v['slots']['edges']} edges) | {t['straightforward (edge list)']:.2f} ms | "
                f"{t['max-degree slots']:.2f} ms | {t['assembled edge features']:.2f} ms | "
                f"{t['shipped (rows)']:.2f} ms | {v['speedup_vs_straightforward']['shipped (rows)']:.2f}× | "
                f"{t['assembled edge features'] / t['shipped (rows)']:.2f}× | " +
                (f"{t['as stepped (api.stepper)']:.2f} ms ({t['shipped (rows)'] / t['as stepped (api.stepper)']:.2f}× "
                 "vs shipped) |" if "as stepped (api.stepper)" in t else "— |"))
    for name, c in result.get("concurrency", {}).items():
        t, r = c["step_p50_ms"], c["speedup_vs_batched"]
        lines += ["", f"{name}: the two bodies' step ({c['model']}), {c['devices']} CPU devices (median of "
                  "interleaved calls, same run; p99 in brackets): " +
                  ", ".join(f"{k} {v:.2f} ms ({c['step_p99_ms'][k]:.2f}, {r[k]:.2f}× vs "
                            f"{'the batched graph' if c.get('base', 'one graph of both') == 'one graph of both' else c['base']})"
                            for k, v in t.items()) + "."]
    if result.get("loop_fusion"):
        lines += ["", "The loop's simulation stages fused (`Scene.fuse`: forces, step and guard dispatched together, "
                  "awaited once per frame; with devices each body's guard and hand-over run in its step's program, and "
                  "a body on its fallback runs the fallback alone) against the "
                  "stages dispatched and awaited one by one, alternating runs in the same process (simulation p50 / "
                  "p99 over the learned-step frames, median over the rounds):", "",
                  "| scene | frames × rounds | staged p50 / p99 | fused p50 / p99 | speed-up (p50) |",
                  "|---|---|---|---|---|"]
        for name, f in result["loop_fusion"].items():
            lines.append(f"| {name} | {f['frames']} × {f['rounds']} | {f['p50_ms']['staged']:.2f} / "
                         f"{f['p99_ms']['staged']:.2f} ms | {f['p50_ms']['fused']:.2f} / {f['p99_ms']['fused']:.2f} ms "
                         f"| {f['speedup_fused_vs_staged']:.2f}× |")
    if result.get("handover_modes"):
        lines += ["", "A guard trip's hand-over in the frame of the trip (`Scene.handover=\"same-frame\"`: that frame "
                  "runs the learned step and then the fallback step) against the next frame (`\"next-frame\"`, the "
                  "demo's: the trip frame shows the previous state, the next frame runs the fallback twice), "
                  "alternating rounds in the same process (simulation p50 / p99, ms, median over the rounds):", "",
                  "| scene | frames × rounds | guard trips per round | learned-step frames, same-frame | "
                  "learned-step frames, next-frame | hand-over frames, same-frame | hand-over frames, next-frame | "
                  "hand-over p50, same / next |", "|---|---|---|---|---|---|---|---|"]
        for name, h in result["handover_modes"].items():
            cell = lambda d: "—" if d["p50_ms"] is None else f"{d['p50_ms']:.2f} / {d['p99_ms']:.2f}"  # noqa: E731
            ho = h["hand-over"]
            ratio = (f"{ho['same-frame']['p50_ms'] / ho['next-frame']['p50_ms']:.2f}×"
                     if ho["same-frame"]["p50_ms"] and ho["next-frame"]["p50_ms"] else "—")
            trips = ", ".join(str(r["guard_trips"]) for r in h["runs"]["next-frame"])
            lines.append(f"| {name} | {h['frames']} × {h['rounds']} | {trips} | {cell(h['learned']['same-frame'])} | "
                         f"{cell(h['learned']['next-frame'])} | {cell(ho['same-frame'])} | {cell(ho['next-frame'])} | "
                         f"{ratio} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
