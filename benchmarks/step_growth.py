"""Why the learned simulators diverge in long rollouts: the linear stability of their step.

For each model, ``tignn_jax.step_growth`` (power iteration on finite differences of the step) measures the
largest factor by which the step amplifies a small disturbance of the state, at:
  * rest: the unloaded body at rest (q = q0, v = 0, σ = 0) under zero force;
  * ramp end: the model's own state after the stability benchmark's "constant" loading has ramped up (step
    20 for the beam, the rise for the bunny), under the load it then holds;
  * hold +20: twenty steps later, under the same held load (skipped when the rollout is no longer finite);
  * data (beam models on the reference mesh, when ``../shared/data/abaqus_beam.npz`` is present): the true
    states of the six test cases at frame 19 under their frame-19 loads (mean and largest growth).
Each growth is measured twice, with finite differences of 1e-2 and 1e-1 state stds; where they differ by more
than 5 % the number is float32 rounding (marked in the table). ``--from-json`` re-renders a stored result. The true dynamics is damped (the FEM beam
settles within 5–10 frames after its load stops), so every
disturbance of it decays: a growth above 1 is the learned step's own instability. At rest and at the ramp end
of the first model, ARPACK (``scipy.sparse.linalg.eigs``, the same finite differences) also gives the leading
eigenvalues μ of the step's Jacobian and the rates (μ − 1)/Δt: real and positive means the step pushes that
disturbance further along itself (anti-damping); a complex pair with a small real part would instead be the
forward-Euler amplification of an undamped oscillation, √(1 + (ωΔt)²).
Writes benchmarks/results/step_growth.{json,md}.

    python benchmarks/step_growth.py [--models beam-abaqus,beam,...] [--iterations 150] [--tag NAME]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
FEATURES = ("q1", "q2", "q3", "v1", "v2", "v3", "σ11", "σ22", "σ33", "σ12", "σ13", "σ23")
DEFAULT_MODELS = ("beam-abaqus", "beam-gnn", "beam-abaqus-small", "bunny-linear", "bunny-128x6")


def scene_of(params) -> str:
    return "beam" if len(params["mesh"]["node_type"]) == 756 else "bunny"


def anchors(params, scene_name: str, hold: int = 20):
    """([(label, z, f)], frame Δt): rest, ramp end and hold +``hold`` along the model's own rollout under the
    stability benchmark's constant loading (the states as far as they are finite)."""
    import jax.numpy as jnp
    from stability import loadings
    from tignn_jax import api

    from tignn_jax import graph as G

    info = params.get("info", {})
    scene, loads = loadings(scene_name, 200, density=info.get("fem_density"),
                            load_radius=float(info.get("fem_load_radius", 0.0)))
    forces = loads["constant"]
    ramp = int(np.argmax(np.all(forces[1:] == forces[:-1], axis=(1, 2)))) + 1   # first step of the held load
    rest = G.rest_state(params["mesh"]["q0"])
    out = [("rest", rest, np.zeros((len(rest), 3), np.float32))]
    fn = api.stepper(params)
    z = jnp.asarray(rest)
    for k in range(ramp + hold):
        if k == ramp:
            out.append((f"ramp end (step {ramp})", np.asarray(z), forces[k].astype(np.float32)))
        z = fn(z, jnp.asarray(forces[k], jnp.float32))
    if np.all(np.isfinite(np.asarray(z))):
        out.append((f"hold +{hold} (step {ramp + hold})", np.asarray(z), forces[ramp + hold].astype(np.float32)))
    return out, scene.frame_dt


