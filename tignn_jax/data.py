"""Reading simulation data sets (the contract in docs/data_format.md) and training-split statistics.

A data set is one ``.npz`` file, or a folder of per-case ``.npz`` files with the same keys whose cases are
stacked along axis 0. States are ``z`` [cases, frames+1, nodes, 12] (q 0-2, v 3-5, Cauchy stress
S11,S22,S33,S12,S13,S23 6-11) and forces ``f`` [cases, frames, nodes, 3] act during step ``z[k] -> z[k+1]``.
"""
from __future__ import annotations

import zipfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

NOT_AN_ARCHIVE = (ValueError, EOFError, zipfile.BadZipFile)   # numpy.load on a file that is not an .npz archive

STATE_DIM = 12
Q, V, SIGMA = slice(0, 3), slice(3, 6), slice(6, 12)
SPLITS = ("train", "val", "test")


class Dataset(NamedTuple):
    """A set of simulations on one mesh (numpy arrays, host memory).

    q0: [N,3] reference coordinates; edges: [2,E] int32 directed edges (senders, receivers);
    node_type: [N] int8 (0 free, 1 clamped); z: [C,T+1,N,12] states; f: [C,T,N,3] forces;
    dt: frame time step; sim_id: [C] 1-based case ids; splits: name -> sim ids.
    """
    q0: np.ndarray
    edges: np.ndarray
    node_type: np.ndarray
    z: np.ndarray
    f: np.ndarray
    dt: float
    sim_id: np.ndarray
    splits: dict


def reference_path() -> Path:
    """Where the Abaqus reference beam file lives relative to a checkout: ``../shared/data/abaqus_beam.npz``."""
    return Path(__file__).resolve().parents[1].parent / "shared" / "data" / "abaqus_beam.npz"


def cells(path: str | Path):
    """The cells [K, 4|8] int32 of a data file's mesh: its ``cells`` entry, or the reference beam's hexes for the
    Abaqus reference data (which store nodes and edges only); None where neither applies (or for a folder)."""
    if Path(path).is_dir():
        return None
    with np.load(path, allow_pickle=False) as raw:
        if "cells" in raw.files:
            return np.asarray(raw["cells"], np.int32)
        q0 = raw["q0"] if "q0" in raw.files else None
    from fem import meshes

    ref, ref_cells, _ = meshes.beam_mesh()
    if q0 is not None and np.shape(q0) == ref.shape and np.allclose(q0, ref, atol=1e-5):
        return np.asarray(ref_cells, np.int32)
    return None


