r"""How far one frame of the bunny reaches, and how linear it is: the measurements behind ``frame_solve``.

On an implicit bunny data set from our FEM (default: the unit patch loads of
``tignn generate bunny --integrator implicit --density 1e-3 --load-radius 5 --rise-frames 10 --seed 0
--out data/bunny_imp_r3_p5.npz``), the FEM's rest linearisation (`fem.implicit.rest_linearization`) gives the
linear backward-Euler frame map

    u_{k+1} = A₀⁻¹ (f_k + c M u_k + M v_k / Δt),   v_{k+1} = (u_{k+1} − u_k) / Δt,   c = (1 + αΔt) / Δt².

Each case is rolled out from rest with its forces through

1. the dense A₀⁻¹ (the exact linear map): how linear the data are;
2. A₀⁻¹ with every entry between nodes more than H mesh edges apart set to zero: how many message-passing
   hops a frame needs (a forward-Euler graph network with P passes sees P hops per step);
3. A₀⁻¹ truncated to its r lowest eigenmodes: whether the response is global (modal) or local.

The error is the relative L2 error of u (and v) over each case's whole rollout, averaged over the val and test
cases (sims 81–100). The stress of the linear map (S₀ u) is scored with ``evaluate``'s per-snapshot measure
by `tignn evaluate --model bunny` instead (README).

    python benchmarks/bunny_reach.py [--data data/bunny_imp_r3_p5.npz] [--hops 1,2,3,4,6,8] [--modes 32,128,512]

Writes benchmarks/results/bunny_reach.{json,md}.
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


def rollout_errors(P, data, free, mass, h, c, rows):
    """Mean relative L2 error of u and v over whole rollouts of the linear map with the operator P."""
    n = data["q0"].shape[0]
    z, f = data["z"][rows].astype(np.float64), data["f"][rows].astype(np.float64)
    cases, frames = f.shape[:2]
    u_true = (z[..., :3] - data["q0"]).reshape(cases, frames + 1, 3 * n)[..., free]
    v_true = z[..., 3:6].reshape(cases, frames + 1, 3 * n)[..., free]
    fk = f.reshape(cases, frames, 3 * n)[..., free]
    u = np.zeros_like(u_true[:, 0])
    v = np.zeros_like(u)
    us, vs = [u], [v]
    for k in range(frames):
        u_new = (fk[:, k] + c * mass * u + mass * v / h) @ P.T
        u, v = u_new, (u_new - u) / h
        us.append(u)
        vs.append(v)
    rel = lambda a, b: np.linalg.norm((a - b).reshape(cases, -1), axis=1) / np.linalg.norm(b.reshape(cases, -1), axis=1)
    return float(rel(np.stack(us, 1), u_true).mean()), float(rel(np.stack(vs, 1), v_true).mean())


def main(argv=None) -> int:
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    sys.path.insert(0, str(ROOT))
    from tignn_jax import framesolve as FS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "bunny_imp_r3_p5.npz"))
    ap.add_argument("--hops", default="1,2,3,4,6,8")
    ap.add_argument("--modes", default="32,128,512")
    args = ap.parse_args(argv)
    if not Path(args.data).exists():
        raise SystemExit(f"{args.data} not found: generate it with the command in this script's docstring")
    hops = [int(x) for x in args.hops.split(",") if x]
    modes = [int(x) for x in args.modes.split(",") if x]
    machine = describe()
    t0 = time.time()
    lin = FS.operators_from_file(args.data)
    t_lin = time.time() - t0
    with np.load(args.data) as npz:
        data = {k: npz[k] for k in ("q0", "z", "f", "edges", "node_type", "sim_id", "dt")}
    h = float(data["dt"])
    norm = {**FS.norm_entries(lin), "dt": np.array([h])}
    free_n = data["node_type"] == 0
    free = np.repeat(free_n, 3)
    A_inv = FS.inverse(norm, data["node_type"]).astype(np.float64)[np.ix_(free, free)]
    mass = np.repeat(lin.mass, 3)[free]
    c = (1.0 + lin.alpha * h) / h ** 2
    rows = np.where((data["sim_id"] > 80) & (data["sim_id"] <= 100))[0]
    n = data["q0"].shape[0]
    graph = csr_matrix((np.ones(data["edges"].shape[1]), (data["edges"][0], data["edges"][1])), shape=(n, n))
    dist = shortest_path(graph, unweighted=True)[np.ix_(free_n, free_n)]
    dist = np.repeat(np.repeat(dist, 3, 0), 3, 1)
    out = {"machine": machine, "data": args.data, "cases": [int(s) for s in data["sim_id"][rows]],
           "rest_linearization_s": t_lin, "dense": {}, "hops": {}, "modes": {}}
    out["dense"]["u"], out["dense"]["v"] = rollout_errors(A_inv, data, free, mass, h, c, rows)
    for hop in hops:
        P = np.where(dist <= hop, A_inv, 0.0)
        e_u, e_v = rollout_errors(P, data, free, mass, h, c, rows)
        out["hops"][hop] = {"u": e_u, "v": e_v, "kept_norm_fraction": float((P ** 2).sum() / (A_inv ** 2).sum())}
    A = np.linalg.inv(A_inv)
    lam, phi = np.linalg.eigh(0.5 * (A + A.T))
    for r in modes:
        P = (phi[:, :r] / lam[:r]) @ phi[:, :r].T
        e_u, e_v = rollout_errors(P, data, free, mass, h, c, rows)
        out["modes"][r] = {"u": e_u, "v": e_v}
    lines = ["# Bunny: how far one frame reaches, and how linear it is", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']}; load average "
             f"{machine['load_average_1m']} at start. Data: `{args.data}`, cases sims 81–100 (val and test). "
             f"Rest linearisation built in {t_lin:.0f} s. Errors: relative L2 of u and v over each whole 20-frame "
             "rollout from rest, mean over the cases (see the script's docstring).", "",
             "| operator | u | v | share of ‖A₀⁻¹‖² kept |", "|---|---|---|---|",
             f"| dense A₀⁻¹ (the linear backward-Euler map) | {out['dense']['u']:.4f} | {out['dense']['v']:.4f} | 1 |"]
    for hop, r in out["hops"].items():
        lines.append(f"| entries within {hop} edges | {r['u']:.4f} | {r['v']:.4f} | {r['kept_norm_fraction']:.6f} |")
    for m, r in out["modes"].items():
        lines.append(f"| {m} lowest modes | {r['u']:.4f} | {r['v']:.4f} | |")
    write_results("bunny_reach", out, "\n".join(lines) + "\n", RESULTS, echo=False)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
