r"""The best P-hop linear frame map of the bunny: what a P-pass graph network could reach at best, fitted.

`bunny_reach.py` truncated the exact linear backward-Euler frame map A₀⁻¹ to node pairs within P mesh edges
(u error 0.26 at 3 edges). Truncation is not the best P-hop operator: on the smooth states a rollout visits,
a node's P-hop neighbourhood also tells something about what lies beyond it. This script fits the best one.

The world is the shipped `bunny-linear` model (the FEM's rest-linearised backward Euler, which reproduces our
FEM's held-out bunny rollouts to u 0.014): its frame map, with c = (1 + αΔt)/Δt²,

    u_{k+1} = A₀⁻¹ (f_k + c M u_k + M v_k / Δt),   v_{k+1} = (u_{k+1} − u_k) / Δt,

is rolled out from rest under the bunny data's unit patch loads (`fem.cases.point_load_forces`, radius 5,
rise over 10 frames, then held; the data's density 1e-3). For each hop count P and each free node i, the
next displacement u_{k+1,i} is regressed (ridge, features standardised) on the current u, v, f of the nodes
within P edges of i: the best linear P-hop map in the least-squares sense over the training transitions,
with per-node weights (a network shares its weights across nodes, so it has less freedom than this; it is
non-linear, which a linear world does not need). v follows from u as in the true map. The fitted map is then
rolled out from rest on held-out load positions and scored like `bunny_reach.py` (relative L2 of u and v over
each whole 20-frame rollout, mean over the cases).

Training sets: ``data`` — the 80 training positions of the data set (seed 0, cases 1–80); ``dense`` — every
free surface node except the 20 held-out positions (what unlimited data would give). Held-out: the data set's
val and test positions (seed 0, cases 81–100). Each fit is scored one step from the true held-out states and
over whole rollouts, and the spectral radius of its unforced map tells whether it amplifies some state.

    python benchmarks/bunny_local_fit.py [--hops 1,2,3,4] [--ridges 1e-6,1e-3,1e-1] [--sets dense]

Writes benchmarks/results/bunny_local_fit.{json,md}.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe, write_results  # noqa: E402
from fem.generate import held_out_rows  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
HELD_OUT = held_out_rows(100)    # seed-0 cases 81–100: the data set's val and test positions


def linear_world(name: str = "bunny-linear"):
    """(A₀⁻¹ on the free dofs, mass on the free dofs, c, Δt, free-node mask, hop distances, scene)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    sys.path.insert(0, str(ROOT))
    import tignn_jax
    from fem import scenes
    from tignn_jax import framesolve as FS

    params, graph = tignn_jax.load_pretrained(name)
    norm, info = params["norm"], params["info"]
    node_type = np.asarray(graph.nodes["node_type"])
    free_n = node_type == 0
    free = np.repeat(free_n, 3)
    n = len(node_type)
    a_inv = np.asarray(norm["fs_ainv"] if "fs_ainv" in norm else FS.inverse(norm, node_type), np.float64)
    h = float(np.asarray(norm["dt"]).reshape(-1)[0])
    alpha = float(np.asarray(norm["fs_alpha"]).reshape(-1)[0])
    mass = np.repeat(np.asarray(norm["fs_mass"], np.float64), 3)
    s, r = np.asarray(graph.senders), np.asarray(graph.receivers)
    dist = shortest_path(csr_matrix((np.ones(len(s)), (s, r)), shape=(n, n)), unweighted=True)
    scene = scenes.bunny_scene(density=float(info["fem_density"]))
    if len(scene.points) != n:
        raise ValueError(f"the bunny scene has {len(scene.points)} nodes, the model {n}")
    return dict(a_inv=a_inv[np.ix_(free, free)], mass=mass[free], c=(1 + alpha * h) / h ** 2, h=h,
                free_n=free_n, free=free, dist=dist[np.ix_(free_n, free_n)], scene=scene,
                radius=float(info["fem_load_radius"]), senders=s, receivers=r)


def forces_for(world, load_nodes=None, n_cases=100, seed=0):
    from fem import cases

    f, picked = cases.point_load_forces(world["scene"], n_cases=n_cases, seed=seed, load_nodes=load_nodes,
                                        rise_frames=10, radius=world["radius"])
    return f.reshape(f.shape[0], f.shape[1], -1)[..., world["free"]], picked


def split_forces(world, dense: bool = True):
    """(held-out forces: the data set's positions 81–100; the data set's training positions 1–80; every other
    free surface position, or None without ``dense``), each [cases, frames, free dofs]."""
    from fem.cases import free_surface

    f_all, picked = forces_for(world)
    rest = None
    if dense:
        surface, _ = free_surface(world["scene"])
        rest = forces_for(world, load_nodes=np.setdiff1d(surface, surface[picked[HELD_OUT]]))[0]
    return f_all[HELD_OUT], f_all[:80], rest


