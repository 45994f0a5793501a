"""Per-case rollout errors of a model on a data set: which cases a split's mean hides (a blown-up rollout).

`tignn evaluate` reports each split's mean and median; this writes, per sim id, the mean over snapshots 1..T of
the relative L2 errors of q, v, σ and u (`evaluate.split_errors`, all nodes: the published "snapshot" measure),
rolling out ``--chunk`` cases at a time so that the memory stays bounded (all 80 bunny training cases at once take
about 17 GB).

    python scripts/case_errors.py --model bunny-128x6 --data data/bunny.npz --split train --out runs/cases.json
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from tignn_jax import api
from tignn_jax import data as D
from tignn_jax import evaluate as EV


def case_errors(params: dict, data: D.Dataset, rows, chunk: int = 10) -> dict:
    """{sim id: {q, v, sigma, u}}: each case's mean relative errors over snapshots 1..T (NaN ones skipped)."""
    rows = np.asarray(rows, int)
    out = {}
    for start in range(0, len(rows), chunk):
        part = rows[start:start + chunk]
        for r, e in zip(part, EV.split_errors(params, data, part)["all"]):    # [T, 4] per case
            out[int(data.sim_id[r])] = {k: float(np.nanmean(e[:, i])) for i, k in enumerate(EV.VARIABLES)}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, help="shipped model name or model.npz path")
    parser.add_argument("--data", required=True, help="data set .npz")
    parser.add_argument("--split", default="test", help="split name or sim ids, e.g. 9,10,12")
    parser.add_argument("--chunk", type=int, default=10, help="cases rolled out at once (default: %(default)s)")
    parser.add_argument("--out", required=True, help="output .json")
    args = parser.parse_args(argv)
    if args.chunk < 1:
        raise SystemExit(f"--chunk must be positive, got {args.chunk}")
    params = api.load_model(args.model) if args.model.endswith(".npz") else api.load_pretrained(args.model)[0]
    data = D.load(args.data)
    errors = case_errors(params, data, D.split_rows(data, D.parse_split(args.split)), args.chunk)
    with open(args.out, "w") as fh:
        json.dump(errors, fh, indent=1)
    u = np.array([e["u"] for e in errors.values()])
    bad = [k for k, e in errors.items() if not np.isfinite(e["u"]) or e["u"] > 10]
    print(f"{len(errors)} cases, u mean {np.mean(u[np.isfinite(u) & (u <= 10)]):.4g}, blown up (u > 10): {bad}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
