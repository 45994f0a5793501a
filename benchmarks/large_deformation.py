"""Large deformations: the beam's models against the converged FEM at loads past the training range.

Loads: the reference tip load of test case 9 (a 20-frame ramp) scaled by 1, 2 and 3, then held, and the 2× load
released. Reference: the FEM's backward Euler on the same frame step, Newton iterated to convergence
(`fem.implicit.simulate_implicit`, up to 25 iterations a frame); for the release, whose first frame the implicit
FEM's Newton iteration does not survive, the explicit FEM (`fem.simulate`, every wave resolved: it rings where
backward Euler damps, so part of every model's error there is the time step's). Models: the shipped learned
linear ``beam``, the FEM's rest linearisation ``beam-linear`` and the shipped corotational GENERIC ``beam-corot``
(made from the FEM's element operators, `tignn_jax.simulators.corotational.from_fem`), each through
`tignn_jax.stepper`.

Per model and load: the mean over frames of the L2 errors of u and σ relative to the case's peak (over frames)
of the FEM's norm; the largest volume change of the model and of the FEM (hex volumes split into tets); the
largest difference of the beam's length (its centre line, the mean of the four inner node lines) from the FEM's;
frames whose energy rose by more than the forces' work (the model's ``diagnostics``: D < −max(1e-4 · max(E, E'),
2 E_round), above the float32 rounding of the difference of the energies before and after the frame, which scales
with the larger (a release drops E by orders of magnitude in a frame), and above the energy the state's own
float32 rounding holds: E_round, the largest energy of the rest state with its positions moved by up to half a
float32 spacing (3 draws; about 1e-3 for the beam, whose coordinates reach 40), the floor of any energy
difference near rest, before and after the frame). Then the
step time of each model on a frame of the 1× ramp (p50 of ``--repeats`` interleaved calls after compilation, one
process) and its ratio to the learned linear beam's, measured in the same run; and the p50 and p99 of every frame
of the cases above, each timed alone (a model whose step is slower on some frames shows it there).

With ``--cells tetra`` the same beam is split into six tets per hex (`fem.hex_to_tet`, the FEM's nodal tet4) and
the models are the FEM's rest linearisation and the corotational model of that tet mesh (nodal volume change);
the step-time ratios are then to the rest linearisation's.

    python benchmarks/large_deformation.py              # 60 frames a case
    python benchmarks/large_deformation.py --quick --out /tmp/ld   # smoke run: 21 frames, 3× only
    python benchmarks/large_deformation.py --cells tetra           # the tet4 beam: large_deformation_tet.{json,md}
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
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _machine import RESULTS_DIR, describe, machine_line, interleaved_ms, write_results  # noqa: E402

CASE = 9
LOADS = (("1x hold", 1.0, "hold"), ("2x hold", 2.0, "hold"), ("3x hold", 3.0, "hold"), ("2x release", 2.0, "release"))
QUICK_LOADS = ("3x hold",)


def centre_line(q0):
    """[stations, 4] node ids: at each x, the four nodes (y, z) ∈ {4, 6}² around the beam's axis."""
    out = []
    for x in np.unique(q0[:, 0]):
        at = [np.where(np.all(np.abs(q0 - [x, y, z]) < 1e-6, axis=1))[0] for y in (4, 6) for z in (4, 6)]
        out.append([a[0] for a in at])
    return np.array(out)


def length(q, line):
    p = q[..., line, :].mean(axis=-2)
    return np.linalg.norm(np.diff(p, axis=-2), axis=-1).sum(axis=-1)


BASE = {"hexahedron": "beam (learned linear)", "tetra": "tet beam: FEM rest linearisation"}


def beam(cells: str):
    """The beam scene, its hex8 mesh or that mesh split into tet4."""
    from fem import mesh, meshes, scenes

    scene = scenes.beam_scene()
    if cells == "tetra":
        tets = mesh.hex_to_tet(scene.cells)
        scene = scene._replace(cells=tets, cell_type="tetra", edges=meshes.mesh_edges(tets))
    return scene


