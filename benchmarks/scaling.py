"""How the step cost grows with the mesh: step time against the number of nodes for the three model classes.

Meshes: the 40×10×10 beam, clamped at x = 0, as structured hex8 meshes of growing size (``fem.box_hex_mesh``: from
5×2×2 elements, 54 nodes, through the paper's 20×5×5, 756 nodes, upwards); the graph is both directions of every
hex edge (``fem.meshes.mesh_edges``), as for the paper's beam.

* `LinearGeneric` (the class of the shipped ``beam`` and ``bunny``) with real operators: the FEM's rest
  linearisation of the mesh with the beam scene's material and damping (``fem.implicit.rest_linearization``, packed
  by ``tignn_jax.simulators.linear.from_rest_linearization``). Its step multiplies by the dense A⁻¹ [3N, 3N], so
  its time and memory grow as N² for large meshes (the build time, the linearisation and the inverse, is reported),
  which limits the meshes (``--linear``) to a few thousand nodes.
* `CorotationalGeneric` (the class of the shipped ``beam-corot``) with the FEM's element operators of the mesh
  (``tignn_jax.simulators.corotational.from_fem``): its element work grows as N, and so does its preconditioner
  past ``schur_limit`` (2048) elements (the rest operator's 32 lowest eigenmodes and its 3 × 3 node blocks,
  `rest_preconditioner`: 3N · 35 numbers; below it the blocks with the volumetric stiffness through a dense
  [K, K] Schur complement, `schur_preconditioner`); the CG iterations a frame needs may grow with the mesh
  (``--corot``: up to about 20 000 nodes).
* `GenericGNN` (the paper's graph network) with random weights (``GenericGNN(config).init``; values do not change
  the time) and statistics of the right scale, on meshes up to ``--gnn`` (default up to 53 568 nodes).

Each model is put on its mesh by ``tignn_jax.make_params`` and stepped by ``tignn_jax.stepper`` (one 0.05 s frame
of one body) from a state near rest under zero force. Times: medians of calls after compilation, the meshes of one
class interleaved (about ``--seconds`` of calls each, 3 to 50 calls); on the CPU backend the process's CPU time
(the cost of the work, which other jobs on a shared machine inflate only through shared caches) with the wall
time beside it, on an accelerator the wall time. The exponent a of time ∝ nodes^a is a least-squares fit in
log-log over the meshes with at least ``--fit-from`` nodes (small meshes are dominated by fixed per-call costs).
Writes scaling.{json,md,png} (scaling_gpu.* on a GPU backend, scaling_<backend>.* on another) to ``--out``
(default benchmarks/results).

    python benchmarks/scaling.py [--linear 10x3x3,...] [--corot 10x3x3,...] [--gnn 5x2x2,...] [--seconds 2]
    python benchmarks/scaling.py --quick --out /tmp/scaling      # smoke run: small meshes, ~40 s
    python benchmarks/scaling.py --render RESULT.json             # tables and plot of a result measured elsewhere
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, machine_line  # noqa: E402

BEAM_SIZE = (40.0, 10.0, 10.0)
LINEAR_MESHES = "5x2x2,10x3x3,14x4x4,20x5x5,24x6x6,28x7x7"
GNN_MESHES = "5x2x2,10x3x3,20x5x5,28x7x7,40x10x10,56x14x14,80x20x20,92x23x23"
QUICK_LINEAR = "5x2x2,10x3x3"
COROT_MESHES = "5x2x2,10x3x3,20x5x5,28x7x7,40x10x10,52x13x13,68x17x17"
QUICK_COROT = "5x2x2,10x3x3"
QUICK_GNN = "5x2x2,10x3x3,20x5x5"
FIT_FROM_NODES = 700
CLASSES = ("linear", "corot", "gnn")
LABELS = {"linear": "LinearGeneric (FEM rest linearisation)", "corot": "CorotationalGeneric (FEM element operators)",
          "gnn": "GenericGNN (random weights)"}


def parse_meshes(text: str) -> list:
    """``"5x2x2,10x3x3"`` → [(5, 2, 2), (10, 3, 3)]: elements along x, y, z."""
    out = []
    for item in [s.strip() for s in text.split(",") if s.strip()]:
        try:
            d = tuple(int(x) for x in item.split("x"))
        except ValueError:
            raise ValueError(f"a mesh is NXxNYxNZ elements, e.g. 20x5x5; got {item!r}") from None
        if len(d) != 3 or min(d) < 1:
            raise ValueError(f"a mesh is three positive element counts, got {item!r}")
        out.append(d)
    return out


def nodes_of(divisions) -> int:
    return int(np.prod(np.asarray(divisions) + 1))


def beam_mesh_of(divisions) -> dict:
    """The refined beam as a model mesh: {"q0" [N,3], "senders", "receivers" [E], "node_type" [N]} and its cells."""
    import fem
    from fem.meshes import beam_node_type, mesh_edges

    points, cells = fem.box_hex_mesh(BEAM_SIZE, divisions)
    edges = mesh_edges(cells)
    return {"q0": points, "senders": edges[0], "receivers": edges[1], "node_type": beam_node_type(points)}, cells


def envelope_of(norm: dict) -> dict:
    """A training envelope for a model that was not trained (the step does not read it)."""
    return {"z_mean": norm["z_mean"], "z_std": norm["z_std"], "z_dev_max": np.ones(12, np.float32),
            "u_max": np.ones(1, np.float32), "f_max": np.ones(1, np.float32)}


def statistics(mesh: dict) -> dict:
    """`GenericGNN`'s normalisation statistics at the scale of the beam's data on ``mesh`` (the rest positions'
    mean and spread, the mean edge length)."""
    q0 = np.asarray(mesh["q0"], np.float64)
    dq = q0[mesh["senders"]] - q0[mesh["receivers"]]
    length = float(np.linalg.norm(dq, axis=1).mean())
    z_mean = np.concatenate([q0.mean(0), np.zeros(9)])
    z_std = np.concatenate([np.full(3, q0.std()), np.full(3, 3.0), np.full(6, 5e3)])
    return {k: np.asarray(v, np.float32) for k, v in {
        "z_mean": z_mean, "z_std": z_std, "dz_std": 0.05 * z_std, "f_std": np.full(3, 1e4),
        "dq_std": np.full(3, np.sqrt(np.mean(dq ** 2))), "dv_std": np.full(3, 1.0),
        "dqn_mean": np.array([length]), "dqn_std": np.array([0.1 * length])}.items()}


def beam_scene_of(divisions) -> tuple:
    """(the refined beam's model mesh, the beam's elastic FEM scene on it)."""
    from fem import scenes

    mesh, cells = beam_mesh_of(divisions)
    scene = scenes.beam_scene(prony=False)._replace(
        name=f"beam {divisions}", points=mesh["q0"], cells=cells, edges=np.stack([mesh["senders"], mesh["receivers"]]),
        node_type=mesh["node_type"])
    return mesh, scene


def linear_params(divisions) -> tuple:
    """(a LinearGeneric model on the refined beam with the FEM's rest linearisation, build seconds)."""
    import tignn_jax
    from fem import implicit, scenes
    from tignn_jax.simulators import linear as LG

    mesh, scene = beam_scene_of(divisions)
    t0 = time.perf_counter()
    problem = scenes.setup_scene(scene)
    lin = implicit.rest_linearization(problem, scene.material)
    stored = LG.from_rest_linearization(lin, scene.frame_dt)
    norm = statistics(mesh)
    params = tignn_jax.make_params(tignn_jax.LinearGeneric(), stored, mesh, envelope_of(norm),
                                   {"kind": "rest-linearised FEM of a refined beam"})
    return params, time.perf_counter() - t0


def corot_params(divisions) -> tuple:
    """(the corotational model of the refined beam, from the FEM's element operators, build seconds)."""
    import tignn_jax
    from fem import scenes
    from tignn_jax.simulators import corotational as C

    mesh, scene = beam_scene_of(divisions)
    t0 = time.perf_counter()
    stored = C.from_fem(scenes.setup_scene(scene), scene.material, scene.frame_dt)
    params = tignn_jax.make_params(C.CorotationalGeneric(), stored, mesh, envelope_of(statistics(mesh)),
                                   {"kind": "corotational FEM element operators of a refined beam"})
    return params, time.perf_counter() - t0


def gnn_params(divisions, config) -> tuple:
    """(a GenericGNN with random weights on the refined beam, build seconds)."""
    import tignn_jax

    mesh, _ = beam_mesh_of(divisions)
    t0 = time.perf_counter()
    model = tignn_jax.GenericGNN(config)
    norm = statistics(mesh)
    stored = model.init(jax.random.PRNGKey(0), norm, mesh)
    params = tignn_jax.make_params(model, stored, mesh, envelope_of(norm), {"kind": "random weights"})
    return params, time.perf_counter() - t0


def sample_state(params: dict, seed: int = 0):
    """A state near rest (q = q0 + 1 % noise of the element size, small v and σ) and zero forces."""
    q0 = np.asarray(params["mesh"]["q0"], np.float32)
    rng = np.random.default_rng(seed)
    z = np.concatenate([q0 + 0.01 * rng.standard_normal(q0.shape), 0.01 * rng.standard_normal((len(q0), 9))], 1)
    z[np.asarray(params["mesh"]["node_type"]) != 0, :6] = np.concatenate([q0, np.zeros_like(q0)], 1)[
        np.asarray(params["mesh"]["node_type"]) != 0]
    return jnp.asarray(z, jnp.float32), jnp.zeros((len(q0), 3), jnp.float32)


def on_cpu() -> bool:
    return jax.default_backend() == "cpu"


def time_interleaved(fns: dict, seconds: float, min_repeats: int = 3, max_repeats: int = 50) -> dict:
    """Compile each fn(), then time the calls round-robin until each has its quota (≈ ``seconds`` of time, between
    ``min_repeats`` and ``max_repeats``). {name: {"ms", "cpu_ms", "wall_ms", "wall_p90_ms", "repeats",
    "compile_s"}}: medians per call of the process's CPU time and of the wall time; "ms" is the CPU time on the CPU
    backend, the wall time on an accelerator (whose work the process's CPU time does not count)."""
    compile_s, quota = {}, {}
    cpu, wall = ({k: [] for k in fns} for _ in range(2))
    for k, fn in fns.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        compile_s[k] = time.perf_counter() - t0
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t0
        quota[k] = int(min(max_repeats, max(min_repeats, seconds / max(first, 1e-6))))
    while any(len(cpu[k]) < quota[k] for k in fns):
        for k, fn in fns.items():
            if len(cpu[k]) < quota[k]:
                t0, c0 = time.perf_counter(), time.process_time()
                jax.block_until_ready(fn())
                cpu[k].append(time.process_time() - c0)
                wall[k].append(time.perf_counter() - t0)
    primary = cpu if on_cpu() else wall
    return {k: {"ms": 1e3 * float(np.median(primary[k])), "cpu_ms": 1e3 * float(np.median(cpu[k])),
                "wall_ms": 1e3 * float(np.median(wall[k])), "wall_p90_ms": 1e3 * float(np.percentile(wall[k], 90)),
                "repeats": len(cpu[k]), "compile_s": compile_s[k]} for k in fns}


def measure(kind: str, meshes, seconds: float, config=None, log=print) -> list:
    """One row per mesh of a model class: nodes, edges, build seconds, step times (`time_interleaved`)."""
    import tignn_jax

    fns, rows = {}, []
    for d in meshes:
        name = "x".join(map(str, d))
        log(f"  {kind} {name}: {nodes_of(d)} nodes, building ...")
        params, build_s = (linear_params(d) if kind == "linear" else corot_params(d) if kind == "corot"
                           else gnn_params(d, config))
        step = tignn_jax.stepper(params)
        z, f = sample_state(params)
        fns[name] = lambda step=step, z=z, f=f: step(z, f)
        arrays = params["arrays"]
        row = {"elements": list(d), "nodes": nodes_of(d), "edges": int(len(params["mesh"]["senders"])),
               "build_s": build_s}
        if kind == "linear":
            row["ainv"] = "blocks" if "ainv_blocks" in arrays else "dense"
        elif kind == "corot":
            local = (f"Schur complement ({arrays['schur_inv'].shape[0]}²)" if "schur_inv" in arrays
                     else "3×3 blocks")
            row["ainv"] = f"{arrays['modes'].shape[1]} modes + {local}"
        if kind in ("linear", "corot"):
            row["operator_mb"] = float(sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(arrays)) / 2 ** 20)
        rows.append(row)
    timed = time_interleaved(fns, seconds)
    for row, t in zip(rows, timed.values()):
        row.update(t)
        row["us_per_node"] = 1e3 * t["ms"] / row["nodes"]
    return rows


