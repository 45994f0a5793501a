r"""How far one frame of the beam reaches: the FEM's velocity response to a change of load, by edge distance.

A forward-Euler graph network with P message passes computes a node's next state from the states and forces
within P mesh edges of it. This measures, with the FEM that makes the training data (explicit, the beam scene,
``--damping`` as in the data), how much of one frame's velocity response to a change of the load lies further
than P edges from the load: there, a P-pass network sees the same inputs with and without the change, so it
must predict the same velocity for both, and that share is a lower bound on its one-step error.

Two tests per load patch (the fingertip patches, directions and peaks of ``tignn generate beam-interactions
--smooth-loads --seed 0``, and the 52 reference line loads at their frame-2 level):

* **from rest**: the load ramps linearly from zero over frame 0 (the data's ``load_interp``). Every velocity
  at frame 1 is caused by the load; the share of ‖v₁‖² at nodes beyond P edges is reported.
* **a change of load rate** (a fingertip stopping, a hold starting): two runs ramp alike over frame 0, then one
  keeps ramping over frame 1 and the other holds. Their states at frame 1 are equal and they differ only in the
  force at the patch during frame 1; the share of ‖Δ‖² = ‖v₂ − v₂'‖² beyond P edges is reported. A P-pass
  model predicts the same velocities beyond P edges for both transitions, so the squared errors of the two add
  up to at least ‖Δ_far‖² / 2: its error, root-mean-square over the pair and relative to the rms of the two
  increments v₂ − v₁ and v₂' − v₁ (what it must predict), is at least ‖Δ_far‖ / 2 / rms increment.

    python benchmarks/beam_reach.py [--patches 16] [--damping 60] [--hops 1,2,3,4,6,10]

Writes benchmarks/results/beam_reach.{json,md}.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def hop_distance(edges, n, sources) -> np.ndarray:
    """[N] mesh-edge distance of every node to the nearest of ``sources``."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    graph = csr_matrix((np.ones(edges.shape[1]), (edges[0], edges[1])), shape=(n, n))
    return shortest_path(graph, indices=np.asarray(sources), unweighted=True).min(axis=0)


def share_beyond(energy, dist, hops) -> dict:
    """{P: share of the node energies ``energy`` [N] at nodes further than P edges}."""
    total = float(energy.sum())
    return {int(p): float(energy[dist > p].sum() / total) if total > 0 else 0.0 for p in hops}


def patch_loads(scene, patches: int, seed: int = 0):
    """[(name, force pattern [N,3] at the peak)]: the first ``patches`` fingertip patches of the seeded
    interaction set and as many reference line loads (their level at frame 2, where training starts)."""
    from fem import cases, scenes

    f, described = cases.fingertip_forces(scene, patches, seed, smooth=True)
    out = []
    for c, d in enumerate(described):
        peak = np.abs(f[c]).sum(axis=(1, 2)).argmax()
        out.append((f"fingertip {c + 1} ({d['profile']}, {len(d['nodes'])} nodes)", f[c, peak]))
    ref = scenes.beam_reference_forces(scene, np.linspace(1, 52, patches).round().astype(int))
    for k, fr in enumerate(ref):
        out.append((f"reference line load {k + 1}", fr[2]))
    return out


