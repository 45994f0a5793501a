"""Large deformations of the bunny: its models against the converged FEM under deep fingertip presses.

Loads: fingertip-sized patch presses (`fem.cases.point_load_forces`, radius 5, the same total force spread along the
loaded node's inward normal, a C¹ rise over 10 frames) at two of the bunny data's held-out test positions (93 and
96 of its 100, which no model was trained on), of 1, 3, 10 and 30 times the unit load, held for the rest of the
case; and the 30× press released after 25 frames. The 30× press dents the bunny by about 7 % of its height.
Reference: the FEM's backward Euler on the same frame step, Newton iterated to convergence
(`fem.implicit.simulate_implicit`, up to 25 iterations a frame). Models, each through `tignn_jax.stepper`: the
shipped learned linear ``bunny`` and the corotational ``bunny-corot`` (the FEM's element operators).

Per model and load, averaged over the two positions: the mean over frames of the L2 errors of u and σ relative to
the case's peak (over frames) of the FEM's norm; the largest volume change of the model and of the FEM; the dent
(the loaded node's displacement along its inward normal at the end of the hold) of the model and of the FEM;
frames whose energy rose by more than the forces' work (as in ``large_deformation.py``). Then the step time of
each model on a frame of the 1× press (p50 of ``--repeats`` interleaved calls after compilation, one process) and
its ratio to the learned linear bunny's, and the p50 and p99 of every frame of the cases above, each timed alone.

    python benchmarks/large_deformation_bunny.py               # 40 frames a case
    python benchmarks/large_deformation_bunny.py --quick --out /tmp/ldb   # smoke run: 16 frames, 30× at one position
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _machine import RESULTS_DIR, describe, interleaved_ms, machine_line, write_results  # noqa: E402
from large_deformation import field_metrics, run_model  # noqa: E402

POSITIONS = (93, 96)          # 1-based positions of the bunny data's farthest-point load sequence (test: 91–100)
LOADS = (("1x hold", 1.0, "hold"), ("3x hold", 3.0, "hold"), ("10x hold", 10.0, "hold"),
         ("30x hold", 30.0, "hold"), ("30x release", 30.0, "release"))
RELEASE_AT = 25
BASE = "bunny (learned linear)"


def scene():
    from fem import scenes

    return scenes.bunny_scene(density=1e-3)    # the bunny data's scene (`configs/bunny.py`)


def forces(sc, frames: int, scale: float, mode: str, positions) -> tuple:
    """([P, T, N, 3] forces, [P] loaded nodes, [P, 3] inward normals) of the presses at ``positions``."""
    from fem import cases

    long = sc._replace(n_frames=frames)
    f, nodes = cases.point_load_forces(long, n_cases=100, seed=0, magnitude=scale, rise_frames=10, radius=5.0)
    pick = np.asarray(positions) - 1
    f, nodes = f[pick], nodes[pick]
    if mode == "release":
        f[:, RELEASE_AT:] = 0.0
    surface, normals = cases.free_surface(sc)
    inward = -np.array([normals[np.flatnonzero(surface == n)[0]] for n in nodes])
    return f.astype(np.float32), nodes, inward


_PRECONDITIONER = {}


def reference(sc, f):
    """The FEM's (q, σ) [T, N, 3|6] under the forces f [T, N, 3]; the Newton iteration's preconditioner (a dense
    inverse: minutes on the bunny) is computed once."""
    from fem import implicit, scenes
    from fem import solver as sv

    problem = scenes.setup_scene(sc._replace(n_frames=len(f)))
    if "p" not in _PRECONDITIONER:
        _PRECONDITIONER["p"] = implicit.preconditioner(problem, sc.material)
    res, _ = implicit.simulate_implicit(problem, sc.material, sv.Loads(nodal=jnp.asarray(f)), _PRECONDITIONER["p"],
                                        max_newton=25)
    return np.asarray(res.q[1:], np.float64), np.asarray(res.sigma[1:], np.float64)


def metrics(zs, q_ref, s_ref, q0, cells, node, inward, hold_end: int) -> dict:
    """`large_deformation.field_metrics` and the dents (the loaded node's inward displacement at the end of the
    hold) of the model and of the FEM."""
    u, u_ref = zs[..., :3] - q0, q_ref - q0
    return {**field_metrics(zs, q_ref, s_ref, q0, cells),
            "dent": float(u[hold_end - 1, node] @ inward), "fem_dent": float(u_ref[hold_end - 1, node] @ inward)}


def models():
    import tignn_jax

    return {BASE: tignn_jax.load_pretrained("bunny")[0],
            "bunny-corot (FEM element operators)": tignn_jax.load_pretrained("bunny-corot")[0]}


def report(result) -> str:
    m = result["machine"]
    lines = ["# Large deformations: the bunny's models against the converged FEM", "",
             f"Patch presses (radius 5) at test positions {', '.join(map(str, result['positions']))} of the bunny "
             f"data, {result['frames']} frames (10-frame rise, then held, or released after {RELEASE_AT}); u and σ "
             "errors relative to each case's peak, averaged over the positions; volume changes as fractions; the "
             "dent is the loaded node's inward displacement at the end of the hold (mean over the positions)"
             + (" — QUICK smoke run" if result["quick"] else "") + ".", "",
             "| model | load | u error | σ error | max volume change (FEM) | dent (FEM) | energy-creating frames |",
             "|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        vc = "non-finite" if r["volume_change_max"] is None else f"{100 * r['volume_change_max']:.2f} %"
        lines.append(f"| {r['model']} | {r['load']} | {r['u_error']:.4f} | {r['sigma_error']:.4f} | {vc} "
                     f"({100 * r['fem_volume_change_max']:.3f} %) | {r['dent']:.3f} ({r['fem_dent']:.3f}) "
                     f"| {r['energy_creating_frames']} |")
    lines += ["", "Step time (`tignn_jax.stepper`, one body, frame 11 of the 1× press, p50 of interleaved calls "
              "after compilation, not pinned):", "", "| model | p50 ms | ratio to the learned linear bunny |",
              "|---|---|---|"]
    for name, t in result["step_ms"].items():
        lines.append(f"| {name} | {t['p50']:.2f} | {t['ratio']:.2f} |")
    lines += ["", "Every frame of the cases above timed alone (`stepper` call to a ready result; each case's first "
              "call left out; the goal: p99 ≤ 1.5 × p50):", "",
              "| model | frames | p50 ms | p99 ms | max ms | p99 / p50 |", "|---|---|---|---|---|---|"]
    for name, t in result["frame_ms"].items():
        lines.append(f"| {name} | {t['frames']} | {t['p50']:.2f} | {t['p99']:.2f} | {t['max']:.2f} | "
                     f"{t['p99'] / t['p50']:.2f} |")
    lines += ["", machine_line(m) + f", load average {m['load_average_1m']} at the start. FEM reference: "
              f"{result['reference']}."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40,
                    help=f"frames per case, > {RELEASE_AT} (default %(default)s; --quick: 16, no release)")
    ap.add_argument("--repeats", type=int, default=100, help="timed calls per model (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 16 frames, the 30x hold at one position")
    ap.add_argument("--out", default=str(RESULTS_DIR),
                    help="folder of large_deformation_bunny.{json,md} (default %(default)s)")
    args = ap.parse_args(argv)
    frames = 16 if args.quick else args.frames
    repeats = 10 if args.quick else args.repeats
    if (not args.quick and frames <= RELEASE_AT) or repeats < 1:
        raise SystemExit(f"--frames must be above {RELEASE_AT} and --repeats positive, got {frames} and {repeats}")
    import tignn_jax

    machine = describe()
    sc = scene()
    q0, cells = np.asarray(sc.points, np.float64), np.asarray(sc.cells)
    positions = POSITIONS[:1] if args.quick else POSITIONS
    params = models()
    rows, frame_ms = [], {name: [] for name in params}
    for label, scale, mode in LOADS:
        if args.quick and label != "30x hold":
            continue
        f, nodes, inward = forces(sc, frames, scale, mode, positions)
        per = {name: [] for name in params}
        for c in range(len(positions)):
            t = time.perf_counter()
            q_ref, s_ref = reference(sc, f[c])
            print(f"{label} at {positions[c]}: FEM reference {time.perf_counter() - t:.0f} s", flush=True)
            hold_end = RELEASE_AT if mode == "release" else frames
            for name, p in params.items():
                zs, created, ms = run_model(p, f[c])
                frame_ms[name] += ms
                per[name].append({**metrics(zs, q_ref, s_ref, q0, cells, nodes[c], inward[c], hold_end),
                                  "energy_creating_frames": created})
        for name, rs in per.items():
            row = {"model": name, "load": label, "finite": all(r["finite"] for r in rs),
                   "energy_creating_frames": sum(r["energy_creating_frames"] for r in rs)}
            for key in ("u_error", "sigma_error", "dent", "fem_dent"):
                row[key] = float(np.mean([r[key] for r in rs]))
            vcs = [r["volume_change_max"] for r in rs]
            row["volume_change_max"] = None if None in vcs else float(np.max(vcs))
            row["fem_volume_change_max"] = float(np.max([r["fem_volume_change_max"] for r in rs]))
            rows.append(row)
    ramp, _, _ = forces(sc, 20, 1.0, "hold", positions[:1])
    steppers, states = {}, {}
    for name, p in params.items():
        steppers[name] = tignn_jax.stepper(p)
        z = jnp.asarray(np.concatenate([q0, np.zeros((len(q0), 9))], axis=1), jnp.float32)
        for k in range(10):
            z = steppers[name](z, jnp.asarray(ramp[0, k]))
        states[name] = z
    f11 = jnp.asarray(ramp[0, 10])
    times = interleaved_ms({name: (lambda s=s, z=states[name]: s(z, f11)) for name, s in steppers.items()}, repeats)
    base = float(np.median(times[BASE]))
    result = {"machine": machine, "quick": args.quick, "frames": frames, "positions": list(positions), "rows": rows,
              "step_ms": {name: {"p50": float(np.median(t)), "ratio": float(np.median(t)) / base}
                          for name, t in times.items()},
              "frame_ms": {name: {"frames": len(t), "p50": float(np.median(t)), "p99": float(np.percentile(t, 99)),
                                  "max": float(np.max(t))} for name, t in frame_ms.items()},
              "reference": "fem.implicit.simulate_implicit, max_newton=25"}
    write_results("large_deformation_bunny", result, report(result), Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
