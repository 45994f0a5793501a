"""``tignn rollout``: a model's predicted states for cases of a data file, as .npz or a ParaView series."""
from __future__ import annotations

from pathlib import Path

from tignn_jax.cli import UsageError


def register(sub) -> None:
    p = sub.add_parser("rollout", help="predict the states of data-set cases from their first state and forces",
                       description="Roll a model out from each selected case's first state under the case's "
                                   "forces and write the predicted states z [cases, frames+1, nodes, 12] with "
                                   "their sim ids to an .npz file.")
    p.add_argument("--model", default="beam", help="shipped model name or model folder/file (default: %(default)s)")
    p.add_argument("--data", required=True, metavar="FILE", help="data file on the model's mesh")
    p.add_argument("--sims", required=True, help="a split name (test) or 1-based sim ids, e.g. 9,10,12")
    p.add_argument("--out", required=True, help="output .npz with z and sim_id")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from tignn_jax import api
    from tignn_jax import data as D
    from tignn_jax import evaluation as EV
    from tignn_jax.cli.evaluate import load_data

    params, _ = api.load_pretrained(args.model)
    data = load_data(args.data)
    try:
        rows = D.split_rows(data, D.parse_split(args.sims))
    except (KeyError, ValueError) as err:
        raise UsageError(f"--sims {args.sims}: {err}") from None
    z = EV.rollout_cases(params, data, rows)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, z=z, sim_id=data.sim_id[rows])
    print(f"wrote {out} (z {z.shape})")
    return 0
