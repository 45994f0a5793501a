"""Stress tests: do the shipped models stay finite and physically sane over long rollouts, with and without the
guards, and how far do they drift from the FEM?

Models: each scene's shipped learned model (``beam``, ``bunny``: learned linear GENERIC models stepped by backward
Euler) and, as the reference, the FEM's own backward-Euler frame step on the same mesh,
``tignn_jax.fem_stepper(<scene>-linear)`` (Newton–CG iterations of the non-linear FEM, `tignn_jax.newton`; not
learned). ``--steps`` frames (default 1000 = 50× the 20-frame training horizon) of Δt = 0.05 from rest
(q = q0, v = 0, σ = 0) under five loadings:

  * release: a reference load case (beam: Abaqus test case 9; bunny: a point load rising over 10 frames) for its
    20 frames, then no load (free vibration and decay);
  * constant: that case's loads, then its final load held;
  * fingertip: a random sequence of fingertip patches (beam: ``fem.cases.fingertip_forces``; bunny: point loads,
    ``fem.cases.point_load_forces``), 20 frames each;
  * 3x load: the constant loading times 3 (outside the training range);
  * noise: the constant loading, with Gaussian noise of 1 % of the training state's std (``envelope["z_std"]``)
    added to the free nodes' input state every frame (the reference: the constant loading without noise).

Reported per run: non-finite values; the largest displacement |u| and velocity |v|; the displacement error
against the reference over its first ``--reference-steps`` frames (L2 over the nodes, relative to the reference's
largest displacement norm over that horizon) and the first frame where it exceeds 10 %; the force guard
(``tignn_jax.force_check``: the largest nodal force over the training maximum); the first frame the state
guard flags (``tignn_jax.state_guard``, tolerance 1.5 × the training envelope), with the state component and node
farthest outside the envelope there and its distance in edges from the nearest loaded node; the energy behaviour
of a model class with an energy balance (``model.diagnostics``: energy E, and each frame's dissipation
D = W − ΔE, which backward Euler keeps ≥ 0; in float32 a frame in equilibrium has D ≈ 0 of either sign, so a
frame counts as dissipative when D ≥ −1e-6 × the run's largest E).
Guarded runs (the same loads and noise): ``tignn_jax.guarded_stepper`` with ``clip`` and ``reset`` and
``tignn_jax.fallback_stepper`` handing a flagged body to the scene's rest-linearised model (``<scene>-linear``)
for 30 frames. Each run is one ``lax.scan`` over the frames.
Also: the explicit FEM (`fem.simulate`) of the beam at 0.9, 1.0 and 1.5 × its stable sub-step: a run beyond the
stable step must report the element inversion (element and time), never return silent NaN.

Writes stability.{json,md,png} to ``--out`` (default benchmarks/results).

    python benchmarks/stability.py [--steps 1000] [--reference-steps 1000] [--scenes beam,bunny]
    python benchmarks/stability.py --quick --out /tmp/stability     # smoke run: beam, 40 frames, linear reference
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
from _machine import RESULTS_DIR, describe, machine_line  # noqa: E402

SCENARIOS = ("release", "constant", "fingertip", "3x load", "noise")
POLICIES = ("clip", "reset", "fallback")
COLUMNS = ("q1", "q2", "q3", "v1", "v2", "v3", "σ11", "σ22", "σ33", "σ12", "σ13", "σ23")
MODELS = {"beam": "beam", "bunny": "bunny"}                       # each scene's shipped learned model
LINEAR = {"beam": "beam-linear", "bunny": "bunny-linear"}         # its rest-linearised FEM (reference mesh, fallback)
REFERENCES = ("newton", "linear")   # the FEM reference: its backward-Euler step, or its rest linearisation
TOLERANCE = 1.5          # the state guard's multiple of the training envelope (the guards' default)
FALLBACK_HOLD = 30       # frames a flagged body stays on the rest-linearised model
NOISE = 0.01             # noise per frame, in training state std
BUNNY_RISE = 10          # the bunny data's loads rise over 10 frames (tignn generate bunny --rise-frames 10)
CHUNK = 100              # states per vmapped diagnostics call


def loadings(name: str, steps: int, seed: int = 0, density: float | None = None, load_radius: float = 0.0):
    """(scene, {scenario: forces [steps, N, 3]}) of the FEM scene ``name``; for the bunny, the mass density and
    load patch radius of the model's training data (``density`` None: the scene's)."""
    from fem import cases, scenes

    if name == "beam":
        scene = scenes.beam_scene()
        base = scenes.beam_reference_forces(scene, [9])[0]      # test case 9 of the published split
    elif name == "bunny":
        scene = scenes.bunny_scene() if density is None else scenes.bunny_scene(density=density)
        base, _ = cases.point_load_forces(scene, n_cases=1, seed=seed + 7, rise_frames=BUNNY_RISE,
                                          radius=load_radius)
        base = base[0]
    else:
        raise ValueError(f"unknown scene {name!r}; scenes: {sorted(MODELS)}")
    n, t0 = len(scene.points), base.shape[0]
    release = np.zeros((steps, n, 3))
    release[:min(t0, steps)] = base[:steps]
    constant = np.repeat(base[-1:], steps, axis=0)
    constant[:min(t0, steps)] = base[:steps]
    cases_needed = -(-steps // scene.n_frames)
    if name == "beam":
        tips, _ = cases.fingertip_forces(scene, cases_needed, seed)
    else:
        tips, _ = cases.point_load_forces(scene, n_cases=cases_needed, seed=seed + 1, rise_frames=BUNNY_RISE,
                                          radius=load_radius)
    fingertip = tips.reshape(-1, n, 3)[:steps]
    return scene, {"release": release, "constant": constant, "fingertip": fingertip, "3x load": 3 * constant,
                   "noise": constant}


def scan_rollout(step, carry0=()):
    """A jitted ``roll(z0, forces [T,N,3], noise [T,N,12]) -> (states [T+1,N,12], flagged [T])`` of
    ``step(carry, z, f) -> (carry, z_next, flagged)``; the noise is added to each frame's input state."""

    @jax.jit
    def roll(z0, forces, noise):
        def body(c, x):
            z, carry = c
            f, e = x
            carry, z, flagged = step(carry, z + e, f)
            return (z, carry), (z, flagged)

        _, (zs, flags) = jax.lax.scan(body, (z0, carry0), (forces, noise))
        return jnp.concatenate([z0[None], zs]), flags

    return roll