def load(path: str | Path) -> Dataset:
    """Read a data set from an ``.npz`` file or a folder of per-case ``.npz`` files.

    Raises FileNotFoundError for a missing path and ValueError naming the key for missing keys or shapes
    that break the contract.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"data set not found: {path}")
    if path.is_dir():
        files = sorted(path.glob("*.npz"))
        if not files:
            raise ValueError(f"data folder {path} holds no .npz files")
        parts = [dict(np.load(p, allow_pickle=False)) for p in files]
        raw = dict(parts[0])
        for key in ("z", "f", "v_solver", "sim_id"):
            if key in raw:
                raw[key] = np.concatenate([np.atleast_1d(p[key]) if key == "sim_id" else p[key] for p in parts])
    else:
        try:
            with np.load(path, allow_pickle=False) as npz:
                raw = {k: npz[k] for k in npz.files}
        except NOT_AN_ARCHIVE as err:
            raise ValueError(f"data set {path} is not a .npz archive") from err
    for key in ("q0", "edges", "node_type", "z", "f", "dt"):
        if key not in raw:
            raise ValueError(f"data set {path} lacks the key {key!r}")
    z = np.asarray(raw["z"], np.float32)
    f = np.asarray(raw["f"], np.float32)
    q0 = np.asarray(raw["q0"], np.float32)
    n = q0.shape[0]
    if z.ndim == 3:
        z, f = z[None], f[None]
    if z.ndim != 4 or z.shape[2:] != (n, STATE_DIM):
        raise ValueError(f"z has shape {z.shape}, expected [cases, frames+1, {n}, {STATE_DIM}]")
    if f.shape != (z.shape[0], z.shape[1] - 1, n, 3):
        raise ValueError(f"f has shape {f.shape}, expected {(z.shape[0], z.shape[1] - 1, n, 3)}")
    edges = np.asarray(raw["edges"], np.int32)
    if edges.ndim != 2 or edges.shape[0] != 2 or edges.min() < 0 or edges.max() >= n:
        raise ValueError(f"edges has shape {edges.shape} or indices outside [0, {n}); expected [2, E]")
    sim_id = np.asarray(raw.get("sim_id", np.arange(1, z.shape[0] + 1)), np.int32).reshape(-1)
    splits = {s: np.asarray(raw[f"split_{s}"], np.int32).reshape(-1) for s in SPLITS if f"split_{s}" in raw}
    return Dataset(q0=q0, edges=edges, node_type=np.asarray(raw["node_type"], np.int8).reshape(n), z=z, f=f,
                   dt=float(raw["dt"]), sim_id=sim_id, splits=splits)


def concatenate(*sets: Dataset) -> Dataset:
    """One data set from several on the same mesh: cases stacked in order, the sim ids of each later set shifted
    past the largest id so far (so ids stay unique), and each split the union of the sets' splits.

    Raises ValueError naming the first field (q0, edges, node_type, dt) in which a set differs from the first.
    """
    if not sets:
        raise ValueError("concatenate needs at least one data set")
    first = sets[0]
    for k, d in enumerate(sets[1:], 1):
        for name in ("q0", "edges", "node_type"):
            a, b = getattr(first, name), getattr(d, name)
            if a.shape != b.shape or not np.array_equal(a, b):
                raise ValueError(f"data set {k} has a different {name} from data set 0 (not the same mesh)")
        if d.dt != first.dt:
            raise ValueError(f"data set {k} has dt = {d.dt}, data set 0 has dt = {first.dt}")
    ids, splits, offset = [], {}, 0
    for d in sets:
        ids.append(d.sim_id + offset)
        for name, members in d.splits.items():
            splits.setdefault(name, []).append(np.asarray(members, np.int32) + offset)
        offset = int(max(offset, (d.sim_id + offset).max()))
    return first._replace(z=np.concatenate([d.z for d in sets]), f=np.concatenate([d.f for d in sets]),
                          sim_id=np.concatenate(ids).astype(np.int32),
                          splits={k: np.concatenate(v) for k, v in splits.items()})


def select(data: Dataset, rows) -> Dataset:
    """The cases at ``rows`` (indices into the case axis), with each split reduced to the kept sim ids."""
    rows = np.asarray(rows, int).ravel()
    if rows.size == 0 or rows.min() < 0 or rows.max() >= len(data.sim_id):
        raise ValueError(f"rows must be non-empty indices in 0..{len(data.sim_id) - 1}, got {rows.tolist()[:10]}")
    kept = data.sim_id[rows]
    return data._replace(z=data.z[rows], f=data.f[rows], sim_id=kept,
                         splits={k: np.asarray(v)[np.isin(v, kept)] for k, v in data.splits.items()})


def from_frame(data: Dataset, start: int) -> Dataset:
    """The same cases observed from frame ``start`` on: z[:, start:], f[:, start:] (T - start frames left).

    For data whose first frames hold a start-up transient the model is not meant to learn (a body at rest set
    in motion by a ramp from zero rings at the frame rate for a few frames); the state at ``start`` becomes
    each case's initial state. Raises ValueError unless 0 <= start < T."""
    frames = data.f.shape[1]
    if not (isinstance(start, (int, np.integer)) and 0 <= start < frames):
        raise ValueError(f"start must be an integer frame in 0..{frames - 1}, got {start!r}")
    return data._replace(z=data.z[:, start:], f=data.f[:, start:])


