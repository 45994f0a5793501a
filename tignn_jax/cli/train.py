"""``tignn train``: train a model from a recipe file on a data file (resumable)."""
from __future__ import annotations

from pathlib import Path

from tignn_jax.cli import UsageError


def register(sub) -> None:
    p = sub.add_parser("train", help="train a model from a recipe in configs/ (resumable)",
                       description="Train a model of any class from a recipe file (configs/*.py, which defines "
                                   "CONFIG) on a data file made by `tignn generate` or the Abaqus reference data. "
                                   "Run the same command again to resume. The model is written to "
                                   "RUN_DIR/model/model.npz, which `tignn evaluate`, `tignn rollout`, "
                                   "`tignn demo` and tignn_jax.load_pretrained accept.")
    p.add_argument("--config", required=True, metavar="FILE", help="recipe file, e.g. configs/beam.py")
    p.add_argument("--data", required=True, nargs="+", metavar="FILE",
                   help="data file(s) on one mesh; several are concatenated")
    p.add_argument("--run-dir", required=True, help="folder for checkpoints, metrics.jsonl and model/model.npz")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args) -> int:
    from tignn_jax.train import load_recipe

    config, trainer = load_recipe(args.config)
    for path in args.data:
        if not Path(path).is_file():
            raise UsageError(f"--data {path}: no such file")
    trainer.run(args.data if len(args.data) > 1 else args.data[0], config, args.run_dir,
                progress=not args.no_progress)
    print(f"model: {Path(args.run_dir).resolve() / 'model' / 'model.npz'}")
    return 0
