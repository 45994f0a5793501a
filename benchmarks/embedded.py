"""Large meshes in real time: the embedded corotational model against the corotational model of the fine mesh.

The beam (40 × 10 × 10, clamped at x = 0, the beam scene's material and damping) meshed by regular hex8 grids
from 20×5×5 (756 nodes) to ``--meshes`` (default up to 120×30×30, 116 281 nodes), each embedded in the same
20×5×5 cage, the mesh of the shipped ``beam-corot`` (`tignn_jax.simulators.embedded.embed`, cell 2).

Accuracy, on the ``--accuracy`` mesh (default 80×20×20, 35 721 nodes): the embedded model against the
corotational model of that fine mesh (`tignn_jax.simulators.corotational`, the FEM's Mooney–Rivlin energy and
element operators of the fine mesh, its solve tightened to a CG tolerance of 1e-3, up to 40 iterations; it is the
reference because the FEM's Newton step needs a dense preconditioner that does not fit at that size, and on the
20×5×5 mesh this class follows the FEM to u 0.014: ``large_deformation.md``). Cases, ``--frames`` frames each:
test case 9's tip line (x = 24 on the face y = 10, along z) with its total load spread evenly over the fine nodes
on that line, ramped over 20 frames to 1× and 3× its reference maximum (600 000) and held, or to 2× and released;
and a fingertip-sized patch (the nodes of the face y = 10 within 2 of x = 30, z = 5), pressed with the same totals
and held. The same metrics as ``large_deformation.py``: u and σ errors relative to the case's peak, volume
changes, the beam's length (its centre line), frames that create energy.

Time, on one pinned core (`tignn_jax.mr.real_time_cores(1)`): ``tignn_jax.step`` through its rest graph, of the
state after 10 frames of the 1× line ramp under the 11th frame's force, p50 and p99 of ``--repeats`` interleaved
calls after compilation; the fine corotational model on the meshes up to ``--corot-up-to`` nodes beside it
(interleaved with the embedded model, mesh by mesh: the ratio is measured in the same run), and the fitted
exponent of time ∝ nodes^a.

    python benchmarks/embedded.py                      # writes benchmarks/results/embedded.{json,md}
    python benchmarks/embedded.py --quick --out /tmp/embedded   # smoke run: the 756-node mesh (its own cage), ~20 s
"""
from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _machine import RESULTS_DIR, describe, interleaved_ms, machine_line, write_results  # noqa: E402

SIZE = (40.0, 10.0, 10.0)
CAGE_CELL = 2.0
MESHES = "20x5x5,40x10x10,60x15x15,80x20x20,100x25x25,120x30x30"
QUICK_MESHES = "20x5x5"
ACCURACY_MESH = "80x20x20"
REFERENCE_MAX = 600_000.0      # test case 9's tip load at its peak (`fem.scenes.beam_reference_forces`)
CASES = (("line 1x hold", "line", 1.0, "hold"), ("line 3x hold", "line", 3.0, "hold"),
         ("line 2x release", "line", 2.0, "release"), ("patch 1x hold", "patch", 1.0, "hold"),
         ("patch 3x hold", "patch", 3.0, "hold"))
QUICK_CASES = ("patch 1x hold",)
RAMP = 20
REFERENCE_CONFIG = {"cg_tolerance": 1e-3, "cg_max_iterations": 40}


def parse_meshes(text: str) -> list:
    """``"20x5x5,40x10x10"`` → [(20, 5, 5), (40, 10, 10)] (`scaling.parse_meshes`), a bad one a usage error."""
    from scaling import parse_meshes as parse

    try:
        return parse(text)
    except ValueError as err:
        raise SystemExit(str(err)) from None


def beam_problem(divisions):
    """(model mesh dict with cells, the FEM problem, the material) of the beam meshed by ``divisions``
    (`scaling.beam_scene_of`: the beam scene's elastic material and damping on the refined mesh)."""
    from fem import scenes
    from scaling import beam_scene_of

    mesh, scene = beam_scene_of(divisions)
    return {**mesh, "cells": scene.cells}, scenes.setup_scene(scene._replace(n_frames=1)), scene.material


