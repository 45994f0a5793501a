"""Numerical stress tests: long rollouts of the shipped models far beyond their 20-step training horizon, and
the FEM near its stability limit.

Learned simulator (the demo's models, ``commands_demo.DEFAULT_MODELS``: ``beam`` and ``bunny``, both learned
linear GENERIC models; the non-linear networks' runs are in ``stability_networks.md``), ``--steps`` (default 1000 = 50× the
training horizon) steps of Δt = 0.05 under five loadings:
  * release: a reference load case ramped for 20 steps, then zero (free vibration and decay);
  * constant: that case's final load held;
  * fingertip: a random sequence of fingertip patches (``fem.cases.fingertip_forces``, 20 steps each);
  * 3x load: the constant load times 3 (out of the training range);
  * noise: the constant load with Gaussian noise of 1 % of the state's std added to the input every step.
Reported per run: NaN/Inf count, max |u| and |v| against the FEM on the same loads (the FEM for the first
``--fem-steps`` frames, batched), the first step at which the u error against the FEM exceeds 10 % (L2 over
the nodes, relative to the largest FEM displacement norm over the horizon; NaN counts as over),
the learned energy and entropy along the rollout (for a model whose network is zero, ``api.network_is_zero``, the
rest-linearised system's energy ½vᵀMv + ½uᵀK₀u and its entropy at unit temperature, the running sum of the
dissipation D = W − ΔE of each step, ``framesolve.energy_balance``), the fraction of steps with S_{k+1} ≥ S_k and the fraction
with entropy production ∇S·Δw ≥ 0 (the step's GENERIC rate: ≥ 0 by construction for an ``exact_degeneracy``
model, up to the clamped rows and rounding), both over the steps before the first non-finite state, and the two
guards: ``api.force_check`` (loads beyond the training range) and ``api.state_check`` (the first step at
which the state leaves the training envelope, against the first non-finite step), and how it leaves: the state
component and node that deviate most at the flagged step, with that node's graph distance (in edges) from
the nearest loaded node.
FEM: the beam at 0.9 (default), 1.0 and 1.5 × its stable sub-step (fewer sub-steps than stable): the run
must either stay bounded or report the inversion (element and time), never return silent NaN.
The FEM reference uses the integrator of the model's training data (``info["fem_integrator"]``: "implicit"
for backward Euler with the frame step, ``fem.implicit``; else the explicit solver) and its damping
(``info["fem_damping"]``). Initial state: the rest positions with zero stress; the velocity follows the convention of the model's
training data (``info["velocity"]``): "gradient" (the reference data: v(0) is the one-sided second-order
difference of the trajectory, so it is taken from the FEM run) or "solver" (v(0) = 0).
Writes benchmarks/results/stability.{json,md} and stability.png.

    python benchmarks/stability.py [--steps 1000] [--fem-steps 100] [--scenes beam,bunny] [--models beam=beam]
    (several models of one scene: --models beam=beam-abaqus+beam; --tag bunny writes stability_bunny.*)
For the bunny the FEM uses the mass density and the load patch radius of the model's training data
(``info["fem_density"]``, ``info["fem_load_radius"]``) where the model records them.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
SCENARIOS = ("release", "constant", "fingertip", "3x load", "noise")
COLUMNS = ("q1", "q2", "q3", "v1", "v2", "v3", "σ11", "σ22", "σ33", "σ12", "σ13", "σ23")
FALLBACK_HOLD = 30   # api.fallback_stepper: steps a flagged body stays on the rest-linearised FEM
BUNNY_RISE = 10   # the bunny data's loads rise over 10 frames (tignn generate bunny --rise-frames 10)


def loadings(name: str, steps: int, seed: int = 0, density: float | None = None, load_radius: float = 0.0):
    """(scene, {scenario: forces [steps, N, 3]}) on the FEM scene whose mesh is the model's mesh; for the bunny,
    the mass density and the load patch radius of the model's training data (``density`` None: the scene's)."""
    from fem import cases, scenes

    if name == "beam":
        scene = scenes.beam_scene()
        base = scenes.beam_reference_forces(scene, [9])[0]      # test case 9 of the published split
    else:
        scene = scenes.bunny_scene() if density is None else scenes.bunny_scene(density=density)
        base, _ = cases.point_load_forces(scene, n_cases=1, seed=seed + 7, rise_frames=BUNNY_RISE,
                                          radius=load_radius)
        base = base[0]
    n = len(scene.points)
    t0 = base.shape[0]
    hold = np.repeat(base[-1:], steps, axis=0)
    release = np.zeros((steps, n, 3))
    release[:t0] = base
    constant = hold.copy()
    constant[:t0] = base
    if name == "beam":
        tips, _ = cases.fingertip_forces(scene, -(-steps // scene.n_frames), seed)
    else:
        tips, _ = cases.point_load_forces(scene, n_cases=-(-steps // scene.n_frames), seed=seed + 1,
                                          rise_frames=BUNNY_RISE, radius=load_radius)
    fingertip = tips.reshape(-1, n, 3)[:steps]
    return scene, {"release": release, "constant": constant, "fingertip": fingertip, "3x load": 3 * constant,
                   "noise": constant}


def rollout(fn, z, scenario: str, f_seq, key, steps: int, z_std, node_type):
    """States [steps+1, N, 12] and per-step flags of ``fn(z, f) -> (z, flagged)`` under the loads ``f_seq``; the
    noise scenario adds 1 % of the state std ``z_std`` to the free nodes' input every step (draws from ``key``)."""
    states, flags = [np.asarray(z)], []
    for k in range(steps):
        if scenario == "noise":
            key, sub = jax.random.split(key)
            z = z + 0.01 * jnp.asarray(z_std) * jax.random.normal(sub, z.shape) * (node_type[:, None] == 0)
        z, flagged = fn(z, f_seq[k])
        states.append(np.asarray(z))
        flags.append(bool(np.any(flagged)))
    return np.stack(states), flags