def save(data: Dataset, path: str | Path, metadata: str = "") -> Path:
    """Write a data set as one ``.npz`` in the contract's keys (what `load` reads)."""
    path = Path(path)
    np.savez(path, q0=data.q0, edges=data.edges, node_type=data.node_type, z=data.z, f=data.f,
             dt=np.float64(data.dt), sim_id=data.sim_id, metadata=np.array(metadata),
             **{f"split_{k}": v for k, v in data.splits.items()})
    return path


def split_rows(data: Dataset, split: str | list[int] | np.ndarray) -> np.ndarray:
    """Row indices (0-based, into ``data.z``) of a named split (``"train"``, ``"val"``, ``"test"``, ``"all"``)
    or of an explicit list of 1-based sim ids."""
    if isinstance(split, str):
        if split == "all":
            return np.arange(data.z.shape[0])
        if split not in data.splits:
            raise ValueError(f"split {split!r} is not in the data set (has {sorted(data.splits)} and 'all')")
        ids = data.splits[split]
    else:
        ids = np.asarray(split, np.int32).reshape(-1)
    lookup = {int(s): i for i, s in enumerate(data.sim_id)}
    missing = [int(s) for s in ids if int(s) not in lookup]
    if missing:
        raise ValueError(f"sim ids {missing} are not in the data set")
    return np.array([lookup[int(s)] for s in ids], np.int64)


def parse_split(text: str) -> str | list[int]:
    """``"test"`` stays a split name; ``"9,10,12"`` becomes a list of sim ids."""
    text = text.strip()
    if text and all(c.isdigit() or c in ", " for c in text):
        return [int(s) for s in text.replace(" ", "").split(",") if s]
    return text


