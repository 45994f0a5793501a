r"""How far the beam's rest-linearised step lands from the data when it starts from a true state.

A ``linear_prior`` model (`tignn_jax.framesolve`) adds a network correction to the FEM's rest-linearised
backward-Euler frame map. Its rollouts from rest are self-consistent (`beam-linear` alone: test u 0.054,
`pareto.md`), but training the correction one step at a time starts every step from a true, non-linear state,
where the linear internal force K₀u is not the body's. This measures that jump: for each frame k of the train
cases, the shipped `beam-linear` step from the true z_k under the true f_k against the true z_{k+1},

    ratio_k(x) = sqrt(Σ (z_{k+1} − step(z_k))_x²) / sqrt(Σ (z_{k+1} − z_k)_x²)     for x = q, v, σ,

summed over nodes, components and train cases: the one-step error of the prior relative to the increment a
correction would start from. A correction network must cancel the part above ~1 before it can add anything.

    python benchmarks/prior_jump.py [--data ../shared/data/abaqus_beam.npz] [--model beam-linear]

Writes benchmarks/results/prior_jump.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
GROUPS = {"q": slice(0, 3), "v": slice(3, 6), "sigma": slice(6, 12)}


def jump_ratios(params: dict, z, f) -> np.ndarray:
    """[T, 3] ratio_k for q, v, σ (see the module docstring) over the cases z [C,T+1,N,12], f [C,T,N,3]."""
    import jax
    import jax.numpy as jnp

    from tignn_jax import api

    step = jax.jit(jax.vmap(api.stepper(params)))   # the model's own step (the linearised solve alone, if zero)
    num = np.zeros((z.shape[1] - 1, len(GROUPS)))
    den = np.zeros_like(num)
    for zc, fc in zip(z, f):
        nxt = np.asarray(step(jnp.asarray(zc[:-1]), jnp.asarray(fc)), np.float64)
        err, inc = zc[1:] - nxt, zc[1:] - zc[:-1]
        for j, s in enumerate(GROUPS.values()):
            num[:, j] += np.sum(err[..., s] ** 2, axis=(1, 2))
            den[:, j] += np.sum(inc[..., s] ** 2, axis=(1, 2))
    return np.sqrt(num / np.maximum(den, 1e-300))


def main(argv=None) -> int:
    from tignn_jax import api
    from tignn_jax import data as D

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(D.reference_path()), help="data set on the model's mesh")
    ap.add_argument("--model", default="beam-linear", help="a linear_prior model (shipped name or path)")
    args = ap.parse_args(argv)
    if not Path(args.data).exists():
        print(f"{args.data} not found: nothing to measure")
        return 1
    params = api.load_pretrained(args.model)[0]   # a shipped name, a model folder or a model.npz
    if not params["config"].get("linear_prior"):
        raise ValueError(f"{args.model} is not a linear_prior model")
    data = D.load(args.data)
    rows = D.split_rows(data, "train")
    z, f = np.asarray(data.z[rows], np.float32), np.asarray(data.f[rows], np.float32)
    ratios = jump_ratios(params, z, f)
    out = {"machine": describe(), "data": Path(args.data).name, "model": args.model, "cases": len(rows),
           "ratio_per_frame": {k: ratios[:, j].round(4).tolist() for j, k in enumerate(GROUPS)}}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "prior_jump.json").write_text(json.dumps(out, indent=1))
    lines = [f"# The rest-linearised step from true states ({args.model} on {out['data']}, {len(rows)} train cases)",
             "", "One step of the prior from the true state z_k under f_k; RMS error against z_{k+1} over the RMS "
             "true increment z_{k+1} − z_k (1 = as large as the increment itself). The reference data's velocities are "
             "central differences of q (numpy.gradient), not the solver's, which accounts for part of the velocity "
             "ratio from the first frame on; the growth with k is the linear force K₀u departing from the body's "
             "as it deflects.", "",
             "| frame k | q | v | σ |", "|---|---|---|---|"]
    lines += [f"| {k} | {r[0]:.3g} | {r[1]:.3g} | {r[2]:.3g} |" for k, r in enumerate(ratios)]
    (RESULTS / "prior_jump.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