def models(cells: str = "hexahedron"):
    import tignn_jax
    from fem import implicit, scenes
    from tignn_jax.simulators import LinearGeneric
    from tignn_jax.simulators import corotational as C
    from tignn_jax.simulators import linear as LG

    scene = beam(cells)
    linear, _ = tignn_jax.load_pretrained("beam-linear")
    if cells == "tetra":
        problem = scenes.setup_scene(scene._replace(n_frames=1))
        stored = C.from_fem(problem, scene.material)
        info = {"kind": "the FEM's energy and element operators, corotated (not learned)"}
        mesh = {"q0": scene.points, "senders": scene.edges[0], "receivers": scene.edges[1],
                "node_type": scene.node_type}
        rest = LG.from_rest_linearization(implicit.rest_linearization(problem, scene.material), scene.frame_dt)
        return {BASE["tetra"]: tignn_jax.make_params(LinearGeneric(), rest, mesh, linear["envelope"], {}),
                "tet beam: corotational": tignn_jax.make_params(C.CorotationalGeneric(), stored, mesh,
                                                                linear["envelope"], info)}
    beam_model, _ = tignn_jax.load_pretrained("beam")
    return {BASE["hexahedron"]: beam_model, "beam-linear (FEM rest linearisation)": linear,
            "beam-corot (FEM element operators)": tignn_jax.load_pretrained("beam-corot")[0]}


def reference(forces, explicit: bool = False, cells: str = "hexahedron"):
    from fem import implicit, scenes
    from fem import solver as sv

    scene = beam(cells)
    problem = scenes.setup_scene(scene._replace(n_frames=len(forces)))
    loads = sv.Loads(nodal=jnp.asarray(forces, jnp.float32))
    if explicit:
        res = sv.simulate(problem, scene.material, loads)
    else:
        res, _ = implicit.simulate_implicit(problem, scene.material, loads, max_newton=25)
    return np.asarray(res.q[1:], np.float64), np.asarray(res.sigma[1:], np.float64)


def rounding_energy(diag, q0, draws: int = 3, seed: int = 0) -> float:
    """E_round: the largest energy (``diag``'s) of the rest state with each position moved by up to half its
    float32 spacing, over ``draws`` random draws."""
    rng = np.random.default_rng(seed)
    rest = np.concatenate([q0, np.zeros((len(q0), 9), np.float32)], axis=1)
    zero = jnp.zeros((len(q0), 3), jnp.float32)
    out = 0.0
    for _ in range(draws):
        moved = rest.copy()
        moved[:, :3] += (rng.uniform(-0.5, 0.5, q0.shape) * np.spacing(np.abs(q0))).astype(np.float32)
        out = max(out, abs(float(diag(jnp.asarray(rest), zero, jnp.asarray(moved))["energy"])))
    return out


def run_model(params, forces):
    import tignn_jax

    step = tignn_jax.stepper(params)
    diag = jax.jit(lambda z, f, z1: params["model"].diagnostics(params["arrays"], z, f, z1))
    q0 = np.asarray(params["mesh"]["q0"], np.float32)
    floor = 2.0 * rounding_energy(diag, q0)
    z = jnp.asarray(np.concatenate([q0, np.zeros((len(q0), 9), np.float32)], axis=1))
    zs, created, ms, energy = [], 0, [], 0.0     # the rest state's energy is 0
    for f in forces:
        f = jnp.asarray(f, jnp.float32)
        t = time.perf_counter()
        z1 = step(z, f).block_until_ready()
        ms.append(1e3 * (time.perf_counter() - t))
        d = diag(z, f, z1)
        scale = max(abs(energy), abs(float(d["energy"])))
        created += int(float(d["dissipation"]) < -max(1e-4 * scale, floor))
        energy = float(d["energy"])
        zs.append(np.asarray(z1, np.float64))
        z = z1
    return np.array(zs), created, ms[1:]   # the first call compiles