def steppers(params: dict, linear: dict) -> dict:
    """{"plain": the model's frame map, "clip"/"reset": guarded_stepper, "fallback": fallback_stepper} as
    `scan_rollout` programs."""
    import tignn_jax

    plain = tignn_jax.stepper(params)
    out = {"plain": scan_rollout(lambda c, z, f: (c, plain(z, f), jnp.zeros((), bool)))}
    for policy in ("clip", "reset"):
        fn = tignn_jax.guarded_stepper(params, policy=policy, tolerance=TOLERANCE)
        out[policy] = scan_rollout(lambda c, z, f, fn=fn: (c, *_one(fn(z, f))))
    fb = tignn_jax.fallback_stepper(params, linear, hold=FALLBACK_HOLD, tolerance=TOLERANCE)

    def fallback(left, z, f):
        z, flagged, left = fb(z, f, left)
        return left, z, flagged[0]

    out["fallback"] = scan_rollout(fallback, jnp.zeros(1, jnp.int32))
    return out


def _one(zf):
    z, flagged = zf
    return z, flagged[0]


def noise_for(params: dict, steps: int, seed: int) -> np.ndarray:
    """[steps, N, 12] float32: NOISE × the training state std per feature on the free nodes, fresh every frame."""
    n = len(params["mesh"]["q0"])
    std = np.asarray(params["envelope"]["z_std"], np.float32)
    free = (np.asarray(params["mesh"]["node_type"]) == 0)[None, :, None]
    rng = np.random.default_rng(seed)
    return (NOISE * std * rng.standard_normal((steps, n, 12), np.float32) * free).astype(np.float32)