def roll(step, f, h):
    """u, v [cases, frames+1, dofs] from rest, with u_{k+1} = step(u, v, f_k)."""
    u = np.zeros((f.shape[0], f.shape[2]))
    v = np.zeros_like(u)
    us, vs = [u], [v]
    for k in range(f.shape[1]):
        u_new = step(u, v, f[:, k])
        u, v = u_new, (u_new - u) / h
        us.append(u)
        vs.append(v)
    return np.stack(us, 1), np.stack(vs, 1)


def exact_step(world, a_inv=None):
    """The world's frame map u_{k+1} = A⁻¹ (f + c M u + M v / h), with ``a_inv`` in place of A₀⁻¹ if given (its
    truncation, say)."""
    P = world["a_inv"] if a_inv is None else a_inv
    m, c, h = world["mass"], world["c"], world["h"]
    return lambda u, v, f: (f + c * m * u + m * v / h) @ P.T


def kind_scale(x):
    """One standard deviation per kind (u, v, f) of features [samples, dofs, 3 kinds]."""
    return x.reshape(len(x), -1, 3, 3).std(axis=(0, 1, 2)) + 1e-30


def spectral_radius(step, dofs: int, h: float, tol: float = 0.0, maxiter: int = 5000) -> float:
    """Largest |eigenvalue| of a linear frame map's unforced response (u, v) → (u', (u' − u)/h), f = 0, by ARPACK
    on matrix-vector products; ``step(u, v, f)`` takes [batch, dofs] (above 1: it amplifies some state)."""
    from scipy.sparse.linalg import LinearOperator, eigs

    def matvec(w):
        w = np.real(np.asarray(w, np.float64)).reshape(-1)
        u, v = w[:dofs][None], w[dofs:][None]
        u1 = step(u, v, np.zeros_like(u))
        return np.concatenate([u1, (u1 - u) / h], 1)[0]

    op = LinearOperator((2 * dofs, 2 * dofs), matvec=matvec, dtype=np.float64)
    return float(np.abs(eigs(op, k=1, which="LM", return_eigenvectors=False, maxiter=maxiter, tol=tol)).max())


def transitions(u, v, f):
    """Features [samples, dofs, 3 kinds] (u, v, f at frame k) and targets u_{k+1} [samples, dofs]."""
    x = np.stack([u[:, :-1], v[:, :-1], f], -1).reshape(-1, u.shape[2], 3)
    return x, u[:, 1:].reshape(-1, u.shape[2])


class LocalMap:
    """Per-node ridge regression of u_{k+1,i} (3 dofs) on (u, v, f) of the nodes within ``hops`` edges."""

    @staticmethod
    def moments(x, y):
        """(per-kind scale, Gram matrix and cross moments of the standardised features): shared by all fits."""
        scale = kind_scale(x)
        xs = (x / scale).reshape(len(x), -1)                                   # [samples, dofs*3]
        return scale, xs.T @ xs, xs.T @ y

    def __init__(self, world, hops: int, moments, ridge: float):
        from scipy.sparse import coo_matrix

        n_free = world["dist"].shape[0]
        scale, gram, cross = moments
        rows, cols_all, vals, support = [], [], [], []
        for i in range(n_free):
            nodes = np.where(world["dist"][i] <= hops)[0]
            cols = ((nodes[:, None] * 3 + np.arange(3))[..., None] * 3 + np.arange(3)).ravel()
            g = gram[np.ix_(cols, cols)]
            g[np.diag_indices_from(g)] += ridge * np.trace(g) / len(g)
            w = np.linalg.solve(g, cross[cols][:, 3 * i:3 * i + 3]) / scale[cols % 3][:, None]   # raw units
            rows.append(np.broadcast_to(np.arange(3 * i, 3 * i + 3), w.shape).ravel())
            cols_all.append(np.broadcast_to(cols[:, None], w.shape).ravel())
            vals.append(w.ravel())
            support.append(len(nodes))
        # the fitted map as one sparse matrix [free dofs, free dofs × (u, v, f)], features ordered (dof, kind)
        self.W = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols_all))),
                            shape=(3 * n_free, 9 * n_free)).tocsr()
        self.mean_support = float(np.mean(support))

    def radius(self, h: float) -> float:
        """Spectral radius of the fitted map's free response (u, v) → (u', v'), f = 0 (the exact map's is < 1)."""
        return spectral_radius(self, self.W.shape[0], h)

    def __call__(self, u, v, f):
        return (self.W @ np.stack([u, v, f], -1).reshape(len(u), -1).T).T