def field_metrics(zs, q_ref, s_ref, q0, cells) -> dict:
    """Finiteness, the u and σ errors relative to the case's peak and the largest volume changes of the model's
    states zs [T, N, 12] and the FEM's (q_ref, s_ref)."""
    from fem.meshes import cell_volumes

    u, u_ref = zs[..., :3] - q0, q_ref - q0
    finite = bool(np.all(np.isfinite(zs)))
    vol0 = cell_volumes(q0, cells).sum()
    vol = lambda qs: np.array([cell_volumes(q, cells).sum() for q in qs]) / vol0 - 1.0
    return {"finite": finite,
            "u_error": float(np.linalg.norm(u - u_ref, axis=(1, 2)).mean() / np.linalg.norm(u_ref, axis=(1, 2)).max()),
            "sigma_error": float(np.linalg.norm(zs[..., 6:] - s_ref, axis=(1, 2)).mean()
                                 / np.linalg.norm(s_ref, axis=(1, 2)).max()),
            "volume_change_max": float(np.abs(vol(zs[..., :3])).max()) if finite else None,
            "fem_volume_change_max": float(np.abs(vol(q_ref)).max())}


def metrics(zs, q_ref, s_ref, q0, cells, line) -> dict:
    """`field_metrics` and the beam's length difference and tip drop."""
    out = field_metrics(zs, q_ref, s_ref, q0, cells)
    u, u_ref = zs[..., :3] - q0, q_ref - q0
    return {**out,
            "length_difference_max": float(np.abs(length(zs[..., :3], line) - length(q_ref, line)).max()
                                           / length(q0, line)) if out["finite"] else None,
            "tip_drop": float(-u[-1, line[-1]].mean(axis=0)[1]),
            "fem_tip_drop": float(-u_ref[-1, line[-1]].mean(axis=0)[1])}


