r"""How far the bunny's response reaches in one frame, against its (unpublished) density.

The paper gives the bunny's C10 = 0.26 and D1 = 0.049 but no density. The density sets how far waves travel in
one frame of Δt = 0.05 and so whether one step of a graph network with a few local message passes can represent
the frame-to-frame map at all. For each density this script simulates a few point-load cases with the explicit
FEM (the scene's load: unit force normal to the surface, smooth rise over 10 frames, then held) and reports:

* wave travel per frame: shear c_s·Δt and dilatational c_p·Δt (small strain, c_s = √(μ/ρ),
  c_p = √((K + 4μ/3)/ρ)) in units of the median mesh edge;
* locality: the fraction of |u|² at frame 20 (and of Σ_k |Δv_k|²) within 3 and 6 graph hops of the loaded node;
* size: the largest |u| and the RMS |u| over the nodes at frame 20;
* smoothness: the cosine of consecutive velocity increments Δv_k, Δv_{k+1} (1 = smooth in time) and
  rms(v_end − v̄)/rms(Δv), where v̄ = (v_k + v_{k+1})/2 is compared with the secant (q_{k+1} − q_k)/Δt
  (0 for motion that is smooth inside the frame);
* a local linear probe: one ridge-regressed map, shared by all free nodes and the three components, from the
  node's u, v, f and their one- and two-ring mean differences to its Δv; R² on the fitted cases and on
  held-out cases. A graph network sees at least this much; a low value means Δv is not a local function
  of the state at this density. (Ridge: 1e-2 × the mean diagonal of the Gram matrix.)

    python benchmarks/bunny_density.py [--densities 1e-5,1e-4,1e-3] [--cases 12]

Writes benchmarks/results/bunny_density.{json,md}. About 1.5 min per density at 1e-4 and above on one core
(the explicit sub-step shrinks with √ρ, so 1e-5 takes ~3× that).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def simulate(density: float, cases: int, seed: int) -> dict:
    """Explicit FEM data of ``cases`` point loads on the bunny at ``density`` (arrays of the data format)."""
    from fem import cases as cs
    from fem.generate import run_cases
    from fem.material import mooney_rivlin
    from fem.scenes import bunny_scene, setup_scene

    scene = bunny_scene()
    m = scene.material
    scene = scene._replace(material=mooney_rivlin(m.c10, m.c01, m.d1, density=density))
    forces, nodes = cs.point_load_forces(scene, cases, seed, rise_frames=10)
    problem = setup_scene(scene)
    with tempfile.TemporaryDirectory() as tmp:
        path = run_cases(scene, problem, forces, Path(tmp) / "d.npz", progress=False, velocity="solver")
        with np.load(path) as d:
            out = {k: d[k] for k in ("q0", "edges", "node_type", "z", "f")}
    out["load_nodes"] = np.asarray(nodes)
    out["sub_steps"] = problem.config.n_sub
    out["material"] = scene.material
    return out


def adjacency(edges, n):
    """The mesh graph as a scipy CSR matrix of ones [n, n] (edges [2, E], both directions)."""
    from scipy.sparse import coo_matrix

    return coo_matrix((np.ones(edges.shape[1]), (edges[0], edges[1])), shape=(n, n)).tocsr()


def ring_means(adj):
    """Row-normalised adjacency (one-ring mean) as a scipy sparse matrix."""
    from scipy.sparse import diags

    return diags(1.0 / np.maximum(adj.sum(1).A1, 1.0)) @ adj


def probe_features(a, u, v, f):
    cols = []
    for x in (u, v, f):
        x1 = a @ x
        x2 = a @ x1
        cols += [x, x1 - x, x2 - x1]
    return np.stack(cols, -1)   # [N, 3, 9]: per component, 9 features


def local_probe(d, fit_cases, held_cases) -> dict:
    z, f = d["z"].astype(np.float64), d["f"].astype(np.float64)
    n = len(d["q0"])
    a = ring_means(adjacency(d["edges"], n))
    free = d["node_type"] == 0

    def design(cases):
        xs, ys = [], []
        for c in cases:
            for k in range(f.shape[1]):
                u = z[c, k, :, :3] - z[c, 0, :, :3]
                x = probe_features(a, u, z[c, k, :, 3:6], f[c, k])[free]      # [Nf, 3, 9]
                xs.append(x.reshape(-1, x.shape[-1]))
                ys.append((z[c, k + 1, :, 3:6] - z[c, k, :, 3:6])[free].reshape(-1))
        return np.concatenate(xs), np.concatenate(ys)

    x, y = design(fit_cases)
    gram = x.T @ x
    w = np.linalg.solve(gram + 1e-2 * np.trace(gram) / len(gram) * np.eye(len(gram)), x.T @ y)
    r2 = lambda xx, yy: float(1.0 - np.sum((yy - xx @ w) ** 2) / np.sum(yy ** 2))
    xh, yh = design(held_cases)
    return {"r2_fit": r2(x, y), "r2_held_out": r2(xh, yh)}


def measure(d) -> dict:
    from fem.meshes import hop_distances

    z, f = d["z"].astype(np.float64), d["f"].astype(np.float64)
    n = len(d["q0"])
    e = d["edges"]
    h = np.median(np.linalg.norm(d["q0"][e[0]] - d["q0"][e[1]], axis=1))
    m = d["material"]
    mu, bulk = 2.0 * (m.c10 + m.c01), 2.0 / m.d1
    c_s, c_p = np.sqrt(mu / m.density), np.sqrt((bulk + 4.0 * mu / 3.0) / m.density)
    dt = 0.05
    rows = []
    hops = hop_distances(e, n, np.asarray(d["load_nodes"], int))   # [cases, n]: one search for all cases
    for c in range(len(z)):
        hop = hops[c]
        u = z[c, :, :, :3] - z[c, :1, :, :3]
        dv = np.diff(z[c, :, :, 3:6], axis=0)
        eu, edv = np.sum(u[-1] ** 2, -1), np.sum(dv ** 2, -1).sum(0)
        rows.append([eu[hop <= 3].sum() / eu.sum(), eu[hop <= 6].sum() / eu.sum(),
                     edv[hop <= 3].sum() / edv.sum(), edv[hop <= 6].sum() / edv.sum(),
                     np.sqrt(eu.max()), np.sqrt(eu.mean())])
    rows = np.median(np.asarray(rows), 0)
    q, v = z[..., :3], z[..., 3:6]
    dv = np.diff(v, axis=1)
    secant = np.diff(q, axis=1) / dt
    mid = 0.5 * (v[:, 1:] + v[:, :-1])
    cos = float(np.sum(dv[:, 1:] * dv[:, :-1]) / np.sqrt(np.sum(dv[:, 1:] ** 2) * np.sum(dv[:, :-1] ** 2)))
    half = len(z) // 2
    return {
        "density": float(m.density), "sub_steps_per_frame": int(d["sub_steps"]), "median_edge": float(h),
        "shear_travel_per_frame_edges": float(c_s * dt / h), "dilatational_travel_per_frame_edges": float(c_p * dt / h),
        "u_frac_within_3_hops": float(rows[0]), "u_frac_within_6_hops": float(rows[1]),
        "dv_frac_within_3_hops": float(rows[2]), "dv_frac_within_6_hops": float(rows[3]),
        "u_max": float(rows[4]), "u_rms": float(rows[5]),
        "dv_consecutive_cosine": cos,
        "mid_vs_secant_over_dv": float(np.sqrt(np.mean((mid - secant) ** 2) / np.mean(dv ** 2))),
        **local_probe(d, range(half), range(half, len(z))),
    }


def write(results: list, cases: int, seconds: float) -> None:
    meta = {"machine": describe(), "cases_per_density": cases, "wall_s": seconds}
    m = meta["machine"]
    cols = [("density", "{:.0e}"), ("sub_steps_per_frame", "{}"), ("shear_travel_per_frame_edges", "{:.2f}"),
            ("dilatational_travel_per_frame_edges", "{:.1f}"), ("u_frac_within_3_hops", "{:.2f}"),
            ("u_frac_within_6_hops", "{:.2f}"), ("dv_frac_within_3_hops", "{:.2f}"), ("u_max", "{:.2f}"),
            ("u_rms", "{:.3f}"), ("dv_consecutive_cosine", "{:.2f}"), ("mid_vs_secant_over_dv", "{:.2f}"),
            ("r2_fit", "{:.2f}"), ("r2_held_out", "{:.2f}")]
    heads = ["density", "explicit sub-steps / frame", "shear travel / frame (edges)",
             "dilatational travel / frame (edges)", "|u|² within 3 hops", "within 6 hops", "Σ|Δv|² within 3 hops",
             "max |u|", "rms |u|", "cos(Δv_k, Δv_k+1)", "rms(v̄ − secant) / rms(Δv)", "local probe R² (fit)",
             "R² (held out)"]
    lines = ["# Bunny: reach of one frame against density", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']}; load average {m['load_average_1m']} at the "
             f"end (another job shared the CPU when it exceeds 1 per core). {cases} point-load cases per density (explicit FEM, unit load normal to "
             f"the surface, smooth rise over 10 frames; half fit the probe, half are held out); {seconds:.0f} s in all. "
             "Medians over cases for the locality and size columns. See the script's docstring for definitions.", "",
             "| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for r in results:
        lines.append("| " + " | ".join(fmt.format(r[k]) for k, fmt in cols) + " |")
    write_results("bunny_density", {"meta": meta, "results": results}, "\n".join(lines) + "\n", RESULTS, echo=False)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--densities", default="1e-5,1e-4,1e-3")
    p.add_argument("--cases", type=int, default=16)
    p.add_argument("--seed", type=int, default=5)
    args = p.parse_args(argv)
    try:
        densities = [float(t) for t in args.densities.split(",") if t.strip()]
    except ValueError:
        raise SystemExit(f"--densities must be comma-separated numbers, got {args.densities!r}")
    if not densities or any(not (np.isfinite(r) and r > 0) for r in densities):
        raise SystemExit(f"--densities must be positive, got {args.densities!r}")
    if args.cases < 2:
        raise SystemExit(f"--cases must be at least 2 (half are held out), got {args.cases}")
    t0 = time.perf_counter()
    results = []
    for rho in densities:
        results.append(measure(simulate(rho, args.cases, args.seed)))
        print(json.dumps(results[-1]))
    write(results, args.cases, time.perf_counter() - t0)
    print(f"wrote {RESULTS / 'bunny_density.md'}")


if __name__ == "__main__":
    main()