def power_fit(nodes, ms, from_nodes: int = FIT_FROM_NODES) -> dict | None:
    """Least-squares fit of log(ms) = log(c) + a log(nodes) over the points with nodes ≥ ``from_nodes``."""
    nodes, ms = np.asarray(nodes, float), np.asarray(ms, float)
    keep = (nodes >= from_nodes) & (ms > 0)
    if keep.sum() < 2:
        return None
    a, logc = np.polyfit(np.log(nodes[keep]), np.log(ms[keep]), 1)
    return {"exponent": float(a), "coefficient_ms": float(np.exp(logc)), "meshes": int(keep.sum()),
            "from_nodes": int(nodes[keep].min()), "to_nodes": int(nodes[keep].max())}


def fits(result: dict) -> dict:
    out = {}
    for kind in CLASSES:
        rows = result.get(kind, [])
        for clock in ("ms", "wall_ms"):
            out[f"{kind}_{clock}"] = power_fit([r["nodes"] for r in rows], [r[clock] for r in rows],
                                               result["fit_from_nodes"])
    return out


def result_stem(backend: str) -> str:
    """scaling.* for the CPU backend, scaling_gpu.* for a GPU, scaling_<backend>.* for another accelerator."""
    return "scaling" if backend == "cpu" else f"scaling_{backend}"


