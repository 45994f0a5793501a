r"""How far the beam's rest-linearised step lands from the data when it starts from a true state.

A ``linear_prior`` model (`tignn_jax.framesolve`) adds a network correction to the FEM's rest-linearised
backward-Euler frame map. Its rollouts from rest are self-consistent (`beam-linear` alone: test u 0.054,
`pareto.md`), but training the correction one step at a time starts every step from a true, non-linear state,
where the linear internal force K₀u is not the body's. This measures that jump: for each frame k of the train
cases, the shipped `beam-linear` step from the true z_k under the true f_k against the true z_{k+1},

    ratio_k(x) = sqrt(Σ (z_{k+1} − step(z_k))_x²) / sqrt(Σ (z_{k+1} − z_k)_x²)     for x = q, v, σ,

summed over nodes, components and train cases: the one-step error of the prior relative to the increment a
correction would start from. A correction network must cancel the part above ~1 before it can add anything.

Where the jump comes from (`stress_split`): the prior's stress S₀u at a true displacement u against the true
stress σ, each split into its hydrostatic part p = (σ₁₁ + σ₂₂ + σ₃₃)/3 and the rest (the deviatoric normal
components and the shears). For a nearly incompressible material (the beam: bulk modulus 2/D1 = 2e7 against a
shear modulus 2(C10 + C01) = 3.1e5) the linear pressure K div u is wrong at second order in the displacement
gradient: a rigid rotation by θ has div u = 2(cos θ − 1) and no stress, yet S₀u carries the pressure
(2/D1)·2(cos θ − 1) (−2e5 at θ = 0.1, tested). The true states of a bending beam rotate, so their S₀u is a
spurious pressure, and K₀u the matching spurious force: a correction must cancel both.

    python benchmarks/prior_jump.py [--data ../shared/data/abaqus_beam.npz] [--model beam-linear] [--tag T]

Writes benchmarks/results/prior_jump[_T].{json,md}.
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


def _split(s):
    """[..., 6] stresses (S11 S22 S33 S12 S13 S23) → (hydrostatic [...], deviatoric remainder [..., 6])."""
    p = s[..., :3].mean(-1)
    return p, np.concatenate([s[..., :3] - p[..., None], s[..., 3:]], axis=-1)


def stress_split(params: dict, z) -> np.ndarray:
    """[T+1, 4] rms over cases and nodes, per snapshot of z [C,T+1,N,12]: the true hydrostatic stress, the prior's
    hydrostatic stress S₀u at the true displacement, the true deviatoric remainder and the prior's (see the module
    docstring). S₀ is the model's rest linearisation (``norm["fs_s*"]``)."""
    import jax.numpy as jnp

    from tignn_jax import framesolve as FS

    norm = {k: jnp.asarray(params["norm"][k]) for k in ("fs_s_rows", "fs_s_cols", "fs_s")}
    q0 = np.asarray(params["mesh"]["q0"], np.float32)
    lin = np.stack([np.stack([np.asarray(FS.apply_s(norm, jnp.asarray(zk[:, :3] - q0))) for zk in zc]) for zc in z])
    (p_true, d_true), (p_lin, d_lin) = _split(np.asarray(z[..., 6:], np.float64)), _split(lin.astype(np.float64))
    rms = lambda a, axes: np.sqrt(np.mean(a ** 2, axis=axes))
    return np.stack([rms(p_true, (0, 2)), rms(p_lin, (0, 2)), rms(d_true, (0, 2, 3)), rms(d_lin, (0, 2, 3))], axis=1)


def main(argv=None) -> int:
    from tignn_jax import api
    from tignn_jax import data as D

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(D.reference_path()), help="data set on the model's mesh")
    ap.add_argument("--model", default="beam-linear", help="a linear_prior model (shipped name or path)")
    ap.add_argument("--tag", default="", help="results go to prior_jump_TAG.{json,md}")
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
    split = stress_split(params, z)
    out = {"machine": describe(), "data": Path(args.data).name, "model": args.model, "cases": len(rows),
           "ratio_per_frame": {k: ratios[:, j].round(4).tolist() for j, k in enumerate(GROUPS)},
           "stress_rms_per_snapshot": {k: split[:, j].round(2).tolist() for j, k in enumerate(
               ("true_hydrostatic", "prior_hydrostatic", "true_deviatoric", "prior_deviatoric"))}}
    name = "prior_jump" + (f"_{args.tag}" if args.tag else "")
    lines = [f"# The rest-linearised step from true states ({args.model} on {out['data']}, {len(rows)} train cases)",
             "", "One step of the prior from the true state z_k under f_k; RMS error against z_{k+1} over the RMS "
             "true increment z_{k+1} − z_k (1 = as large as the increment itself). The reference data's velocities are "
             "central differences of q (numpy.gradient), not the solver's, which accounts for part of the velocity "
             "ratio from the first frame on; the growth with k is the linear force K₀u departing from the body's "
             "as it deflects.", "",
             "| frame k | q | v | σ |", "|---|---|---|---|"]
    lines += [f"| {k} | {r[0]:.3g} | {r[1]:.3g} | {r[2]:.3g} |" for k, r in enumerate(ratios)]
    lines += ["", "## The prior's stress at the true displacements", "",
              "S₀u against the true σ at each snapshot k of the same cases, split into the hydrostatic part "
              "p = (σ₁₁ + σ₂₂ + σ₃₃)/3 and the deviatoric remainder (rms over cases and nodes; see the module "
              "docstring: the linearised pressure of a nearly incompressible material is wrong at second order in "
              "the rotation).", "",
              "| snapshot k | true p | prior p | ratio | true deviatoric | prior deviatoric | ratio |",
              "|---|---|---|---|---|---|---|"]
    lines += [f"| {k} | {r[0]:.4g} | {r[1]:.4g} | {r[1] / max(r[0], 1e-30):.3g} | {r[2]:.4g} | {r[3]:.4g} | "
              f"{r[3] / max(r[2], 1e-30):.3g} |" for k, r in enumerate(split)]
    m = out["machine"]
    lines += ["", f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']} ({m['backend']})."]
    write_results(name, out, "\n".join(lines) + "\n", RESULTS, echo=False)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
