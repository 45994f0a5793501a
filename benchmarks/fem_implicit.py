r"""The implicit FEM (backward Euler at the frame step, `fem.implicit`) as a cheaper baseline than the explicit one.

Beam: the six test cases of the Abaqus data (sims 9, 10, 12, 13, 38, 44), reference mesh, the reference scene's
material and damping; errors as in benchmarks/pareto.py (relative L2 over all 756 nodes, mean over snapshots
1..20 and cases; the FEM's v = numpy.gradient of its q, the data's convention) for the explicit solver and the
implicit one with 1, 2 and 4 backward-Euler steps per frame. Bunny: one point-load case (rise over 10
frames), implicit against explicit (its own stable sub-step): the mean relative L2 difference of u over the
frames. Cost: median wall time of a run of one case after compilation, per frame; the preconditioner
(computed once per mesh and step) is reported separately. Both solvers are timed in the same run.

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \
        taskset -c 0 python benchmarks/fem_implicit.py [--repeats 5]
    python benchmarks/fem_implicit.py --quick --out /tmp/fem_implicit     # smoke run, ~40 s

``--quick``: one test case, its first 2 frames, one run each, 1 implicit step per frame only, no bunny; the
preconditioner is the shipped ``beam-linear`` model's A⁻¹ (the same rest operator at the frame step, built when
the model loads), not a new linearisation. Writes fem_implicit.{json,md} to ``--out`` (default
benchmarks/results).
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
from _machine import describe, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
TEST_SIMS = (9, 10, 12, 13, 38, 44)


def _median_ms(fn, repeats: int, warm: bool = True) -> float:
    """Median wall time [ms] of ``repeats`` calls of ``fn``, after a compiling call unless ``warm`` is False (fn
    already ran)."""
    if warm:
        jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(times))


QUICK_FRAMES = 2


def beam(repeats: int, quick: bool = False) -> list:
    from fem import Loads, implicit, simulate, simulate_batch
    from fem import scenes as fs
    from tignn_jax import data as D
    from tignn_jax import evaluation as EV

    path = D.reference_path()
    if not path.exists():
        raise SystemExit(f"reference data not found at {path}")
    data = D.load(path)
    rows = D.split_rows(data, list(TEST_SIMS[:1] if quick else TEST_SIMS))
    frames = QUICK_FRAMES if quick else data.f.shape[1]
    scene = fs.beam_scene()
    problem = fs.setup_scene(scene._replace(n_frames=frames))
    forces = jnp.asarray(fs.beam_reference_forces(scene, data.sim_id[rows])[:, :frames], jnp.float32)
    true = data.z[rows, :frames + 1]

    def errors(q, sig):
        q, sig = np.asarray(q, np.float64), np.asarray(sig, np.float64)
        v = np.gradient(q, float(data.dt), axis=1, edge_order=2)
        e = EV.relative_errors(np.concatenate([q, v, sig], -1), true, data.q0)[:, 1:]
        return {k: float(np.mean(e[..., i])) for i, k in enumerate(("q", "v", "sigma", "u"))}

    out = []
    one = Loads(nodal=forces[0])
    if quick:   # one case: its errors from the single-case run that is timed (one compilation less)
        res = jax.tree_util.tree_map(lambda a: a[None], simulate(problem, scene.material, one, on_inversion="ignore"))
    else:
        res = simulate_batch(problem, scene.material, Loads(nodal=forces))
    ms = _median_ms(lambda: simulate(problem, scene.material, one, on_inversion="ignore").q, repeats, warm=not quick)
    out.append(dict(name="explicit (stable sub-step)", steps_per_frame=problem.config.n_sub,
                    ms_per_frame=ms / frames, **errors(res.q, res.sigma)))
    for n_sub in ((1,) if quick else (1, 2, 4)):
        t0 = time.perf_counter()
        pinv = shipped_preconditioner(scene) if quick else implicit.preconditioner(problem, scene.material, n_sub)
        pre_s = time.perf_counter() - t0
        if quick:
            res, diag = jax.tree_util.tree_map(lambda a: a[None], implicit.simulate_implicit(
                problem, scene.material, one, pinv, n_sub=n_sub))
        else:
            res, diag = implicit.simulate_implicit_batch(problem, scene.material, Loads(nodal=forces), pinv,
                                                         n_sub=n_sub)
        ms = _median_ms(lambda: implicit.simulate_implicit(problem, scene.material, one, pinv, n_sub=n_sub)[0].q,
                        repeats, warm=not quick)
        out.append(dict(name=f"implicit, {n_sub} step(s) per frame", steps_per_frame=n_sub,
                        ms_per_frame=ms / frames, preconditioner_s=pre_s,
                        preconditioner="beam-linear's A⁻¹" if quick else "fem.implicit.preconditioner",
                        newton_residual_max=float(np.max(diag.residual)),
                        newton_iterations_max=int(np.max(diag.newton_iterations)), **errors(res.q, res.sigma)))
    return out


def shipped_preconditioner(scene):
    """The shipped ``beam-linear`` model's A⁻¹ [3N, 3N]: the inverse of the beam's rest operator
    (1 + αΔt) M / Δt² + K₀ at the frame step (identity on the clamped nodes), what `fem.implicit.preconditioner`
    computes for one step per frame; checked to be built for the scene's damping and density."""
    import tignn_jax

    linear, _ = tignn_jax.load_pretrained("beam-linear")
    info = linear["info"]
    if not (np.isclose(info.get("fem_damping", np.nan), scene.damping, rtol=1e-6)
            and np.isclose(info.get("fem_density", np.nan), scene.material.density, rtol=1e-6)):
        raise SystemExit("beam-linear was built for another damping or density than the beam scene")
    return jnp.asarray(linear["arrays"]["ainv"])


