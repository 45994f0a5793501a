r"""Can one set of shared weights learn the bunny's local frame map? A linear message-passing probe.

`bunny_local_fit.py` showed that a per-node linear map over 4 mesh hops reproduces the rest-linearised bunny's
rollouts to u 0.7 % (20 frames, held-out load positions), but it has per-node weights (about 9 M numbers) and
needs load positions all over the surface to generalise. A graph network shares its weights across nodes. This
probe asks whether that is enough, in the same world (the shipped `bunny-linear` frame map under the data's
patch loads, the same training and held-out positions), with a network that is exactly as expressive as
needed and no more: linear in the state, its coefficients functions of the rest mesh only,

    h⁰ = B xᵢ,   hˡ⁺¹ᵢ = hˡᵢ + Σ_{j→i} Aˡ(gᵢⱼ) hˡⱼ,   u_{k+1,i} = u_{k,i} + Δt v_{k,i} + C h^Pᵢ,

with xᵢ = (u, v, f) of node i (standardised per kind), B [d×9] and C [3×d] shared, and Aˡ(g) [d×d] from an MLP
of the rest edge geometry g (the edge vector and length, and both end nodes' rest position, lumped mass,
degree and number of clamped neighbours). P layers see P hops. No biases: the map is linear in the state, so
the one-step loss is what a linear world needs, and the spectral radius of its unforced map is defined.

It is a probe, not a GENERIC model: a positive answer says what a thermodynamics-informed network for the bunny
must contain (state-linear messages with geometry-dependent coefficients), not that one has been built.

    python benchmarks/bunny_linear_gnn.py [--layers 4] [--width 16] [--steps 3000] [--noise 0] [--per-sample]

Writes benchmarks/results/bunny_linear_gnn.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe  # noqa: E402
import bunny_local_fit as blf  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def geometry(world):
    """(edge geometry [E, 13], senders, receivers) over the edges between free nodes (indices among them)."""
    free_n = world["free_n"]
    idx = -np.ones(len(free_n), np.int64)
    idx[free_n] = np.arange(free_n.sum())
    s, r = world["senders"], world["receivers"]
    keep = free_n[s] & free_n[r]
    clamped_nb = np.bincount(r[~free_n[s] & free_n[r]], minlength=len(free_n))[free_n]
    pts = np.asarray(world["scene"].points, np.float64)[free_n]
    mass = world["mass"][0::3]
    s, r = idx[s[keep]], idx[r[keep]]
    degree = np.bincount(r, minlength=len(pts))
    node = np.stack([*((pts - pts.mean(0)) / pts.std(0)).T, np.log(mass), degree, clamped_nb], 1)
    node = (node - node.mean(0)) / (node.std(0) + 1e-12)
    e = pts[s] - pts[r]
    ell = np.linalg.norm(e, axis=1, keepdims=True)
    g = np.concatenate([e / ell.mean(), ell / ell.mean(), node[s][:, 3:], node[r]], 1)   # 3 + 1 + 3 + 6
    return g.astype(np.float32), s, r


def init(key, layers, width, g_dim, hidden=64):
    keys = jax.random.split(key, 2 + 2 * layers)
    glorot = jax.nn.initializers.glorot_normal()
    p = {"B": glorot(keys[0], (9, width)), "C": 0.1 * glorot(keys[1], (width, 3)), "A": []}
    for l in range(layers):
        p["A"].append({"w1": glorot(keys[2 + 2 * l], (g_dim, hidden)), "b1": jnp.zeros(hidden),
                       "w2": 0.1 * glorot(keys[3 + 2 * l], (hidden, width * width)), "b2": jnp.zeros(width * width)})
    return p


def apply(p, x, g, s, r):
    """Δu beyond u + Δt v, [batch, nodes, 3], for standardised inputs x [batch, nodes, 9]; linear in x."""
    width = p["B"].shape[1]
    h = x @ p["B"]
    for a in p["A"]:
        A = (jnp.tanh(g @ a["w1"] + a["b1"]) @ a["w2"] + a["b2"]).reshape(-1, width, width)
        msg = jnp.einsum("eab,neb->nea", A, h[:, s])
        h = h + jnp.zeros_like(h).at[:, r].add(msg)
    return h @ p["C"]


def main(argv=None) -> int:
    import optax

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=4)
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--noise", type=float, default=0.0, help="input noise in feature stds (a ridge, for stability)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--per-sample", action="store_true",
                    help="divide each transition's inputs and target by its target's norm (the map is linear, so "
                         "this only weights the loss: every transition counts alike, as in a relative error)")
    args = ap.parse_args(argv)
    if min(args.layers, args.width, args.steps, args.batch) < 1 or not args.lr > 0 or args.noise < 0:
        raise SystemExit(f"--layers, --width, --steps, --batch must be positive, --lr > 0, --noise >= 0; got {vars(args)}")
    machine = describe()
    t0 = time.time()
    world = blf.linear_world()
    h = world["h"]
    step = blf.exact_step(world)
    f_te, _, f_tr = blf.split_forces(world)
    x, y = blf.transitions(*blf.roll(step, f_tr, h), f_tr)          # [S, dofs, 3], [S, dofs]
    n = x.shape[1] // 3
    scale = blf.kind_scale(x)
    target = (y - x[..., 0] - h * x[..., 1]).reshape(len(x), n, 3)
    t_scale = target.std()
    xs = (x.reshape(len(x), n, 3, 3) / scale).reshape(len(x), n, 9).astype(np.float32)
    ts = (target / t_scale).astype(np.float32)
    if args.per_sample:
        w = np.sqrt((ts ** 2).mean(axis=(1, 2), keepdims=True)) + 1e-6
        xs, ts = (xs / w).astype(np.float32), (ts / w).astype(np.float32)
    g, s, r = geometry(world)
    g, s, r = jnp.asarray(g), jnp.asarray(s), jnp.asarray(r)
    params = init(jax.random.PRNGKey(args.seed), args.layers, args.width, g.shape[1])
    sched = optax.cosine_decay_schedule(args.lr, args.steps, alpha=1e-2)
    opt = optax.adam(sched)
    state = opt.init(params)

    def loss_fn(p, xb, tb, key):
        xb = xb + args.noise * jax.random.normal(key, xb.shape)
        return jnp.mean((apply(p, xb, g, s, r) - tb) ** 2)

    @jax.jit
    def train_step(p, st, xb, tb, key):
        loss, grads = jax.value_and_grad(loss_fn)(p, xb, tb, key)
        upd, st = opt.update(grads, st, p)
        return optax.apply_updates(p, upd), st, loss

    rng = np.random.default_rng(args.seed)
    key = jax.random.PRNGKey(args.seed + 1)
    curve = []
    t_train = time.time()
    from tqdm import tqdm

    bar = tqdm(range(args.steps), desc="linear GNN", mininterval=5)
    for i in bar:
        b = rng.integers(0, len(xs), args.batch)
        key, sub = jax.random.split(key)
        params, state, loss = train_step(params, state, jnp.asarray(xs[b]), jnp.asarray(ts[b]), sub)
        if i % 100 == 0 or i == args.steps - 1:
            curve.append([i, float(loss)])
            bar.set_postfix(loss=f"{float(loss):.4g}")
    train_s = time.time() - t_train
    fwd = jax.jit(lambda p, xb: apply(p, xb, g, s, r))

    def model_step(u, v, f):
        xin = (np.stack([u, v, f], -1).reshape(len(u), n, 3, 3) / scale).reshape(len(u), n, 9)
        du = np.asarray(fwd(params, jnp.asarray(xin, jnp.float32)), np.float64).reshape(len(u), -1) * t_scale
        return u + h * v + du

    u_t, v_t = blf.roll(step, f_te, h)
    xt, yt = blf.transitions(u_t, v_t, f_te)
    one = float(np.linalg.norm(model_step(*np.moveaxis(xt, -1, 0)) - yt) / np.linalg.norm(yt))
    kin = float(np.linalg.norm(yt - xt[..., 0] - h * xt[..., 1]) / np.linalg.norm(yt))
    e_u, e_v = blf.rel_errors(*blf.roll(model_step, f_te, h), u_t, v_t)
    seen = rng.choice(len(f_tr), 20, replace=False)   # 20 training positions, scored the same way
    u_s, v_s = blf.roll(step, f_tr[seen], h)
    xs_, ys_ = blf.transitions(u_s, v_s, f_tr[seen])
    one_seen = float(np.linalg.norm(model_step(*np.moveaxis(xs_, -1, 0)) - ys_)
                     / np.linalg.norm(ys_ - xs_[..., 0] - h * xs_[..., 1]))
    seen_u, seen_v = blf.rel_errors(*blf.roll(model_step, f_tr[seen], h), u_s, v_s)
    radius = blf.spectral_radius(model_step, 3 * n, h, tol=1e-4, maxiter=3000)
    n_params = int(sum(np.size(a) for a in jax.tree_util.tree_leaves(params)))
    out = {"machine": machine, "args": vars(args), "params": n_params, "train_s": train_s, "curve": curve,
           "one_step_u": one, "one_step_of_kinematic_residual": one / kin, "rollout_u": e_u, "rollout_v": e_v,
           "spectral_radius": radius, "train_positions_one_step_of_kinematic_residual": one_seen,
           "train_positions_rollout_u": seen_u, "train_positions_rollout_v": seen_v, "total_s": time.time() - t0}
    RESULTS.mkdir(parents=True, exist_ok=True)
    tag = (f"{args.layers}x{args.width}" + (f"_noise{args.noise:g}" if args.noise else "")
           + ("_per-sample" if args.per_sample else ""))
    runs_path = RESULTS / "bunny_linear_gnn.json"
    runs = json.loads(runs_path.read_text()) if runs_path.exists() else {}
    runs[tag] = out
    runs_path.write_text(json.dumps(runs, indent=1))
    lines = ["# Bunny: a linear message-passing network with shared weights (probe)", "",
             "World, training positions (959) and held-out positions (81–100) as in `bunny_local_fit.md`; the "
             "network and its measures in the script's docstring. One-step: relative L2 error of u_{k+1} from the "
             "true held-out states (u_k + Δt v_k alone: "
             f"{kin:.4f}); rollout: relative L2 over each whole 20-frame rollout from rest, mean over the 20 cases.",
             "Training positions: the same measures on 20 of the positions trained on.",
             "", "| run | layers × width | parameters | noise | steps | training | one-step u | share of kinematic "
             "residual | radius | rollout u | rollout v | training positions: share / rollout u | machine |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for k, o in runs.items():
        a = o["args"]
        lines.append(f"| {k} | {a['layers']} × {a['width']} | {o['params']} | {a['noise']:g} | {a['steps']} | "
                     f"{o['train_s']:.0f} s | {o['one_step_u']:.5f} | {o['one_step_of_kinematic_residual']:.4f} | "
                     f"{o['spectral_radius']:.4f} | {o['rollout_u']:.4g} | {o['rollout_v']:.4g} | "
                     f"{o.get('train_positions_one_step_of_kinematic_residual', float('nan')):.4f} / "
                     f"{o.get('train_positions_rollout_u', float('nan')):.4g} | "
                     f"{o['machine']['cpu']}, load {o['machine']['load_average_1m']} |")
    (RESULTS / "bunny_linear_gnn.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
