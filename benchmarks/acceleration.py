"""How much acceleration the training data show: what they can say about a learned model's restoring force.

A step of the beam's momentum balance is Δv = Δt m⁻¹ (f − f_int(u)) (plus damping). Where the data's velocity
barely changes from frame to frame, the balance holds as f ≈ f_int(u) along the whole trajectory, and any model
whose force port B and restoring force K are scaled down together, c·(B f − K u), fits those frames to within
that small change: how hard the body pulls back once the load stops or is held (the stress test's release and
constant loadings) is then not in the data. This script measures, per data set and per frame k, the median over
the cases of |v_{k+1} − v_k| / |v_k| (L2 over all nodes; frames where |v_k| is below 1e-3 of the case's largest
are left out) and, over each case's frames, the share of ‖Δv‖² in frames after which the load stops rising
(frames whose load does not grow: holds and releases).

    python benchmarks/acceleration.py [--data ../shared/data/abaqus_beam.npz data/beam_int_smooth_d60.npz ...]
Writes benchmarks/results/acceleration.{json,md}.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def acceleration_stats(z, f) -> dict:
    """z [C,T+1,N,12], f [C,T,N,3] (numpy; f[k] acts over the step k → k+1) → per-frame median |Δv|/|v| [T] and
    the cases' mean share of ‖Δv‖² in the steps whose load does not grow (and the share of such steps)."""
    v = np.asarray(z[..., 3:6], np.float64)
    dv = np.sqrt(np.sum(np.diff(v, axis=1) ** 2, axis=(-2, -1)))            # [C, T]
    nv = np.sqrt(np.sum(v[:, :-1] ** 2, axis=(-2, -1)))                       # [C, T]
    moving = nv > 1e-3 * nv.max(axis=1, keepdims=True)
    ratio = np.where(moving, dv / np.maximum(nv, 1e-30), np.nan)
    load = np.sqrt(np.sum(np.asarray(f, np.float64) ** 2, axis=(-2, -1)))   # [C, T]
    grows = np.diff(load, axis=1) > 1e-6 * load.max(axis=1, keepdims=True)
    flat = np.concatenate([np.zeros_like(grows[:, :1]), ~grows], axis=1)      # [C, T]: the load does not grow
    energy = dv ** 2
    share = np.sum(energy * flat, axis=1) / np.maximum(np.sum(energy, axis=1), 1e-30)
    return {"per_frame_median": np.nanmedian(ratio, axis=0).tolist(),
            "median": float(np.nanmedian(ratio)), "p90": float(np.nanpercentile(ratio, 90)),
            "flat_load_frames": float(flat.mean()), "dv_energy_in_flat_load_frames": float(share.mean()),
            "cases": int(z.shape[0]), "frames": int(z.shape[1] - 1)}


def main(argv=None) -> int:
    from tignn_jax import data as D

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", nargs="+", default=[str(D.reference_path())], help="data set files")
    args = ap.parse_args(argv)
    rows = []
    for path in args.data:
        if not Path(path).exists():
            raise SystemExit(f"--data {path!r}: no such file")
        data = D.load(path)
        rows.append({"data": Path(path).name, **acceleration_stats(data.z, data.f)})
    result = {"machine": describe(), "rows": rows}
    lines = ["# How much acceleration the training data show", "",
             "Per data set: |v_{k+1} − v_k| / |v_k| (L2 over all nodes; median and 90th percentile over cases and "
             "frames, and the median per frame), the share of frames whose load does not grow (holds, releases) "
             "and the mean share of each case's ‖Δv‖² in them. A small change per frame means the frames "
             "constrain only the balance f ≈ f_int(u), not the scale of the restoring force (this script's "
             "docstring).", "",
             "| data | cases × frames | median | p90 | frames 1, 5, 10, 19 (median) | frames with the load not growing | "
             "their share of ‖Δv‖² |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        per = r["per_frame_median"]
        picks = ", ".join(f"{per[k]:.4f}" for k in (0, 4, 9, len(per) - 1) if k < len(per))
        lines.append(f"| {r['data']} | {r['cases']} × {r['frames']} | {r['median']:.4f} | {r['p90']:.4f} | {picks} | "
                     f"{r['flat_load_frames']:.0%} | {r['dv_energy_in_flat_load_frames']:.0%} |")
    write_results("acceleration", result, "\n".join(lines) + "\n", RESULTS, echo=False)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
