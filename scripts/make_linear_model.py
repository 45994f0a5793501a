"""Build a rest-linearised FEM model in the model format (`tignn_jax.framesolve.linear_model`): the FEM's rest
linearisation of a scene stepped by backward Euler, on the mesh and with the normalisation of an existing model
of that scene. Not a learned simulator: the fallback of ``api.fallback_stepper`` and a baseline.

    python scripts/make_linear_model.py --like beam-abaqus --scene beam --out tignn_jax/models/beam-linear

The damping (and the bunny's density) are the FEM data's of the model ``--like`` where it records them
(``info["fem_damping"]``, ``info["fem_density"]``), else the scene's. The rest linearisation takes about 40 s for the beam (one ``jax.jvp`` per degree of freedom).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--like", default="beam-abaqus", help="the model whose mesh and normalisation to use")
    ap.add_argument("--scene", default="beam", choices=("beam", "bunny"), help="the FEM scene to linearise")
    ap.add_argument("--out", required=True, help="model folder to write (model.npz)")
    args = ap.parse_args(argv)
    from fem import scenes
    from tignn_jax import api
    from tignn_jax import framesolve as FS

    like, _ = api.load_pretrained(args.like)
    recorded = like.get("info", {})
    if args.scene == "beam":
        scene = scenes.beam_scene()
    else:   # the density of the model's data where it records one
        scene = scenes.bunny_scene(**({"density": recorded["fem_density"]} if "fem_density" in recorded else {}))
    params, info = FS.linear_model(like, scene, recorded.get("fem_damping"))
    info["like"] = args.like
    path = api.save_model(params, Path(args.out) / "model.npz", info)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB): {json.dumps(info)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