def bunny(repeats: int) -> list:
    from fem import Loads, implicit, simulate
    from fem import cases as cs
    from fem import scenes as fs

    scene = fs.bunny_scene()
    problem = fs.setup_scene(scene)
    f, nodes = cs.point_load_forces(scene, 100, 0, rise_frames=10)
    loads = Loads(nodal=jnp.asarray(f[1], jnp.float32))
    ref = simulate(problem, scene.material, loads)
    ms_exp = _median_ms(lambda: simulate(problem, scene.material, loads, on_inversion="ignore").q, repeats)
    t0 = time.perf_counter()
    pinv = implicit.preconditioner(problem, scene.material)
    pre_s = time.perf_counter() - t0
    res, diag = implicit.simulate_implicit(problem, scene.material, loads, pinv)
    ms_imp = _median_ms(lambda: implicit.simulate_implicit(problem, scene.material, loads, pinv)[0].q, repeats)
    u_ref = np.asarray(ref.q, np.float64)[1:] - scene.points
    u_imp = np.asarray(res.q, np.float64)[1:] - scene.points
    rel = np.sqrt(((u_imp - u_ref) ** 2).sum((1, 2)) / (u_ref ** 2).sum((1, 2)))
    return [dict(name="explicit (stable sub-step)", steps_per_frame=problem.config.n_sub, ms_per_frame=ms_exp / 20),
            dict(name="implicit, 1 step per frame", steps_per_frame=1, ms_per_frame=ms_imp / 20,
                 preconditioner_s=pre_s, newton_residual_max=float(np.max(diag.residual)),
                 newton_iterations_max=int(np.max(diag.newton_iterations)),
                 u_difference_to_explicit_mean=float(rel.mean()), u_difference_to_explicit_last=float(rel[-1]),
                 load_node=int(nodes[1]))]


def report(result: dict) -> str:
    m = result["machine"]
    frames = result.get("frames", 20)
    lines = ["# The implicit FEM as a baseline" + (" (QUICK smoke run)" if result.get("quick") else ""), "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']}; load average {m['load_average_1m']} at the "
             f"start. XLA_FLAGS=`{result['xla_flags']}`. Cost: median of {result['repeats']} {frames}-frame runs of "
             "one case after compilation, per frame; the preconditioner (dense rest operator, once per mesh and step) "
             "is listed apart." + (" QUICK: one test case, its first 2 frames, the preconditioner taken from the "
                                   "shipped beam-linear model." if result.get("quick") else ""), "",
             "## Beam, Abaqus test split (errors against the Abaqus data, as in pareto.md)", "",
             "| solver | steps per frame | ms per frame | × faster than explicit | u | v | σ | q | "
             "preconditioner [s] | Newton residual max / iterations max |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    base = result["beam"][0]["ms_per_frame"]
    for r in result["beam"]:
        pre = f"{r['preconditioner_s']:.1f}" if "preconditioner_s" in r else "–"
        newton = (f"{r['newton_residual_max']:.1e} / {r['newton_iterations_max']}" if "newton_residual_max" in r
                  else "–")
        lines.append(f"| {r['name']} | {r['steps_per_frame']} | {r['ms_per_frame']:.2f} | "
                     f"{base / r['ms_per_frame']:.1f} "
                     f"| {r['u']:.4f} | {r['v']:.4f} | {r['sigma']:.4f} | {r['q']:.2e} | {pre} | {newton} |")
    b = result.get("bunny")
    if not b:
        return "\n".join(lines) + "\n"
    lines += ["", "## Bunny, one point load (load case 2 of `tignn generate bunny`, rise over 10 frames)", "",
              f"Explicit: {b[0]['steps_per_frame']} sub-steps per frame, {b[0]['ms_per_frame']:.1f} ms per frame. "
              f"Implicit (1 step per frame): {b[1]['ms_per_frame']:.1f} ms per frame "
              f"({b[0]['ms_per_frame'] / b[1]['ms_per_frame']:.1f}× faster), preconditioner "
              f"{b[1]['preconditioner_s']:.0f} s once; u differs from the explicit run by "
              f"{b[1]['u_difference_to_explicit_mean']:.3f} (relative L2, mean over frames; "
              f"{b[1]['u_difference_to_explicit_last']:.3f} at the last frame); Newton residual max "
              f"{b[1]['newton_residual_max']:.1e}, at most {b[1]['newton_iterations_max']} iterations.", "",
              "Backward Euler damps every mode with ω·Δt ≫ 1 and lags the slow ones by O(ω·Δt); the difference "
              "above is that numerical damping, not a solver error (the explicit run resolves the bunny's "
              "dilatational waves, ~330 sub-steps per frame)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    import os

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per solver (default: %(default)s; quick 1)")
    ap.add_argument("--quick", action="store_true", help="smoke run: one beam case, 2 frames, no bunny")
    ap.add_argument("--out", default=str(RESULTS), help="folder of fem_implicit.{json,md} (default %(default)s)")
    args = ap.parse_args(argv)
    repeats = 1 if args.quick else args.repeats
    if repeats < 1:
        raise SystemExit(f"--repeats must be positive, got {args.repeats}")
    result = {"machine": describe(), "xla_flags": os.environ.get("XLA_FLAGS", "(unset)"), "repeats": repeats,
              "quick": args.quick, "frames": QUICK_FRAMES if args.quick else 20}
    result["beam"] = beam(repeats, args.quick)
    if not args.quick:
        result["bunny"] = bunny(repeats)
    result["machine_at_end"] = describe()
    write_results("fem_implicit", result, report(result), Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