def holding(fallback):
    """``api.fallback_stepper``'s ``(z, f, left) -> (z, flagged, left)`` as ``(z, f) -> (z, flagged)`` for
    `rollout`, carrying ``left`` (the steps the body still has to spend on the fallback) from call to call."""
    left = [jnp.zeros(1, jnp.int32)]

    def fn(z, f):
        z, flagged, left[0] = fallback(z, f, left[0])
        return z, flagged

    return fn


def displacement_error(zs, uf, q0) -> np.ndarray:
    """[len(uf)]: the L2 displacement error of states ``zs`` against the FEM's displacements ``uf`` over its
    horizon, relative to the FEM's largest displacement norm there."""
    return np.linalg.norm((zs[:len(uf), :, :3] - q0) - uf, axis=(1, 2)) / max(
        float(np.linalg.norm(uf, axis=(1, 2)).max()), 1e-12)


def fallback_model(model: str, params: dict, scene, damping: float | None = None) -> dict:
    """The rest-linearised FEM of ``scene`` that ``model`` falls back to: the shipped one the demo hands it to
    (`commands_demo.FALLBACKS`) where that was built for the same damping and density, which saves the
    linearisation (about 40 s for the beam); otherwise `framesolve.linear_model` builds it."""
    from tignn_jax import api
    from tignn_jax import framesolve as FS
    from tignn_jax.commands_demo import FALLBACKS

    damping = float(scene.damping if damping is None else damping)
    if model in FALLBACKS:
        linear, _ = api.load_pretrained(FALLBACKS[model])
        built = linear.get("info", {})
        if np.isclose(built.get("fem_damping", np.nan), damping, rtol=1e-6) and \
                np.isclose(built.get("fem_density", np.nan), scene.material.density, rtol=1e-6):
            return linear
    return FS.linear_model(params, scene, damping)[0]