def envelope(mesh: dict) -> dict:
    """A training envelope for models that were not trained (`scaling.envelope_of`; the step does not read it)."""
    from scaling import envelope_of, statistics

    return envelope_of(statistics(mesh))


def embedded_params(mesh, problem, material):
    import tignn_jax
    from tignn_jax.simulators import embedded

    stored = embedded.embed(problem, material, CAGE_CELL)
    return tignn_jax.make_params(embedded.EmbeddedCorotational(), stored, mesh, envelope(mesh),
                                 {"kind": f"the beam embedded in a cage of cell {CAGE_CELL}"})


def corot_params(mesh, problem, material, config=None):
    import tignn_jax
    from tignn_jax.simulators import corotational as C

    model = C.CorotationalGeneric(C.CorotationalConfig(**(config or {})))
    return tignn_jax.make_params(model, C.from_fem(problem, material), mesh, envelope(mesh),
                                 {"kind": "the fine mesh's corotational model"})


def load_nodes(q0, where: str):
    """The loaded nodes: the tip line (x = 24, y = 10) or the patch (y = 10, within 2 of x = 30, z = 5)."""
    top = np.abs(q0[:, 1] - SIZE[1]) < 1e-6
    if where == "line":
        return np.flatnonzero(top & (np.abs(q0[:, 0] - 24.0) < 1e-6))
    return np.flatnonzero(top & (np.hypot(q0[:, 0] - 30.0, q0[:, 2] - 5.0) <= 2.0 + 1e-6))


def forces(q0, where: str, scale: float, mode: str, frames: int) -> np.ndarray:
    """[frames, N, 3]: the total scale · 600 000 along −y, spread evenly over the loaded nodes, ramped over 20
    frames, then held (or, for a release, dropped to zero after the ramp)."""
    nodes = load_nodes(q0, where)
    if len(nodes) == 0:
        raise SystemExit(f"the mesh has no nodes on the {where} load (x = 24 must be a grid line)")
    ramp = np.minimum(np.arange(1, frames + 1) / RAMP, 1.0)
    if mode == "release":
        ramp[RAMP:] = 0.0
    out = np.zeros((frames, len(q0), 3), np.float32)
    out[:, nodes, 1] = -(scale * REFERENCE_MAX / len(nodes)) * ramp[:, None]
    return out


def centre_line(q0):
    """[stations, m] node ids: at each x, the nodes whose (y, z) are the grid values nearest the axis (5, 5)."""
    near = lambda c: np.unique(q0[:, c])[np.argsort(np.abs(np.unique(q0[:, c]) - 5.0))[:2]]
    ys, zs = near(1), near(2)
    if abs(abs(ys[0] - 5.0) - abs(ys[1] - 5.0)) > 1e-6:
        ys = ys[:1]
    if abs(abs(zs[0] - 5.0) - abs(zs[1] - 5.0)) > 1e-6:
        zs = zs[:1]
    on = np.isin(np.round(q0[:, 1], 6), np.round(ys, 6)) & np.isin(np.round(q0[:, 2], 6), np.round(zs, 6))
    xs = np.unique(q0[on, 0])
    return np.array([np.flatnonzero(on & (q0[:, 0] == x)) for x in xs])


def accuracy(divisions, frames: int, cases, log=print) -> list:
    from large_deformation import metrics, run_model

    mesh, problem, material = beam_problem(divisions)
    q0, cells = np.asarray(mesh["q0"], np.float64), np.asarray(mesh["cells"])
    line = centre_line(q0)
    t = time.perf_counter()
    models = {"embedded (cage 20×5×5)": embedded_params(mesh, problem, material),
              "fine corotational (reference)": corot_params(mesh, problem, material, REFERENCE_CONFIG)}
    log(f"  built the models of {len(q0)} nodes in {time.perf_counter() - t:.0f} s")
    rows = []
    for label, where, scale, mode in CASES:
        if label not in cases:
            continue
        f = forces(q0, where, scale, mode, frames)
        runs = {}
        for name, params in models.items():
            t = time.perf_counter()
            runs[name] = run_model(params, f)
            log(f"  {label}: {name} {time.perf_counter() - t:.0f} s")
        (zr, created_ref, _), (ze, created, _) = runs["fine corotational (reference)"], runs["embedded (cage 20×5×5)"]
        m = metrics(ze, zr[..., :3], zr[..., 6:], q0, cells, line)
        rows.append({"case": label, **m, "energy_creating_frames": created,
                     "reference_energy_creating_frames": created_ref,
                     "dent": float(-(zr[RAMP - 1, load_nodes(q0, where), 1] - q0[load_nodes(q0, where), 1]).mean()),
                     "embedded_dent": float(-(ze[RAMP - 1, load_nodes(q0, where), 1]
                                              - q0[load_nodes(q0, where), 1]).mean())})
    return rows