def _exp(fit, from_nodes) -> str:
    return f"{fit['exponent']:.2f} ({fit['meshes']} meshes, {fit['from_nodes']}–{fit['to_nodes']} nodes)" if fit \
        else f"n/a (fewer than 2 meshes with ≥ {from_nodes} nodes)"


def format_md(result: dict) -> str:
    m, f = result["machine"], result["fits"]
    cpu = m["backend"] == "cpu"
    clock, other = ("CPU", "wall") if cpu else ("wall", "CPU")
    cfg = result["gnn_config"]
    lines = ["# Scaling: step time against mesh size" + (" (QUICK smoke run)" if result["quick"] else ""), "",
             machine_line(m) + "; accelerator: "
             f"{m['accelerator']}; load average {m['load_average_1m']} at the start, {result['load_average_1m_end']} "
             f"at the end (above the core count: other processes shared the CPU); "
             f"XLA_FLAGS=`{m['xla_flags'] or '(unset)'}`. "
             f"One step = one 0.05 s frame of one body (`tignn_jax.stepper`). Times: medians of interleaved calls "
             f"after compilation, {clock} time per call ({other} time in brackets). Whole run "
             f"{result['wall_seconds'] / 60:.1f} min.", ""]
    for kind in CLASSES:
        rows = result.get(kind, [])
        if not rows:
            continue
        extra = (" | A⁻¹ | arrays (MB)" if kind == "linear" else " | preconditioner | arrays (MB)" if kind == "corot"
                 else "")
        title = LABELS[kind] + (f", hidden {cfg['hidden']}, {cfg['mlp_layers']} layers, {cfg['passes']} passes"
                                if kind == "gnn" else "")
        lines += [f"## {title}", "", f"| elements | nodes | edges | build s | step ms, {clock} ({other}) | calls | "
                  f"µs / node{extra} |", "|---|---|---|---|---|---|---" + ("|---|---" if extra else "") + "|"]
        for r in rows:
            lines.append(f"| {'×'.join(map(str, r['elements']))} | {r['nodes']} | {r['edges']} | {r['build_s']:.1f} | "
                         f"{r['ms']:.3f} ({r['cpu_ms' if not cpu else 'wall_ms']:.3f}) | {r['repeats']} | "
                         f"{r['us_per_node']:.2f}" + (f" | {r['ainv']} | {r['operator_mb']:.1f}" if extra else "")
                         + " |")
        lines += ["", f"Fitted exponent a of time ∝ nodes^a: {_exp(f[f'{kind}_ms'], result['fit_from_nodes'])}; from "
                  f"the {'wall' if cpu else 'CPU'}-time medians "
                  f"{_exp(f[f'{kind}_wall_ms' if cpu else f'{kind}_ms'], result['fit_from_nodes'])}.", ""]
    lines += ["Build: for LinearGeneric the FEM's rest linearisation (node blocks by coloured `jax.jvp` products, "
              "`fem.implicit.coloured_jacobian`, compilation included) and the dense inverse of A = K + "
              "(1 + αΔt)/Δt² M; for CorotationalGeneric the FEM's element stiffness columns (`jax.jvp`), the sparse "
              "rest operator and its lowest eigenmodes (shift-invert Lanczos, `scipy.sparse.linalg.eigsh`, on an LU "
              "factor in nested-dissection order); for "
              "GenericGNN the weights' initialisation and the mesh's slot topology. LinearGeneric keeps A⁻¹ whole "
              "below 32 MB and as the upper blocks of a 4 × 4 split above "
              "(`tignn_jax.simulators.linear.ainv_blocks`).", ""]
    ratios = corot_ratios(result)
    if ratios:
        lines += ["Corotational step time over the linear one's on the same mesh, measured in the same run: "
                  + ", ".join(f"{n} nodes {r:.1f}×" for n, r in ratios) + ".", ""]
    if cpu:
        lines += ["On a GPU machine `python benchmarks/scaling.py` writes scaling_gpu.* (wall-clock times).", ""]
    return "\n".join(lines)