def report(result) -> str:
    m = result["machine"]
    tets = result.get("cells") == "tetra"
    lines = [f"# Large deformations: the {'tet4 ' if tets else ''}beam's models against the converged FEM", "",
             f"Test case {CASE}'s tip load scaled, {result['frames']} frames (20-frame ramp, then held or released); "
             "u and σ errors relative to each case's peak; volume and length changes as fractions"
             + (" — QUICK smoke run" if result["quick"] else "") + ".", "",
             "| model | load | u error | σ error | max volume change (FEM) | max length difference | tip drop (FEM) "
             "| energy-creating frames |", "|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        vc = "non-finite" if r["volume_change_max"] is None else f"{100 * r['volume_change_max']:.2f} %"
        ld = "—" if r["length_difference_max"] is None else f"{100 * r['length_difference_max']:.2f} %"
        lines.append(f"| {r['model']} | {r['load']} | {r['u_error']:.4f} | {r['sigma_error']:.4f} | {vc} "
                     f"({100 * r['fem_volume_change_max']:.3f} %) | {ld} | {r['tip_drop']:.2f} "
                     f"({r['fem_tip_drop']:.2f}) "
                     f"| {r['energy_creating_frames']} |")
    lines += ["", "Step time (`tignn_jax.stepper`, one body, frame 11 of the 1× ramp, p50 of interleaved calls after "
              "compilation, not pinned):",
              "",
              f"| model | p50 ms | ratio to the {'rest linearisation' if tets else 'learned linear beam'} |",
              "|---|---|---|"]
    for name, t in result["step_ms"].items():
        lines.append(f"| {name} | {t['p50']:.2f} | {t['ratio']:.2f} |")
    lines += ["", "Every frame of the cases above timed alone (`stepper` call to a ready result, the model's "
              "diagnostics between frames; each case's first call, which may compile, left out): how steady the "
              "step is along ramps, holds and releases (the goal: p99 ≤ 1.5 × p50).", "",
              "| model | frames | p50 ms | p99 ms | max ms | p99 / p50 |", "|---|---|---|---|---|---|"]
    for name, t in result["frame_ms"].items():
        lines.append(f"| {name} | {t['frames']} | {t['p50']:.2f} | {t['p99']:.2f} | {t['max']:.2f} | "
                     f"{t['p99'] / t['p50']:.2f} |")
    lines += ["", machine_line(m) + ", load average "
              f"{m['load_average_1m']} at the start. FEM reference: {result['reference']}."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60, help="frames per case, ≥ 21 (default %(default)s; --quick: 21)")
    ap.add_argument("--repeats", type=int, default=100, help="timed calls per model (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 21 frames, the 3x hold only, 10 repeats")
    ap.add_argument("--cells", choices=("hexahedron", "tetra"), default="hexahedron",
                    help="the beam's hex8 mesh or its tet4 split (default %(default)s)")
    ap.add_argument("--out", default=str(RESULTS_DIR),
                    help="folder of large_deformation[_tet].{json,md} (default %(default)s)")
    args = ap.parse_args(argv)
    frames = 21 if args.quick else args.frames
    repeats = 10 if args.quick else args.repeats
    if frames < 21 or repeats < 1:
        raise SystemExit(f"--frames must be at least 21 and --repeats positive, got {frames} and {repeats}")
    from fem import scenes

    machine = describe()
    scene = beam(args.cells)
    q0, cells, line = np.asarray(scene.points, np.float64), np.asarray(scene.cells), centre_line(scene.points)
    params = models(args.cells)
    rows, frame_ms = [], {name: [] for name in params}
    for label, scale, mode in LOADS:
        if args.quick and label not in QUICK_LOADS:
            continue
        forces = scale * scenes.beam_reference_forces(scene, [CASE], after=frames - 20, mode=mode)[0]
        t = time.perf_counter()
        q_ref, s_ref = reference(forces, explicit=mode == "release", cells=args.cells)
        print(f"{label}: FEM reference {time.perf_counter() - t:.0f} s", flush=True)
        for name, p in params.items():
            zs, created, ms = run_model(p, forces)
            frame_ms[name] += ms
            rows.append({"model": name, "load": label, **metrics(zs, q_ref, s_ref, q0, cells, line),
                         "energy_creating_frames": created})
    import tignn_jax

    # timed on a frame of the 1x ramp: the state after 10 frames, the 11th frame's force
    ramp = scenes.beam_reference_forces(scene, [CASE])[0].astype(np.float32)
    steppers, states = {}, {}
    for name, p in params.items():
        steppers[name] = tignn_jax.stepper(p)
        z = jnp.asarray(np.concatenate([q0, np.zeros((len(q0), 9))], axis=1), jnp.float32)
        for f in ramp[:10]:
            z = steppers[name](z, jnp.asarray(f))
        states[name] = z
    f = jnp.asarray(ramp[10])
    times = interleaved_ms({name: (lambda s=s, z=states[name]: s(z, f)) for name, s in steppers.items()}, repeats)
    base = float(np.median(times[BASE[args.cells]]))
    step_ms = {name: {"p50": float(np.median(t)), "ratio": float(np.median(t)) / base} for name, t in times.items()}
    result = {"machine": machine, "quick": args.quick, "frames": frames, "case": CASE, "cells": args.cells,
              "rows": rows,
              "step_ms": step_ms,
              "frame_ms": {name: {"frames": len(t), "p50": float(np.median(t)), "p99": float(np.percentile(t, 99)),
                                  "max": float(np.max(t))} for name, t in frame_ms.items()},
              "reference": "fem.implicit.simulate_implicit, max_newton=25 (release: the explicit fem.simulate)"}
    name = "large_deformation" + ("_tet" if args.cells == "tetra" else "")
    write_results(name, result, report(result), Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
