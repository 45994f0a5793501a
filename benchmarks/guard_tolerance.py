"""How tight the learned beam's guard should be: the fallback stepper at several envelope tolerances, against
the FEM.

``api.fallback_stepper`` hands a body to the rest-linearised FEM (``beam-linear``) for ``--hold`` steps when its
learned state leaves ``tolerance`` × the training envelope (``api.state_guard``). A looser tolerance keeps the
network running longer (fewer hand-overs); a tighter one hands over before the network has drifted as far. This
runs the five loadings of ``benchmarks/stability.py`` (release, constant, fingertip, 3× load, 1 % state noise;
``--steps`` steps each) through the fallback stepper at each of ``--tolerances`` and reports the hand-overs, the
non-finite values and the displacement error against the FEM over its first ``--fem-steps`` steps (L2 over the
nodes, relative to the FEM's largest displacement over that horizon, as ``stability.py``): at the horizon, its
mean and its maximum over the horizon. Writes benchmarks/results/guard_tolerance.{json,md}.

    python benchmarks/guard_tolerance.py [--model beam-abaqus-64x2] [--tolerances 1.25,1.5,2,3] [--steps 300]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stability  # noqa: E402
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def sweep(model: str, tolerances, steps: int, fem_steps: int, hold: int = 30) -> dict:
    """{"runs": {tolerance: {scenario: {...}}}, "mean": {tolerance: {...}}} for ``model`` on the beam scene."""
    import fem
    from fem import scenes
    from tignn_jax import api

    if steps < 20:
        raise ValueError(f"steps must be at least 20 (the loadings start with the 20-frame load ramp), got {steps}")
    if fem_steps > steps:
        raise ValueError(f"fem_steps ({fem_steps}) must not exceed steps ({steps})")
    params, graph = api.load_pretrained(model)
    scene, loads = stability.loadings("beam", steps)
    q0 = np.asarray(params["mesh"]["q0"], np.float64)
    units = float(np.sum(q0 * scene.points) / np.sum(scene.points ** 2))
    fem_names = [s for s in stability.SCENARIOS if s != "noise"]
    problem = scenes.setup_scene(scene._replace(n_frames=fem_steps))
    batch = fem.Loads(nodal=jnp.asarray(np.stack([loads[s][:fem_steps] for s in fem_names])))
    fem_q = np.asarray(fem.simulate_batch(problem, scene.material, batch).q) * units   # [S, fem_steps+1, N, 3]
    linear = stability.fallback_model(model, params, scene)
    z_std, node_type = params["norm"]["z_std"], graph.nodes["node_type"]
    runs = {}
    for tol in tolerances:
        guarded = api.fallback_stepper(params, linear, hold=hold, tolerance=tol)
        runs[tol] = {}
        for s in stability.SCENARIOS:
            qf = fem_q[fem_names.index("constant" if s == "noise" else s)]
            # the data's convention for the first velocity, as stability.py: a one-sided difference of the FEM's q
            z = graph.nodes["z"].at[:, 3:6].set(jnp.asarray((-3 * qf[0] + 4 * qf[1] - qf[2]) / (2 * scene.frame_dt),
                                                            jnp.float32))
            zs, flags = stability.rollout(stability.holding(guarded), z, s, jnp.asarray(loads[s], jnp.float32),
                                          jax.random.PRNGKey(1), steps, z_std, node_type)
            err = stability.displacement_error(zs, qf - q0, q0)
            runs[tol][s] = {"hand_overs": int(sum(flags)), "nan_or_inf": int(np.size(zs) - np.isfinite(zs).sum()),
                            "u_error_at_fem_horizon": float(err[-1]), "u_error_mean": float(np.mean(err[1:])),
                            "u_error_max": float(np.max(err[1:]))}
    mean = {tol: {k: float(np.mean([r[k] for r in rows.values()]))
                  for k in ("hand_overs", "u_error_at_fem_horizon", "u_error_mean", "u_error_max")}
            for tol, rows in runs.items()}
    return {"runs": runs, "mean": mean}


def format_md(result: dict) -> str:
    m, a = result["machine"], result["args"]
    lines = ["# The learned beam's guard tolerance against the FEM", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']}. Model `{a['model']}` through "
             f"`api.fallback_stepper` (hold {a['hold']} steps on `beam-linear`) at each tolerance (× the training "
             f"envelope, `api.state_guard`); the five loadings of `stability.py`, {a['steps']} steps each; u error "
             f"against the FEM over its first {a['fem_steps']} steps (L2, relative to the FEM's largest displacement "
             f"over them). {result['wall_s']:.0f} s.", "",
             "| tolerance | loading | hand-overs | NaN/Inf | u error at step " + str(a["fem_steps"]) +
             " | u error, mean over the horizon | u error, max over the horizon |", "|---|---|---|---|---|---|---|"]
    for tol, rows in result["runs"].items():
        for s, r in rows.items():
            lines.append(f"| {tol} | {s} | {r['hand_overs']} | {r['nan_or_inf']} | {r['u_error_at_fem_horizon']:.3f} | "
                         f"{r['u_error_mean']:.3f} | {r['u_error_max']:.3f} |")
        mm = result["mean"][tol]
        lines.append(f"| {tol} | **mean of the five** | {mm['hand_overs']:.1f} | | {mm['u_error_at_fem_horizon']:.3f} | "
                     f"**{mm['u_error_mean']:.3f}** | {mm['u_error_max']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="beam-abaqus-64x2")
    ap.add_argument("--tolerances", default="1.25,1.5,2,3", help="comma-separated envelope tolerances")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--fem-steps", type=int, default=100)
    ap.add_argument("--hold", type=int, default=30)
    ap.add_argument("--tag", default="", help="write guard_tolerance_TAG.* instead")
    args = ap.parse_args(argv)
    try:
        tolerances = [float(t) for t in args.tolerances.split(",") if t]
    except ValueError:
        raise SystemExit(f"--tolerances must be comma-separated numbers, got {args.tolerances!r}")
    if not tolerances or min(tolerances) <= 0:
        raise SystemExit(f"--tolerances must be positive, got {args.tolerances!r}")
    t0 = time.perf_counter()
    result = sweep(args.model, tolerances, args.steps, args.fem_steps, args.hold)
    result.update(machine=describe(), args=vars(args), wall_s=time.perf_counter() - t0)
    stem = f"guard_tolerance_{args.tag}" if args.tag else "guard_tolerance"
    write(result, stem)
    return 0


def write(result: dict, stem: str) -> None:
    """``stem``.json and .md in ``RESULTS`` (tolerances as the JSON's keys, as strings); prints the table."""
    result = {**result, "runs": {str(k): v for k, v in result["runs"].items()},
              "mean": {str(k): v for k, v in result["mean"].items()}}
    write_results(stem, result, format_md(result), RESULTS)


if __name__ == "__main__":
    sys.exit(main())