def model_runs(name: str, model: str, steps: int, fem_steps: int, newton_fallback: bool = False) -> dict:
    import fem
    from fem import scenes
    from tignn_jax import api
    from tignn_jax import model as M
    from tignn_jax import framesolve as FS

    params, graph = api.load_pretrained(model)
    info = params.get("info", {})
    scene, loads = loadings(name, steps, density=info.get("fem_density"),
                            load_radius=float(info.get("fem_load_radius") or 0.0))
    if "fem_damping" in info:   # the model was trained on FEM data with this damping
        scene = scene._replace(damping=float(info["fem_damping"]))
    q0 = np.asarray(params["mesh"]["q0"], np.float64)
    units = float(np.sum(q0 * scene.points) / np.sum(scene.points ** 2))
    if not np.allclose(q0, scene.points * units, atol=1e-3 * np.abs(q0).max()):
        raise ValueError(f"model {model!r} is not on the {name} scene's mesh")
    # FEM reference, batched over the scenarios (noise uses the constant load's reference)
    fem_names = [s for s in SCENARIOS if s != "noise"]
    problem = scenes.setup_scene(scene._replace(n_frames=fem_steps))
    batch = fem.Loads(nodal=jnp.asarray(np.stack([loads[s][:fem_steps] for s in fem_names])))
    t0 = time.perf_counter()
    if info.get("fem_integrator") == "implicit":   # trained on backward-Euler frames
        from fem import implicit
        res, _ = implicit.simulate_implicit_batch(problem, scene.material, batch)
    else:
        res = fem.simulate_batch(problem, scene.material, batch)
    fem_q = np.asarray(res.q)                      # [S, fem_steps+1, N, 3]
    fem_s = time.perf_counter() - t0
    fem_v = np.asarray(res.v)
    cfg, norm, w = api._config(params), params["norm"], params["weights"]
    nt, topo = graph.nodes["node_type"], params["topo"]
    z_std = np.asarray(norm["z_std"])
    step = api.stepper(params)
    # a model whose network is zero has E = S = 0 as a network: its energy is the rest-linearised system's
    linear_energy = api.network_is_zero(params)
    energy = jax.jit(jax.vmap(lambda z, f: M.energy_entropy(w, cfg, norm, z, f, nt, topo)))
    production = jax.jit(jax.vmap(lambda z, f: M.rates(w, cfg, norm, z, f, nt, topo).entropy_rate))

    def entropy_production(zs, fs, chunk=50):   # ∇S·Δw per step (the GENERIC entropy production of the step)
        return np.concatenate([np.asarray(production(jnp.asarray(zs[i:i + chunk]), fs[i:i + chunk]))
                               for i in range(0, len(zs), chunk)])
    out = {"model": model, "fem_wall_s": fem_s, "fem_steps": fem_steps, "runs": {},
           "energy": "linear" if linear_energy else "learned"}
    from fem.meshes import hop_distances
    hops = hop_distances(np.stack([np.asarray(graph.senders), np.asarray(graph.receivers)]),
                         len(q0))   # [N, N] graph distances (756 or 1330 nodes: small)
    guarded = {p: api.guarded_stepper(params, policy=p) for p in api.GUARD_POLICIES}
    if not cfg.frame_solve:   # the rest-linearised FEM of the same scene as the fallback (a linear model is its own)
        linear = fallback_model(model, params, scene, info.get("fem_damping"))
        guarded["fallback"] = api.fallback_stepper(params, linear, hold=FALLBACK_HOLD)
        if newton_fallback:   # the FEM's non-linear backward-Euler step (Newton–CG iterations) as the fallback
            from tignn_jax import newton
            guarded["fallback (Newton)"] = api.fallback_stepper(params, linear, hold=FALLBACK_HOLD,
                                                                step=newton.fallback_step(linear, scene))
        from tignn_jax import data as D
        if "fem_damping" not in info and D.reference_path().exists():   # trained on the reference data:
            ref = D.load(D.reference_path())                           # calibrate on its train split
            rows = D.split_rows(ref, "train")
            bound = api.consistency_bound(params, linear, ref.z[rows, :-1], ref.f[rows])
            guarded["fallback+consistency"] = api.fallback_stepper(params, linear, hold=FALLBACK_HOLD,
                                                                   consistency=bound)

    def roll(fn, z, s, f_seq, key):
        return rollout(fn, z, s, f_seq, key, steps, z_std, nt)

    def u_error(zs, uf):
        return displacement_error(zs, uf, q0)

    def first_over(err):   # the first step with u error > 10 % (NaN counts as over), or None
        over = np.where(~(err[1:] <= 0.10))[0]
        return int(over[0] + 1) if len(over) else None

    def guarded_run(policy, s, z, f_seq, uf):   # the same loads (and noise) through the guarded steppers
        fn = guarded[policy]
        if policy.startswith("fallback"):        # it carries each body's steps left on the fallback
            fn = holding(fn)
        zs, flags = roll(fn, z, s, f_seq, jax.random.PRNGKey(1))
        err = u_error(zs, uf)
        return {"nan_or_inf": int(np.size(zs) - np.count_nonzero(np.isfinite(zs))),
                "flagged_steps": int(sum(flags)), "first_flagged_step": flags.index(True) + 1 if any(flags) else None,
                "max_u_model": float(np.nanmax(np.linalg.norm(zs[..., :3] - q0, axis=-1))),
                "u_error_at_fem_horizon": float(err[-1]),
                "first_step_u_error_over_10pct": first_over(err),
                "u_error": err.tolist()}
    gradient_velocity = info.get("velocity", "gradient") == "gradient"
    for s in SCENARIOS:
        f_seq = jnp.asarray(loads[s], jnp.float32)
        guard = api.force_check(params, np.asarray(loads[s]))
        ref = fem_names.index("constant" if s == "noise" else s)
        z = graph.nodes["z"]
        if gradient_velocity:   # the data convention the model was trained with: v(0) = one-sided 2nd-order
            qf = fem_q[ref] * units  # difference of the trajectory (numpy.gradient), not the rest value 0
            v0 = (-3 * qf[0] + 4 * qf[1] - qf[2]) / (2 * scene.frame_dt)
            z = z.at[:, 3:6].set(jnp.asarray(v0, z.dtype))
        t0 = time.perf_counter()
        zs, _ = roll(lambda z_, f_: (step(z_, f_), False), z, s, f_seq, jax.random.PRNGKey(0))  # [steps+1, N, 12]
        wall = time.perf_counter() - t0
        finite = np.isfinite(zs)
        u = np.linalg.norm(zs[..., :3] - q0, axis=-1).max(-1)
        v = np.linalg.norm(zs[..., 3:6], axis=-1).max(-1)
        if linear_energy:   # the rest-linearised system's energy and cumulative dissipation (exact for its step)
            bal = FS.energy_balance(params["norm"], np.nan_to_num(zs), f_seq, nt, q0)
            e_s = np.stack([bal["E"][:-1], bal["S"][:-1]], axis=1)
        else:
            e_s = np.asarray(energy(jnp.asarray(np.nan_to_num(zs[:-1])), f_seq))
        uf = (fem_q[ref] * units - q0)
        # error relative to the largest FEM displacement over the horizon (a relative error of the tiny
        # first-step displacement says nothing about the rollout)
        err = u_error(zs, uf)
        checks = [api.state_check(params, zk) for zk in zs]
        flagged = [k for k, c in enumerate(checks) if c["out_of_distribution"]]
        leaves = _how_it_leaves(params, zs[flagged[0]], loads[s][:flagged[0]], hops) if flagged else None
        nonfinite = [k for k, c in enumerate(checks) if not c["finite"]]
        live = max(nonfinite[0] - 1, 0) if nonfinite else steps   # entropy statistics over the steps between finite states
        ds = np.diff(e_s[:live + 1, 1])
        rate = bal["D"][:live] if linear_energy else entropy_production(zs[:live], f_seq[:live])
        out["runs"][s] = {
            "nan_or_inf": int(np.size(finite) - np.count_nonzero(finite)),
            "max_u_model": float(np.nanmax(u)), "max_u_fem": float(np.abs(np.linalg.norm(uf, axis=-1)).max()),
            "max_v_model": float(np.nanmax(v)),
            "max_v_fem": float(np.linalg.norm(fem_v[ref] * units, axis=-1).max()),
            "u_error_at_fem_horizon": float(err[-1]),
            "first_step_u_error_over_10pct": first_over(err),
            "entropy_steps": int(live),
            "entropy_non_decreasing_fraction": float(np.mean(ds >= 0)) if live else float("nan"),
            "entropy_production_non_negative_fraction": float(np.mean(rate >= 0)) if live else float("nan"),
            "entropy_production_min_mean": [float(np.min(rate)), float(np.mean(rate))] if live else [float("nan")] * 2,
            "energy_first_last": [float(e_s[0, 0]), float(e_s[-1, 0])],
            "guard": guard, "ms_per_step": 1e3 * wall / steps,
            "first_step_state_flagged": flagged[0] if flagged else None,
            "first_step_non_finite": nonfinite[0] if nonfinite else None,
            "leaves_envelope_by": leaves,
            "guarded": {p: guarded_run(p, s, z, f_seq, uf) for p in guarded},
            "series": {"u_max": u.tolist(), "v_max": v.tolist(), "u_error": err.tolist(),
                       "E": e_s[:, 0].tolist(), "S": e_s[:, 1].tolist()}}
    return out


