"""`tignn fem-example`: the beam of the paper through the FEM, written for ParaView and as a plot."""
from __future__ import annotations

import argparse
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fem-example", help="run the paper's beam (one reference load case) through the FEM",
                       description="Run one reference load case of the 40x10x10 beam through the explicit FEM and "
                                   "write an XDMF time series (ParaView) and a plot of the response.")
    p.add_argument("--out", default="out/fem_example", help="output folder (default: %(default)s)")
    p.add_argument("--sim", type=int, default=1, help="reference load case 1..52 (default: %(default)s, tip load)")
    p.add_argument("--frames", type=int, default=20, help="output frames of 0.05 (default: %(default)s)")
    p.set_defaults(func=run)


def run(args) -> int:
    import jax
    import numpy as np

    from . import Loads, simulate, write_xdmf
    from .scenes import beam_reference_forces, beam_scene, setup_scene

    if not 1 <= args.sim <= 52:
        raise SystemExit(f"--sim must be in 1..52, got {args.sim}")
    if not 1 <= args.frames <= 20:
        raise SystemExit(f"--frames must be in 1..20, got {args.frames}")
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
    xdmf = write_xdmf(out / "beam.xdmf", scene.points, scene.cells, scene.cell_type, np.asarray(res.t),
                      np.asarray(res.q), np.asarray(res.v), np.asarray(res.sigma))
    png = _plot(out / "beam.png", scene, res, forces)
    u_tip = np.asarray(res.q[-1] - scene.points)[scene.points[:, 0] == scene.points[:, 0].max()].mean(0)
    print(f"tip displacement at t = {float(res.t[-1]):.2f}: {np.round(u_tip, 3).tolist()}")
    print(f"wrote {xdmf} (open in ParaView) and {png}")
    return 0


def _plot(path, scene, res, forces):
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