def timing(meshes, corot_up_to: int, repeats: int, log=print) -> list:
    """One row per mesh: the two models' `tignn_jax.step` times, interleaved mesh by mesh (`interleaved_ms`)."""
    import jax
    import jax.numpy as jnp

    import tignn_jax

    rows = []
    for d in meshes:
        mesh, problem, material = beam_problem(d)
        q0 = np.asarray(mesh["q0"], np.float32)
        ramp = forces(q0, "line", 1.0, "hold", RAMP)
        kinds = {"embedded": embedded_params}
        if len(q0) <= corot_up_to:
            kinds["corotational"] = corot_params
        row, fns = {"elements": list(d), "nodes": len(q0)}, {}
        for kind, make in kinds.items():
            t = time.perf_counter()
            params = make(mesh, problem, material)
            row[f"{kind}_build_s"] = time.perf_counter() - t
            graph = tignn_jax.rest_graph(params)
            for f in ramp[:10]:
                graph = tignn_jax.step(params, graph, jnp.asarray(f))
            f11 = jnp.asarray(ramp[10])
            fns[kind] = lambda p=params, g=graph, f=f11: tignn_jax.step(p, g, f).nodes["z"]
            if kind == "embedded":
                row["cage_nodes"] = int(params["arrays"]["project"].shape[0])
                row["embedded_mb"] = float(sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(
                    params["arrays"])) / 2 ** 20)
        for kind, t in interleaved_ms(fns, repeats).items():
            row[f"{kind}_p50"], row[f"{kind}_p99"] = float(np.median(t)), float(np.percentile(t, 99))
        log(f"  {len(q0)} nodes: " + ", ".join(f"{k} {row[k + '_p50']:.2f} ms" for k in fns))
        rows.append(row)
        del fns, params, graph
        jax.clear_caches()     # the programs hold their models' arrays as constants: a large mesh's weigh on the next
        gc.collect()
    return rows


def power_fit(rows, key: str, from_nodes: int = 4000):
    pts = [(r["nodes"], r[key]) for r in rows if key in r and r["nodes"] >= from_nodes]
    if len(pts) < 2:
        return None
    n, ms = np.log(np.array(pts)).T
    return float(np.polyfit(n, ms, 1)[0])