def _how_it_leaves(params, z, past_forces, hops) -> dict:
    """The state component and node farthest outside the training envelope in ``z`` (as ``api.state_check``
    measures it: v and σ deviations over the largest deviation seen in training, |u| over the largest training
    displacement; in training standard deviations for models saved without the envelope) and that node's
    distance in edges from the nearest node loaded at any earlier step (None if nothing was loaded)."""
    from tignn_jax import api

    z = np.asarray(z, np.float64)
    mean, std = (np.asarray(params["norm"][k], np.float64) for k in ("z_mean", "z_std"))
    dev = np.abs((z[:, 3:] - mean[3:]) / std[3:])
    if "z_dev_max" in params["norm"]:
        score = np.asarray(api._envelope_ratios(params, z, np), np.float64)
    else:
        score = dev
    score = np.where(np.isfinite(score), score, np.inf)
    node, col = np.unravel_index(int(np.argmax(score)), score.shape)
    loaded = np.where(np.abs(np.asarray(past_forces)).sum(axis=(0, 2)) > 0)[0] if len(past_forces) else []
    return {"component": (COLUMNS[3:] + ("|u|",))[col], "node": int(node),
            "deviation": float(dev[node, col]) if col < dev.shape[1] else None,
            "envelope_ratio": float(score[node, col]) if "z_dev_max" in params["norm"] else None,
            "hops_from_load": int(hops[node, loaded].min()) if len(loaded) else None}