def displacement_error(zs, u_ref, q0) -> np.ndarray:
    """[len(u_ref)]: the L2 displacement error of ``zs`` against the reference's displacements ``u_ref`` over its
    horizon, relative to the reference's largest displacement norm there (NaN where zs is not finite)."""
    scale = max(float(np.linalg.norm(u_ref, axis=(1, 2)).max()), 1e-12)
    return np.linalg.norm((zs[:len(u_ref), :, :3] - q0) - u_ref, axis=(1, 2)) / scale


def first_over(err, bound: float = 0.10):
    """The first frame with an error above ``bound`` (NaN counts as above), or None."""
    over = np.where(~(err[1:] <= bound))[0]
    return int(over[0] + 1) if len(over) else None


def diagnostics_fn(params: dict):
    """The model class's energy balance ``fn(z [B,N,12], f [B,N,3], z_next) -> {"energy", "work", "dissipation"}``
    [B] each, jitted for float64 inputs; None for a class without ``diagnostics``."""
    model = params["model"]
    if not hasattr(model, "diagnostics"):
        return None
    return jax.jit(jax.vmap(lambda z, f, zn: model.diagnostics(params["arrays"], z, f, zn)))


def energy_series(params: dict, zs, forces, noise, fn=None) -> dict | None:
    """E per state and the dissipation D per frame of a model class with ``diagnostics`` (None otherwise),
    from each frame's input state (the state plus the noise) to its output; evaluated in float64 on the
    float32 states."""
    fn = diagnostics_fn(params) if fn is None else fn
    if fn is None:
        return None
    zs = np.nan_to_num(np.asarray(zs, np.float32)).astype(np.float64)
    inputs = zs[:-1] + noise
    forces = np.asarray(forces, np.float64)
    with jax.enable_x64(True):   # the balance of the float32 states, summed in float64 (K's entries are large)
        parts = [fn(*(jnp.asarray(_pad(a[i:i + CHUNK])) for a in (inputs, forces, zs[1:])))
                 for i in range(0, len(inputs), CHUNK)]
    sizes = [min(CHUNK, len(inputs) - i) for i in range(0, len(inputs), CHUNK)]
    parts = [{k: np.asarray(v, np.float64)[:n] for k, v in p.items()} for p, n in zip(parts, sizes)]
    with jax.enable_x64(True):   # E(z₀): the balance of the frame z₀ → z₀ under no force
        e0 = float(np.asarray(fn(*(jnp.asarray(_pad(a)) for a in (zs[:1], np.zeros_like(forces[:1]), zs[:1]))
                                 )["energy"])[0])
    energy = np.concatenate([[e0]] + [p["energy"] for p in parts])
    return {"E": energy, "D": np.concatenate([np.asarray(p["dissipation"], np.float64) for p in parts])}


def energy_summary(series: dict | None) -> dict:
    """The run's energy behaviour: E at the start, its largest and last values, the fraction of frames with
    D ≥ −1e-6 × max E (dissipative up to float32 rounding) and the most negative D over max E."""
    if series is None:
        return {}
    e, d = series["E"], series["D"]
    scale = max(float(np.abs(e).max()), 1e-30)
    return {"E_first": float(e[0]), "E_max": float(e.max()), "E_last": float(e[-1]),
            "dissipative_fraction": float(np.mean(d >= -1e-6 * scale)), "D_min_over_E_max": float(d.min() / scale)}


def how_it_leaves(params: dict, z, past_forces, hops) -> dict:
    """The state component and node farthest outside the training envelope in ``z`` (as the state guard measures
    it: v and σ deviations over the largest training deviation, |u| over the largest training displacement) and
    that node's distance in edges from the nearest node loaded at any earlier frame (None if none was)."""
    from tignn_jax import guards

    score = np.asarray(guards._envelope_ratios(params, np.asarray(z, np.float64), np), np.float64)
    score = np.where(np.isfinite(score), score, np.inf)
    node, col = np.unravel_index(int(np.argmax(score)), score.shape)
    loaded = np.where(np.abs(np.asarray(past_forces)).sum(axis=(0, 2)) > 0)[0] if len(past_forces) else []
    return {"component": (COLUMNS[3:] + ("|u|",))[col], "node": int(node), "envelope_ratio": float(score[node, col]),
            "hops_from_load": int(hops[node, loaded].min()) if len(loaded) else None}