def corot_ratios(result: dict) -> list:
    """[(nodes, corotational ms / linear ms)] on the meshes both classes were timed on."""
    linear = {r["nodes"]: r["ms"] for r in result.get("linear", [])}
    return [(r["nodes"], r["ms"] / linear[r["nodes"]]) for r in result.get("corot", []) if r["nodes"] in linear]


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = result["machine"]
    clock = "CPU" if m["backend"] == "cpu" else "wall"
    fig, ax = plt.subplots(figsize=(7.5, 5))
    for kind, colour in zip(CLASSES, ("C0", "C2", "C3")):
        rows = result.get(kind, [])
        if not rows:
            continue
        fit = result["fits"][f"{kind}_ms"]
        x = np.array([r["nodes"] for r in rows], float)
        y = np.array([r["ms"] for r in rows], float)
        label = LABELS[kind] + (f": a = {fit['exponent']:.2f}" if fit else "")
        ax.loglog(x, y, "o-", color=colour, label=label)
        if fit:
            xs = np.geomspace(fit["from_nodes"], fit["to_nodes"], 20)
            ax.loglog(xs, fit["coefficient_ms"] * xs ** fit["exponent"], ":", color=colour, lw=2,
                      label=f"fit time ∝ nodes^{fit['exponent']:.2f} (≥ {fit['from_nodes']} nodes)")
    ax.axvline(756, color="0.6", lw=0.8, ls="--", label="the paper's beam (756 nodes)")
    ax.set_xlabel("nodes (40×10×10 beam, structured hex8 mesh)")
    ax.set_ylabel(f"step time (ms, {clock} time per 0.05 s frame, median)")
    ax.set_title(f"{m['cpu'] if m['backend'] == 'cpu' else m['accelerator']} ({m['backend']})"
                 + (" — QUICK" if result["quick"] else ""), fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_result(result: dict, out: Path, stem: str) -> None:
    """``stem``.json, .md and .png in ``out``; prints the tables."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1))
    md = format_md(result)
    (out / f"{stem}.md").write_text(md)
    plot(result, out / f"{stem}.png")
    print(md)
    print(f"wrote {out}/{stem}.{{json,md,png}}")


def main(argv=None) -> int:
    from tignn_jax.simulators.generic_gnn import GNNConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--linear", default=None, help=f"LinearGeneric meshes, NXxNYxNZ elements (default "
                                                   f"{LINEAR_MESHES}; --quick {QUICK_LINEAR}; '' for none)")
    ap.add_argument("--corot", default=None, help=f"CorotationalGeneric meshes (default {COROT_MESHES}; --quick "
                                                  f"{QUICK_COROT}; '' for none)")
    ap.add_argument("--gnn", default=None, help=f"GenericGNN meshes (default {GNN_MESHES}; --quick {QUICK_GNN}; "
                                                "'' for none)")
    ap.add_argument("--hidden", type=int, default=64, help="GenericGNN width (default %(default)s)")
    ap.add_argument("--passes", type=int, default=3, help="GenericGNN message passes (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=None, help="time of timed calls per mesh (default 2; quick 0.3)")
    ap.add_argument("--fit-from", type=int, default=FIT_FROM_NODES,
                    help="fit the exponents over meshes with at least this many nodes (default %(default)s; "
                         "--quick: 50)")
    ap.add_argument("--quick", action="store_true", help="smoke run: small meshes, short timings")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="output folder (default %(default)s)")
    ap.add_argument("--render", default=None, metavar="JSON",
                    help="only write the tables and plot of a result measured elsewhere (e.g. on a GPU machine)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    if args.render:
        path = Path(args.render)
        if not path.exists():
            raise SystemExit(f"--render: no such file {path}")
        result = json.loads(path.read_text())
        result["fits"] = fits(result)
        write_result(result, out, result_stem(result["machine"]["backend"]))
        return 0
    try:
        linear = parse_meshes(args.linear if args.linear is not None else QUICK_LINEAR if args.quick else LINEAR_MESHES)
        corot = parse_meshes(args.corot if args.corot is not None else QUICK_COROT if args.quick else COROT_MESHES)
        gnn = parse_meshes(args.gnn if args.gnn is not None else QUICK_GNN if args.quick else GNN_MESHES)
        config = GNNConfig(hidden=args.hidden, passes=args.passes).check()
    except ValueError as err:
        ap.error(str(err))
    seconds = args.seconds or (0.3 if args.quick else 2.0)
    fit_from = 50 if args.quick and args.fit_from == FIT_FROM_NODES else args.fit_from
    machine = describe()
    machine["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    machine["accelerator"] = "none (CPU backend)" if on_cpu() else jax.devices()[0].device_kind
    t0 = time.perf_counter()
    result = {"machine": machine, "quick": args.quick, "fit_from_nodes": fit_from, "gnn_config": config._asdict()}
    if linear:
        print(f"LinearGeneric on {len(linear)} meshes ...", flush=True)
        result["linear"] = measure("linear", linear, seconds)
    if corot:
        print(f"CorotationalGeneric on {len(corot)} meshes ...", flush=True)
        result["corot"] = measure("corot", corot, seconds)
    if gnn:
        print(f"GenericGNN on {len(gnn)} meshes ...", flush=True)
        result["gnn"] = measure("gnn", gnn, seconds, config)
    result.update(wall_seconds=time.perf_counter() - t0, load_average_1m_end=describe()["load_average_1m"])
    result["fits"] = fits(result)
    write_result(result, out, result_stem(jax.default_backend()))
    return 0


if __name__ == "__main__":
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sys.exit(main())