def report(result) -> str:
    m = result["machine"]
    lines = ["# Large meshes: the embedded corotational model against the fine mesh's corotational model", "",
             f"The beam meshed by regular hex8 grids, each embedded in the 20×5×5 cage (cell {CAGE_CELL}); "
             "`tignn_jax.simulators.embedded`" + (" — QUICK smoke run" if result["quick"] else "") + ".", "",
             f"## Accuracy on the {result['accuracy_nodes']}-node mesh", "",
             f"{result['frames']} frames a case (20-frame ramp, then held or released); reference: the fine "
             f"mesh's corotational model, CG tolerance {REFERENCE_CONFIG['cg_tolerance']}; u and σ errors relative "
             "to each case's peak; volume and length as fractions; dent: the loaded nodes' mean drop at the end "
             "of the ramp.", "",
             "| case | u error | σ error | max volume change (reference) | max length difference | dent "
             "(reference) | energy-creating frames (reference) |", "|---|---|---|---|---|---|---|"]
    for r in result["accuracy"]:
        vc = "non-finite" if r["volume_change_max"] is None else f"{100 * r['volume_change_max']:.2f} %"
        ld = "—" if r["length_difference_max"] is None else f"{100 * r['length_difference_max']:.2f} %"
        lines.append(f"| {r['case']} | {r['u_error']:.4f} | {r['sigma_error']:.4f} | {vc} "
                     f"({100 * r['fem_volume_change_max']:.2f} %) | {ld} | {r['embedded_dent']:.3f} "
                     f"({r['dent']:.3f}) | {r['energy_creating_frames']} "
                     f"({r['reference_energy_creating_frames']}) |")
    lines += ["", "## Step time against mesh size", "",
              f"`tignn_jax.step` on one pinned core, the state after 10 frames of the 1× line ramp, p50 / p99 of "
              f"{result['repeats']} interleaved calls after compilation (ms).", "",
              "| elements | nodes | embedded p50 / p99 | fine corotational p50 / p99 | fine ÷ embedded (p50) "
              "| embedded arrays (MB) | build s (embedded, corotational) |", "|---|---|---|---|---|---|---|"]
    for r in result["timing"]:
        corot = (f"{r['corotational_p50']:.2f} / {r['corotational_p99']:.2f}" if "corotational_p50" in r
                 else "not run")
        ratio = f"{r['corotational_p50'] / r['embedded_p50']:.1f}×" if "corotational_p50" in r else "—"
        build = f"{r['embedded_build_s']:.1f}" + (f", {r['corotational_build_s']:.1f}"
                                                  if "corotational_build_s" in r else "")
        lines.append(f"| {'×'.join(map(str, r['elements']))} | {r['nodes']} | {r['embedded_p50']:.2f} / "
                     f"{r['embedded_p99']:.2f} | {corot} | {ratio} | {r['embedded_mb']:.1f} | {build} |")
    for key, name in (("embedded_p50", "embedded"), ("corotational_p50", "fine corotational")):
        a = result["exponents"].get(key)
        if a is not None:
            lines.append(f"\nFitted exponent a of p50 ∝ nodes^a, {name}, meshes from 4 000 nodes: {a:.2f}.")
    lines += ["", machine_line(m) + f", load average {m['load_average_1m']} at the start, "
              f"{result['load_average_end']} at the end; whole run {result['minutes']:.1f} min."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--meshes", default=None, help=f"timed meshes (default {MESHES}; --quick {QUICK_MESHES})")
    ap.add_argument("--accuracy", default=None,
                    help=f"the mesh of the accuracy cases (default {ACCURACY_MESH}; --quick 20x5x5)")
    ap.add_argument("--corot-up-to", type=int, default=40_000,
                    help="time the fine corotational model on meshes up to this many nodes (default %(default)s)")
    ap.add_argument("--frames", type=int, default=60, help="frames per case, ≥ 21 (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=50, help="timed calls per model and mesh (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="smoke run: the 756-node mesh, 21 frames, one case")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="folder of embedded.{json,md} (default %(default)s)")
    args = ap.parse_args(argv)
    from tignn_jax import mr

    pinned, _ = mr.real_time_cores(1)
    meshes = parse_meshes(args.meshes or (QUICK_MESHES if args.quick else MESHES))
    acc = parse_meshes(args.accuracy or ("20x5x5" if args.quick else ACCURACY_MESH))[0]
    frames = 21 if args.quick else args.frames
    repeats = 5 if args.quick else args.repeats
    if frames < 21 or repeats < 1:
        raise SystemExit(f"--frames must be at least 21 and --repeats positive, got {frames} and {repeats}")
    t0 = time.perf_counter()
    machine = describe()
    print(f"accuracy on {'x'.join(map(str, acc))} ...", flush=True)
    cases = QUICK_CASES if args.quick else tuple(c[0] for c in CASES)
    rows = accuracy(acc, frames, cases)
    print("timing ...", flush=True)
    timed = timing(meshes, args.corot_up_to, repeats)
    import os

    result = {"machine": machine, "pinned": list(pinned), "quick": args.quick, "frames": frames, "repeats": repeats,
              "accuracy_nodes": int(np.prod(np.asarray(acc) + 1)), "accuracy": rows, "timing": timed,
              "exponents": {k: power_fit(timed, k) for k in ("embedded_p50", "corotational_p50")},
              "load_average_end": round(os.getloadavg()[0], 2), "minutes": (time.perf_counter() - t0) / 60}
    write_results("embedded", result, report(result), Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