def rel_errors(u, v, u_t, v_t):
    rel = lambda a, b: np.linalg.norm((a - b).reshape(len(a), -1), axis=1) / np.linalg.norm(b.reshape(len(b), -1), axis=1)
    return float(rel(u, u_t).mean()), float(rel(v, v_t).mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hops", default="1,2,3,4")
    ap.add_argument("--ridges", default="1e-6,1e-3,1e-1",
                    help="ridges to try, each relative to the Gram block's mean diagonal (a ridge r is input noise "
                         "of about sqrt(r) feature stds)")
    ap.add_argument("--sets", default="dense", help="training sets: data, dense (see the docstring)")
    args = ap.parse_args(argv)
    hops = [int(x) for x in args.hops.split(",") if x]
    ridges = [float(x) for x in args.ridges.split(",") if x]
    sets = [s for s in args.sets.split(",") if s]
    bad = [s for s in sets if s not in ("data", "dense")]
    if bad or not hops or min(hops) < 1:
        raise SystemExit(f"--sets must name data or dense (got {bad}); --hops positive integers (got {hops})")
    machine = describe()
    t0 = time.time()
    world = linear_world()
    step = exact_step(world)
    f_test, f_data, f_dense = split_forces(world, dense="dense" in sets)
    u_t, v_t = roll(step, f_test, world["h"])
    train_forces = {"data": f_data, "dense": f_dense}
    out = {"machine": machine, "world": "bunny-linear (rest-linearised backward Euler)",
           "free_nodes": int(world["free_n"].sum()), "held_out_cases": (HELD_OUT + 1).tolist(),
           "ridges": ridges, "truncated_check": {}, "fits": {}}
    for hop in hops:   # the truncation of bunny_reach.py, in this world, for comparison
        Pt = np.where(np.repeat(np.repeat(world["dist"] <= hop, 3, 0), 3, 1), world["a_inv"], 0.0)
        out["truncated_check"][hop] = rel_errors(*roll(exact_step(world, Pt), f_test, world["h"]), u_t, v_t)
    xt, yt = transitions(u_t, v_t, f_test)
    kinematic = yt - xt[..., 0] - world["h"] * xt[..., 1]    # what u_k + Δt v_k leaves to predict
    out["kinematic_one_step_u"] = float(np.linalg.norm(kinematic) / np.linalg.norm(yt))
    for name in sets:
        f_tr = train_forces[name]
        x, y = transitions(*roll(step, f_tr, world["h"]), f_tr)
        mom = LocalMap.moments(x, y)
        del x, y
        out["fits"][name] = {"positions": int(len(f_tr)), "transitions": int(len(f_tr) * f_tr.shape[1]), "runs": []}
        for hop in hops:
            for ridge in ridges:
                t1 = time.time()
                fit = LocalMap(world, hop, mom, ridge)
                err = fit(*np.moveaxis(xt, -1, 0)) - yt
                e_u, e_v = rel_errors(*roll(fit, f_test, world["h"]), u_t, v_t)
                run = {"hops": hop, "ridge": ridge, "u": e_u, "v": e_v,
                       "one_step_u": float(np.linalg.norm(err) / np.linalg.norm(yt)),
                       "one_step_of_kinematic_residual": float(np.linalg.norm(err) / np.linalg.norm(kinematic)),
                       "spectral_radius": fit.radius(world["h"]), "mean_support_nodes": fit.mean_support,
                       "fit_s": time.time() - t1}
                out["fits"][name]["runs"].append(run)
                print(f"{name} P={hop} ridge {ridge:g}: support {fit.mean_support:.0f} nodes, one-step u "
                      f"{run['one_step_u']:.5f} ({run['one_step_of_kinematic_residual']:.4f} of the kinematic "
                      f"residual), radius {run['spectral_radius']:.4f}, rollout u {e_u:.4g} v {e_v:.4g} "
                      f"({run['fit_s']:.0f} s)", flush=True)
    out["total_s"] = time.time() - t0
    lines = ["# Bunny: the best P-hop linear frame map, fitted", "",
             f"Machine: {machine['cpu']}, {machine['cores']} cores, jax {machine['jax']}; load average "
             f"{machine['load_average_1m']} at start; {out['total_s']:.0f} s in all. World: the shipped "
             "`bunny-linear` frame map (see the script's docstring); held-out: the data set's load positions "
             "81–100. Rollout: relative L2 of u and v over each whole 20-frame rollout from rest, mean over the "
             "20 cases. One-step: relative L2 error of u_{k+1} predicted from the true states, and the same error "
             "as a share of what u_k + Δt v_k leaves to predict (that residual is "
             f"{out['kinematic_one_step_u']:.4f} of u_{{k+1}}). Radius: the spectral radius of the map's "
             "unforced response (above 1: it amplifies some state every frame).", "",
             "Truncated A₀⁻¹ (`bunny_reach.py`'s operator, in this world): " +
             ", ".join(f"P = {hop}: u {tu:.4f}, v {tv:.4f}" for hop, (tu, tv) in out["truncated_check"].items()) + ".",
             "", "| training set | P (hops) | support (nodes) | ridge | one-step u | share of kinematic residual "
             "| radius | rollout u | rollout v |", "|---|---|---|---|---|---|---|---|---|"]
    for name in sets:
        tag = f"{name} ({out['fits'][name]['positions']} positions)"
        for r in out["fits"][name]["runs"]:
            lines.append(f"| {tag} | {r['hops']} | {r['mean_support_nodes']:.0f} | {r['ridge']:g} | "
                         f"{r['one_step_u']:.5f} | {r['one_step_of_kinematic_residual']:.4f} | "
                         f"{r['spectral_radius']:.4f} | {r['u']:.4g} | {r['v']:.4g} |")
    write_results("bunny_local_fit", out, "\n".join(lines) + "\n", RESULTS, echo=False)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
