"""Can an implicit step built on the rest state's tangent carry the beam's non-linear dynamics?

``frame_solve`` and ``linear_prior`` (`tignn_jax.framesolve`) treat the stiff part of a frame implicitly with the
FEM's rest Jacobian: the solve with A₀ = (1 + αh)M/h² + K₀. This rolls out such steps on the held-out reference
and fingertip cases of the FEM (grouped as `interactions.py` groups them), with no network:

* ``linear``: the rest linearisation itself, force K₀u and stress increments S₀Δu (the step of `beam-linear`
  and of an untrained ``linear_prior`` model, `framesolve.prior_step` with a zero correction);
* ``exact force``: the same solve, but the FEM's internal force f_int(u) and nodal stress σ(u) at the current
  displacement in place of K₀u and S₀u (a W-method: linearly implicit Euler whose Jacobian is the rest one).
  This is the best a ``linear_prior`` correction could reach if it learned the force's and stress's
  non-linear remainder exactly, one step at a time::

      Δv = A₀⁻¹ [f − α M v − f_int(u) − h K₀ v] / h,   u' = u + h (v + Δv),   σ' = σ(u');

* ``exact force, rotated solve``: the same with the rest tangent turned with the body, R A₀⁻¹ Rᵀ and R K₀ Rᵀ,
  R block-diagonal with each node's rotation (`tignn_jax.newton.rotations`: the polar factor of the least-squares
  deformation gradient over the node's edges), the warped-stiffness idea applied to the solve;
* ``backward Euler, rotated, k iterations``: k simplified-Newton iterations on the backward-Euler residual with
  the fixed matrix (1 + αh)M + h² R K₀ Rᵀ;
* ``backward Euler, 1 Newton step, k CG``: one Newton step of backward Euler from Δv = 0 with the exact tangent
  at the predictor u + h v (applied as Kᵀw by `jax.vjp`), solved by k conjugate-gradient iterations
  preconditioned with R A₀⁻¹ Rᵀ / h² (the package's `tignn_jax.newton`, a fallback step); ``from v' = 0``: the
  iteration starts from v' = 0, the predictor u (the package's default: after a sudden load the predictor
  u + h v overshoots and one Newton step from it diverges, `tests/test_newton.py`).

For a nearly incompressible body (the beam: bulk modulus 2/D1 = 2e7, shear 3.1e5) the rest tangent's stiff
volumetric modes point along the rest geometry; once an element rotates, its volumetric stiffness acts along
rotated directions that the solve with K₀ no longer holds implicitly, and the explicit remainder is stiff.
Errors relative to each case's largest true norm, as in `interactions.py`; the cost of one step of each kind
from the same state, timed in turn.

    python benchmarks/rest_tangent.py [--splits test] [--tag NAME]

Writes benchmarks/results/rest_tangent[_TAG].{json,md}.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, interleaved_ms, write_results  # noqa: E402
from interactions import groups, peak_errors, profiles_of  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]
ITERATIONS = {"backward Euler, rotated, 1 iteration": 1, "backward Euler, rotated, 3 iterations": 3}
NEWTON_CG = {   # kind: (Newton iterations, CG iterations each, predictor: tignn_jax.newton.newton_cg)
    "backward Euler, 1 Newton step, 5 CG": (1, 5, "velocity"),
    "backward Euler, 1 Newton step from v' = 0, 5 CG": (1, 5, "zero"),
    "backward Euler, 2 Newton steps from v' = 0, 2 CG each": (2, 2, "zero"),
    "backward Euler, 2 Newton steps from v' = 0, 3 CG each": (2, 3, "zero"),   # tignn_jax.newton's default
    "backward Euler, 3 Newton steps from v' = 0, 2 CG each": (3, 2, "zero")}
KINDS = ("linear", "exact force", "exact force, rotated solve", *ITERATIONS, *NEWTON_CG)


def scene_operators(problem, material, lin, node_type, q0, dt: float) -> dict:
    """What every step kind shares, built once per scene: the rest linearisation ``lin``
    (`fem.implicit.RestLinearization`) as ``framesolve`` entries with the dense A₀⁻¹ ("norm"), the FEM's internal
    force and nodal stress ("force", "stress"), the node types and the rest positions."""
    import jax.numpy as jnp

    from fem import implicit
    from tignn_jax import framesolve as FS

    norm = {**FS.norm_entries(lin), "dt": np.array([dt], np.float32)}
    force, stress = implicit.force_and_stress(problem, material)
    return {"norm": {k: jnp.asarray(v) for k, v in FS.with_inverse(norm, np.asarray(node_type)).items()},
            "force": force, "stress": stress, "node_type": jnp.asarray(node_type), "x0": jnp.asarray(q0, jnp.float32)}


def make_step(kind: str, ops: dict, edges=None):
    """A jitted step (z [N,12], f [N,3]) → z_next of the given kind (see the module docstring) on a scene's
    `scene_operators`; the rotated kinds need the mesh edges [2,E]."""
    import jax
    import jax.numpy as jnp

    from tignn_jax import framesolve as FS
    from tignn_jax.newton import newton_cg, rotations

    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    norm, nt, x0, force, stress = (ops[k] for k in ("norm", "node_type", "x0", "force", "stress"))
    if kind == "linear":
        zero = lambda z: jnp.zeros_like(z)
        return jax.jit(lambda z, f: z + FS.prior_step(norm, z, f, zero(z), nt, x0))
    h, alpha, free, m = FS._constants(norm, nt, jnp.float32)
    rotated = kind != "exact force"
    if rotated and edges is None:
        raise ValueError("the rotated solve needs the mesh edges [2,E]")
    rotation = rotations(x0, *(jnp.asarray(e, jnp.int32) for e in edges)) if rotated else None
    if kind in NEWTON_CG:    # Newton iterations by preconditioned CG: the package's step (tignn_jax.newton)
        newton, cg, predictor = NEWTON_CG[kind]
        return jax.jit(newton_cg(norm, nt, x0, force, stress, rotation, cg, newton, predictor))
    solve = lambda w, turn, back: turn((norm["fs_ainv"] @ (back(w) * free).reshape(-1)).reshape(-1, 3)) * free

    def step(z, f):
        u, v = (z[:, :3] - x0) * free, z[:, 3:6] * free
        if rotated:   # R A₀⁻¹ Rᵀ and R K₀ Rᵀ with per-node rotations: the rest tangent turned with the body
            rot = rotation(z[:, :3])
            back, turn = (lambda w: jnp.einsum("nji,nj->ni", rot, w)), (lambda w: jnp.einsum("nij,nj->ni", rot, w))
        else:
            back = turn = lambda w: w
        if kind in ITERATIONS:   # simplified Newton on backward Euler, (M(1 + αh) + h² R K₀ Rᵀ) the fixed matrix
            dv = jnp.zeros_like(v)
            for _ in range(ITERATIONS[kind]):
                r = h * (f - force(u + h * (v + dv)) - alpha * m * (v + dv)) - m * dv
                dv = dv + solve(r * free / h ** 2, turn, back)
        else:            # one W-method step: f_int(u + h v) linearised about u with the (turned) rest tangent
            rhs = (h * (f - alpha * m * v - force(u)) - h * h * turn(FS.apply_k(norm, back(v)))) * free / h ** 2
            dv = solve(rhs, turn, back)
        u_next = u + h * (v + dv)
        return jnp.concatenate([x0 + u_next, v + dv, stress(u_next).astype(z.dtype)], axis=1)

    return jax.jit(step)


def rollouts(step, z0, forces) -> np.ndarray:
    """[C, T+1, N, 12] states of ``step`` from z0 [C,N,12] under forces [C,T,N,3] (lax.scan, cases vmapped)."""
    import jax
    import jax.numpy as jnp

    def one(z, fs):
        return jax.lax.scan(lambda c, f: (step(c, f),) * 2, z, fs)[1]

    z0 = jnp.asarray(z0, jnp.float32)
    states = jax.jit(jax.vmap(one))(z0, jnp.asarray(forces, jnp.float32))
    return np.concatenate([np.asarray(z0)[:, None], np.asarray(states)], axis=1)


def errors(pred, true, q0) -> dict:
    """Peak-relative errors of rollouts over their finite cases (`interactions.peak_errors`), with the count of
    finite rollouts and the first non-finite step of each other one."""
    ok = np.all(np.isfinite(pred), axis=(2, 3))              # [C, T+1]
    finite = ok.all(axis=1)
    out = {"cases": int(len(pred)), "finite": int(finite.sum()),
           "first_non_finite_step": [int(np.argmin(c)) for c in ok if not c.all()]}
    if finite.any():
        out.update(peak_errors(pred[finite], np.asarray(true)[finite], q0))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene-file", default="data/beam_ref_d60.npz",
                    help="a generated file of the scene (its cells and material build the FEM's force and tangent)")
    ap.add_argument("--reference", default="data/beam_ref_f2.npz", help="the reference cases (FEM)")
    ap.add_argument("--interactions", default="data/beam_int_f2.npz", help="the fingertip cases (FEM)")
    ap.add_argument("--profiles", default="data/beam_int_smooth_d60.npz",
                    help="the file the fingertip cases were generated into (its metadata names the profiles)")
    ap.add_argument("--splits", default="test", help="comma-separated split names, each reported apart")
    ap.add_argument("--repeats", type=int, default=50, help="timed steps per kind (median reported)")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)

    from fem import implicit
    from tignn_jax import data as D
    from tignn_jax import framesolve as FS

    for path in (args.scene_file, args.reference, args.interactions, args.profiles):
        if not (ROOT / path).exists():
            print(f"{path} not found (generate the beam data sets first): nothing to measure")
            return 1
    reference, interactions = D.load(ROOT / args.reference), D.load(ROOT / args.interactions)
    problem, material = FS.problem_from_file(ROOT / args.scene_file)
    t0 = time.perf_counter()
    lin = implicit.rest_linearization(problem, material)
    build_s = time.perf_counter() - t0
    ops = scene_operators(problem, material, lin, reference.node_type, reference.q0, float(reference.dt))
    steps = {k: make_step(k, ops, reference.edges) for k in KINDS}
    profiles = profiles_of(ROOT / args.profiles)
    splits = [s for s in args.splits.split(",") if s]
    # cost: one step from a mid-case state of the first test fingertip case, all kinds in turn (after compiling)
    case = D.split_rows(interactions, "test")[0]
    z_mid, f_mid = (np.asarray(a, np.float32) for a in (interactions.z[case, 10], interactions.f[case, 10]))
    ms = interleaved_ms({k: (lambda st=st: st(z_mid, f_mid)) for k, st in steps.items()}, args.repeats)
    result = {"machine": describe(), "scene_file": args.scene_file, "linearisation_s": round(build_s, 1),
              "ms_per_step": {k: float(np.median(v)) for k, v in ms.items()}, "repeats": args.repeats, "kinds": {}}
    for kind, step in steps.items():
        rows = {}
        for s in splits:
            for g, data, r in groups(reference, interactions, profiles, s):
                pred = rollouts(step, data.z[r, 0], data.f[r])
                rows[f"{s}/{g}"] = errors(pred, data.z[r], data.q0)
        result["kinds"][kind] = rows
        print(kind, json.dumps({g: (round(x["u"], 4) if "u" in x else None, x["finite"]) for g, x in rows.items()}),
              flush=True)

    stem = "rest_tangent" + (f"_{args.tag}" if args.tag else "")
    m = result["machine"]
    lines = ["# Implicit steps on the rest tangent: the beam's held-out cases", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']} ({m['backend']}); the rest linearisation "
             f"built in {build_s:.0f} s.", "",
             f"Data: `{args.reference}` and `{args.interactions}` (profiles from `{args.profiles}`); the scene from "
             f"`{args.scene_file}`. No network; every step is described in `benchmarks/rest_tangent.py`. ms per "
             f"step: median of {args.repeats} steps from one mid-case state after compiling, the steps timed in turn "
             "(single process, XLA's default threading). Errors relative to each case's largest true norm, mean over the "
             "finite cases and their snapshots; finite: rollouts with no NaN/Inf; the others' first non-finite step.", "",
             "| step | ms per step | split/group | cases | finite | first non-finite steps | u | v | σ | q | u max |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for kind, rows in result["kinds"].items():
        t = result["ms_per_step"][kind]
        for g, r in rows.items():
            vals = " | ".join(f"{r[k]:.3g}" if k in r else "–" for k in ("u", "v", "sigma", "q", "u_max"))
            bad = ", ".join(map(str, sorted(r["first_non_finite_step"]))) or "–"
            lines.append(f"| {kind} | {t:.2f} | {g} | {r['cases']} | {r['finite']} | {bad} | {vals} |")
    write_results(stem, result, "\n".join(lines) + "\n", RESULTS, echo=False)
    print(f"wrote {RESULTS / stem}.{{json,md}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
