"""Write a data set's rows of one split as a smaller file set that fits a transfer limit.

    python scripts/bunny_heldout_subset.py data/bunny.npz --split test --out DIR

DIR/<split>_z.npy holds the states z [cases, T+1, N, 12] (float32) and DIR/<split>_rest.npz every other key, the
per-case arrays reduced to the same rows, so a machine without the FEM time can evaluate on them;
``--merge DIR --out FILE`` joins the two back into one data-set file (the format of README's data-set table).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


# the keys with one entry per case (README's data-set table); every other key describes the mesh or the set
PER_CASE = ("f", "v_solver", "sim_id", "newton_residual", "newton_iterations")


def subset(path: str, split: str, out: Path) -> None:
    raw = np.load(path, allow_pickle=False)
    ids = np.asarray(raw[f"split_{split}"])
    rows = np.array([int(np.nonzero(raw["sim_id"] == s)[0][0]) for s in ids])
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / f"{split}_z.npy", raw["z"][rows])
    rest = {k: raw[k][rows] if k in PER_CASE else raw[k] for k in raw.files if k != "z"}
    rest[f"split_{split}"] = ids
    for other in ("train", "val", "test"):
        if other != split:
            rest.pop(f"split_{other}", None)
    np.savez(out / f"{split}_rest.npz", **rest)


def merge(folder: Path, split: str, out: str) -> None:
    rest = dict(np.load(folder / f"{split}_rest.npz", allow_pickle=False))
    np.savez(out, z=np.load(folder / f"{split}_z.npy"), **rest)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", help="the full data-set file (omit with --merge)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--merge", help="a folder written by this script: join it into --out")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    if a.merge:
        merge(Path(a.merge), a.split, a.out)
    else:
        subset(a.data, a.split, Path(a.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
