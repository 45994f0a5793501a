"""Which part of the learned GENERIC step makes it unstable: the growth's split into its terms.

For each beam model, at the states of ``step_growth.py`` (rest; ramp end and hold +20 of the model's own
rollout under the stability benchmark's constant load) and at the six test cases' true frame-19 states (when
``../shared/data/abaqus_beam.npz`` is present), ``tignn_jax.step_growth`` finds the step's dominant mode x
(power iteration) and ``tignn_jax.growth_terms`` splits xᵀ(J − I)x, ≈ growth − 1 for a real eigenvalue, into
  L∇²E (L frozen), (∂L·x)∇E (L's change with the state times ∇E), M∇²S and (∂M·x)∇S,
with the whole step's xᵀ(J − I)x beside them (reverse mode; the terms sum to it). A convex E with a skew,
constant L only rotates a disturbance, and a concave S with a PSD M only damps it, so a term that is positive
and large says where the model's anti-damping lives.

A model is a shipped name, a model.npz path, or either with ``+static_l`` (the same weights with ``static_l``:
L decoded at the rest state), optionally labelled ``label=spec`` (``--models`` is comma-separated, so a label
holds no comma).
Writes benchmarks/results/step_growth_terms.{json,md} (``--tag T``: step_growth_terms_T.*).

    python benchmarks/growth_terms.py [--models beam-abaqus,beam-abaqus+static_l,...] [--iterations 150] [--tag T]
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_MODELS = ("beam-abaqus", "beam-gnn", "beam-abaqus-small", "beam-abaqus+static_l")
TERMS = ("L_hessian", "L_change", "M_hessian", "M_change")


def load(spec: str):
    """(label, params) of a ``[label=]name_or_path[+static_l]`` spec."""
    from tignn_jax import api

    label, _, spec = spec.rpartition("=")
    base, _, flag = spec.partition("+")
    if flag not in ("", "static_l"):
        raise ValueError(f"model spec {spec!r}: the only modifier is '+static_l', got '+{flag}'")
    params, _ = api.load_pretrained(base)   # a shipped name or a model path
    if flag:
        params = dict(params, config={**params["config"], "static_l": True})
    return label or spec, params


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default=",".join(DEFAULT_MODELS))
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--tag", default="", help="write step_growth_terms_TAG.* instead of step_growth_terms.*")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    from step_growth import anchors
    from tignn_jax import api
    from tignn_jax import data as D

    reference = D.load(D.reference_path()) if D.reference_path().exists() else None
    rows, t_start = [], time.time()
    for spec in [m for m in args.models.split(",") if m]:
        label, params = load(spec)
        if len(params["mesh"]["node_type"]) != 756:
            raise ValueError(f"{label}: growth_terms.py measures beam models (756 nodes)")
        states, _ = anchors(params, "beam")
        if reference is not None:
            states += [(f"test sim {int(reference.sim_id[r])}, frame 19", reference.z[r, 19], reference.f[r, 19])
                       for r in D.split_rows(reference, "test")]
        for anchor, z, f in states:
            g = api.step_growth(params, z, f, iterations=args.iterations)
            if not np.isfinite(g["growth"]):   # reported, not dropped: the power iteration left finite numbers
                rows.append({"model": label, "anchor": anchor, "growth": float("nan"),
                             **{k: float("nan") for k in (*TERMS, "total")}})
                print(f"{label:>28s} {anchor:>24s}: growth not finite", flush=True)
                continue
            terms = api.growth_terms(params, z, f, g["mode"])
            rows.append({"model": label, "anchor": anchor, "growth": g["growth"], **terms})
            print(f"{label:>28s} {anchor:>24s}: growth {g['growth']:.3f}  "
                  + "  ".join(f"{k} {terms[k]:+.3f}" for k in (*TERMS, "total")), flush=True)
    result = {"machine": describe(), "iterations": args.iterations, "rows": rows, "wall_s": time.time() - t_start}
    stem = f"step_growth_terms_{args.tag}" if args.tag else "step_growth_terms"
    write_results(stem, result, render(result), RESULTS, echo=False)
    print(f"wrote {RESULTS / stem}.{{json,md}} in {time.time() - t_start:.0f} s")
    return 0


def render(result: dict) -> str:
    m = result["machine"]
    lines = ["# Where the learned step's growth comes from", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, jax {m['jax']}. {result['iterations']} power iterations per state "
             "(`tignn_jax.step_growth`), then `tignn_jax.growth_terms` along the dominant mode x (state stds): "
             "xᵀ(J − I)x split by the product rule into L∇²E (L frozen), (∂L·x)∇E, M∇²S (M frozen) and "
             "(∂M·x)∇S; 'step' is the whole step's xᵀ(J − I)x (reverse mode), ≈ growth − 1 for a real "
             "eigenvalue. `+static_l`: the same weights with L decoded at the rest state (no training).", "",
             "| model | state | growth | L∇²E | (∂L·x)∇E | M∇²S | (∂M·x)∇S | step |", "|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['model']} | {r['anchor']} | {r['growth']:.3f} | " + " | ".join(
            f"{r[k]:+.4f}" for k in (*TERMS, "total")) + " |")
    lines += ["", "Largest term per model (share of the states where it is the largest of the four in magnitude):", ""]
    for model in dict.fromkeys(r["model"] for r in result["rows"]):
        rows = [r for r in result["rows"] if r["model"] == model]
        top = [max(TERMS, key=lambda k: abs(r[k])) for r in rows if np.isfinite(r["total"])]
        lines.append(f"- {model}: " + ", ".join(f"{k} {top.count(k)}/{len(top)}" for k in TERMS if top.count(k)))
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