def fem_limit(factors=(0.9, 1.0, 1.5), frames: int = 20) -> list:
    import fem
    from fem import scenes

    scene = scenes.beam_scene()
    forces = scenes.beam_reference_forces(scene, [9])[0][:frames]
    stable = scenes.setup_scene(scene._replace(n_frames=frames)).config.n_sub   # at the default safety 0.9
    rows = []
    for factor in factors:
        n_sub = max(1, int(round(stable * 0.9 / factor)))
        prob = scenes.setup_scene(scene._replace(n_frames=frames), n_sub=n_sub)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = fem.simulate(prob, scene.material, fem.Loads(nodal=jnp.asarray(forces)), on_inversion="warn")
        q = np.asarray(res.q)
        rows.append({"step_over_stable": factor, "n_sub": n_sub, "nan_or_inf": int(np.sum(~np.isfinite(q))),
                     "inverted_element": int(res.inverted), "inversion_time": float(res.inversion_time),
                     "reported": [str(w.message) for w in caught],
                     "max_u": float(np.nanmax(np.abs(q - scene.points)))})
    return rows


def _leaves_text(run) -> str:
    how = run.get("leaves_envelope_by")
    if not how:
        return "—"
    size = (f"{how['envelope_ratio']:.3g}× the training envelope" if how.get("envelope_ratio") is not None
            else f"{how['deviation']:.3g} std")
    return f"{how['component']} at node {how['node']}, {size} ({how['hops_from_load']})"


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes_ = result["models"]
    fig, axes = plt.subplots(len(scenes_), 3, figsize=(14, 3.6 * len(scenes_)), squeeze=False)
    for row, (name, r) in zip(axes, scenes_.items()):
        for s, run in r["runs"].items():
            row[0].semilogy(run["series"]["u_max"], label=s)
            row[1].semilogy(np.maximum(run["series"]["u_error"], 1e-6), label=s)
            row[2].plot(np.asarray(run["series"]["S"]) - run["series"]["S"][0], label=s)
        row[0].set(title=f"{name} ({r['model']}): max |u| per step", xlabel="step")
        row[1].axhline(0.1, color="k", lw=0.8, ls="--")
        row[1].set(title="relative u error vs FEM", xlabel="step")
        row[2].set(title="entropy S − S₀ (learned, or the linear system's dissipation)", xlabel="step")
        row[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    from tignn_jax.commands_demo import DEFAULT_MODELS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--fem-steps", type=int, default=100)
    ap.add_argument("--scenes", default="beam,bunny")
    ap.add_argument("--models", default="", help="override the demo's models, e.g. beam=beam (the FEM then runs "
                    "with the damping recorded in the model, info['fem_damping'], when there is one)")
    ap.add_argument("--tag", default="", help="write stability_TAG.* instead of stability.* (e.g. a second "
                    "scene run separately)")
    ap.add_argument("--newton-fallback", action="store_true", help="also hand flagged bodies to the FEM's non-linear "
                    "backward-Euler step by Newton–CG iterations (`tignn_jax.newton`) instead of the rest-linearised one")
    ap.add_argument("--keep-others", action="store_true",
                    help="keep the scenes not run now from the existing results (each keeps its machine record)")
    ap.add_argument("--report-only", action="store_true", help="rewrite the .md and .png from the .json of an "
                    "earlier run (no rollouts)")
    args = ap.parse_args(argv)
    if args.tag and not args.tag.replace("-", "").replace("_", "").isalnum():
        raise SystemExit(f"--tag must be letters, digits, - and _, got {args.tag!r}")
    stem = f"stability_{args.tag}" if args.tag else "stability"
    if args.steps < args.fem_steps or args.fem_steps < 20:
        raise SystemExit(f"need --steps ≥ --fem-steps ≥ 20, got {args.steps} and {args.fem_steps}")
    if args.report_only:
        result = json.loads((RESULTS / f"{stem}.json").read_text())
        plot(result, RESULTS / f"{stem}.png")
        write_report(result, stem, recorded_fem_steps(result))
        return 0
    kept_from = None
    if args.keep_others and (RESULTS / f"{stem}.json").exists():   # checked before the long runs
        kept_from = json.loads((RESULTS / f"{stem}.json").read_text())
        ran = (kept_from["steps"], recorded_fem_steps(kept_from))
        if ran != (args.steps, args.fem_steps):
            raise SystemExit(f"--keep-others: the kept results ran {ran[0]} / {ran[1]} steps, "
                             f"this run {args.steps} / {args.fem_steps}")
    machine = describe()
    chosen = {k: [v] for k, v in DEFAULT_MODELS.items()}
    for item in [m for m in args.models.split(",") if m]:
        scene_name, _, model_names = item.partition("=")
        if scene_name not in chosen or not model_names:
            raise SystemExit(f"--models wants SCENE=MODEL[+MODEL...] with SCENE in {sorted(chosen)}, got {item!r}")
        chosen[scene_name] = model_names.split("+")
    models = {}
    for name in [s for s in args.scenes.split(",") if s]:
        for model in chosen[name]:
            label = name if len(chosen[name]) == 1 else f"{name} ({model})"
            try:
                models[label] = model_runs(name, model, args.steps, args.fem_steps, args.newton_fallback)
            except ValueError as err:
                print(f"{label}: skipped ({err})")
    if not models:
        raise SystemExit("no model ran (see the skipped lines above)")
    for r in models.values():
        r["machine"] = machine
    if kept_from is not None:
        kept = {k: {**r, "machine": r.get("machine", kept_from["machine"]), "earlier_run": True}
                for k, r in kept_from["models"].items() if k not in models}
        models = {**kept, **models}
    result = {"machine": machine, "steps": args.steps, "fem_steps": args.fem_steps, "models": models,
              "fem_limit": fem_limit()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result))
    plot(result, RESULTS / f"{stem}.png")
    write_report(result, stem, args.fem_steps)
    return 0