def flagged_frames(params: dict, zs, guard=None) -> np.ndarray:
    """[T+1] bool: the state guard's verdict on every state of a rollout (``guard``: a jitted vmap of
    `tignn_jax.state_guard`, made here if None)."""
    import tignn_jax

    guard = jax.jit(jax.vmap(tignn_jax.state_guard(params, TOLERANCE))) if guard is None else guard
    zs = np.asarray(zs, np.float32)
    return np.concatenate([np.asarray(guard(jnp.asarray(_pad(zs[i:i + CHUNK]))))[:min(CHUNK, len(zs) - i)]
                           for i in range(0, len(zs), CHUNK)])


def _pad(a):
    """``a`` padded to CHUNK rows by repeating its last row (one compiled shape for every chunk)."""
    return a if len(a) == CHUNK else np.concatenate([a, np.repeat(a[-1:], CHUNK - len(a), axis=0)])


def basic(zs, q0) -> dict:
    finite = np.isfinite(zs)
    bad = np.where(~finite.all(axis=(1, 2)))[0]
    return {"nan_or_inf": int(finite.size - np.count_nonzero(finite)),
            "first_step_non_finite": int(bad[0]) if len(bad) else None,
            "max_u": float(np.nanmax(np.linalg.norm(zs[..., :3] - q0, axis=-1))),
            "max_v": float(np.nanmax(np.linalg.norm(zs[..., 3:6], axis=-1)))}


def scene_runs(name: str, steps: int, reference_steps: int, seed: int = 0, model: str | None = None,
               policies=POLICIES, reference: str = "newton", log=print) -> dict:
    """Every loading of one scene through its model (plain and guarded) and its FEM reference: ``"newton"``, the
    FEM's backward-Euler step (`tignn_jax.fem_stepper`), or ``"linear"``, the scene's rest-linearised model (the
    FEM linearised about rest: cheap to compile, exact only for small displacements)."""
    import tignn_jax
    from fem.meshes import hop_distances

    model = model or MODELS[name]
    params, graph = tignn_jax.load_pretrained(model)
    linear, _ = tignn_jax.load_pretrained(LINEAR[name])
    info = params.get("info", {})
    scene, loads = loadings(name, steps, seed, density=info.get("fem_density"),
                            load_radius=float(info.get("fem_load_radius") or 0.0))
    q0 = np.asarray(params["mesh"]["q0"], np.float64)
    if q0.shape != scene.points.shape or not np.allclose(q0, scene.points, atol=1e-4 * np.abs(q0).max()):
        raise ValueError(f"model {model!r} is not on the {name} scene's mesh")
    z0 = graph.nodes["z"]
    zero_noise = np.zeros((steps, len(q0), 12), np.float32)
    noise = noise_for(params, steps, seed)
    hops = hop_distances(np.stack([np.asarray(graph.senders), np.asarray(graph.receivers)]), len(q0))
    rolls = steppers(params, linear)
    rolls = {k: v for k, v in rolls.items() if k == "plain" or k in policies}
    if reference not in REFERENCES:
        raise ValueError(f"reference must be one of {REFERENCES}, got {reference!r}")
    ref_step = tignn_jax.fem_stepper(linear) if reference == "newton" else tignn_jax.stepper(linear)
    fem = scan_rollout(lambda c, z, f: (c, ref_step(z, f), jnp.zeros((), bool)))
    guard = jax.jit(jax.vmap(tignn_jax.state_guard(params, TOLERANCE)))
    balance = diagnostics_fn(params)
    out = {"model": model, "model_class": params["model"].name,
           "reference": f"fem_stepper({LINEAR[name]})" if reference == "newton" else LINEAR[name],
           "nodes": len(q0), "runs": {}, "reference_runs": {}}
    references = {}
    for s in SCENARIOS:
        f_seq = jnp.asarray(loads[s], jnp.float32)
        if s != "noise":   # the noise runs are compared with the constant loading's reference
            log(f"  {name} {s}: FEM reference ({reference_steps} frames)")
            t0 = time.perf_counter()
            zr, _ = fem(z0, f_seq[:reference_steps], zero_noise[:reference_steps])
            zr = np.asarray(zr, np.float64)
            references[s] = zr
            out["reference_runs"][s] = {**basic(zr, q0), "frames": reference_steps,
                                        "wall_s": time.perf_counter() - t0,
                                        "series": {"u_max": np.nanmax(np.linalg.norm(zr[..., :3] - q0, axis=-1),
                                                                      axis=-1).tolist()}}
        zr = references["constant" if s == "noise" else s]
        u_ref = zr[..., :3] - q0
        e = noise if s == "noise" else zero_noise
        log(f"  {name} {s}: model")
        zs, _ = rolls["plain"](z0, f_seq, jnp.asarray(e))
        zs = np.asarray(zs, np.float64)
        err = displacement_error(zs, u_ref, q0)
        flags = flagged_frames(params, zs, guard)
        first = int(np.argmax(flags)) if flags.any() else None
        energy = energy_series(params, zs, loads[s], e, balance)
        run = {**basic(zs, q0), "u_error_at_reference_horizon": float(err[-1]),
               "u_error_max": float(np.nanmax(err)) if np.isfinite(err).any() else float("nan"),
               "first_step_u_error_over_10pct": first_over(err),
               "force_guard": tignn_jax.force_check(params, loads[s]),
               "first_step_state_flagged": first, "flagged_states": int(flags.sum()),
               "leaves_envelope_by": how_it_leaves(params, zs[first], loads[s][:first], hops) if first else None,
               "energy": energy_summary(energy), "guarded": {},
               "series": {"u_max": np.nanmax(np.linalg.norm(zs[..., :3] - q0, axis=-1), axis=-1).tolist(),
                          "u_error": err.tolist(),
                          **({"E": energy["E"].tolist()} if energy is not None else {})}}
        for policy in [p for p in policies if p in rolls]:
            log(f"  {name} {s}: {policy}")
            zg, fl = rolls[policy](z0, f_seq, jnp.asarray(e))
            zg, fl = np.asarray(zg, np.float64), np.asarray(fl)
            eg = displacement_error(zg, u_ref, q0)
            run["guarded"][policy] = {**basic(zg, q0), "flagged_steps": int(fl.sum()),
                                      "first_flagged_step": int(np.argmax(fl)) + 1 if fl.any() else None,
                                      "u_error_at_reference_horizon": float(eg[-1]),
                                      "first_step_u_error_over_10pct": first_over(eg), "u_error": eg.tolist()}
        out["runs"][s] = run
    return out


