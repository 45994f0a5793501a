"""Two beams in contact: the corotational model's implicit contact against the FEM's, at loads past the training.

Scene: the FEM's two beams (`fem.scenes.two_beams_scene`): B turned 90° over A's free half, 10 above it, B's
reference load line at its free end (test case 14: x = 40, top face, downwards) ramped over 20 frames to 1×, 2×
and 3× the reference maximum, then held; B bends onto A, which bends under it. Contact: the FEM's
(`fem.scenes.TWO_BEAMS_CONTACT`: penalty springs between surface nodes closer than r0 = 2, k = 2.5e5).

Reference: the explicit FEM (`fem.simulate_batch`, every wave resolved, the contact in every sub-step), the three
loads as one batch; it takes long (tens of minutes on one core), so it is kept in ``--cache`` and reused.
Models, both beams the shipped ``beam-corot``, same radius and stiffness:

* contact in the implicit step: `tignn_jax.contact_stepper` (both beams in one backward-Euler solve, the penalty's
  energy in it);
* contact explicit between frames: ``tignn_jax.stepper(params, 2)`` with `tignn_jax.mr.forcing.contact_forces` at
  each frame's start as external forces (how the demo coupled its beams before);
* the learned linear ``beam`` the same way (the demo's beams before the corotational model).

Per model and load: the mean over frames of the L2 errors of u and σ (both beams, world axes) relative to the
case's peak of the FEM's norm; the lower beam A's deflection at its free end at the last frame; each beam's
largest volume change and largest length difference from the FEM's (centre line); the closest approach of the two
surfaces (the FEM's too); frames whose whole energy (both beams' and the contact's over all surface pairs) rose by
more than the load's work. Then every frame's time (p50, p99, max) of each model, and the ratio of the p50s to the
same model with the contact between the frames, measured in the same run.

    python benchmarks/contact_beams.py                 # writes contact_beams.{json,md}
    python benchmarks/contact_beams.py --quick --out /tmp/cb   # smoke run: 4 frames, 1× only, no cache
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _machine import RESULTS_DIR, describe, machine_line, write_results  # noqa: E402

CASE = 14
LOADS = (("1x hold", 1.0), ("2x hold", 2.0), ("3x hold", 3.0))
RAMP = 20
# B in the FEM's world: x = 36 − y_B, y = x_B − 25, z = z_B + 20
POSE_B = np.array([[0.0, -1.0, 0.0, 36.0], [1.0, 0.0, 0.0, -25.0], [0.0, 0.0, 1.0, 20.0], [0.0, 0.0, 0.0, 1.0]])
DEFAULT_CACHE = Path(__file__).resolve().parents[1] / "data" / "contact_beams_fem.npz"


def loads(frames: int, scales) -> np.ndarray:
    """[cases, frames, 1512, 3]: B's load (nodes 756..1511, world axes) of each scale, ramped then held."""
    from fem import scenes

    beam = scenes.beam_scene()
    one = scenes.beam_reference_forces(beam, [CASE], after=frames - RAMP, mode="hold")[0]
    n = len(beam.points)
    out = np.zeros((len(scales), frames, 2 * n, 3), np.float32)
    for c, s in enumerate(scales):
        out[c, :, n:] = s * one       # B's load points down (−z), the same in B's frame and the world's
    return out


def reference(forces, cache: Path | None):
    """The explicit FEM's (q [C, T, N, 3], σ [C, T, N, 6]) for forces [C, T, N, 3], from ``cache`` when it holds
    these forces."""
    import jax.numpy as jnp

    from fem import scenes
    from fem import solver as sv

    if cache is not None and cache.exists():
        kept = np.load(cache)
        if kept["forces"].shape == forces.shape and np.array_equal(kept["forces"], forces):
            return kept["q"], kept["sigma"]
    scene = scenes.two_beams_scene()
    problem = scenes.setup_scene(scene._replace(n_frames=forces.shape[1]), contact=scenes.two_beams_contact(scene))
    res = sv.simulate_batch(problem, scene.material, sv.Loads(nodal=jnp.asarray(forces)))
    q, sigma = np.asarray(res.q)[:, 1:], np.asarray(res.sigma)[:, 1:]
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, forces=forces, q=q, sigma=sigma)
    return q, sigma


