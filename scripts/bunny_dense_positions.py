"""Print the bunny load positions of a dense training set, as the comma-separated node ids `--load-nodes` takes.

The data set `tignn generate bunny --seed 0 ...` places 100 positions by farthest-point sampling; cases 81–100
are its val and test positions. This lists every other free surface node whose distance to each of those 20
positions is at least ``--min-distance``. The default, 5.5, is the data set's own spacing: each held-out position's
nearest training position (cases 1–80) lies 5.54–6.11 away, so no position of the dense set is nearer to a held-out
one than the data set's training positions already were.

    python scripts/bunny_dense_positions.py > data/dense_nodes.txt
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from fem import cases, scenes
from fem.generate import held_out_rows


def dense_positions(min_distance: float = 5.5, n_cases: int = 100, seed: int = 0):
    """(node ids of the dense set, node ids of the held-out positions): free surface nodes at least
    ``min_distance`` from every held-out position (`fem.generate.held_out_rows`) of the seeded data set."""
    if not (np.isfinite(min_distance) and min_distance >= 0):
        raise ValueError(f"min_distance must be a finite number >= 0, got {min_distance}")
    scene = scenes.bunny_scene()
    surface, _ = cases.free_surface(scene)
    _, picked = cases.point_load_forces(scene, n_cases=n_cases, seed=seed)
    held = picked[held_out_rows(n_cases)]
    d = np.linalg.norm(scene.points[surface][:, None] - scene.points[held][None], axis=-1).min(axis=1)
    return surface[d >= min_distance], held


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--min-distance", type=float, default=5.5,
                        help="least distance to every held-out position (default: %(default)s)")
    parser.add_argument("--limit", type=int, default=None, help="only the first N positions (a smoke test)")
    args = parser.parse_args(argv)
    nodes, held = dense_positions(args.min_distance)
    nodes = nodes[: args.limit] if args.limit else nodes
    print(f"{len(nodes)} positions at least {args.min_distance} from the {len(held)} held-out ones", file=sys.stderr)
    print(",".join(map(str, nodes.tolist())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
