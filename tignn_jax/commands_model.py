"""``tignn train``, ``tignn rollout`` and ``tignn evaluate``: the learned simulator from the command line."""
from __future__ import annotations

import json
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser("train", help="train the GENERIC graph network on a data set (resumable)")
    p.add_argument("--data", required=True, help="data set .npz file or folder")
    p.add_argument("--split", default="train", help="training split name or sim ids (e.g. 3,4,5)")
    p.add_argument("--val", default="val", help="validation split name or sim ids ('' for none)")
    p.add_argument("--config", default="beam", help="named TrainConfig (tiny, beam, bunny)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a TrainConfig field, e.g. --set epochs=50 (repeatable)")
    p.add_argument("--run-dir", required=True, help="folder for checkpoints, metrics.jsonl and best/model.npz")
    p.add_argument("--time-limit", type=float, default=None, help="stop (with a checkpoint) after this many s")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--init-from", default=None, metavar="MODEL_OR_RUN",
                   help="warm start from a model.npz or a run folder's best model (same architecture)")
    p.set_defaults(func=_train)

    p = subparsers.add_parser("rollout", help="predict states of data-set cases from their first state and forces")
    p.add_argument("--model", default="beam-abaqus", help="shipped model name or model.npz path")
    p.add_argument("--data", required=True)
    p.add_argument("--sims", required=True, help="split name or 1-based sim ids, e.g. 9,10,12")
    p.add_argument("--out", required=True, help="output .npz with z [sims, frames+1, nodes, 12] and sim_id")
    p.set_defaults(func=_rollout)

    p = subparsers.add_parser("evaluate", help="rollout errors per split, structure diagnostics, box plot")
    p.add_argument("--model", default="beam-abaqus")
    p.add_argument("--data", required=True)
    p.add_argument("--splits", default="train,val,test", help="comma-separated split names")
    p.add_argument("--out", default=None, help="folder for report.json, report.md and boxplot.png")
    p.add_argument("--no-structure", action="store_true", help="skip degeneracy/entropy diagnostics")
    p.set_defaults(func=_evaluate)


def _train(args) -> int:
    from tignn_jax import data as D
    from tignn_jax import train as T

    if args.config not in T.CONFIGS:
        raise SystemExit(f"unknown --config {args.config!r}; choose from {sorted(T.CONFIGS)}")
    cfg = T.CONFIGS[args.config]
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in cfg._fields:
            raise SystemExit(f"--set {item!r}: unknown field; fields are {cfg._fields}")
        kind = float if getattr(cfg, key) is None else type(getattr(cfg, key))   # None: an optional level
        cfg = cfg._replace(**{key: value.lower() in ("1", "true", "yes") if kind is bool else kind(value)})
    data = D.load(args.data)
    frame_ops = None
    if cfg.frame_solve and not args.init_from:
        from tignn_jax import framesolve as FS
        frame_ops = FS.operators_cached(args.data, Path(args.run_dir) / "frame_ops.npz")
    T.train(data, cfg, args.run_dir, train_split=D.parse_split(args.split),
            val_split=D.parse_split(args.val) if args.val else None, time_limit_s=args.time_limit,
            progress=not args.no_progress, init_from=args.init_from, frame_ops=frame_ops)
    print(f"run folder: {Path(args.run_dir).resolve()}")
    return 0


def _rollout(args) -> int:
    import numpy as np

    from tignn_jax import api
    from tignn_jax import data as D
    from tignn_jax import evaluate as EV

    params, _ = api.load_pretrained(args.model)
    data = D.load(args.data)
    rows = D.split_rows(data, D.parse_split(args.sims))
    z = EV.rollout_cases(params, data, rows)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, z=z, sim_id=data.sim_id[rows])
    print(f"wrote {out} (z {z.shape})")
    return 0


def _evaluate(args) -> int:
    from tignn_jax import api
    from tignn_jax import data as D
    from tignn_jax import evaluate as EV

    params, _ = api.load_pretrained(args.model)
    data = D.load(args.data)
    splits = [s for s in args.splits.split(",") if s]
    report, raw = EV.evaluate(params, data, splits, structure=not args.no_structure)
    table = EV.format_table(report)
    print(table)
    if args.out:
        out = Path(args.out)
        EV.write_report(report, out / "report.json")
        (out / "report.md").write_text(table + "\n")
        if "train" in raw and "test" in raw:
            EV.box_plot(raw, out / "boxplot.png")
        print(f"wrote {out}")
    print(json.dumps({s: {v: report[s]["all"][v]["mean"] for v in EV.VARIABLES} for s in splits}))
    return 0