def models() -> dict:
    """{name: (coupling, params)}: "implicit" through `tignn_jax.contact_stepper`, "explicit" through the
    stepper of two bodies with the contact's forces at the frame's start."""
    import tignn_jax

    corot, _ = tignn_jax.load_pretrained("beam-corot")
    learned, _ = tignn_jax.load_pretrained("beam")
    return {"beam-corot, contact in the implicit step": ("implicit", corot),
            "beam-corot, contact explicit between frames": ("explicit", corot),
            "beam (learned linear), contact explicit between frames": ("explicit", learned)}


def surface(params) -> np.ndarray:
    from tignn_jax.mr.surface import surface_nodes, surface_triangles

    q0 = np.asarray(params["mesh"]["q0"])
    cells = params["arrays"].get("cells") if "cells" in params["arrays"] else None
    if cells is None:
        from fem.meshes import beam_mesh

        cells = beam_mesh()[1]
    return surface_nodes(surface_triangles(np.asarray(cells), q0))


def stepper(coupling: str, params, r0: float, k: float):
    """``fn((z_a, z_b), (f_a, f_b)) -> (z_a, z_b)`` in the beams' model frames."""
    import jax
    import jax.numpy as jnp

    import tignn_jax
    from tignn_jax.mr.forcing import contact_forces

    if coupling == "implicit":
        return tignn_jax.contact_stepper(params, [np.eye(4), POSE_B], r0, k)
    step = tignn_jax.stepper(params, 2)
    s = jnp.asarray(surface(params))
    rot, shift = jnp.asarray(POSE_B[:3, :3], jnp.float32), jnp.asarray(POSE_B[:3, 3], jnp.float32)

    @jax.jit
    def fn(zs, fs):
        fa, fb = contact_forces(zs[0][s, :3], zs[1][s, :3] @ rot.T + shift, r0, k, capacity=256)
        f = jnp.concatenate([fs[0].at[s].add(fa), fs[1].at[s].add(fb @ rot)])
        z = step(jnp.concatenate(zs), f)
        return z[:len(zs[0])], z[len(zs[0]):]

    return fn


def rotate_voigt(sigma, rot):
    """σ [..., 6] (S11 S22 S33 S12 S13 S23) in a body's axes → the world's, R σ Rᵀ."""
    i, j = (0, 1, 2, 0, 0, 1), (0, 1, 2, 1, 2, 2)
    full = np.zeros(sigma.shape[:-1] + (3, 3))
    for c, (a, b) in enumerate(zip(i, j)):
        full[..., a, b] = full[..., b, a] = sigma[..., c]
    full = rot @ full @ rot.T
    return np.stack([full[..., a, b] for a, b in zip(i, j)], axis=-1)


def run_model(coupling: str, params, forces, r0: float, k: float):
    """(world states [T, 1512, 12] (q, v, σ), energy-creating frames, whether all are finite, the milliseconds of
    each frame after the first) over forces [T, 1512, 3] (world axes) from rest."""
    import jax
    import jax.numpy as jnp

    fn = stepper(coupling, params, r0, k)
    model, arrays = params["model"], params["arrays"]
    energy = jax.jit(lambda z: model.diagnostics(arrays, z, jnp.zeros_like(z[:, :3]), z)["energy"])
    q0 = np.asarray(params["mesh"]["q0"], np.float32)
    n, rot, s = len(q0), POSE_B[:3, :3], surface(params)
    z0 = jnp.asarray(np.concatenate([q0, np.zeros((n, 9), np.float32)], axis=1))
    zs, e, created, out, ms = (z0, z0), 0.0, 0, [], []
    for f in forces:
        fs = (jnp.asarray(f[:n]), jnp.asarray(f[n:] @ rot))
        t = time.perf_counter()
        nxt = jax.block_until_ready(fn(zs, fs))
        ms.append(1e3 * (time.perf_counter() - t))
        world = world_states(nxt)
        work = float(jnp.sum(fs[1] * (nxt[1][:, :3] - zs[1][:, :3])))
        d = np.linalg.norm(world[:n][s, None, :3] - world[n:][None, s, :3], axis=-1)
        e_next = sum(float(energy(z)) for z in nxt) + 0.5 * k * float(np.sum(np.maximum(r0 - d, 0.0) ** 2))
        if np.isfinite(e_next):
            created += int(e_next - e > work + 1e-4 * max(abs(e), abs(e_next), abs(work)) + 1e-2)
        zs, e = nxt, e_next
        out.append(world)
    out = np.array(out)
    return out, created, bool(np.all(np.isfinite(out))), ms[1:]     # the first call compiles


