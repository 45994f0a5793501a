"""The beam models on fingertip interactions: rollout errors by what the fingertip did.

The reference load cases only ever press harder; a fingertip also holds, lets go and moves. This rolls each
model out on the held-out cases of two FEM data sets on the same mesh (the 52 reference cases and the 64
fingertip cases, both cut to start at the same frame) and reports, per group (the reference cases, and the
fingertip cases by profile: ramp, hold, release, move), the mean over cases and snapshots of the relative L2
error of u, v, σ and q made relative to the case's largest true norm ("peak": while a fingertip holds, v ≈ 0 and
the per-snapshot measure is a ratio of round-off), the largest such error of u at any snapshot, and how many
rollouts stay finite. The profiles come from the ``cases`` list in the metadata of the file the fingertip
cases were generated into (``tignn generate beam-interactions``), in case order.
Writes benchmarks/results/interactions[_TAG].{json,md}.

    python benchmarks/interactions.py --models beam,runs/X/best/model.npz [--splits val,test] [--tag NAME]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402
from device_step import integrator_text, model_label  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]
VARS = ("u", "v", "sigma", "q")


def profiles_of(path) -> list:
    """The fingertip profile of each case, in order, from a generated file's metadata."""
    with np.load(path, allow_pickle=False) as npz:
        meta = json.loads(str(npz["metadata"])) if "metadata" in npz.files else {}
    cases = meta.get("cases")
    if not cases or any("profile" not in c for c in cases):
        raise ValueError(f"{path} has no 'cases' list with a 'profile' per case in its metadata")
    return [c["profile"] for c in cases]


def groups(reference, interactions, profiles, split: str) -> list:
    """[(group name, data set, rows)]: the reference split, then the fingertip split by profile."""
    from tignn_jax import data as D

    out = [("reference", reference, D.split_rows(reference, split))]
    rows = D.split_rows(interactions, split)
    if len(profiles) != len(interactions.sim_id):
        raise ValueError(f"{len(profiles)} profiles for {len(interactions.sim_id)} fingertip cases")
    for name in sorted({profiles[r] for r in rows}):
        out.append((name, interactions, np.array([r for r in rows if profiles[r] == name])))
    return out


def errors(params, data, rows) -> dict:
    """Peak-relative errors of the rollouts of ``rows``: mean per variable, the largest u error, finite count."""
    from tignn_jax import evaluate as EV

    pred = EV.rollout_cases(params, data, rows)
    finite = np.all(np.isfinite(pred), axis=(1, 2, 3))
    return {**peak_errors(pred, data.z[rows], data.q0), "cases": int(len(rows)), "finite": int(finite.sum())}


def peak_errors(pred, true, q0) -> dict:
    """The mean over cases and snapshots 1..T of each variable's error relative to the case's peak, and the largest
    u error, of predicted states pred [C,T+1,N,12] against true ones."""
    from tignn_jax import evaluate as EV

    e = EV.relative_errors(pred, true, q0, reference="peak")[:, 1:]
    out = {name: float(np.mean(e[..., EV.VARIABLES.index(name)])) for name in VARS}
    out["u_max"] = float(np.max(e[..., EV.VARIABLES.index("u")]))
    return out


def describe_model(m: dict) -> str:
    """The table's config column: the architecture and step, the learned linear operators, or that the model is
    the linear FEM step."""
    if m.get("kind", "").startswith("learned linear GENERIC"):
        return "learned linear GENERIC operators, backward Euler"
    if not m["learned"]:
        return "the FEM's rest-linearised backward-Euler step (not learned)"
    c = m["config"]
    return f"{c['hidden']}×{c['passes']}, {integrator_text(c)}" + (", convex free energy" if c.get("convex") else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="beam,beam-gnn", help="comma-separated shipped names or model paths")
    ap.add_argument("--reference", default="data/beam_ref_f2.npz", help="the reference cases (FEM)")
    ap.add_argument("--interactions", default="data/beam_int_f2.npz", help="the fingertip cases (FEM)")
    ap.add_argument("--profiles", default="data/beam_int_smooth_d60.npz",
                    help="the file the fingertip cases were generated into (its metadata names the profiles)")
    ap.add_argument("--splits", default="val,test", help="comma-separated split names, each reported apart")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)

    from tignn_jax import api
    from tignn_jax import data as D

    reference, interactions = D.load(ROOT / args.reference), D.load(ROOT / args.interactions)
    profiles = profiles_of(ROOT / args.profiles)
    splits = [s for s in args.splits.split(",") if s]
    found = [(s, g, d, r) for s in splits for g, d, r in groups(reference, interactions, profiles, s)]
    result = {"machine": describe(), "splits": splits, "reference": args.reference,
              "interactions": args.interactions, "models": {}}
    for name in [m for m in args.models.split(",") if m]:
        params, _ = api.load_pretrained(name)
        t0 = time.perf_counter()
        rows = {f"{s}/{g}": errors(params, data, r) for s, g, data, r in found}
        cfg = params["config"]
        result["models"][name] = {"groups": rows, "seconds": time.perf_counter() - t0,
                                  "learned": not api.network_is_zero(params),
                                  "kind": str(params.get("info", {}).get("kind", "")),
                                  "config": {k: cfg.get(k) for k in ("hidden", "passes", "integrator", "substeps",
                                                                     "relaxation", "frame_solve", "convex",
                                                                     "free_energy")}}
        print(name, json.dumps({g: round(r["u"], 4) for g, r in rows.items()}), flush=True)

    stem = "interactions" + (f"_{args.tag}" if args.tag else "")
    lines = ["# The beam models on the fingertip cases", "",
             f"Machine: {result['machine']}.", "",
             f"Data: `{args.reference}` (reference cases) and `{args.interactions}` (fingertip cases; profiles from "
             f"`{args.profiles}`). Errors relative to each case's largest true norm, mean over cases and snapshots; "
             "u max: the largest u error at any snapshot; finite: rollouts with no NaN/Inf.", "",
             "| model | config | split/group | cases | finite | u | v | σ | q | u max |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, m in result["models"].items():
        text = describe_model(m)
        for g, r in m["groups"].items():
            lines.append(f"| {model_label(name)} | {text} | {g} | {r['cases']} | {r['finite']} | {r['u']:.3g} | "
                         f"{r['v']:.3g} | {r['sigma']:.3g} | {r['q']:.3g} | {r['u_max']:.3g} |")
    write_results(stem, result, "\n".join(lines) + "\n", RESULTS, echo=False)
    print(f"wrote {RESULTS / stem}.{{json,md}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
