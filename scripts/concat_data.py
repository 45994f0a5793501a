"""Stack data-set files of one scene into one file that `tignn train` reads like a generated one.

`tignn_jax.data.concatenate` stacks the cases (later sets' sim ids shifted past the largest id so far, splits
united); this script also keeps the first file's mesh cells and metadata (material, density, damping), which
``frame_solve`` training needs to rebuild the scene's rest linearisation. The files must share the mesh, the
time step and the material; a difference is an error naming it.

    python scripts/concat_data.py data/bunny_imp_r3_p5.npz data/bunny_p5_f5.npz --out data/bunny_p5_f1f5.npz

``--train-later``: the later files are training data only. Every case of theirs forms the train split, and
the first file contributes only its val and test splits (for a dense training set around held-out positions:
`scripts/bunny_dense_positions.py`).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from tignn_jax import data as D


def main(argv=None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", help="data-set .npz files of one scene, in order")
    parser.add_argument("--out", required=True, help="output .npz")
    parser.add_argument("--train-later", action="store_true",
                        help="train = every case of the files after the first; val and test = the first file's")
    args = parser.parse_args(argv)
    if args.train_later and len(args.files) < 2:
        raise ValueError("--train-later needs at least two files")
    sets = [D.load(p) for p in args.files]
    raw = [np.load(p, allow_pickle=False) for p in args.files]
    metas = [json.loads(str(r["metadata"]) or "{}") if "metadata" in r.files else {} for r in raw]
    materials = [m.get("material") for m in metas]
    for path, mat in zip(args.files[1:], materials[1:]):
        if mat != materials[0]:
            raise ValueError(f"{path} has the material {mat}, {args.files[0]} has {materials[0]}")
    for path, r in zip(args.files[1:], raw[1:]):
        if "cells" in raw[0].files and ("cells" not in r.files or not np.array_equal(r["cells"], raw[0]["cells"])):
            raise ValueError(f"{path} does not have the cells of {args.files[0]}")
    data = D.concatenate(*sets)
    if args.train_later:
        first = {k: np.asarray(v, np.int32) for k, v in sets[0].splits.items() if k in ("val", "test")}
        data = data._replace(splits={"train": data.sim_id[len(sets[0].sim_id):], **first})
    meta = dict(metas[0])
    meta["concatenated_from"] = [str(p) for p in args.files]
    out = Path(args.out)
    extra = {k: raw[0][k] for k in ("cells", "cell_type") if k in raw[0].files}
    np.savez(out, q0=data.q0, edges=data.edges, node_type=data.node_type, z=data.z, f=data.f,
             dt=np.float64(data.dt), sim_id=data.sim_id, metadata=np.array(json.dumps(meta)),
             **{f"split_{k}": v for k, v in data.splits.items()}, **extra)
    print(f"{out}: {len(data.sim_id)} cases (sim ids {data.sim_id.min()}..{data.sim_id.max()})")
    return out


if __name__ == "__main__":
    main()