def recorded_fem_steps(result: dict) -> int:
    """The FEM reference steps of a stored result; results written before they were recorded used the default,
    100 (their reports say so)."""
    return int(result.get("fem_steps") or 100)


def _worst_dissipation(run: dict) -> float:
    """The most negative step dissipation of a run over its largest |E| (from the E and S series)."""
    e, d = np.abs(np.asarray(run["series"]["E"])), np.diff(np.asarray(run["series"]["S"]))
    return float(d.min() / max(e.max(), 1e-300)) if d.size else float("nan")


def write_report(result: dict, stem: str, fem_steps: int) -> None:
    """benchmarks/results/{stem}.md from a run's result."""
    machine, models, steps = result["machine"], result["models"], result["steps"]
    lines = ["# Numerical stress tests", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']}; load average "
             f"{machine['load_average_1m']} at start. {steps}-step rollouts (Δt = 0.05; the training horizon "
             f"is 20); FEM reference over the first {fem_steps} steps." + "".join(
                 f" The {name} rows come from an earlier run (load average {r['machine']['load_average_1m']} at "
                 f"its start, jax {r['machine']['jax']})." for name, r in models.items() if r.get("earlier_run")),
             "",
             "| scene | loading | NaN/Inf | max u model / FEM | max v model / FEM | u error at FEM horizon | "
             "first step u error > 10 % | S non-decreasing (steps) | entropy production ≥ 0 (min) | force guard | "
             "first step state flagged / non-finite | leaves the envelope by (hops from the load) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in models.items():
        for s, run in r["runs"].items():
            g = run["guard"]
            lines.append(
                f"| {name} | {s} | {run['nan_or_inf']} | {run['max_u_model']:.3g} / {run['max_u_fem']:.3g} | "
                f"{run['max_v_model']:.3g} / {run['max_v_fem']:.3g} | {run['u_error_at_fem_horizon']:.3f} | "
                f"{run['first_step_u_error_over_10pct']} | {100 * run['entropy_non_decreasing_fraction']:.0f} % "
                f"({run['entropy_steps']}) | "
                f"{100 * run['entropy_production_non_negative_fraction']:.0f} % "
                f"({run['entropy_production_min_mean'][0]:.2g}) | "
                f"{'FLAGGED' if g['out_of_distribution'] else 'ok'} ({g['max_force_ratio']:.2f}× train max) | "
                f"{run['first_step_state_flagged']} / {run['first_step_non_finite']} | {_leaves_text(run)} |")
    linear = {name: r for name, r in models.items() if r.get("energy") == "linear"}
    if linear:
        lines += ["", "E and S of the models whose network is zero (" + ", ".join(
            f"`{r['model']}`" for r in linear.values()) + ") are the rest-linearised "
            "system's energy ½vᵀMv + ½uᵀK₀u and the running sum of each step's dissipation D = W − ΔE "
            "(`framesolve.energy_balance`; W the external work): the backward-Euler step makes D ≥ 0 in exact "
            "arithmetic. The noise runs add noise to the state between steps, which changes E outside any step: "
            "there D < 0 where the noise added energy, so their entropy columns measure the noise, not the step. "
            "In float32 states a step at rest or in a held equilibrium has D ≈ 0 and rounding makes it either sign: "
            "the most negative D of each run against the run's largest E (the rounding scale): " + "; ".join(
                f"{name} {s_}: {_worst_dissipation(run):.1e}" for name, r in linear.items()
                for s_, run in r["runs"].items()) + "."]
    lines += ["", "The same loads through `api.guarded_stepper` (a step whose state leaves 1.5× the training "
              "envelope, or is non-finite, is replaced: `clip` clips it into the envelope, `reset` puts the body "
              "back at rest; a safeguard, not physics) and `api.fallback_stepper` (`fallback`: such a body is "
              "handed to the scene's rest-linearised backward-Euler FEM, `framesolve.linear_model`, with its "
              f"stress set to S₀u, for that step and the next {FALLBACK_HOLD}; not learned, but physically "
              "consistent and unconditionally stable; the steps flagged count the hand-overs; "
              "`fallback+consistency`, for models trained on the reference data: also where the network's step "
              "departs from the linear one by more than 1.5× its largest departure on the train split, "
              "`api.consistency_bound`; `fallback (Newton)`, with `--newton-fallback`: the same hand-overs to the "
              "FEM's non-linear backward-Euler step by Newton–CG iterations, `tignn_jax.newton`, which needs no "
              "consistent stress to start from):", "",
              "| scene | loading | policy | NaN/Inf | steps flagged (first) | max u model | u error at FEM horizon | "
              "first step u error > 10 % |", "|---|---|---|---|---|---|---|---|"]
    for name, r in models.items():
        for s, run in r["runs"].items():
            for policy, g in run.get("guarded", {}).items():
                lines.append(f"| {name} | {s} | {policy} | {g['nan_or_inf']} | {g['flagged_steps']} "
                             f"({g['first_flagged_step']}) | {g['max_u_model']:.3g} | "
                             f"{g['u_error_at_fem_horizon']:.3f} | {g['first_step_u_error_over_10pct']} |")
    lines += ["", "FEM near its stability limit (beam, 20 frames; sub-step relative to the stable one):", "",
              "| h / h_stable | sub-steps per frame | NaN/Inf in output | inverted element | time | reported |",
              "|---|---|---|---|---|---|"]
    for row in result["fem_limit"]:
        lines.append(f"| {row['step_over_stable']:.2f} | {row['n_sub']} | {row['nan_or_inf']} | "
                     f"{row['inverted_element']} | {row['inversion_time']:.3g} | "
                     f"{'; '.join(row['reported'])[:160] or 'nothing to report'} |")
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
