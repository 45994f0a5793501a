"""``tignn rollout``: a model's predicted states for cases of a data file, as .npz and, with ``--paraview``, a
ParaView series per case (VTU frames and a .pvd index, as ``tignn generate --paraview`` writes the FEM's), so the
learned and the FEM rollouts open side by side."""
from __future__ import annotations

from pathlib import Path

from tignn_jax import DEFAULT_MODEL
from tignn_jax.cli import UsageError


def register(sub) -> None:
    p = sub.add_parser("rollout", help="predict the states of data-set cases from their first state and forces",
                       description="Roll a model out from each selected case's first state under the case's "
                                   "forces and write the predicted states z [cases, frames+1, nodes, 12] with "
                                   "their sim ids to an .npz file.")
    p.add_argument("--model", default=DEFAULT_MODEL,
                   help="shipped model name or model folder/file (default: %(default)s)")
    p.add_argument("--data", required=True, metavar="FILE", help="data file on the model's mesh")
    p.add_argument("--sims", required=True, help="a split name (test) or 1-based sim ids, e.g. 9,10,12")
    p.add_argument("--out", required=True, help="output .npz with z and sim_id")
    p.add_argument("--paraview", action="store_true",
                   help="also write each case as a ParaView series OUT_case<id>.pvd (+ VTU frames): u, v, σ and "
                        "von Mises, and the FEM's u and the error |u - u_FEM| from the data")
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
    out = Path(args.out)
    if out.suffix != ".npz":
        out = out.with_name(out.name + ".npz")       # as numpy.savez names it: report the file it writes
    if out.is_dir():
        raise UsageError(f"--out {args.out}: {out} is a folder")
    z = EV.rollout_cases(params, data, rows)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, z=z, sim_id=data.sim_id[rows])
    print(f"wrote {out} (z {z.shape})")
    if args.paraview:
        from fem.mesh import write_series

        cells = params["mesh"].get("cells")
        cells = D.cells(args.data) if cells is None else cells
        if cells is None:
            raise UsageError(f"--paraview: neither the model nor {args.data} keeps the mesh's cells")
        kind = "hexahedron" if cells.shape[1] == 8 else "tetra"
        t = data.dt * np.arange(z.shape[1])
        for c, row in enumerate(rows):
            true = data.z[row]
            extra = {"u_fem": true[..., :3] - data.q0,
                     "u_error": np.linalg.norm(z[c, ..., :3] - true[..., :3], axis=-1)}
            path = write_series(out.with_name(f"{out.stem}_case{int(data.sim_id[row]):03d}.pvd"), data.q0, cells,
                                kind, t, z[c, ..., :3], z[c, ..., 3:6], z[c, ..., 6:12], extra)
            print(f"wrote {path}")
    return 0