def measure(scene, loads, hops) -> list:
    import jax.numpy as jnp

    from fem import scenes, solver

    problem = scenes.setup_scene(scene._replace(n_frames=2))
    n = len(scene.points)
    rows = []
    for name, pattern in loads:
        ramp = np.stack([pattern, 2 * pattern])      # keeps ramping over frame 1
        hold = np.stack([pattern, pattern])          # holds over frame 1
        res = [solver.simulate(problem, scene.material, solver.Loads(nodal=jnp.asarray(x, jnp.float32)),
                               on_inversion="ignore") for x in (ramp, hold)]
        v = [np.asarray(r.v, np.float64) for r in res]
        if not np.array_equal(v[0][:2], v[1][:2]):   # the premise: the two runs differ only from frame 1 on
            raise RuntimeError(f"{name}: the ramping and holding runs differ before frame 1")
        src = np.where(np.abs(pattern).sum(axis=1) > 0)[0]
        dist = hop_distance(scene.edges, n, src)
        diff = v[0][2] - v[1][2]
        increment = np.linalg.norm(v[0][2] - v[0][1])
        rms_increment = np.sqrt((increment ** 2 + np.linalg.norm(v[1][2] - v[1][1]) ** 2) / 2)
        beyond = share_beyond((diff ** 2).sum(axis=1), dist, hops)
        rows.append({"load": name, "nodes_loaded": int(len(src)),
                     "from_rest_share_beyond": share_beyond((v[0][1] ** 2).sum(axis=1), dist, hops),
                     "rate_change_share_beyond": beyond,
                     "rate_change_over_increment": float(np.linalg.norm(diff) / increment),
                     "error_bound": {p: float(np.sqrt(s) * np.linalg.norm(diff) / 2 / rms_increment)
                                     for p, s in beyond.items()},
                     "nodes_beyond": {int(p): int((dist > p).sum()) for p in hops}})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--patches", type=int, default=16, help="fingertip patches and reference loads each")
    parser.add_argument("--damping", type=float, default=60.0, help="mass damping α (the training data's)")
    parser.add_argument("--hops", default="1,2,3,4,6,10")
    parser.add_argument("--out", default=str(RESULTS / "beam_reach"))
    args = parser.parse_args(argv)
    if args.patches < 1:
        raise SystemExit(f"--patches must be at least 1, got {args.patches}")
    if not (np.isfinite(args.damping) and args.damping >= 0):
        raise SystemExit(f"--damping must be a finite number >= 0, got {args.damping}")
    try:
        hops = sorted({int(h) for h in args.hops.split(",")})
    except ValueError:
        raise SystemExit(f"--hops: cannot read {args.hops!r} (use e.g. 1,2,3)") from None
    from fem import scenes

    machine = describe()
    t0 = time.perf_counter()
    scene = scenes.beam_scene(damping=args.damping)
    rows = measure(scene, patch_loads(scene, args.patches), hops)
    result = {"machine": machine, "damping": args.damping, "hops": hops, "frame_dt": scene.frame_dt,
              "seconds": time.perf_counter() - t0, "rows": rows}
    for kind in ("fingertip", "reference"):
        sel = [r for r in rows if r["load"].startswith(kind)]
        result[f"{kind}_median"] = {
            key: {p: float(np.median([r[key][p] for r in sel])) for p in hops}
            for key in ("from_rest_share_beyond", "rate_change_share_beyond", "error_bound")}
        result[f"{kind}_median"]["rate_change_over_increment"] = float(
            np.median([r["rate_change_over_increment"] for r in sel]))
    out = Path(args.out)
    write_results(out.stem, result, format_md(result), out.parent)
    return 0


def format_md(r: dict) -> str:
    hops = r["hops"]
    head = " | ".join(f"> {p} edges" for p in hops)
    lines = ["# Beam: how far one frame reaches (the FEM's own response)", "",
             f"Machine: {r['machine']['cpu']}, {r['machine']['cores']} cores; {r['seconds']:.0f} s. Beam scene, "
             f"explicit FEM, mass damping α = {r['damping']:g}, frame Δt = {r['frame_dt']:g} (see the script's "
             "docstring for the two tests). A P-pass network sees P edges per step; the share of the response "
             "further away is what it cannot see. Medians over the loads:", "",
             f"| loads | test | {head} |", "|---|---|" + "---|" * len(hops)]
    for kind in ("fingertip", "reference"):
        m = r[f"{kind}_median"]
        lines.append(f"| {kind} | share of ‖v₁‖² from rest | "
                     + " | ".join(f"{m['from_rest_share_beyond'][p]:.3f}" for p in hops) + " |")
        lines.append(f"| {kind} | share of a load-rate change's ‖Δv₂‖² | "
                     + " | ".join(f"{m['rate_change_share_beyond'][p]:.3f}" for p in hops) + " |")
        lines.append(f"| {kind} | least relative one-step v error of a P-pass model (rms over the pair) | "
                     + " | ".join(f"{m['error_bound'][p]:.3f}" for p in hops) + " |")
    lines += ["", "The load-rate change against the increment of the ramping run (‖v₂ − v₂'‖ / ‖v₂ − v₁‖), "
              f"median: fingertip {r['fingertip_median']['rate_change_over_increment']:.2f}, reference "
              f"{r['reference_median']['rate_change_over_increment']:.2f}. The shipped beams have 3 passes, "
              "`bunny-128x6` 6. The reference *cases* change their load rate only at frame 0 (a linear ramp "
              "after it), and training starts at frame 2 (`beam`) or from a first state whose finite-difference "
              "velocity already carries the motion (`beam-abaqus`): after that the velocity field persists, "
              "which is local. The fingertip cases start, stop, release and move their loads mid-case; "
              "`--smooth-loads` spreads each such change over several frames (C¹ histories), which makes "
              "the part a frame cannot see smaller than in this abrupt test (not measured here).", "",
              "Per load (share of a load-rate change's ‖Δv₂‖² beyond 3 edges, and the least error):", ""]
    lines += [f"- {row['load']}: {row['rate_change_share_beyond'].get(3, float('nan')):.3f}, "
              f"bound {row['error_bound'].get(3, float('nan')):.3f}" for row in r["rows"]]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
