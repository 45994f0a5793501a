"""``tignn evaluate``: rollout errors of a model per split of a data file, with a report and a box plot."""
from __future__ import annotations

import json
from pathlib import Path

from tignn_jax import DEFAULT_MODEL
from tignn_jax.cli import UsageError


def register(sub) -> None:
    p = sub.add_parser("evaluate", help="rollout errors of a model per split of a data file",
                       description="Roll a model out from each case's first state under the case's forces and "
                                   "report relative L2 errors of q, v, σ and u per split (mean and median over "
                                   "cases and snapshots), with the model class's structure diagnostics.")
    p.add_argument("--model", default=DEFAULT_MODEL,
                   help="shipped model name or model folder/file (default: %(default)s)")
    p.add_argument("--data", required=True, metavar="FILE", help="data file on the model's mesh")
    p.add_argument("--splits", default="train,val,test", help="comma-separated split names (default: %(default)s)")
    p.add_argument("--out", default=None, help="folder for report.json, report.md and boxplot.png")
    p.add_argument("--no-structure", action="store_true", help="skip the structure diagnostics")
    p.set_defaults(func=run)


def run(args) -> int:
    from tignn_jax import api
    from tignn_jax import evaluation as EV

    params, _ = api.load_pretrained(args.model)
    data = load_data(args.data)
    splits = [s for s in args.splits.split(",") if s]
    if not splits:
        raise UsageError(f"--splits {args.splits!r}: no split named (comma-separated names, e.g. train,val,test)")
    unknown = [s for s in splits if s not in data.splits]
    if unknown:
        raise UsageError(f"--splits: {unknown} not in the data file, which has {sorted(data.splits)}")
    if args.out and Path(args.out).exists() and not Path(args.out).is_dir():
        raise UsageError(f"--out {args.out}: a file, not a folder")
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


def load_data(path):
    """The data set at ``path``; UsageError naming it where it is missing or not a data file."""
    from tignn_jax import data as D

    if not Path(path).exists():
        raise UsageError(f"--data {path}: no such file")
    try:
        return D.load(path)
    except (KeyError, OSError, ValueError) as err:
        raise UsageError(f"--data {path}: not a data file ({err})") from None