def normalization(data: Dataset, rows: np.ndarray, chunk: int = 8) -> dict:
    """Per-feature statistics of the rows' cases (the training split), float32 numpy arrays.

    z_mean, z_std [12]: node state; dz_std [12]: per-frame increment z[k+1]-z[k] of free nodes' q, v and all
    nodes' stress (the output scale); f_std [3]: RMS of the nodal forces that are not zero (a load on a few
    nodes of a large mesh would otherwise be scaled by the near-zero RMS over all nodes and enter the network as
    an outlier: the bunny's unit point load read as 75); f_max [1]: the largest nodal force magnitude (the
    out-of-distribution bound of ``api.force_check``); dq_std [3] and dqn_mean, dqn_std [1]: edge vector
    q_j - q_i and its length over all frames; dv_std [3]: edge velocity difference v_j - v_i; du_std [3]: edge
    displacement difference (q_j - q_i) - (X_j - X_i); u_std [3]: node displacement q - X; x0_mean [3], x0_std [3]: rest
    positions (mean and isotropic scale); dt [1]: the frame time step; z_dev_max [12] and u_max [1]:
    the training envelope (see ``envelope``).
    Vectors (q, v, their increments, f, dq) get one isotropic scale (RMS over components), so a direction
    unseen in training is not blown up; stress components get their own std, floored at 1e-2 of the largest;
    every scale is positive. The sums run over ``chunk`` cases at a time (float64), so the memory does not grow
    with the number of cases.
    """
    rows = np.asarray(rows, int).ravel()
    if not (isinstance(chunk, (int, np.integer)) and chunk >= 1):
        raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
    s, r = data.edges
    free = data.node_type == 0
    rest_dq = data.q0[s] - data.q0[r]
    m = _Moments()
    # a few cases at a time: the float64 edge arrays of ~700 bunny cases at once would take ~27 GB
    for a in range(0, len(rows), chunk):
        z = data.z[rows[a:a + chunk]].astype(np.float64)
        f = data.f[rows[a:a + chunk]].astype(np.float64)
        dz = z[:, 1:] - z[:, :-1]
        dq = z[..., s, :3] - z[..., r, :3]
        flat = z.reshape(-1, STATE_DIM)
        m.add("z", flat)
        m.add("dz_free", dz[:, :, free].reshape(-1, STATE_DIM))
        m.add("dz", dz.reshape(-1, STATE_DIM))
        m.add("f", _nonzero_rows(f.reshape(-1, 3)))
        m.peak("f_max", np.linalg.norm(f, axis=-1))
        m.add("dq", dq.reshape(-1, 3))
        m.add("dqn", np.linalg.norm(dq, axis=-1).reshape(-1, 1))
        m.add("dv", (z[..., s, 3:6] - z[..., r, 3:6]).reshape(-1, 3))
        m.add("du", (dq - rest_dq).reshape(-1, 3))
        m.add("u", (z[..., :3] - data.q0).reshape(-1, 3))
    z_mean = m.mean("z")
    z_std = np.concatenate([m.centred_rms("z", slice(0, 3)), m.centred_rms("z", slice(3, 6)),
                            _floored(m.std("z")[6:])])
    dz_std = np.concatenate([m.rms("dz_free", slice(0, 3)), m.rms("dz_free", slice(3, 6)),
                             _floored(m.std("dz")[6:])])
    dqn_mean = float(m.mean("dqn")[0])
    stats = dict(
        z_mean=z_mean,
        z_std=z_std,
        dz_std=dz_std,
        f_std=m.rms("f"),
        f_max=np.array([m.peaks.get("f_max", 0.0)]),
        dq_std=m.rms("dq"),
        dv_std=m.rms("dv"),
        du_std=m.rms("du"),
        u_std=m.rms("u"),
        x0_mean=data.q0.mean(0),
        x0_std=_iso(data.q0 - data.q0.mean(0)),
        dqn_mean=np.array([dqn_mean]),
        dqn_std=np.array([max(float(m.std("dqn")[0]), 1e-3 * dqn_mean, 1e-12)]),
        dt=np.array([data.dt]),
    )
    dev_max, u_max = np.zeros(STATE_DIM), 0.0   # the envelope needs the mean and scale: a second pass
    for a in range(0, len(rows), chunk):
        env = envelope(data.z[rows[a:a + chunk]], data.q0, z_mean, z_std)
        dev_max, u_max = np.maximum(dev_max, env["z_dev_max"]), max(u_max, float(env["u_max"][0]))
    stats.update(z_dev_max=dev_max, u_max=np.array([u_max]))
    return {k: np.asarray(v, np.float32) for k, v in stats.items()}


class _Moments:
    """Running count, sum and sum of squares per column of named [M, d] arrays (float64), and running maxima:
    the statistics of `normalization`, accumulated a few cases at a time."""

    def __init__(self):
        self.n, self.s1, self.s2, self.peaks = {}, {}, {}, {}

    def add(self, key, x):
        x = np.asarray(x, np.float64)
        self.n[key] = self.n.get(key, 0) + len(x)
        self.s1[key] = self.s1.get(key, 0.0) + x.sum(axis=0)
        self.s2[key] = self.s2.get(key, 0.0) + np.square(x).sum(axis=0)

    def peak(self, key, x):
        if np.size(x):
            self.peaks[key] = max(self.peaks.get(key, 0.0), float(np.max(x)))

    def mean(self, key):
        return self.s1[key] / self.n[key]

    def std(self, key):
        """Population std per column (0 for a constant column; the sums are float64)."""
        return np.sqrt(np.maximum(self.s2[key] / self.n[key] - self.mean(key) ** 2, 0.0))

    def rms(self, key, cols=slice(None)):
        """`_iso` of the columns: one RMS over all their entries, repeated 3 times (1 if all zero or none)."""
        if not self.n.get(key):
            return np.ones(3)
        s2 = self.s2[key][cols]
        rms = float(np.sqrt(s2.sum() / (self.n[key] * s2.size)))
        return np.full(3, rms if rms > 0 else 1.0)

    def centred_rms(self, key, cols):
        """`_iso` of the columns after subtracting their means: the RMS of their standard deviations."""
        rms = float(np.sqrt(np.mean(self.std(key)[cols] ** 2)))
        return np.full(3, rms if rms > 0 else 1.0)