def leading_eigenvalues(params, z, f, k: int = 6) -> list:
    """The k eigenvalues of the step's Jacobian (state-std units, prescribed entries left out) of largest
    modulus, by ARPACK on ``tignn_jax.step_jacobian``, the finite differences ``step_growth`` iterates."""
    from scipy.sparse.linalg import LinearOperator, eigs
    from tignn_jax import api

    jac = api.step_jacobian(params, z, f)
    shape = np.shape(z)

    def matvec(x):
        return np.asarray(jac(np.real(np.asarray(x)).reshape(shape)), np.float64).ravel()

    op = LinearOperator((np.size(z), np.size(z)), matvec=matvec, dtype=np.float64)
    vals = eigs(op, k=k, which="LM", ncv=max(3 * k, 20), tol=1e-4, return_eigenvectors=False)
    return sorted(vals, key=lambda v: -abs(v))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default=",".join(DEFAULT_MODELS), help="shipped names or model.npz paths")
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--tag", default="", help="write step_growth_TAG.* instead of step_growth.*")
    ap.add_argument("--from-json", default="", help="only re-render the .md of a stored step_growth*.json")
    args = ap.parse_args()
    if args.from_json:
        path = Path(args.from_json)
        path.with_suffix(".md").write_text(render(json.loads(path.read_text())))
        print(f"wrote {path.with_suffix('.md')}")
        return
    warnings.filterwarnings("ignore")
    from tignn_jax import api
    from tignn_jax import data as D

    machine = describe()
    reference = None
    path = D.reference_path()
    if path.exists():
        reference = D.load(path)
    rows = []
    eig_rows = []
    t_start = time.time()
    for i, name in enumerate([m for m in args.models.split(",") if m]):
        params, _ = api.load_pretrained(name)
        scene = scene_of(params)
        states, dt = anchors(params, scene)
        if scene == "beam" and reference is not None:
            test = D.split_rows(reference, "test")
            growths = [api.step_growth(params, reference.z[r, 19], reference.f[r, 19],
                                       iterations=args.iterations)["growth"] for r in test]
            data_growth = {"mean": float(np.mean(growths)), "max": float(np.max(growths)), "cases": len(test)}
        else:
            data_growth = None
        for label, z, f in states:
            g = api.step_growth(params, z, f, iterations=args.iterations)
            # the same with 10x the finite difference: a measure that moves with it is float32 rounding, not the
            # Jacobian (a frame_solve model's dense solve cancels large stiff terms away from rest)
            check = api.step_growth(params, z, f, iterations=max(args.iterations // 3, 30), eps=1e-1)["growth"]
            top = np.argsort(-g["feature_share"])[:2]
            rows.append({"model": name, "scene": scene, "anchor": label, "growth": g["growth"],
                         "growth_eps_0.1": check, "rounding_limited": bool(abs(check / g["growth"] - 1) > 0.05),
                         "mode_features": {FEATURES[j]: float(g["feature_share"][j]) for j in top},
                         "top_node": g["top_node"],
                         "top_node_q0": [round(float(c), 2) for c in np.asarray(params["mesh"]["q0"])[g["top_node"]]],
                         "top_node_clamped": bool(params["mesh"]["node_type"][g["top_node"]] != 0)})
            print(f"{name:>20s} {label:>22s}: growth {g['growth']:.4f}  mode "
                  + ", ".join(f"{FEATURES[j]} {g['feature_share'][j]:.2f}" for j in top), flush=True)
            if i == 0 and not label.startswith("hold"):
                vals = leading_eigenvalues(params, z, f)
                eig_rows.append({"model": name, "anchor": label,
                                 "mu": [[float(v.real), float(v.imag)] for v in vals],
                                 "rate": [[float((v.real - 1) / dt), float(v.imag / dt)] for v in vals]})
        if data_growth is not None:
            rows.append({"model": name, "scene": scene, "anchor": "data: test states at frame 19",
                         "growth": data_growth["max"], "growth_mean": data_growth["mean"]})
            print(f"{name:>20s} data frame 19: mean {data_growth['mean']:.4f}, max {data_growth['max']:.4f}")
    result = {"machine": machine, "iterations": args.iterations, "rows": rows, "eigenvalues": eig_rows,
              "wall_s": time.time() - t_start}
    stem = f"step_growth_{args.tag}" if args.tag else "step_growth"
    write_results(stem, result, render(result), RESULTS, echo=False)
    print(f"wrote {RESULTS / stem}.{{json,md}} in {time.time() - t_start:.0f} s")


def render(result: dict) -> str:
    """The Markdown report of a result (``--from-json`` re-renders a stored one)."""
    machine, rows, eig_rows = result["machine"], result["rows"], result["eigenvalues"]
    lines = ["# Linear stability of the learned step", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']}; "
             f"{result['iterations']} power iterations per state (finite differences of size 1e-2 state stds; "
             "`tignn_jax.step_growth`). Growth = the largest eigenvalue modulus of the step's Jacobian: the factor "
             "by which a small disturbance grows per step. The true, damped dynamics contracts (< 1)."
             + (" In brackets the same with a 10× larger difference (fewer iterations); where the two differ by "
                "more than 5 % the measure is float32 rounding rather than the Jacobian (marked: the bunny models "
                "away from rest, whose positions of ~50 are stored in float32 against velocity and stress stds "
                "of 1e-2 and 1e-3; `bunny-linear`'s step is affine, so its Jacobian everywhere is the one "
                "measured at rest)." if any("growth_eps_0.1" in r for r in rows) else
                " (Measured before the second difference size was added: beam models only, whose growth "
                "agrees within 1–4 % between differences of 1e-2 and 1e-1 in `step_growth.md`.)"), "",
             "| model | state | growth per step | mode (largest feature shares) | where |", "|---|---|---|---|---|"]
    for r in rows:
        if "mode_features" in r:
            where = (f"node {r['top_node']} at ({', '.join(f'{c:.1f}' for c in r['top_node_q0'])})"
                     + (" (clamped)" if r["top_node_clamped"] else ""))
            mode = ", ".join(f"{k} {v:.2f}" for k, v in r["mode_features"].items())
            growth = f"{r['growth']:.3f}"
            if "growth_eps_0.1" in r:
                growth += f" (ε 0.1: {r['growth_eps_0.1']:.3f})"
                if r["rounding_limited"]:
                    growth += " **rounding-limited**"
            lines.append(f"| {r['model']} | {r['anchor']} | {growth} | {mode} | {where} |")
        else:
            lines.append(f"| {r['model']} | {r['anchor']} | {r['growth']:.3f} (largest; mean "
                         f"{r['growth_mean']:.3f}) | | |")
    if eig_rows:
        lines += ["", "Leading eigenvalues μ of the step's Jacobian and the rates (μ − 1)/Δt (ARPACK, same "
                  "finite differences):", "", "| model | state | μ | rate (1/s) |", "|---|---|---|---|"]
        for e in eig_rows:
            mus = ", ".join(f"{a:.3f}{b:+.3f}i" for a, b in e["mu"])
            rates = ", ".join(f"{a:.2f}{b:+.2f}i" for a, b in e["rate"])
            lines.append(f"| {e['model']} | {e['anchor']} | {mus} | {rates} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
