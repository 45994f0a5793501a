"""Train and pack the learned linear GENERIC models (`tignn_jax.linear_generic`): the bunny and the beam.

    python scripts/linear_generic.py train --data data/bunny.npz --run runs/lg        # resumable
    python scripts/linear_generic.py pack --data data/bunny.npz --run runs/lg --out tignn_jax/models/bunny
    tignn evaluate --model tignn_jax/models/bunny --data data/bunny.npz --splits val,test

    python scripts/linear_generic.py train --scene beam --data data/beam_ref_d60.npz data/beam_int_smooth_d60.npz \
        --run runs/lg-beam --element-channels --cell-pressure --tied-pressure --measure peak ...
    python scripts/linear_generic.py pack --scene beam --data data/beam_ref_d60.npz data/beam_int_smooth_d60.npz \
        --run runs/lg-beam --out tignn_jax/models/beam

``train`` fits whole 20-frame rollouts of the training positions (``--batch`` of them per step, or all),
validating every ``--val-every`` steps; ``pack`` writes the best parameters as a model in the ``frame_solve``
format (its network zero: the learned part is the operators) with their training record and the FEM scene of
the data; a packed model is evaluated like any other (``tignn evaluate``, ``benchmarks/bunny_learned.py``).

The bunny's training split is the shipped bunny models': positions 1–80 less the nine (1, 8, 12, 21, 34, 50, 58,
61, 79) that `runs/r3.train_ids` left out, val 81–90, test 91–100. The beam's are the data files' own named
splits (the reference cases' published split and the fingertip cases' split), concatenated.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
LEFT_OUT = (1, 8, 12, 21, 34, 50, 58, 61, 79)
TRAIN_IDS = tuple(i for i in range(1, 81) if i not in LEFT_OUT)
VAL_IDS = tuple(range(81, 91))


def config_from(args):
    from tignn_jax.linear_generic import LinearConfig

    return LinearConfig(hidden=args.hidden, mu=args.mu, kappa=args.kappa, density=args.density, alpha=args.alpha,
                        tied_pressure=args.tied_pressure, element_channels=args.element_channels,
                        cell_pressure=args.cell_pressure, prior=args.prior)


def fem_prior(run: Path, scene: str, data_path, compute: bool):
    """The FEM's rest linearisation of the data's scene (its damping and density) for a model with a prior:
    computed once into ``run``/prior.npz (about 40 s for the beam), then read from there."""
    from fem import implicit, scenes

    path = run / "prior.npz"
    if path.exists():
        with np.load(path) as raw:
            return implicit.RestLinearization(*(raw[k] if raw[k].ndim else float(raw[k])
                                                for k in implicit.RestLinearization._fields))
    if not compute:
        raise FileNotFoundError(f"{path} is missing: the run was trained without --prior, or elsewhere")
    meta = metadata(data_path)
    density = meta["material"]["density"]
    sc = (scenes.beam_scene(density=density, damping=meta["damping"]) if scene == "beam"
          else scenes.bunny_scene(density=density)._replace(damping=meta["damping"]))
    lin = implicit.rest_linearization(scenes.setup_scene(sc), sc.material)
    np.savez(path, **lin._asdict())
    return lin


def metadata(path) -> dict:
    """The generation record of a data file (``tignn generate`` writes one). The Abaqus reference data carry
    none: for them, the FEM scene identified against them (`fem.scenes.beam_scene`'s defaults: density and
    mass damping fitted on the train cases, README's FEM-vs-Abaqus row)."""
    with np.load(path, allow_pickle=False) as raw:
        if "metadata" in raw.files:
            return json.loads(str(raw["metadata"]))
    from fem import scenes

    return {"material": {"density": scenes.BEAM_DENSITY}, "damping": scenes.BEAM_DAMPING,
            "command": "the Abaqus reference data (the FEM scene for the prior: the one identified against them)"}


def split_ids(scene: str, data):
    """(train rows, val rows, train ids, val ids) of the scene's split in the (concatenated) data set."""
    from tignn_jax import data as D

    if scene == "bunny":
        train, val = list(TRAIN_IDS), list(VAL_IDS)
    else:
        train, val = [int(x) for x in data.splits["train"]], [int(x) for x in data.splits["val"]]
    return D.split_rows(data, train), D.split_rows(data, val), train, val


def cmd_train(args) -> int:
    import jax
    jax.config.update("jax_enable_x64", args.float64)
    from tignn_jax import data as D
    from tignn_jax import linear_generic as LG

    data = D.concatenate(*(D.load(p) for p in args.data))    # the cases, for the split (train builds the geometry)
    rows_tr, rows_va, train_ids, val_ids = split_ids(args.scene, data)
    run = Path(args.run)
    run.mkdir(parents=True, exist_ok=True)
    config = config_from(args)
    (run / "config.json").write_text(json.dumps({"config": config._asdict(), "steps": args.steps, "lr": args.lr,
                                                 "seed": args.seed, "data": [str(x) for x in args.data],
                                                 "batch": args.batch, "float64": args.float64,
                                                 "scene": args.scene, "measure": args.measure,
                                                 "weights": args.weights,
                                                 "train_ids": train_ids, "val_ids": val_ids}, indent=1))
    t0 = time.perf_counter()
    prior = fem_prior(run, args.scene, args.data[0], True) if args.prior else None
    best = LG.train(args.data, rows_tr, rows_va, run, config, steps=args.steps, lr=args.lr, seed=args.seed,
                    val_every=args.val_every, batch=args.batch, measure=args.measure, prior=prior,
                    weights=args.weights)
    print(json.dumps({"best": best, "seconds_this_run": round(time.perf_counter() - t0, 1)}))
    return 0


def cmd_pack(args) -> int:
    import jax
    jax.config.update("jax_enable_x64", True)
    from flax import serialization

    from tignn_jax import api
    from tignn_jax import framesolve as FS
    from tignn_jax import linear_generic as LG

    run = Path(args.run)
    saved = json.loads((run / "config.json").read_text())
    config = LG.LinearConfig(**saved["config"])
    data, geo = LG.geometry_from_file(args.data)
    if config.prior:
        geo = LG.with_prior(geo, fem_prior(run, args.scene, args.data[0], False))
    params = serialization.from_bytes(LG.init(config, geo), (run / "best.msgpack").read_bytes())
    lin = LG.to_rest_linearization(params, geo, config)
    like, _ = api.load_pretrained(args.like or {"bunny": "bunny-linear", "beam": "beam-linear"}[args.scene])
    model = FS.model_from_operators(like, lin, float(data.dt))
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    best = min(records, key=lambda r: r["val_loss"])
    metas = []
    for path in args.data:
        metas.append(metadata(path))
    meta = metas[0]   # the FEM scene of the first file (the stress tests rebuild it)
    commands = [f"{m.get('command', 'tignn generate')} ({path}" + (f", seed {m['seed']})" if "seed" in m else ")")
                for m, path in zip(metas, args.data)]
    info = {"kind": "learned linear GENERIC operators (tignn_jax.linear_generic), backward Euler",
            "scene": args.scene, "learned": {"density": best["density"], "alpha": best["alpha"]},
            # the FEM scene the training data came from (the stress tests rebuild it from these)
            "fem_density": meta["material"]["density"], "fem_damping": meta["damping"],
            **({"fem_load_radius": meta["load_radius"]} if meta.get("load_radius") is not None else {}),
            "fem_integrator": "implicit" if str(meta.get("integrator", "")).startswith("implicit") else "explicit",
            "data": "; ".join(commands),
            "training": {**{k: saved.get(k) for k in ("steps", "lr", "seed", "train_ids", "val_ids", "measure",
                                                      "weights")},
                         "config": saved["config"], "best_step": best["step"], "val": best["val"]},
            "velocity": like.get("info", {}).get("velocity", "solver")}
    path = api.save_model(model, Path(args.out) / "model.npz", info)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB); K blocks {len(lin.k_rows)}, S blocks {len(lin.s_rows)}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    tr = sub.add_parser("train", help="fit the operators to the training positions' rollouts (resumable)")
    tr.add_argument("--data", required=True, nargs="+",
                    help="the data set, or several on the same mesh (tignn generate bunny|beam-... ; README)")
    tr.add_argument("--scene", choices=("bunny", "beam"), default="bunny", help="which split (module docstring)")
    tr.add_argument("--measure", choices=("snapshot", "peak"), default="snapshot",
                    help="relative errors over each snapshot's norm or each case's peak (linear_generic.relative_errors)")
    tr.add_argument("--run", required=True, help="run folder (metrics.jsonl, ckpt.msgpack, best.msgpack)")
    tr.add_argument("--steps", type=int, default=300)
    tr.add_argument("--lr", type=float, default=3e-3)
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--val-every", type=int, default=10)
    tr.add_argument("--batch", type=int, default=None, help="training cases per step (default: all)")
    tr.add_argument("--float64", action="store_true", help="train in float64 (about 2x slower)")
    tr.add_argument("--hidden", type=int, default=32, help="width of the coefficient networks")
    tr.add_argument("--mu", type=float, default=1.0, help="initial shear modulus scale (learned)")
    tr.add_argument("--kappa", type=float, default=10.0, help="initial bulk modulus scale (learned)")
    tr.add_argument("--density", type=float, default=1e-3, help="initial density scale (learned)")
    tr.add_argument("--alpha", type=float, default=1.0, help="initial mass damping scale (learned)")
    tr.add_argument("--element-channels", action="store_true", help="cells' own shear strains too (LinearConfig)")
    tr.add_argument("--tied-pressure", action="store_true", help="the stress's pressure is the energy's (LinearConfig)")
    tr.add_argument("--cell-pressure", action="store_true", help="cells' own volume changes too (LinearConfig)")
    tr.add_argument("--weights", type=lambda t: tuple(float(x) for x in t.split(",")), default=(1.0, 1.0, 1.0),
                    help="weights of the u, v and σ errors in the loss, e.g. 1,0.25,1 (default 1,1,1)")
    tr.add_argument("--prior", action="store_true",
                    help="start from the FEM's rest linearisation of the data's scene and learn a correction (LinearConfig)")
    pk = sub.add_parser("pack", help="write the best parameters as a model folder")
    pk.add_argument("--data", required=True, nargs="+", help="the data files it was trained on (mesh, cells, provenance)")
    pk.add_argument("--scene", choices=("bunny", "beam"), default="bunny")
    pk.add_argument("--run", required=True)
    pk.add_argument("--like", default=None,
                    help="the model whose mesh and normalisation to use (default: bunny-linear or beam-linear)")
    pk.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    return {"train": cmd_train, "pack": cmd_pack}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