def world_states(zs) -> np.ndarray:
    """[1512, 12] in the world: A as it is, B's positions, velocities and stresses turned by its pose."""
    rot, shift = POSE_B[:3, :3], POSE_B[:3, 3]
    a, b = (np.asarray(z, np.float64) for z in zs)
    b = np.concatenate([b[:, :3] @ rot.T + shift, b[:, 3:6] @ rot.T, rotate_voigt(b[:, 6:], rot)], axis=1)
    return np.concatenate([a, b])


def metrics(states, q_ref, s_ref, q_rest, cells, line, s) -> dict:
    """Errors, volume, length, A's deflection and the closest approach of the beams (docstring)."""
    from fem.meshes import cell_volumes
    from large_deformation import length

    n = len(q_rest) // 2
    u, u_ref = states[..., :3] - q_rest, q_ref - q_rest
    out = {"u_error": float(np.linalg.norm(u - u_ref, axis=(1, 2)).mean() / np.linalg.norm(u_ref, axis=(1, 2)).max()),
           "sigma_error": float(np.linalg.norm(states[..., 6:] - s_ref, axis=(1, 2)).mean()
                                / np.linalg.norm(s_ref, axis=(1, 2)).max())}
    for name, nodes in (("a", slice(0, n)), ("b", slice(n, 2 * n))):
        q0 = q_rest[nodes]
        vol0 = cell_volumes(q0, cells).sum()
        vol = lambda qs: np.array([cell_volumes(q, cells).sum() for q in qs]) / vol0 - 1.0  # noqa: E731
        out[f"volume_change_max_{name}"] = float(np.abs(vol(states[:, nodes, :3])).max())
        out[f"fem_volume_change_max_{name}"] = float(np.abs(vol(q_ref[:, nodes])).max())
        out[f"length_difference_max_{name}"] = float(np.abs(length(states[:, nodes, :3], line)
                                                            - length(q_ref[:, nodes], line)).max() / length(q0, line))
    out["a_deflection"] = float(-u[-1, line[-1], 2].mean())
    out["fem_a_deflection"] = float(-u_ref[-1, line[-1], 2].mean())
    gap = lambda q: min(float(np.linalg.norm(x[:n][s, None] - x[n:][None, s], axis=-1).min()) for x in q)  # noqa
    out["closest"], out["fem_closest"] = gap(states[..., :3]), gap(q_ref)
    return out


