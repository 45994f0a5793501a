"""Reading simulation data sets (the contract in notes/DATA_FORMAT.md) and training-split statistics.

A data set is one ``.npz`` file, or a folder of per-case ``.npz`` files with the same keys whose cases are
stacked along axis 0. States are ``z`` [cases, frames+1, nodes, 12] (q 0-2, v 3-5, Cauchy stress
S11,S22,S33,S12,S13,S23 6-11) and forces ``f`` [cases, frames, nodes, 3] act during step ``z[k] -> z[k+1]``.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

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
        with np.load(path, allow_pickle=False) as npz:
            raw = {k: npz[k] for k in npz.files}
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


def normalization(data: Dataset, rows: np.ndarray) -> dict:
    """Per-feature statistics of the rows' cases (the training split), float32 numpy arrays.

    z_mean, z_std [12]: node state; dz_std [12]: per-frame increment z[k+1]-z[k] (the step scale c of the
    model's output coordinates); f_std [3]: force; dq_std [3] and dqn_mean, dqn_std [1]: edge vector
    q_i - q_j and its length over all frames.
    """
    z, f = data.z[rows], data.f[rows]
    s, r = data.edges
    dq = z[..., s, :3] - z[..., r, :3]
    dqn = np.linalg.norm(dq, axis=-1)
    free = data.node_type == 0
    dz = (z[:, 1:] - z[:, :-1])
    dz_std = np.concatenate([dz[:, :, free, :6].reshape(-1, 6).std(0), dz[..., 6:].reshape(-1, 6).std(0)])
    eps = 1e-8
    stats = dict(
        z_mean=z.reshape(-1, STATE_DIM).mean(0),
        z_std=z.reshape(-1, STATE_DIM).std(0) + eps,
        dz_std=dz_std + eps,
        f_std=np.sqrt((f.reshape(-1, 3) ** 2).mean(0)) + eps,
        dq_std=np.sqrt((dq.reshape(-1, 3) ** 2).mean(0)) + eps,
        dqn_mean=np.array([dqn.mean()]),
        dqn_std=np.array([dqn.std()]) + eps,
    )
    return {k: np.asarray(v, np.float32) for k, v in stats.items()}
