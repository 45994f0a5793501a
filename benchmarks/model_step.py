"""Step time of the GENERIC graph network on the beam mesh (756 nodes, 3960 edges), CPU.

Measures, after compilation, the median of repeated jit-compiled calls of
  * one inference step (forward + one reverse pass for ∇E and ∇S) for several sizes (hidden × passes);
  * the same step written the straightforward way (edge list with scatter-add aggregation, edge MLP on the
    concatenated [e, h_s, h_r], separate reverse passes for ∇E and ∇S) at the chosen size, for the ratio;
  * one training step per sample (loss with ∇E, ∇S, degeneracy residuals; its gradient) for both layouts.
Variants are measured round-robin in the same process so the shared machine's load hits all alike.
Writes benchmarks/results/model_step.{json,md}.

    python benchmarks/model_step.py [--repeats 50] [--sizes 16x2,24x3,32x4] [--chosen 24x3] [--model NAME]
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax import data as D
from tignn_jax import model as M
from tignn_jax import train as T

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import write_results  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


class EdgeListNetwork(nn.Module):
    """The same function as ``model.Network`` written the straightforward way: the edge MLP
    (Dense, act, Dense) runs on every edge of an edge list on the concatenated [x_ij, h_s, h_r], and messages
    are summed with a scatter-add (segment_sum)."""
    config: M.ModelConfig

    @nn.compact
    def __call__(self, x_node, x_edge, senders, receivers):
        c = self.config
        hid, act = c.hidden, M.ACTIVATIONS[c.activation]
        h = M.MLP(hid, hid, c.mlp_layers, c.activation)(x_node)
        f = x_node[:, -3:]
        n = x_node.shape[0]
        k = 6
        for _ in range(c.passes):
            m = nn.Dense(hid)(act(nn.Dense(hid)(jnp.concatenate([x_edge, h[senders], h[receivers]], axis=1))))
            msg = jax.ops.segment_sum(m, receivers, n) / k
            h = h + M.MLP(hid, hid, c.mlp_layers, c.activation)(jnp.concatenate([h, msg, f], axis=1))
        return M.MLP(hid, 2 + M.N_L + M.N_M, c.mlp_layers, c.activation, out_scale=0.1)(h)


def edge_list_features(norm, z, f, node_type, senders, receivers):
    q, v, sigma = z[:, :3], z[:, 3:6], z[:, 6:]
    mean, std = norm["z_mean"], norm["z_std"]
    x_node = jnp.concatenate([(v - mean[3:6]) / std[3:6], (sigma - mean[6:]) / std[6:],
                              jax.nn.one_hot(node_type, 2), f / norm["f_std"]], axis=1)
    dq = q[senders] - q[receivers]
    length = jnp.linalg.norm(dq, axis=1, keepdims=True)
    dv = (v[senders] - v[receivers]) / norm["dv_std"]
    grad = (dv[:, :, None] * (dq / norm["dqn_mean"])[:, None, :]).reshape(-1, 9)
    return x_node, jnp.concatenate([dq / norm["dq_std"], (length - norm["dqn_mean"]) / norm["dqn_std"], dv, grad],
                                   axis=1)


def _embedding(strict: bool) -> jnp.ndarray:
    """The entries → 12x12 matrix map as a 0/1 matrix [entries, 144] (the straightforward way: a matmul)."""
    rows, cols = np.tril_indices(12, k=-1 if strict else 0)
    e = np.zeros((len(rows), 144), np.float32)
    e[np.arange(len(rows)), rows * 12 + cols] = 1.0
    return jnp.asarray(e)


def edge_list_rates(weights, config, norm, z, f, node_type, senders, receivers):
    """Straightforward GENERIC increment: two separate reverse passes, dense L and M built per node."""
    net = EdgeListNetwork(config)

    def out(z_):
        return net.apply({"params": weights}, *edge_list_features(norm, z_, f, node_type, senders, receivers),
                         senders, receivers)

    g_e = jax.grad(lambda z_: out(z_)[:, 0].sum())(z)
    g_s = jax.grad(lambda z_: out(z_)[:, 1].sum())(z)
    heads = out(z)
    n = z.shape[0]
    scale = M.state_scale(norm)
    g_e, g_s = g_e * scale, g_s * scale
    l_mat = (heads[:, 2:2 + M.N_L] @ _embedding(strict=True)).reshape(n, 12, 12)
    m_mat = (heads[:, 2 + M.N_L:] @ _embedding(strict=False)).reshape(n, 12, 12)
    big_l = l_mat - jnp.swapaxes(l_mat, 1, 2)
    big_m = m_mat @ jnp.swapaxes(m_mat, 1, 2)
    dw = jnp.einsum("nij,nj->ni", big_l, g_e) + jnp.einsum("nij,nj->ni", big_m, g_s)
    clamped = (node_type != 0)[:, None] & (jnp.arange(12) < 6)[None, :]
    dw = jnp.where(clamped, 0.0, dw)
    return dw, jnp.einsum("nij,nj->ni", big_l, g_s), jnp.einsum("nij,nj->ni", big_m, g_e)


def assembled_step(weights, config, norm, node_type, topo):
    """A jit-compiled step of the shipped model with its edge features assembled per slot ([R,K,F] x_edge
    times the first edge layer, as before the factored form): the same function, for the speed ratio."""
    import contextlib

    def network_out(weights_, config_, norm_, z, f, nt, topo_, split=False):
        x_node, x_edge = M._features(norm_, z, f, nt, topo_, config_.edge_velocity, config_.edge_strain,
                                     config_.node_position, edge_traction=config_.edge_traction)
        es, heads = M.Network(config_).apply({"params": weights_}, x_node, x_edge, topo_,
                                             M._coarse_inputs(config_, norm_, z, topo_))
        return (es, heads) if split else jnp.concatenate([es, heads], axis=1)

    @contextlib.contextmanager
    def swapped():
        saved, M._network_out = M._network_out, network_out
        try:
            yield
        finally:
            M._network_out = saved

    fn = jax.jit(lambda z, f: M.step_state(weights, config, norm, z, f, node_type, topo))

    def call(z, f):
        with swapped():   # the swap matters while tracing (the first call); later calls reuse the trace
            return fn(z, f)
    return call


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--train-repeats", type=int, default=8)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--sizes", default="16x2,16x3,24x3,24x4,32x3,32x4,48x4,50x10")
    parser.add_argument("--chosen", default="24x3")
    parser.add_argument("--model", default="beam-abaqus", help="shipped model for the public api.step timing")
    args = parser.parse_args(argv)

    d = D.load(D.reference_path())
    rows = D.split_rows(d, "train")
    norm = {k: jnp.asarray(v) for k, v in D.normalization(d, rows).items()}
    nt = jnp.asarray(d.node_type, jnp.int32)
    s, r = jnp.asarray(d.edges[0]), jnp.asarray(d.edges[1])
    topo = M.topology(d.edges[0], d.edges[1], len(d.node_type), d.q0)
    z, f = jnp.asarray(d.z[rows[0], 10]), jnp.asarray(d.f[rows[0], 10])

    fns = {}
    for spec in args.sizes.split(","):
        h, p = map(int, spec.split("x"))
        cfg = M.ModelConfig(hidden=h, passes=p)
        w = M.init_weights(jax.random.PRNGKey(0), cfg, norm, z, f, nt, topo)
        fn = jax.jit(lambda w, z, f, cfg=cfg: M.step_state(w, cfg, norm, z, f, nt, topo))
        fns[f"slots {spec}"] = (fn, (w, z, f), M.count_params(w))
    h, p = map(int, args.chosen.split("x"))
    cfg = M.ModelConfig(hidden=h, passes=p)
    x_node, x_edge = edge_list_features(norm, z, f, nt, s, r)
    w_edge = EdgeListNetwork(cfg).init(jax.random.PRNGKey(0), x_node, x_edge, s, r)["params"]
    fn = jax.jit(lambda w, z, f: z + edge_list_rates(w, cfg, norm, z, f, nt, s, r)[0] * M.state_scale(norm))
    fns[f"edge-list {args.chosen}"] = (fn, (w_edge, z, f), M.count_params(w_edge))

    try:
        from tignn_jax import api
        from tignn_jax import graph as G
        params, _ = api.load_pretrained(args.model)
        graph = G.from_state(z, d.edges, d.node_type)
        f_np = np.asarray(f)
        fns[f"api.step {args.model} (validated)"] = (lambda p, g, fo: api.step(p, g, fo).nodes["z"],
                                                      (params, graph, f_np), M.count_params(params["weights"]))
    except ValueError as err:
        print(f"no shipped model timed: {err}")
    times = {k: [] for k in fns}
    for fn, a, _ in fns.values():
        jax.block_until_ready(fn(*a))
    for _ in range(args.repeats):
        for name, (fn, a, _) in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(*a))
            times[name].append(time.perf_counter() - t)

    # training step per sample, both layouts, chosen size
    b = args.batch
    batch = T.Batch(jnp.asarray(d.z[rows[:b], 10]), jnp.asarray(d.f[rows[:b], 10]), jnp.asarray(d.z[rows[:b], 11]))
    tcfg = T.TrainConfig(hidden=h, passes=p, batch_size=b)
    w_slots = fns[f"slots {args.chosen}"][1][0]
    slot_loss = jax.jit(jax.grad(lambda w: T.loss_fn(w, batch, jax.random.PRNGKey(0), norm, tcfg, nt, topo)[0]))

    def edge_loss(w):
        dw, dl, dm = jax.vmap(lambda z_, f_: edge_list_rates(w, cfg, norm, z_, f_, nt, s, r))(batch.z, batch.f)
        target = (batch.z_next - batch.z) / M.state_scale(norm)
        return jnp.mean((dw - target) ** 2) + jnp.mean(dl ** 2 + dm ** 2)

    edge_grad = jax.jit(jax.grad(edge_loss))
    train = {"train slots": (slot_loss, w_slots), "train edge-list": (edge_grad, w_edge)}
    ttimes = {k: [] for k in train}
    for fn, w in train.values():
        jax.block_until_ready(fn(w))
    for _ in range(args.train_repeats):
        for name, (fn, w) in train.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(w))
            ttimes[name].append((time.perf_counter() - t) / b)

    ms = lambda x: float(np.median(x) * 1e3)
    result = {
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "jax": jax.__version__, "backend": jax.default_backend(),
                    "load_avg_start": os.getloadavg()},
        "graph": {"nodes": int(len(d.node_type)), "edges": int(d.edges.shape[1]), "slots": list(topo.nbr.shape)},
        "step_ms": {k: {"p50": ms(v), "p90": float(np.percentile(v, 90) * 1e3), "params": fns[k][2]}
                    for k, v in times.items()},
        "train_ms_per_sample": {k: ms(v) for k, v in ttimes.items()},
        "repeats": args.repeats, "train_batch": b,
    }
    base = result["step_ms"][f"edge-list {args.chosen}"]["p50"]
    result["speedup_vs_edge_list"] = {
        "step": base / result["step_ms"][f"slots {args.chosen}"]["p50"],
        "train": result["train_ms_per_sample"]["train edge-list"] / result["train_ms_per_sample"]["train slots"]}
    lines = ["# Model step time (beam, 756 nodes, 3960 edges)", "",
             f"Machine: {result['machine']['processor']}, {result['machine']['cpus']} CPUs, jax "
             f"{jax.__version__} ({jax.default_backend()}); load average at start "
             f"{result['machine']['load_avg_start'][0]:.2f} (shared machine). Median of {args.repeats} calls "
             "after compilation, variants interleaved.", "",
             "| variant | params | step p50 (ms) | step p90 (ms) |", "|---|---|---|---|"]
    for k, v in result["step_ms"].items():
        lines.append(f"| {k} | {v['params']} | {v['p50']:.2f} | {v['p90']:.2f} |")
    lines += ["", f"Training step (loss with ∇E, ∇S and degeneracy residuals, and its gradient), batch {b}, "
              "per sample:", "", "| layout | ms per sample |", "|---|---|"]
    for k, v in result["train_ms_per_sample"].items():
        lines.append(f"| {k} | {v:.1f} |")
    lines += ["", f"Speed-up of the slot layout (gather-only, fused first edge layer, one reverse pass for ∇E and "
              f"∇S) over the straightforward edge-list version at {args.chosen}: step "
              f"{result['speedup_vs_edge_list']['step']:.2f}×, training {result['speedup_vs_edge_list']['train']:.2f}×."]
    write_results("model_step", result, "\n".join(lines) + "\n", RESULTS, echo=False)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
