"""Skip what a scene does not need: each skip, decided when the program is built, with its measured saving.

Every pair (with the work / without it) is timed in the same run, interleaved, median over repeats after
compilation, on this CPU:
  FEM (fem/)
    * no Prony terms → no internal variables or viscous update: the beam with and without its Prony series,
      timed in a child process with a time limit (in an earlier session repeated in-process runs with Prony terms
      stopped in a runtime deadlock; a deadlock is reported as such, not waited on);
    * no object–object contact → no candidate search or penalty forces: the two beams, 20 frames;
  learned simulator (tignn_jax/)
    * inference computes ∇E and ∇S only: not the E, S values, degeneracy residuals L∇S, M∇E or the entropy
      production that training and evaluation need;
    * static graph data (topology, node types, normalisation) built once, not per frame;
    * the rest-mesh constants of ``elastic_port`` and ``port_hops`` computed once (``model.with_rest``);
    * a network whose every weight is zero (the rest-linearised `bunny-linear`, `beam-linear`) is not run;
  mixed-reality loop (tignn_jax/scene.py)
    * no object–object contact → the forces stage skips the contact search (two beams side by side);
    * bodies at rest and untouched are not stepped (the fingertip approaching, before the first touch);
    * colour by displacement → the stress is not colour-mapped (render stage);
    * a body on its fallback (after a guard trip) is stepped by the fallback alone, not by its learned step too.
Clamped nodes are not integrated: in the FEM and the network their rates are masked in place (one select
over the state), so there is no separate work to skip; that is stated, not timed.
Writes benchmarks/results/skips.{json,md}.

    python benchmarks/skips.py [--repeats 7]
    python benchmarks/skips.py --only-prony    # the Prony row alone, e.g. after its child deadlocked
    python benchmarks/skips.py --only-held     # the held body's row alone
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, interleaved_ms, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def interleaved(fns: dict, repeats: int) -> dict:
    """Median seconds of each zero-argument function (each called once first, to compile)."""
    return {k: 1e-3 * float(np.median(v)) for k, v in interleaved_ms(fns, repeats).items()}


def fem_skips(repeats: int, frames: int) -> list:
    import fem
    from fem import scenes

    out = [prony_skip(repeats, frames)]
    two = scenes.two_beams_scene()
    f2 = scenes.two_beams_forces(two)[0][:frames]
    two = two._replace(n_frames=frames)
    runs = {}
    for name, kw in (("with", {"contact": scenes.two_beams_contact(two)}), ("without", {})):
        prob = scenes.setup_scene(two, **kw)
        loads = fem.Loads(nodal=jnp.asarray(f2))
        runs[name] = (lambda p=prob, ld=loads: fem.simulate(p, two.material, ld, on_inversion="ignore").q)
        runs[name + "_nsub"] = prob.config.n_sub
    t = interleaved({k: v for k, v in runs.items() if not k.endswith("nsub")}, repeats)
    out.append({"skip": f"no object–object contact → no contact search or forces (FEM, two beams, {frames} frames)",
                "with_ms": 1e3 * t["with"], "without_ms": 1e3 * t["without"],
                "detail": f"sub-steps per frame: {runs['with_nsub']} with contact (its stable step), "
                          f"{runs['without_nsub']} without; the saving includes both"})
    return out


PRONY_LIMIT_S = 900


def prony_pair(repeats: int, frames: int) -> dict:
    """Median seconds of `fem.simulate` of the beam (reference load case 3) with and without its Prony terms,
    interleaved; the same mesh, loads, density and stable sub-step (the Prony terms do not change it)."""
    import fem
    from fem import scenes

    runs, n_sub = {}, {}
    for name, prony in (("with", True), ("without", False)):
        sc = scenes.beam_scene(prony=prony)._replace(n_frames=frames)
        loads = fem.Loads(nodal=jnp.asarray(scenes.beam_reference_forces(sc, [3])[0]))
        prob = scenes.setup_scene(sc)
        runs[name] = lambda p=prob, m=sc.material, ld=loads: fem.simulate(p, m, ld, on_inversion="ignore").q
        n_sub[name] = prob.config.n_sub
    return {**interleaved(runs, repeats), "n_sub": n_sub}


def prony_skip(repeats: int, frames: int) -> dict:
    """The Prony pair in a child process (single-threaded XLA), so a runtime deadlock cannot hang the run."""
    import os
    import subprocess

    env = dict(os.environ, XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    row = {"skip": f"no Prony terms → no internal variables or viscous update (FEM, one beam, {frames} frames)"}
    try:
        done = subprocess.run([sys.executable, __file__, "--prony-child", "--repeats", str(repeats),
                               "--fem-frames", str(frames)], capture_output=True, text=True, env=env,
                              timeout=PRONY_LIMIT_S, check=True)
        t = json.loads(done.stdout.strip().splitlines()[-1])
    except subprocess.TimeoutExpired:
        return {**row, "with_ms": float("nan"), "without_ms": float("nan"),
                "detail": f"not measured: the child process did not finish within {PRONY_LIMIT_S} s (deadlock)"}
    return {**row, "with_ms": 1e3 * t["with"], "without_ms": 1e3 * t["without"],
            "detail": f"sub-steps per frame {t['n_sub']['with']} with, {t['n_sub']['without']} without (the same "
                      "stable step); single-threaded XLA in a child process"}


def model_skips(repeats: int) -> list:
    from tignn_jax import api
    from tignn_jax import model as M

    params, graph = api.load_pretrained("beam-abaqus")
    cfg, norm, w = api._config(params), params["norm"], params["weights"]
    nt, topo = graph.nodes["node_type"], params["topo"]
    rng = np.random.default_rng(0)
    q0 = params["mesh"]["q0"]
    z = jnp.asarray(np.concatenate([q0 + 0.05 * rng.normal(size=q0.shape), rng.normal(size=(len(q0), 9))], 1),
                    jnp.float32)
    f = jnp.asarray(rng.normal(size=(len(q0), 3)), jnp.float32)

    @jax.jit
    def full(z, f):   # what training/evaluation computes per step
        r = M.rates(w, cfg, norm, z, f, nt, topo)
        e, s = M.energy_entropy(w, cfg, norm, z, f, nt, topo)
        return z + r.dw * M.state_scale(norm), r.deg_l, r.deg_m, r.entropy_rate, e, s

    infer = jax.jit(lambda z, f: M.step_state(w, cfg, norm, z, f, nt, topo))
    t = interleaved({"with": lambda: full(z, f), "without": lambda: infer(z, f)}, repeats * 10)
    out = [{"skip": "inference: ∇E, ∇S only (no E, S values, degeneracy residuals or entropy production)",
            "with_ms": 1e3 * t["with"], "without_ms": 1e3 * t["without"], "detail": "beam-abaqus, 756 nodes"}]

    mesh = params["mesh"]
    edges = np.stack([mesh["senders"], mesh["receivers"]])

    def rebuilt():   # static data rebuilt from the mesh every frame (what a naive loop does)
        topo_ = M.topology(edges[0], edges[1], len(nt), mesh["q0"])
        nt_ = jnp.asarray(mesh["node_type"], jnp.int32)
        norm_ = {k: jnp.asarray(np.asarray(v)) for k, v in params["norm"].items()}
        return infer_args(z, f, nt_, topo_, norm_)

    infer_args = jax.jit(lambda z, f, nt_, topo_, norm_: M.step_state(w, cfg, norm_, z, f, nt_, topo_))
    t = interleaved({"with": rebuilt, "without": lambda: infer_args(z, f, nt, topo, norm)}, repeats * 10)
    out.append({"skip": "static graph data (topology, node types, normalisation) built once, kept on device",
                "with_ms": 1e3 * t["with"], "without_ms": 1e3 * t["without"],
                "detail": "per frame: rebuild + step vs step"})
    out.append(rest_constants_skip(repeats))
    out += zero_network_skips(repeats)
    return out


def zero_network_pair(params: dict):
    """(api.stepper of the model, its full step with the network traced (jitted), a load [N,3]: the training
    range's largest nodal force, downwards, on the last six free nodes)."""
    from tignn_jax import api
    from tignn_jax import model as M

    cfg, norm, w = api._config(params), params["norm"], params["weights"]
    nt, topo = jnp.asarray(params["mesh"]["node_type"]), params["topo"]
    full = jax.jit(lambda z, f: M.step_state(w, cfg, norm, z, f, nt, topo))
    free = np.flatnonzero(np.asarray(nt) == 0)
    f = np.zeros((int(nt.shape[0]), 3), np.float32)
    f[free[-6:], 2] = -float(norm["f_max"][0])
    return api.stepper(params), full, jnp.asarray(f)


def zero_network_skips(repeats: int) -> list:
    """The shipped rest-linearised models (`bunny-linear`, the bunny scene's; `beam-linear`, the beams'
    fallback) carry a GENERIC network whose every weight is zero, so its rate is exactly zero: `api.stepper`
    runs the linearised solve alone (``api.network_is_zero``, decided from the weights when the stepper is
    built). Timed against the same model's full step, which traces the network, on a state ten loaded steps
    from rest."""
    from tignn_jax import api

    out = []
    for name in ("bunny-linear", "beam-linear"):
        params, graph = api.load_pretrained(name)
        if not api.network_is_zero(params):
            raise RuntimeError(f"{name}: its network is not zero, so the skip does not apply")
        cfg = api._config(params)
        skip, full, f = zero_network_pair(params)
        nt = params["mesh"]["node_type"]
        z = graph.nodes["z"]
        for _ in range(10):
            z = full(z, f)
        t = interleaved({"with": lambda: full(z, f), "without": lambda: skip(z, f)}, repeats * 10)
        out.append({"skip": f"a network with every weight zero is not run ({name}: the rest-linearised solve alone)",
                    "with_ms": 1e3 * t["with"], "without_ms": 1e3 * t["without"],
                    "detail": f"{name}, {len(nt)} nodes, {cfg.hidden}×{cfg.passes} network; "
                              "api.stepper vs the traced full step"})
    return out


def rest_constants_skip(repeats: int) -> dict:
    """elastic_port's edge stiffnesses and port_hops' edge coefficients depend on the weights and the rest mesh
    only: ``model.with_rest`` computes them once for inference instead of in every step. Timed on the bunny
    mesh with the session-13 bunny architecture (32×3, force_port, elastic_port, port_hops=2, edge strain, load
    context), untrained, its port weights drawn at random so the spread is not the identity."""
    from realtime import unit_statistics

    from fem import scenes as fs
    from tignn_jax import model as M
    from tignn_jax import train as T

    scene = fs.bunny_scene()
    q0 = np.asarray(scene.points, np.float32)
    n, (s, r) = len(q0), scene.edges
    rng = np.random.default_rng(0)
    z = jnp.asarray(np.concatenate([q0, 0.01 * rng.normal(size=(n, 9))], 1), jnp.float32)
    f = jnp.asarray(np.where(np.arange(n)[:, None] == 100, 1.0, 0.0) * np.array([0.0, 0.0, -1.0]), jnp.float32)
    norm = unit_statistics("port_gain", "spring_k")
    cfg = T.CONFIGS["bunny"].model._replace(hidden=32, passes=3, edge_strain=True, force_port=True,
                                            load_context=True, elastic_port=True, port_hops=2)
    nt = jnp.asarray(scene.node_type, jnp.int32)
    topo = M.model_topology(cfg, s, r, n, q0)
    w = M.init_weights(jax.random.PRNGKey(0), cfg, norm, z, f, nt, topo)
    w = {**w, "port_spread": 0.1 * jax.random.normal(jax.random.PRNGKey(1), w["port_spread"].shape)}
    cached = M.with_rest(w, cfg, norm, nt, topo)
    step = jax.jit(lambda z, f, norm_: M.step_state(w, cfg, norm_, z, f, nt, topo))
    t = interleaved({"with": lambda: step(z, f, norm), "without": lambda: step(z, f, cached)}, repeats * 10)
    return {"skip": "rest-mesh constants (elastic_port stiffnesses, port_hops coefficients) computed once, not "
                    "per step", "with_ms": 1e3 * t["with"], "without_ms": 1e3 * t["without"],
            "detail": f"bunny 32×3 with both port options, untrained, {n} nodes"}


def held_body_skip(repeats: int) -> dict:
    """A body on its fallback is stepped by the fallback alone: per frame, the loop used to run the body's
    learned step too (dispatched on its own, its result discarded) before the fallback step."""
    from tignn_jax.commands_demo import build_scene

    scene, _ = build_scene("beam", 3)
    fb = scene.fallback[0]
    z = jnp.asarray(scene.bodies[0].z, jnp.float32)
    f = jnp.zeros((z.shape[0], 3), jnp.float32)
    learned, held = jax.jit(scene.bodies[0].step_fn), jnp.asarray(False)   # one body's learned step
    t = interleaved({"with": lambda: (jax.block_until_ready(learned(z, f)), fb(z, f, held))[1],
                     "without": lambda: fb(z, f, held)}, repeats * 20)
    return {"skip": "a body on its fallback is stepped by the fallback alone, not by its learned step too "
                    "(beam-abaqus held on beam-linear)",
            "with_ms": 1e3 * t["with"], "without_ms": 1e3 * t["without"],
            "detail": "per held frame: learned step dispatched and discarded, then the fallback step, against "
                      "the fallback step alone (the loop with one body per core, `scene._concurrent_frame`)"}


def loop_skips(frames: int) -> list:
    from tignn_jax import scene as sc
    from tignn_jax.commands_demo import build_scene

    out = []
    scene, _ = build_scene("two-beams", frames + 3)
    far = scene._replace(contact_radius=0.0)
    t_with = sc.run(scene, frames=frames + 3, warmup=3)[1]
    t_without = sc.run(far, frames=frames + 3, warmup=3)[1]
    out.append({"skip": "no object–object contact → the forces stage has no contact search (two beams)",
                "with_ms": float(np.median(t_with.forces)), "without_ms": float(np.median(t_without.forces)),
                "detail": "forces stage p50 per frame (fingertip forces remain)"})

    scene, _ = build_scene("beam", frames + 3)
    a = sc.run(scene._replace(skip_rest=False), frames=frames + 3, warmup=3)[1]
    b = sc.run(scene, frames=frames + 3, warmup=3)[1]
    untouched = int(np.sum(b.step < 0.2 * np.median(a.step)))
    out.append({"skip": "bodies at rest and untouched are not stepped (one beam, press track)",
                "with_ms": float(np.mean(a.step)), "without_ms": float(np.mean(b.step)),
                "detail": f"mean step per frame over the track; {untouched} of {len(b.step)} timed frames came "
                          "before the first touch"})

    c = sc.run(scene._replace(colour_by="displacement"), frames=frames + 3, warmup=3)[1]
    out.append({"skip": "colour by displacement → stress not colour-mapped (render stage, one beam)",
                "with_ms": float(np.median(b.render)), "without_ms": float(np.median(c.render)),
                "detail": "render p50 per frame, 640×480"})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--frames", type=int, default=120, help="frames of the loop measurements")
    ap.add_argument("--fem-frames", type=int, default=5, help="frames of the FEM measurements")
    ap.add_argument("--prony-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--only-prony", action="store_true",
                    help="re-measure only the Prony row (its child process) and replace it in the existing "
                         "skips.json / skips.md, marked with this run's machine load and date")
    ap.add_argument("--only-held", action="store_true",
                    help="likewise for the row of a body on its fallback (measured alone and put in place)")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.frames < 1 or args.fem_frames < 1:
        raise SystemExit(f"--repeats, --frames and --fem-frames must be positive, got {args.repeats}, "
                         f"{args.frames}, {args.fem_frames}")
    if args.prony_child:
        print(json.dumps(prony_pair(args.repeats, args.fem_frames)))
        return 0
    if args.only_prony:
        return update_row(lambda: prony_skip(args.repeats, args.fem_frames), "no Prony")
    if args.only_held:
        return update_row(lambda: held_body_skip(args.repeats), "a body on its fallback")
    machine = describe()
    rows = (model_skips(args.repeats) + loop_skips(args.frames) + [held_body_skip(args.repeats)]
            + fem_skips(args.repeats, args.fem_frames))
    for r in rows:
        with_saving(r)
    machine["load_average_1m_at_end"] = describe()["load_average_1m"]
    write_results("skips", {"machine": machine, "skips": rows}, format_md(machine, rows), RESULTS)
    return 0


def with_saving(row: dict) -> dict:
    """The row with its saving (ms) and ratio added (ratio nan for a row not measured)."""
    row["saving_ms"] = row["with_ms"] - row["without_ms"]
    row["ratio"] = row["with_ms"] / row["without_ms"] if row["without_ms"] > 0 else float("nan")
    return row


def update_row(measure, key: str) -> int:
    """Measure one pair alone (``measure()`` → row; its ratio is self-contained: both sides timed in the same
    run) and put it in place of the existing results' row whose skip starts with ``key`` (appended if there is
    none); the row says when and under which load it was measured."""
    import time

    path = RESULTS / "skips.json"
    if not path.exists():
        raise SystemExit(f"{path} does not exist: run the whole benchmark first")
    data = json.loads(path.read_text())
    at = describe()
    row = with_saving(measure())
    row["detail"] += (f"; re-measured on its own ({time.strftime('%Y-%m-%d', time.gmtime())}, {at['cpu']}, "
                      f"load average {at['load_average_1m']} at its start), not in the run of the other rows")
    rows = [row if r["skip"].startswith(key) else r for r in data["skips"]]
    if not any(r["skip"].startswith(key) for r in data["skips"]):
        rows.append(row)
    data["skips"] = rows
    path.write_text(json.dumps(data, indent=1))
    text = format_md(data["machine"], rows)
    (RESULTS / "skips.md").write_text(text)
    print(text)
    return 0


def format_md(machine: dict, rows: list) -> str:
    """skips.md from the machine description and the rows (a row not measured shows — in its numbers)."""
    num = lambda x, fmt: "—" if not np.isfinite(x) else format(x, fmt)
    lines = ["# Skip what a scene does not need", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']}; load average "
             f"{machine['load_average_1m']} at start, {machine['load_average_1m_at_end']} at end. Pairs timed in "
             "the same run (interleaved medians after compilation, or loop stages over the same track).", "",
             "| skip | with the work (ms) | skipped (ms) | saving (ms) | ratio | measured as |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        ratio = num(r["ratio"], ".2f")
        lines.append(f"| {r['skip']} | {num(r['with_ms'], '.3f')} | {num(r['without_ms'], '.3f')} | "
                     f"{num(r['saving_ms'], '.3f')} | {ratio}{'' if ratio == '—' else '×'} | {r['detail']} |")
    lines += ["", "Clamped nodes: their q, v rates are masked in place (FEM: the `free` mask in the velocity "
              "update; network: one select on the increment), so no separate work exists to skip."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
