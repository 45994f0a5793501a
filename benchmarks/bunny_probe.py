r"""What in the bunny's state predicts its velocity increment: the measurements behind the coarse level.

On a bunny data set from our FEM (default: the implicit one, ``tignn generate bunny --integrator implicit
--rise-frames 10 --out data/bunny_imp.npz``; sims with inverted elements left out as in the README), with
train = sims 1–80 and val = sims 81–90:

1. The stress divergence: the internal force Σ_e V_e σ̄_e ∇N_a computed from the stored nodal Cauchy stresses
   (element means of the nodal values, rest geometry), against M Δv / Δt − f at the free nodes: cosine and
   regression slope. If the stored stresses carried the internal force, a graph network could read Δv off
   its neighbours' stresses.
2. Global linear maps: ridge regression from the cluster means (``tignn_jax.model.coarse_graph``, C clusters)
   of u, v and f at frame k to Δv of every free node (one map for the whole body, fitted on train); the
   fraction of Δv's variance it explains (R²) on train and val, and its val rollouts (v += Δv, q += Δt v,
   backward Euler's kinematics) with the errors of the model evaluation (mean over snapshots 1..20 of the
   relative L2 error of u and v).

    python benchmarks/bunny_probe.py [--data data/bunny_imp.npz] [--clusters 4,8,16,32]

Writes benchmarks/results/bunny_probe.{json,md}.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
EXCLUDED = (1, 8, 12, 21, 34, 50, 58, 61, 79)   # sims whose elements invert at thin features (README)


def _tensor(s):
    t = np.zeros(s.shape[:-1] + (3, 3))
    t[..., 0, 0], t[..., 1, 1], t[..., 2, 2] = s[..., 0], s[..., 1], s[..., 2]
    t[..., 0, 1] = t[..., 1, 0] = s[..., 3]
    t[..., 0, 2] = t[..., 2, 0] = s[..., 4]
    t[..., 1, 2] = t[..., 2, 1] = s[..., 5]
    return t


def stress_divergence(data, cells, rows, frames=(3, 8, 14)) -> dict:
    """Cosine and slope of dt·(f − f_int(σ)) against M Δv over the free nodes, per (case, frame)."""
    q0 = data.q0.astype(np.float64)
    x = q0[cells]
    jac = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], -1)
    vol = np.abs(np.linalg.det(jac)) / 6
    inv = np.linalg.inv(jac)                                     # rows: ∇ξ_k
    grad = np.concatenate([-inv.sum(1, keepdims=True), inv], 1)  # [K,4,3] ∇N_a
    n = len(q0)
    mass = np.zeros(n)
    np.add.at(mass, cells.ravel(), np.repeat(vol / 4, 4))
    free = data.node_type == 0
    out = []
    for r in rows:
        for k in frames:
            z0, z1 = data.z[r, k].astype(np.float64), data.z[r, k + 1].astype(np.float64)
            fe = np.einsum("kij,kaj->kai", _tensor(z0[:, 6:][cells].mean(1)), grad) * vol[:, None, None]
            f_int = np.zeros((n, 3))
            np.add.at(f_int, cells.ravel(), fe.reshape(-1, 3))
            pred = ((data.f[r, k] - f_int) * data.dt)[free].ravel()
            true = ((z1[:, 3:6] - z0[:, 3:6]) * mass[:, None])[free].ravel()
            out.append((pred @ true / np.linalg.norm(pred) / np.linalg.norm(true), pred @ true / (pred @ pred)))
    out = np.asarray(out)
    return {"cosine_mean": float(out[:, 0].mean()), "cosine_abs_max": float(np.abs(out[:, 0]).max()),
            "slope_mean": float(out[:, 1].mean()), "samples": len(out)}


def linear_maps(data, train, val, clusters, lams=(1e-3, 1e-2, 1e-1)) -> list:
    from tignn_jax import model as M

    q0 = data.q0.astype(np.float64)
    free = data.node_type == 0
    frames = data.f.shape[1]
    rows = []
    for c in clusters:
        pool = np.asarray(M.coarse_graph(data.edges[0], data.edges[1], data.q0, c).pool, np.float64)

        def features(u, v, f):
            return np.concatenate([(pool @ u).ravel(), (pool @ v).ravel(), (pool @ f).ravel()])

        def samples(cases):
            x, y = [], []
            for r in cases:
                z = data.z[r].astype(np.float64)
                for k in range(frames):
                    x.append(features(z[k, :, :3] - q0, z[k, :, 3:6], data.f[r, k]))
                    y.append((z[k + 1, free, 3:6] - z[k, free, 3:6]).ravel())
            return np.asarray(x), np.asarray(y)

        xt, yt = samples(train)
        xv, yv = samples(val)
        mu, sd, ym = xt.mean(0), xt.std(0) + 1e-12, yt.mean(0)
        xs = (xt - mu) / sd
        for lam in lams:
            a = np.linalg.solve(xs.T @ xs + lam * len(xs) * np.eye(xs.shape[1]), xs.T @ (yt - ym))

            def r2(x, y):
                p = ((x - mu) / sd) @ a + ym
                return float(1 - np.sum((p - y) ** 2) / np.sum((y - y.mean(0)) ** 2))

            eu, ev = [], []
            for r in val:
                z = data.z[r].astype(np.float64)
                q, v = z[0, :, :3].copy(), z[0, :, 3:6].copy()
                for k in range(frames):
                    dv = ((features(q - q0, v, data.f[r, k]) - mu) / sd) @ a + ym
                    v[free] += dv.reshape(-1, 3)
                    q[free] += data.dt * v[free]
                    ut, vt = z[k + 1, :, :3] - q0, z[k + 1, :, 3:6]
                    eu.append(np.linalg.norm(q - q0 - ut) / np.linalg.norm(ut))
                    ev.append(np.linalg.norm(v - vt) / np.linalg.norm(vt))
            rows.append({"clusters": c, "features": int(xs.shape[1]), "ridge": lam, "r2_train": r2(xt, yt),
                         "r2_val": r2(xv, yv), "rollout_val_u": float(np.mean(eu)),
                         "rollout_val_v": float(np.mean(ev))})
            print(rows[-1], flush=True)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/bunny_imp.npz")
    ap.add_argument("--clusters", default="4,8,16,32")
    args = ap.parse_args(argv)
    from tignn_jax import data as D

    data = D.load(args.data)
    cells = np.load(args.data)["cells"]
    train = np.array([s - 1 for s in range(1, 81) if s not in EXCLUDED])
    val = np.arange(80, 90)
    div = stress_divergence(data, cells, [1, 29, 84])
    print("stress divergence", div, flush=True)
    maps = linear_maps(data, train, val, [int(c) for c in args.clusters.split(",")])
    result = {"machine": describe(), "data": args.data, "train_cases": len(train), "val_sims": "81-90",
              "stress_divergence": div, "linear_maps": maps}
    lines = ["# What predicts the bunny's velocity increment (benchmarks/bunny_probe.py)", "",
             f"Data: `{args.data}` ({len(train)} train cases from sims 1–80, val sims 81–90).", "",
             "## Divergence of the stored nodal stresses against M Δv (free nodes)", "",
             f"cosine mean {div['cosine_mean']:.3f} (largest |cosine| {div['cosine_abs_max']:.3f}), regression "
             f"slope mean {div['slope_mean']:.1f}, over {div['samples']} (case, frame) samples: the stored "
             "(volume-averaged) nodal stresses do not carry the internal force.", "",
             "## Ridge-regressed global linear maps from C cluster means of (u, v, f) to Δv", "",
             "| clusters | features | ridge | R² train | R² val | val rollout u | val rollout v |",
             "|---|---|---|---|---|---|---|"]
    for m in maps:
        lines.append(f"| {m['clusters']} | {m['features']} | {m['ridge']:g} | {m['r2_train']:.3f} | "
                     f"{m['r2_val']:.3f} | {m['rollout_val_u']:.3f} | {m['rollout_val_v']:.3f} |")
    lines += ["", f"Machine: {result['machine']}"]
    write_results("bunny_probe", result, "\n".join(lines) + "\n", RESULTS, echo=False)
    print(f"wrote {RESULTS / 'bunny_probe.md'}")


if __name__ == "__main__":
    main()
