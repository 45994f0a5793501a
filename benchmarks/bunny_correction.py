"""What can a correction on the bunny's rest linearisation gain at best? The exact non-linear force as the oracle.

A ``linear_prior`` + ``frame_solve`` model steps z ← z + W⁻¹ (Δt (J₀ z + B f) + e), with e the network's
increment (`tignn_jax.framesolve`). The learned corrections tried so far did not beat e = 0 (README, bunny
sessions 17–18). This benchmark replaces the network by the best a state-wise correction of the force could
know: the FEM's own non-linear internal force, e_v = Δt (K₀ u − f_int(u)) / m (the linearly implicit Euler step
with the exact force), and rolls the held-out cases out three ways from their first state with their forces:

  * ``prior``: e = 0 (the shipped ``bunny-linear``); its σ is S₀ u (the rest-linear stress of its own u);
  * ``exact force``: the oracle e_v above, σ still carried as S₀ u;
  * ``exact force, σ = σ(u)``: the same u, with σ the FEM's non-linear nodal stress of that u.

It also measures, at one frame, how the data's stress relates to the data's and the prior's displacements:
σ(u_true) (the FEM's stress map on the true u; must be ~0: the data's σ is that), S₀ u_true and S₀ u_prior.
On a nearly incompressible body (the bunny: bulk / shear modulus = (2/D1) / (2 C10) ≈ 78) a displacement error
of a few per cent in the volumetric directions is a stress error of the same order as the stress, so σ is only
as good as the consistency of u and σ. Errors are relative L2 over each case's whole rollout (all nodes, all
frames), then the mean over cases, per load magnitude (the peak resultant of a case's forces). Writes benchmarks/results/bunny_correction.{json,md}.
Needs the bunny patch-load data (README: ``tignn generate bunny ...``); exits cleanly without it.

    python benchmarks/bunny_correction.py [--data data/bunny_p5_f1f5.npz] [--cases 81-100,181-200]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _machine import describe, write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
MODES = ("prior", "exact force", "exact force, σ = σ(u)")


def parse_cases(text: str) -> list:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        try:
            out += list(range(int(a), int(b) + 1)) if b else [int(a)]
        except ValueError:
            raise SystemExit(f"--cases: cannot read {part!r} (use e.g. 81-100,181-200)") from None
    return out


def scene_functions(path: Path, ops_cache: Path):
    """(data, norm with A₀⁻¹, f_int(u), σ(u)) of the scene a data file was generated from."""
    import jax
    import jax.numpy as jnp

    from fem import implicit
    from tignn_jax import framesolve as FS

    d = np.load(path, allow_pickle=False)
    mat = json.loads(str(d["metadata"]))["material"]
    nt, dt = d["node_type"], float(d["dt"])
    force, stress = implicit.force_and_stress(*FS.problem_from_file(path))
    norm = {**FS.norm_entries(FS.operators_cached(path, ops_cache)), "dt": np.array([dt], np.float32)}
    norm = {k: jnp.asarray(v) for k, v in FS.with_inverse(norm, nt).items()}
    return d, norm, force, jax.jit(stress), mat



def case_errors(zt, f, q0, node_type, dt: float, norm: dict, force, stress, frame: int) -> dict:
    """One case's rollouts ``MODES`` from its first state zt[0] under its forces f [T,N,3] against its states
    zt [T+1,N,12] ({mode: {u, v, sigma}}: relative L2 over the whole rollout), and the stress check at ``frame``.
    ``norm``: the rest linearisation's entries with A₀⁻¹ and "dt"; ``force``(u) / ``stress``(u): the FEM's
    internal force and nodal stress of displacements u [N,3]."""
    import jax
    import jax.numpy as jnp

    from tignn_jax import framesolve as FS

    x0, ntj = jnp.asarray(q0, jnp.float32), jnp.asarray(node_type)
    free = jnp.asarray(np.asarray(node_type) == 0, jnp.float32)[:, None]
    mass = jnp.asarray(norm["fs_mass"])[:, None]

    def make_step(exact_force: bool):
        @jax.jit
        def step(z, f):
            u = z[:, :3] - x0
            e = jnp.zeros_like(z)
            if exact_force:   # the linearly implicit Euler step with the FEM's own non-linear force
                e = e.at[:, 3:6].set(dt * (FS.apply_k(norm, u * free) - force(u)) / mass * free)
            return z + FS.prior_step(norm, z, f, e, ntj, x0)
        return step

    rel = lambda a, b: float(np.linalg.norm(a - b) / np.linalg.norm(b))
    out = {}
    for name in ("prior", "exact force"):
        step, z, states = make_step(name == "exact force"), jnp.asarray(zt[0]), [np.asarray(zt[0])]
        for k in range(f.shape[0]):
            z = step(z, jnp.asarray(f[k]))
            states.append(np.asarray(z))
        zp = np.stack(states)
        sig = {name: zp[..., 6:]}
        if name == "exact force":
            sig["exact force, σ = σ(u)"] = np.stack([np.asarray(stress(jnp.asarray(x[:, :3] - q0))) for x in zp])
        for key, s in sig.items():
            out[key] = {"u": rel(zp[..., :3] - q0, zt[..., :3] - q0), "v": rel(zp[..., 3:6], zt[..., 3:6]),
                        "sigma": rel(s, zt[..., 6:])}
        if name == "prior":
            k = min(frame, f.shape[0])
            ut, up = jnp.asarray(zt[k, :, :3] - q0), jnp.asarray(zp[k, :, :3] - q0)
            s0 = FS.apply_s(norm, ut * free), FS.apply_s(norm, up * free)
            out["stress check"] = {"σ(u_true)": rel(np.asarray(stress(ut)), zt[k, :, 6:]),
                                   "S0 u_true": rel(np.asarray(s0[0]), zt[k, :, 6:]),
                                   "S0 u_prior": rel(np.asarray(s0[1]), zt[k, :, 6:]),
                                   "u_prior": rel(np.asarray(up), np.asarray(ut))}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="data/bunny_p5_f1f5.npz")
    parser.add_argument("--ops", default="data/bunny_frame_ops.npz", help="cache of the rest linearisation")
    parser.add_argument("--cases", default="81-100,181-200", help="sim ids (default: the val and test positions "
                        "at unit and 5x loads of the session-18 split)")
    parser.add_argument("--frame", type=int, default=15, help="frame of the stress-consistency check")
    args = parser.parse_args(argv)
    path = Path(args.data)
    if not path.exists():
        print(f"no bunny data at {path}: generate it first (README); nothing measured")
        return 0
    t_start = time.perf_counter()
    d, norm, force, stress, mat = scene_functions(path, Path(args.ops))
    ids = list(np.asarray(d["sim_id"]))
    rows, skipped = [], []
    for c in parse_cases(args.cases):
        if c not in ids:
            raise SystemExit(f"--cases: sim id {c} is not in {path}")
        zt, f = d["z"][ids.index(c)], d["f"][ids.index(c)]
        if not np.isfinite(zt).all():
            skipped.append(c)
            continue
        row = {"sim_id": int(c), "load": float(np.linalg.norm(f.sum(axis=1), axis=-1).max()),   # peak resultant
               **case_errors(zt, f, d["q0"], d["node_type"], float(d["dt"]), norm, force, stress, args.frame)}
        rows.append(row)
        print(f"case {c}: prior u {row['prior']['u']:.4f} σ {row['prior']['sigma']:.4f}; exact force u "
              f"{row['exact force']['u']:.4f} σ {row['exact force']['sigma']:.4f}", flush=True)
    if not rows:
        raise SystemExit("no finite case among --cases")
    loads = sorted({round(r["load"], 2) for r in rows})
    groups = {}
    for load in loads:
        sel = [r for r in rows if round(r["load"], 2) == load]
        groups[f"{load:g}"] = {
            "cases": len(sel),
            **{m: {**{k: float(np.nanmean([r[m][k] for r in sel])) for k in ("u", "v", "sigma")},
                   "nonfinite": int(sum(not np.isfinite(r[m]["u"]) for r in sel))} for m in MODES},
            "stress check": {k: float(np.mean([r["stress check"][k] for r in sel])) for k in sel[0]["stress check"]}}
    bulk_over_shear = (2.0 / mat["d1"]) / (2.0 * mat["c10"]) if mat.get("d1") and mat.get("c10") else None
    result = {"machine": describe(), "data": str(path), "skipped_nonfinite": skipped, "frame": args.frame,
              "bulk_over_shear": bulk_over_shear, "by_total_load": groups, "cases": rows,
              "wall_s": time.perf_counter() - t_start}
    lines = ["# The bunny's rest linearisation with the exact non-linear force: the ceiling of a force correction", "",
             f"Data `{path}`; {len(rows)} cases (non-finite left out: {skipped}); bulk / shear modulus "
             f"{bulk_over_shear:.0f}. Relative L2 error over each whole rollout, mean over cases, per peak resultant load.", "",
             "| peak load | cases | rollout | u | v | σ | non-finite rollouts (left out of the means) |",
             "|---|---|---|---|---|---|---|"]
    for load, g in groups.items():
        for m in MODES:
            lines.append(f"| {load} | {g['cases']} | {m} | {g[m]['u']:.4f} | {g[m]['v']:.4f} | {g[m]['sigma']:.4f} | {g[m]['nonfinite']} |")
    lines += ["", f"Stress consistency at frame {args.frame} (relative error against the data's σ, mean over cases):", "",
              "| peak load | σ(u_true) | S₀ u_true | S₀ u_prior | u_prior against u_true |", "|---|---|---|---|---|"]
    for load, g in groups.items():
        s = g["stress check"]
        lines.append(f"| {load} | {s['σ(u_true)']:.4f} | {s['S0 u_true']:.4f} | {s['S0 u_prior']:.4f} | {s['u_prior']:.4f} |")
    write_results("bunny_correction", result, "\n".join(lines) + "\n", RESULTS, echo=False)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
