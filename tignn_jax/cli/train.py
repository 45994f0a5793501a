"""``tignn train``: train a model from a recipe (a file in ``configs/`` or a named one) on a data file
(resumable), and write its model card."""
from __future__ import annotations

import zipfile
from pathlib import Path

from tignn_jax.cli import UsageError


def register(sub) -> None:
    p = sub.add_parser("train", help="train a model from a recipe (resumable), with a generated model card",
                       description="Train a model on a data file made by `tignn generate` (or the Abaqus reference "
                                   "data), from a recipe file (configs/*.py, which defines CONFIG) or a named recipe "
                                   "whose scales come from the data: linear, corotational, embedded or tignn. Run the "
                                   "same command again to resume. The model is written to RUN_DIR/model/model.npz "
                                   "with its MODEL_CARD.md; `tignn evaluate`, `tignn rollout`, `tignn demo`, "
                                   "`tignn view` and tignn_jax.load_pretrained accept RUN_DIR.")
    p.add_argument("--config", required=True, metavar="RECIPE",
                   help="linear, corotational, embedded or tignn (tignn_jax.train.defaults), or a recipe file, e.g. "
                        "configs/beam.py")
    p.add_argument("--data", required=True, nargs="+", metavar="FILE",
                   help="data file(s) on one mesh; several are concatenated")
    p.add_argument("--run-dir", required=True, help="folder for checkpoints, metrics and model/ (model.npz, "
                                                    "MODEL_CARD.md)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change a field of the recipe, e.g. steps=20 or model.hidden=16 (repeatable)")
    p.add_argument("--no-card", action="store_true", help="do not evaluate the model and write its card")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args) -> int:
    from tignn_jax.train import defaults, load_recipe

    named = args.config in defaults.NAMES
    if not named and not Path(args.config).is_file():
        raise UsageError(f"--config {args.config!r}: no recipe file by that name, "
                         f"nor one of {', '.join(defaults.NAMES)}")
    for path in args.data:
        if not Path(path).exists():
            raise UsageError(f"--data {path}: no such file")
        if Path(path).is_file() and not zipfile.is_zipfile(path):
            raise UsageError(f"--data {path}: not a data file (.npz)")
    if named:
        config, trainer = defaults.default_recipe(args.config, args.data[0])
    else:
        try:
            config, trainer = load_recipe(args.config)
        except ValueError as e:
            raise UsageError(f"--config {args.config}: {e}")
    try:
        config = defaults.override(config, args.set)
        if args.set and hasattr(config, "check"):
            config.check()
    except ValueError as e:
        message = str(e)
        raise UsageError(message if message.startswith("--set") else f"--set {' '.join(args.set)}: {message}")
    data = args.data if len(args.data) > 1 else args.data[0]
    params = trainer.run(data, config, args.run_dir, progress=not args.no_progress)
    model = Path(args.run_dir).resolve() / "model" / "model.npz"
    print(f"model: {model}")
    if not args.no_card and params is not None:
        from tignn_jax.model_card import write_model_card

        recipe = f"`tignn train --config {args.config}" + "".join(f" --set {s}" for s in args.set) + "`"
        card = write_model_card(params, args.data, args.run_dir, recipe)
        print(f"card: {card}")
    return 0