def fem_limit(factors=(0.9, 1.0, 1.5), frames: int = 20) -> list:
    """The explicit FEM of the beam under test case 9 at ``factors`` × its stable sub-step, ``frames`` frames:
    non-finite outputs, the inverted element and time, and what the run reported."""
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


def plot(result: dict, path: Path) -> None:
    """Per scene: the largest displacement per frame (model solid, FEM reference dashed), the model's displacement
    error against the reference, and the model's energy."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes_ = result["scenes"]
    fig, axes = plt.subplots(len(scenes_), 3, figsize=(15, 3.9 * len(scenes_)), squeeze=False)
    for row, (name, r) in zip(axes, scenes_.items()):
        for i, (s, run) in enumerate(r["runs"].items()):
            c = f"C{i}"
            row[0].semilogy(np.maximum(run["series"]["u_max"], 1e-9), color=c, label=f"{s}: {r['model']}")
            ref = r["reference_runs"].get(s)
            if ref is not None:
                row[0].semilogy(np.maximum(ref["series"]["u_max"], 1e-9), color=c, ls="--", lw=0.9,
                                label=f"{s}: FEM reference")
            row[1].semilogy(np.maximum(run["series"]["u_error"], 1e-6), color=c, label=s)
            if "E" in run["series"]:
                row[2].semilogy(np.maximum(run["series"]["E"], 1e-12), color=c, label=s)
        row[0].set(title=f"{name}: largest displacement per frame", xlabel="frame (Δt = 0.05)",
                   ylabel="max |u| (length, data units)")
        row[1].axhline(0.1, color="k", lw=0.8, ls=":", label="10 %")
        row[1].set(title=f"{r['model']}: u error against {r['reference']}", xlabel="frame (Δt = 0.05)",
                   ylabel="relative L2 error of u")
        row[2].set(title=f"{r['model']}: energy E = ½vᵀMv + ½uᵀKu", xlabel="frame (Δt = 0.05)",
                   ylabel="E (work, data units)")
        for ax in row:
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=6.5, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _leaves_text(run) -> str:
    how = run.get("leaves_envelope_by")
    if not how:
        return "—"
    return f"{how['component']} at node {how['node']}, {how['envelope_ratio']:.3g}× ({how['hops_from_load']})"


def _fmt(x, spec=".3g"):
    return "—" if x is None else format(x, spec)


def report(result: dict) -> str:
    m = result["machine"]
    lines = ["# Stress tests of the shipped models", "",
             machine_line(m) + "; load average "
             f"{m['load_average_1m']} at the start. {result['steps']}-frame rollouts from rest (Δt = 0.05; the "
             f"training horizon is 20); the FEM reference ("
             + ("`tignn_jax.fem_stepper`, the FEM's backward-Euler step by Newton–CG"
                if result["reference"] == "newton" else "the scene's rest-linearised model, the FEM linearised about "
                "rest: exact for small displacements only")
             + f") over the first {result['reference_steps']} frames."
             + (" QUICK run: short rollouts, indicative only." if result["quick"] else ""), "",
             "| scene | loading | model | NaN/Inf | max u model / FEM | max v model / FEM | u error at FEM horizon "
             "(max) | first frame u error > 10 % | force guard | first frame flagged (states flagged) | leaves the "
             "envelope by (hops from the load) | E max → last | dissipative frames (min D / max E) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in result["scenes"].items():
        for s, run in r["runs"].items():
            ref = r["reference_runs"]["constant" if s == "noise" else s]
            g, en = run["force_guard"], run["energy"]
            energy = (f"{en['E_max']:.3g} → {en['E_last']:.3g} | {100 * en['dissipative_fraction']:.1f} % "
                      f"({en['D_min_over_E_max']:.1e})") if en else "— | —"
            lines.append(
                f"| {name} | {s} | {r['model']} | {run['nan_or_inf']} | {run['max_u']:.3g} / {ref['max_u']:.3g} | "
                f"{run['max_v']:.3g} / {ref['max_v']:.3g} | {run['u_error_at_reference_horizon']:.3f} "
                f"({run['u_error_max']:.3f}) | {_fmt(run['first_step_u_error_over_10pct'], 'd')} | "
                f"{'FLAGGED' if g['out_of_distribution'] else 'ok'} ({g['max_force_ratio']:.2f}× train max) | "
                f"{_fmt(run['first_step_state_flagged'], 'd')} ({run['flagged_states']}) | {_leaves_text(run)} | "
                f"{energy} |")
    lines += ["", "The FEM reference itself (not learned; no guard):", "",
              "| scene | loading | frames | NaN/Inf | first frame non-finite | max u | max v | "
              "wall s (compile included) |",
              "|---|---|---|---|---|---|---|---|"]
    for name, r in result["scenes"].items():
        for s, ref in r["reference_runs"].items():
            lines.append(f"| {name} | {s} | {ref['frames']} | {ref['nan_or_inf']} | "
                         f"{_fmt(ref['first_step_non_finite'], 'd')} | {ref['max_u']:.3g} | {ref['max_v']:.3g} | "
                         f"{ref['wall_s']:.1f} |")
    lines += ["", "Energy: E = ½vᵀMv + ½uᵀKu of the linear model and D = W − ΔE per frame (W: the external work); "
              "backward Euler keeps D ≥ 0 in exact arithmetic. In the noise runs E is measured from each frame's "
              "noisy input, so D is the step's own dissipation.", "",
              f"Guarded (the same loads and noise): `guarded_stepper` replaces a state that leaves {TOLERANCE}× the "
              "training envelope or is not finite (`clip`: clipped into the envelope, `reset`: the body at rest; a "
              "safeguard, not physics); `fallback_stepper` hands such a body to the scene's rest-linearised model "
              f"for {FALLBACK_HOLD} frames, its stress set to the linear model's S u (`fallback`). Steps flagged "
              "count the replacements or hand-overs.", "",
              "| scene | loading | policy | NaN/Inf | steps flagged (first) | max u | u error at FEM horizon | "
              "first frame u error > 10 % |", "|---|---|---|---|---|---|---|---|"]
    for name, r in result["scenes"].items():
        for s, run in r["runs"].items():
            for policy, g in run["guarded"].items():
                lines.append(f"| {name} | {s} | {policy} | {g['nan_or_inf']} | {g['flagged_steps']} "
                             f"({_fmt(g['first_flagged_step'], 'd')}) | {g['max_u']:.3g} | "
                             f"{g['u_error_at_reference_horizon']:.3f} | "
                             f"{_fmt(g['first_step_u_error_over_10pct'], 'd')} |")
    if result.get("fem_limit"):
        lines += ["", "The explicit FEM near its stability limit (beam, test case 9; sub-step relative to the stable "
                  "one):", "", "| h / h_stable | sub-steps per frame | NaN/Inf in output | inverted element | time | "
                  "reported |", "|---|---|---|---|---|---|"]
        for row in result["fem_limit"]:
            lines.append(f"| {row['step_over_stable']:.2f} | {row['n_sub']} | {row['nan_or_inf']} | "
                         f"{row['inverted_element']} | {row['inversion_time']:.3g} | "
                         f"{'; '.join(row['reported'])[:160] or 'nothing to report'} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=1000, help="frames per rollout (default %(default)s; --quick: 40)")
    ap.add_argument("--reference-steps", type=int, default=None,
                    help="frames of the FEM reference per loading (default: all; --quick: 40)")
    ap.add_argument("--scenes", default="beam,bunny", help="scenes, of beam,bunny (default %(default)s; "
                                                           "--quick: beam)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the fingertip loads and the noise (default 0)")
    ap.add_argument("--reference", choices=REFERENCES, default=None,
                    help="the FEM reference: newton = tignn_jax.fem_stepper (the FEM's backward-Euler step; "
                         "default), linear = the scene's rest-linearised model (--quick's default)")
    ap.add_argument("--no-fem-limit", action="store_true",
                    help="skip the explicit FEM's stability-limit runs (about 40 s; --quick skips them)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: the beam, 40 frames, the rest-linearised reference, no stability-limit runs")
    ap.add_argument("--model", default=None,
                    help="a shipped model on the scene's mesh instead of the scene's default (one scene only; e.g. "
                         "--scenes beam --model beam-corot)")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="folder of stability.{json,md,png} (default %(default)s)")
    args = ap.parse_args(argv)
    steps = 40 if args.quick else args.steps
    scenes_ = ["beam"] if args.quick else [s for s in args.scenes.split(",") if s]
    reference_steps = 40 if args.quick else args.reference_steps or steps
    reference = args.reference or ("linear" if args.quick else "newton")
    if not 20 <= reference_steps <= steps:
        raise SystemExit(f"need 20 ≤ --reference-steps ≤ --steps, got {reference_steps} and {steps}")
    unknown = [s for s in scenes_ if s not in MODELS]
    if unknown or not scenes_:
        raise SystemExit(f"--scenes: unknown {unknown}; choose from {sorted(MODELS)}")
    if args.model and len(scenes_) != 1:
        raise SystemExit(f"--model {args.model} needs exactly one scene, got --scenes {','.join(scenes_)}")
    machine = describe()
    result = {"machine": machine, "steps": steps, "reference_steps": reference_steps, "reference": reference,
              "seed": args.seed,
              "quick": args.quick, "tolerance": TOLERANCE, "scenes": {}}
    for name in scenes_:
        print(f"{name} ...", flush=True)
        result["scenes"][name] = scene_runs(name, steps, reference_steps, args.seed, model=args.model,
                                            reference=reference)
    if not (args.no_fem_limit or args.quick):
        print("FEM stability limit ...", flush=True)
        result["fem_limit"] = fem_limit()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "stability.json").write_text(json.dumps(result))
    plot(result, out / "stability.png")
    md = report(result)
    (out / "stability.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