def envelope(z, q0, z_mean, z_std) -> dict:
    """The training envelope of states z [..., N, 12] (what `tignn_jax.guards.state_check` compares a state against):
    z_dev_max [12], the largest |z − z_mean| / z_std of each feature, and u_max [1], the largest nodal
    displacement |q − q0|. Stress and velocity are heavy-tailed where loads concentrate (on the bunny's patch
    loads σ reaches 100–540 standard deviations, on the beam σ23 41), so a fixed bound in standard deviations
    flags states the model was trained on."""
    z = np.asarray(z, np.float64)
    dev = np.abs((z - np.asarray(z_mean, np.float64)) / np.asarray(z_std, np.float64)).reshape(-1, STATE_DIM)
    u = np.linalg.norm(z[..., :3] - np.asarray(q0, np.float64), axis=-1)
    return {"z_dev_max": dev.max(0), "u_max": np.array([u.max()])}


def _nonzero_rows(x) -> np.ndarray:
    """The rows of x [M,3] that are not all zero."""
    return x[np.any(x != 0, axis=1)]


def _iso(x) -> np.ndarray:
    """One scale for a vector quantity [M,3]: RMS over all entries, repeated 3 times (1 if all zero)."""
    rms = float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else 0.0
    return np.full(3, rms if rms > 0 else 1.0)


def _floored(std) -> np.ndarray:
    top = float(np.max(std))
    return np.maximum(std, 1e-2 * top) if top > 0 else np.ones_like(std)


def synthetic_beam(nx: int = 4, ny: int = 2, nz: int = 2, cases: int = 3, frames: int = 4, seed: int = 0,
                   dt: float = 0.05) -> Dataset:
    """A small smooth data set on a grid of nx×ny×nz nodes (spacing 1), clamped at x = 0, for tests and examples.

    Each case bends the bar in y with tip displacement a·t² (a from the seed): u_y = a t² (x/L)², v = du/dt,
    stress S11 = -k y' ∂²u_y/∂x² (y' = y − y_mid) and S12 = k ∂u_y/∂x, the other components 0; the force is a
    constant push on the tip nodes. Not a physical solution, just smooth and learnable."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    q0 = g.astype(np.float32)
    index = {tuple(p): i for i, p in enumerate(g.tolist())}
    pairs = [(i, index[tuple(p + d)]) for i, p in enumerate(g) for d in np.eye(3, dtype=int)
             if tuple(p + d) in index]
    edges = np.array(pairs + [(b, a) for a, b in pairs], np.int32).T
    node_type = (g[:, 0] == 0).astype(np.int8)
    length = float(nx - 1)
    x, y = q0[:, 0] / length, q0[:, 1] - (ny - 1) / 2
    t = np.arange(frames + 1) * dt
    amp = rng.uniform(0.5, 1.5, cases)
    z = np.zeros((cases, frames + 1, len(q0), STATE_DIM), np.float32)
    f = np.zeros((cases, frames, len(q0), 3), np.float32)
    for c in range(cases):
        uy = amp[c] * t[:, None] ** 2 * x[None] ** 2
        z[c, :, :, :3] = q0
        z[c, :, :, 1] += uy
        z[c, :, :, 4] = 2 * amp[c] * t[:, None] * x[None] ** 2
        z[c, :, :, 6] = -100.0 * y[None] * 2 * amp[c] * t[:, None] ** 2 / length ** 2
        z[c, :, :, 9] = 100.0 * 2 * amp[c] * t[:, None] ** 2 * x[None] / length
        f[c, :, g[:, 0] == nx - 1, 1] = 10.0 * amp[c]
    ids = np.arange(1, cases + 1, dtype=np.int32)
    return Dataset(q0=q0, edges=edges, node_type=node_type, z=z, f=f, dt=dt, sim_id=ids,
                   splits={"train": ids[:max(cases - 1, 1)], "val": ids[-1:], "test": ids[-1:]})
