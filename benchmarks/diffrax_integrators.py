"""Does diffrax integrate a learned GENERIC rate better than our own loop? The paper's network, both ways.

The paper's model (`tignn_jax.simulators.GenericGNN`) is a learned rate dz/dt = L∇E + M∇S stepped by forward Euler
at the data's frame step Δt, the force held over the frame; `tignn_jax.rollout` runs T frames as one ``lax.scan``
of that step. The same trajectory through diffrax: ``diffeqsolve(ODETerm(rate), Euler(), dt0=Δt, saveat=every
frame)`` with the rate reading the frame's force at ``t``. Both are jitted; each call rolls T frames from rest
under a tip load on a beam-sized grid (21 × 6 × 6 = 756 nodes, as the paper's beam) with the paper's network
(width 64, 2 layers per MLP, 3 message passes; weights at their initialisation: the cost does not depend on them).
Reported: the largest difference of the two trajectories, relative to the states' scale, and the milliseconds per
frame (median of ``--repeats`` interleaved calls after compilation, `_machine.interleaved_ms`), with their ratio.
diffrax's adaptive and higher-order solvers are not compared: the network was trained as a forward-Euler map at Δt,
so another solver would integrate a different model.

Writes diffrax.{json,md} to ``--out`` (default benchmarks/results). Needs the ``bench`` extra (diffrax).

    python benchmarks/diffrax_integrators.py [--frames 20] [--repeats 30]
    python benchmarks/diffrax_integrators.py --quick --out /tmp/diffrax    # smoke run: small grid, 5 frames
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import RESULTS_DIR, describe, machine_line, interleaved_ms, write_results  # noqa: E402


def model_on_grid(nx: int, ny: int, nz: int, hidden: int, passes: int):
    """(params, rest graph, data) of an initialised network on an nx × ny × nz grid beam (`data.synthetic_beam`,
    whose statistics scale the network's inputs and outputs)."""
    import jax

    import tignn_jax
    from tignn_jax import data as D
    from tignn_jax.simulators import GenericGNN, GNNConfig

    data = D.synthetic_beam(nx=nx, ny=ny, nz=nz, cases=2, frames=4, seed=0)
    rows = np.arange(len(data.z))
    norm = D.normalization(data, rows)
    mesh = {"q0": np.asarray(data.q0, np.float32), "senders": data.edges[0], "receivers": data.edges[1],
            "node_type": data.node_type}
    model = GenericGNN(GNNConfig(hidden=hidden, mlp_layers=2, passes=passes))
    stored = model.init(jax.random.PRNGKey(0), norm, mesh)
    envelope = {"z_mean": norm["z_mean"], "z_std": norm["z_std"], "z_dev_max": 10 * norm["z_std"],
                "u_max": np.ones(1, np.float32), "f_max": np.full(1, 1e9, np.float32)}
    params = tignn_jax.make_params(model, stored, mesh, envelope, {})
    return params, tignn_jax.rest_graph(params), data


def run(frames: int, repeats: int, grid=(21, 6, 6), hidden: int = 64, passes: int = 3) -> dict:
    import diffrax
    import jax
    import jax.numpy as jnp

    import tignn_jax
    from tignn_jax.simulators.generic_gnn import generic_rate, state_scale

    params, graph, data = model_on_grid(*grid, hidden, passes)
    model, arrays = params["model"], params["arrays"]
    dt = float(data.dt)
    q0 = np.asarray(params["mesh"]["q0"])
    forces = np.zeros((frames, len(q0), 3), np.float32)
    tip = np.where(q0[:, 0] == q0[:, 0].max())[0]
    forces[:, tip, 1] = -float(np.asarray(data.f).std()) * np.minimum(1.0, (np.arange(frames) + 1) / 10)[:, None]
    z0, f_seq = graph.nodes["z"], jnp.asarray(forces)
    scale = state_scale(arrays["norm"])

    @jax.jit
    def ours(z, f):      # the frame map `tignn_jax.rollout` scans
        def frame(zk, fk):
            zn = model.step_state(arrays, zk, fk)
            return zn, zn
        return jnp.concatenate([z[None], jax.lax.scan(frame, z, f)[1]])

    def rate(t, z, f_all):
        k = jnp.clip(jnp.floor(t / dt + 1e-3).astype(jnp.int32), 0, frames - 1)   # Euler evaluates at frame k's t
        dw, _, _, _ = generic_rate(model.config, arrays, z, f_all[k])
        return dw * scale / dt

    ts = dt * jnp.arange(frames + 1)

    @jax.jit
    def theirs(z, f):
        sol = diffrax.diffeqsolve(diffrax.ODETerm(rate), diffrax.Euler(), t0=0.0, t1=frames * dt, dt0=dt, y0=z,
                                  args=f, saveat=diffrax.SaveAt(ts=ts), max_steps=frames + 1)
        return sol.ys

    a, b = np.asarray(ours(z0, f_seq)), np.asarray(theirs(z0, f_seq))
    span = float(np.abs(a - a[:1]).max()) or 1.0
    diff = float(np.abs(a - b).max()) / span
    times = interleaved_ms({"ours: lax.scan of the frame map": lambda: ours(z0, f_seq),
                            "diffrax Euler": lambda: theirs(z0, f_seq)}, repeats)
    per_frame = {k: float(np.median(v)) / frames for k, v in times.items()}
    p90 = {k: float(np.percentile(v, 90)) / frames for k, v in times.items()}
    return {"nodes": int(len(q0)), "frames": frames, "repeats": repeats, "network": {"hidden": hidden,
            "mlp_layers": 2, "passes": passes}, "max_difference_relative": diff, "ms_per_frame_p50": per_frame,
            "ms_per_frame_p90": p90,
            "ratio_diffrax_to_ours": per_frame["diffrax Euler"] / per_frame["ours: lax.scan of the frame map"],
            "diffrax": diffrax.__version__}


def report(result: dict) -> str:
    r = result
    lines = ["# A learned GENERIC rate: our rollout against diffrax", "",
             f"The paper's network (width {r['network']['hidden']}, message passes: {r['network']['passes']}) on a "
             f"{r['nodes']}-node grid beam, {r['frames']} frames of forward Euler at the frame step, from rest under "
             f"a ramped tip load; diffrax {r['diffrax']}.", "",
             "| integrator | ms per frame p50 | p90 |", "|---|---|---|"]
    for k, v in r["ms_per_frame_p50"].items():
        lines.append(f"| {k} | {v:.2f} | {r['ms_per_frame_p90'][k]:.2f} |")
    lines += ["", f"diffrax / ours: {r['ratio_diffrax_to_ours']:.2f}. Largest difference of the trajectories: "
              f"{r['max_difference_relative']:.1e} of their range (float32).", ""]
    if r.get("quick"):
        lines += ["QUICK RUN (smoke test settings): not a measurement.", ""]
    m = r["machine"]
    lines += [machine_line(m) + ", load average "
              f"{m['load_average_1m']} at the start."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=20, help="frames per rollout (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=30, help="timed calls per integrator (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="smoke run: a 5 × 2 × 2 grid, width 8, 5 frames, 3 repeats")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="folder of diffrax.{json,md} (default %(default)s)")
    args = ap.parse_args(argv)
    if args.frames < 1 or args.repeats < 1:
        raise SystemExit(f"--frames and --repeats must be positive, got {args.frames} and {args.repeats}")
    try:
        import diffrax  # noqa: F401
    except ImportError:
        raise SystemExit("diffrax is not installed: pip install -e '.[bench]'") from None
    machine = describe()
    if args.quick:
        result = run(5, 3, grid=(5, 2, 2), hidden=8, passes=1)
    else:
        result = run(args.frames, args.repeats)
    result.update(machine=machine, quick=args.quick)
    write_results("diffrax", result, report(result), Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