def report(result) -> str:
    m = result["machine"]
    lines = ["# Two beams in contact: the models against the explicit FEM", "",
             f"B's reference load at its free end (case {CASE}) ramped over {RAMP} frames, then held, "
             f"{result['frames']} frames; the FEM's contact (r0 = {result['r0']}, k = {result['k']:g}) in every model. "
             "u and σ errors (both beams, world axes) relative to each case's peak; volume and length changes as "
             "fractions; A's deflection at its free end at the last frame; the closest approach of the surfaces"
             + (" — QUICK smoke run" if result["quick"] else "") + ".", "",
             "| model | load | u error | σ error | max volume change A, B (FEM) | max length difference A, B "
             "| A's deflection (FEM) | closest approach (FEM) | energy-creating frames |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        if not r["finite"]:
            lines.append(f"| {r['model']} | {r['load']} | non-finite | | | | | | {r['energy_creating_frames']} |")
            continue
        lines.append(
            f"| {r['model']} | {r['load']} | {r['u_error']:.4f} | {r['sigma_error']:.4f} | "
            f"{100 * r['volume_change_max_a']:.2f} %, {100 * r['volume_change_max_b']:.2f} % "
            f"({100 * r['fem_volume_change_max_a']:.3f} %, {100 * r['fem_volume_change_max_b']:.3f} %) | "
            f"{100 * r['length_difference_max_a']:.2f} %, {100 * r['length_difference_max_b']:.2f} % | "
            f"{r['a_deflection']:.2f} ({r['fem_a_deflection']:.2f}) | {r['closest']:.2f} ({r['fem_closest']:.2f}) | "
            f"{r['energy_creating_frames']} |")
    t = result["frame_ms"]
    lines += ["", "Every frame of the cases above timed alone (a call to a ready result, the energy check between "
              "frames; each case's first call, which compiles, left out; not pinned): the contact's cost against the "
              "same model with the contact between the frames, measured in the same run.", "",
              "| model | frames | p50 ms | p99 ms | max ms | p99 / p50 | p50 ratio to contact between frames |",
              "|---|---|---|---|---|---|---|"]
    base = t["beam-corot, contact explicit between frames"]["p50"]
    for name, v in t.items():
        lines.append(f"| {name} | {v['frames']} | {v['p50']:.2f} | {v['p99']:.2f} | {v['max']:.2f} | "
                     f"{v['p99'] / v['p50']:.2f} | {v['p50'] / base:.2f} |")
    lines += ["", machine_line(m) + f", load average {m['load_average_1m']} at the start. FEM reference: "
              f"{result['reference']}."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=30, help=f"frames per case, > {RAMP} (default %(default)s)")
    ap.add_argument("--cache", default=str(DEFAULT_CACHE),
                    help="the FEM reference's file, computed when missing (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 4 frames, 1x only, no cache")
    ap.add_argument("--out", default=str(RESULTS_DIR), help="folder of contact_beams.{json,md} (default %(default)s)")
    args = ap.parse_args(argv)
    frames = 4 if args.quick else args.frames
    if frames <= RAMP and not args.quick:
        raise SystemExit(f"--frames must be above {RAMP}, got {frames}")
    from fem import scenes
    from large_deformation import centre_line

    machine = describe()
    cases = LOADS[:1] if args.quick else LOADS
    forces = loads(frames if not args.quick else RAMP, [s for _, s in cases])[:, :frames]
    t = time.perf_counter()
    q_ref, s_ref = reference(forces, None if args.quick else Path(args.cache))
    print(f"FEM reference: {time.perf_counter() - t:.0f} s", flush=True)
    two = scenes.two_beams_scene()
    q_rest, cells = np.asarray(two.points, np.float64), np.asarray(two.cells[: len(two.cells) // 2])
    line = centre_line(q_rest[: len(q_rest) // 2])
    r0, k = scenes.TWO_BEAMS_CONTACT["r0"], scenes.TWO_BEAMS_CONTACT["stiffness"]
    rows, pick = [], models()
    s = surface(pick["beam-corot, contact in the implicit step"][1])
    frame_ms = {name: [] for name in pick}
    for c, (label, _) in enumerate(cases):
        for name, (coupling, params) in pick.items():
            states, created, finite, ms = run_model(coupling, params, forces[c], r0, k)
            frame_ms[name] += ms
            row = {"model": name, "load": label, "finite": finite, "energy_creating_frames": created}
            if finite:
                row.update(metrics(states, q_ref[c], s_ref[c], q_rest, cells, line, s))
            rows.append(row)
            print(name, label, {k_: round(v, 4) for k_, v in row.items() if isinstance(v, float)}, flush=True)
    result = {"machine": machine, "quick": args.quick, "frames": frames, "case": CASE, "r0": r0, "k": k,
              "rows": rows,
              "frame_ms": {name: {"frames": len(v), "p50": float(np.median(v)), "p99": float(np.percentile(v, 99)),
                                  "max": float(np.max(v))} for name, v in frame_ms.items()},
              "reference": "fem.simulate_batch (explicit, the FEM's two-beam contact in every sub-step)"}
    write_results("contact_beams", result, report(result), Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
