"""``tignn fem-example``: one reference load case of the paper's beam through the explicit FEM, for ParaView.

Writes ``beam.pvd`` (a PVD collection of one VTU file per output frame, ``beam_frames/frame_XXXX.vtu``, with the
displacement u, velocity v, Cauchy stress σ and its von Mises value as point data; `fem.mesh.write_series`) and
``beam.png`` (the mean tip displacement and the energy balance over time).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from tignn_jax.cli import UsageError

CASES = 52        # the reference load cases (13 positions × 4 faces)
MAX_FRAMES = 20   # the reference data's frames


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``fem-example`` subcommand to ``sub`` (the ``tignn`` parser's subparsers)."""
    p = sub.add_parser("fem-example", help="run the paper's beam (one reference load case) through the FEM",
                       description="Run one reference load case of the 40x10x10 beam through the explicit FEM and "
                                   "write a ParaView time series (a PVD collection of VTU files, one per frame) "
                                   "and a plot of the tip displacement and the energies.")
    p.add_argument("--out", default="out/fem_example", help="output folder (default: %(default)s)")
    p.add_argument("--sim", type=int, default=1,
                   help=f"reference load case 1..{CASES} (default: %(default)s, a tip load)")
    p.add_argument("--frames", type=int, default=MAX_FRAMES,
                   help=f"output frames of 0.05 time units each, 1..{MAX_FRAMES} (default: %(default)s)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Simulate the load case and write the series and the plot.

    Args:
      args: the parsed ``--out``, ``--sim`` and ``--frames``.

    Returns:
      0.

    Raises:
      UsageError: ``--sim`` or ``--frames`` out of range.
    """
    if not 1 <= args.sim <= CASES:
        raise UsageError(f"--sim must be in 1..{CASES}, got {args.sim}")
    if not 1 <= args.frames <= MAX_FRAMES:
        raise UsageError(f"--frames must be in 1..{MAX_FRAMES}, got {args.frames}")

    import jax
    import numpy as np

    from fem import Loads, simulate, write_series
    from fem.scenes import beam_reference_forces, beam_scene, setup_scene

    scene = beam_scene()._replace(n_frames=args.frames)
    problem = setup_scene(scene)
    forces = beam_reference_forces(scene, [args.sim])[0]
    print(f"beam: {len(scene.points)} nodes, {len(scene.cells)} hex8, load case {args.sim}, "
          f"{problem.config.n_frames} frames x {problem.config.n_sub} sub-steps")
    t0 = time.perf_counter()
    res = simulate(problem, scene.material, Loads(nodal=forces))
    jax.block_until_ready(res.q)
    print(f"simulated in {time.perf_counter() - t0:.1f} s (including compilation)")
    out = Path(args.out)
    pvd = write_series(out / "beam.pvd", scene.points, scene.cells, scene.cell_type, np.asarray(res.t),
                       np.asarray(res.q), np.asarray(res.v), np.asarray(res.sigma))
    png = _plot(out / "beam.png", scene, res)
    u_tip = np.asarray(res.q[-1] - scene.points)[scene.points[:, 0] == scene.points[:, 0].max()].mean(0)
    print(f"tip displacement at t = {float(res.t[-1]):.2f}: {np.round(u_tip, 3).tolist()}")
    print(f"wrote {pvd} (open in ParaView) and {png}")
    return 0


def _plot(path, scene, res):
    """The mean tip displacement and the energies (with the balance residual) over time, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    t = np.asarray(res.t)
    tip = scene.points[:, 0] == scene.points[:, 0].max()
    u = np.asarray(res.q)[:, tip].mean(1) - scene.points[tip].mean(0)
    e = res.energies
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for i, name in enumerate("xyz"):
        ax[0].plot(t, u[:, i], label=f"u_{name}")
    ax[0].set(xlabel="t", ylabel="mean tip displacement", title="beam tip")
    ax[0].legend()
    for name in ("kinetic", "strain", "viscous", "external"):
        ax[1].plot(t, np.asarray(getattr(e, name)), label=name)
    balance = np.asarray(e.kinetic + e.strain + e.viscous + e.damping - e.external)
    ax[1].plot(t, balance, "k--", label="balance residual")
    ax[1].set(xlabel="t", ylabel="energy", title="energies")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
