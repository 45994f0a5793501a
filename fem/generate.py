"""Data generation: load cases → FEM runs (batched with `vmap`) → one data-set file.

The data-set file is the one contract between `fem` and `tignn_jax` (keys of the Abaqus reference file plus
``cells``, ``cell_type``, ``metadata``)::

    q0 [N,3] f32, edges [2,E] i32, node_type [N] i8, z [C,T+1,N,12] f32 (q, v, σ: S11 S22 S33 S12 S13 S23),
    f [C,T,N,3] f32 (force acting during frame k), dt (), cells [K,n] i32, cell_type str, metadata JSON str,
    v_solver [C,T+1,N,3] f32 (the solver's own velocity), sim_id [C] i32 (1-based).

z's v is either ``velocity="gradient"``: numpy.gradient of q over the frames, second order, as in the reference
data (so frame 0 of a run from rest has a one-sided, non-zero velocity), or ``velocity="solver"``: the solver's
own velocity (zero at a rest start; what a simulator stepping from rest sees).

Long runs are resumable: each finished case is written to ``<out>.parts/case_XXXXX.npz`` as soon as its batch
is done, and a rerun skips the cases already there before assembling the final file.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .solver import Loads, check, simulate_batch


def run_cases(scene, problem, forces, out, *, batch_size: int = 8, progress: bool = True, xdmf: bool = False,
              metadata: dict | None = None, sim_ids=None, velocity: str = "gradient",
              worker: tuple[int, int] = (0, 1), integrator: str = "explicit",
              newton_iterations: int = 12) -> Path | None:
    """Simulate every case of ``forces`` [C, T, N, 3] and write the data set to ``out`` (.npz).

    Cases are run in batches of ``batch_size`` (vmapped; the last batch is padded, so one compilation serves
    all); finished cases are kept in ``<out>.parts/`` and skipped on a rerun. ``integrator='implicit'`` runs
    `fem.implicit` (backward Euler with the frame step; its preconditioner is computed once and kept in the parts
    folder, at most ``newton_iterations`` Newton iterations per frame) and keeps each case's Newton residuals
    and iteration counts. ``worker = (k, n)`` runs only
    the cases c with c mod n = k, so n processes can share the work (one core each); the worker that finds
    every part present at its end writes ``out`` and returns its path, the others return None.
    """
    forces = np.asarray(forces, np.float32)
    if forces.ndim != 4 or forces.shape[1:] != (problem.config.n_frames, len(scene.points), 3):
        raise ValueError(f"forces must be [cases, {problem.config.n_frames}, {len(scene.points)}, 3], "
                         f"got {forces.shape}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be positive, got {batch_size}")
    if velocity not in ("gradient", "solver"):
        raise ValueError(f"velocity must be 'gradient' or 'solver', got {velocity!r}")
    if integrator not in ("explicit", "implicit"):
        raise ValueError(f"integrator must be 'explicit' or 'implicit', got {integrator!r}")
    if not (isinstance(newton_iterations, (int, np.integer)) and newton_iterations >= 1):
        raise ValueError(f"newton_iterations must be a positive integer, got {newton_iterations!r}")
    k, n_workers = worker
    if not (n_workers >= 1 and 0 <= k < n_workers):
        raise ValueError(f"worker must be (k, n) with 0 <= k < n, got {worker}")
    out = Path(out)
    parts = out.with_name(out.name + ".parts")
    parts.mkdir(parents=True, exist_ok=True)
    n_cases = len(forces)
    sim_ids = np.arange(1, n_cases + 1) if sim_ids is None else np.asarray(sim_ids)
    todo = [c for c in range(k, n_cases, n_workers) if not _part(parts, c).exists()]
    bar = _progress(total=n_cases, initial=n_cases - len(todo), enabled=progress, desc=f"{scene.name} cases")
    t_start = time.perf_counter()
    run = _implicit_runner(scene, problem, parts, newton_iterations) if (integrator == "implicit" and todo) else None
    for start in range(0, len(todo), batch_size):
        idx = todo[start:start + batch_size]
        padded = idx + [idx[-1]] * (batch_size - len(idx))
        loads = Loads(nodal=jnp.asarray(forces[padded]))
        extra = {}
        if run is None:
            res = simulate_batch(problem, scene.material, loads)
        else:
            res, diag = run(loads)
            extra = {"newton_residual": np.asarray(diag.residual),
                     "newton_iterations": np.asarray(diag.newton_iterations)}
        jax.block_until_ready(res.q)
        check(res, "warn")
        for j, c in enumerate(idx):
            q, v = np.asarray(res.q[j], np.float32), np.asarray(res.v[j], np.float32)
            sig = np.asarray(res.sigma[j], np.float32)
            v_fd = np.gradient(q.astype(np.float64), scene.frame_dt, axis=0, edge_order=2).astype(np.float32)
            np.savez(_part(parts, c), z=np.concatenate([q, v_fd, sig], -1), v_solver=v,
                     inverted=np.asarray(res.inverted[j]), **{k: a[j] for k, a in extra.items()})
            if xdmf:
                from .mesh import write_series

                write_series(out.with_name(f"{out.stem}_case{int(sim_ids[c]):03d}.pvd"), scene.points, scene.cells,
                           scene.cell_type, np.asarray(res.t), q, v, sig)
        bar.update(len(idx))
    bar.close()
    wall = time.perf_counter() - t_start
    if not all(_part(parts, c).exists() for c in range(n_cases)):
        return None      # other workers are still running; the last one assembles
    meta = dict(metadata or {}, wall_time_s=wall, cases_run=len(todo),
                load_average_1m_at_end=round(os.getloadavg()[0], 2), cpu_count=os.cpu_count())
    return assemble(scene, problem, forces, parts, out, metadata=meta, sim_ids=sim_ids, velocity=velocity)


def _implicit_runner(scene, problem, parts: Path, newton_iterations: int = 12):
    """``loads -> (Result, Diagnostics)`` of `fem.implicit` for the batch; the preconditioner is cached in the
    parts folder (it takes minutes to compute on the bunny and depends only on the problem)."""
    from . import implicit

    implicit.check_scope(problem, scene.material)   # before minutes of preconditioner
    cache = parts / "implicit_preconditioner.npy"
    if cache.exists():
        pinv = jnp.asarray(np.load(cache))
    else:
        pinv = implicit.preconditioner(problem, scene.material)
        tmp = parts / f"implicit_preconditioner.{os.getpid()}.tmp.npy"
        np.save(tmp, np.asarray(pinv))
        os.replace(tmp, cache)
    return lambda loads: implicit.simulate_implicit_batch(problem, scene.material, loads, pinv,
                                                          max_newton=int(newton_iterations))


def _part(parts: Path, c: int) -> Path:
    """The file of finished case ``c`` in the parts folder."""
    return parts / f"case_{c:05d}.npz"


def assemble(scene, problem, forces, parts: Path, out: Path, *, metadata: dict, sim_ids,
             velocity: str = "gradient") -> Path:
    cases = [np.load(_part(parts, c)) for c in range(len(forces))]
    z = np.stack([c["z"] for c in cases])
    newton = {}
    if all("newton_residual" in c for c in cases):
        newton = {k: np.stack([c[k] for c in cases]) for k in ("newton_residual", "newton_iterations")}
        metadata = dict(metadata, integrator="implicit (fem.implicit, backward Euler, one step per frame)",
                        n_sub=1, newton_residual_max=float(newton["newton_residual"].max()))
    v_solver = np.stack([c["v_solver"] for c in cases])
    if velocity == "solver":
        z[..., 3:6] = v_solver
        v_note = "z[..., 3:6] = v_solver (the solver's velocity; zero at the rest start)"
    else:
        v_note = "z[..., 3:6] = numpy.gradient(q, dt, axis=time, edge_order=2); v_solver = solver velocity"
    meta = {
        "scene": scene.name, "cell_type": scene.cell_type,
        "material": {k: np.asarray(v).tolist() for k, v in scene.material._asdict().items()},
        "frame_dt": scene.frame_dt, "n_frames": scene.n_frames, "n_sub": problem.config.n_sub,
        "damping": scene.damping, "load_interp": scene.load_interp, "code_version": _version(),
        "velocity": v_note,
    }
    if scene.cell_type == "tetra":
        meta["tet_formulation"] = problem.config.tet_formulation
    meta.update(metadata)
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez_compressed(
        tmp, q0=scene.points.astype(np.float32), edges=scene.edges.astype(np.int32),
        node_type=scene.node_type.astype(np.int8), z=z,
        f=np.asarray(forces, np.float32), dt=np.float64(scene.frame_dt), cells=scene.cells.astype(np.int32),
        cell_type=np.array(scene.cell_type), metadata=np.array(json.dumps(meta)),
        v_solver=v_solver, sim_id=np.asarray(sim_ids, np.int32), **newton,
        **{f"split_{k}": v for k, v in default_splits(sim_ids).items()})
    os.replace(tmp, out)   # atomic: a reader never sees a half-written file
    return out


PUBLISHED_VAL = (1, 2, 6, 16, 17)           # the reference data's published split (sim ids)
PUBLISHED_TEST = (9, 10, 12, 13, 38, 44)


def default_splits(sim_ids) -> dict:
    """Train/val/test sim ids: the published split when the cases are the 52 reference cases (ids 1..52),
    otherwise the last 10 % of the cases for test, the 10 % before for validation, the rest for training
    (cases are generated in seeded random order, so this is a random split)."""
    ids = np.asarray(sim_ids, np.int32)
    if sorted(ids.tolist()) == list(range(1, 53)):
        val, test = np.array(PUBLISHED_VAL, np.int32), np.array(PUBLISHED_TEST, np.int32)
        return {"train": np.setdiff1d(ids, np.concatenate([val, test])), "val": val, "test": test}
    n = len(ids)
    k = max(1, n // 10) if n >= 3 else 0
    return {"train": ids[: n - 2 * k], "val": ids[n - 2 * k: n - k], "test": ids[n - k:]}


def held_out_rows(n_cases: int) -> np.ndarray:
    """0-based case rows of a generated set of ``n_cases`` (sim ids 1..n) that `default_splits` keeps out of
    training (val, then test): e.g. rows 80–99 of the seeded 100-case bunny set, its positions 81–100."""
    s = default_splits(np.arange(1, int(n_cases) + 1))
    return np.concatenate([s["val"], s["test"]]).astype(np.int64) - 1


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("tignn-jax")
    except PackageNotFoundError:
        return "unknown"


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress(total, initial, enabled, desc):
    if not enabled:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, desc=desc, unit="case")
