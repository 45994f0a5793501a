"""The thermodynamics-informed graph network: encode-process-decode with a GENERIC integrator.

Per node i the decoder gives an energy density E_i, an entropy density S_i and the entries of two 12x12
matrices: l_i (strictly lower-triangular, 66 entries) and m_i (lower-triangular, 78 entries). With
L_i = l_i - l_iᵀ (skew-symmetric) and M_i = m_i m_iᵀ (symmetric positive semi-definite), the state z
[N,12] evolves by the GENERIC equation

    dz/dt = L ∇E + M ∇S,   E = Σ_i E_i,  S = Σ_i S_i,

with ∇E, ∇S the gradients of the network's E and S with respect to the whole state z (automatic
differentiation through the message passing, both in one reverse pass). The operators are written in
scaled coordinates w = z / s, s = sqrt(dz_std · z_std) per feature (a diagonal change of variables keeps L
skew and M symmetric PSD), with the time step Δt absorbed, so one forward-Euler step is

    z_{k+1} = z_k + s ⊙ (L ∇_w E + M ∇_w S).

Clamped nodes (node_type 1) keep q and v (their rate is zeroed); their stress evolves like any other node's.
Inputs: node features v, sigma (normalised), node-type one-hot and the external force f (which enters every
node update); edge features q_i - q_j and its length (normalised), so ∇_q E comes only from relative positions.
"""
from __future__ import annotations

from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

STATE_DIM = 12
N_L = STATE_DIM * (STATE_DIM - 1) // 2   # 66 strictly-lower entries of l
N_M = STATE_DIM * (STATE_DIM + 1) // 2   # 78 lower entries of m
ACTIVATIONS = {"silu": nn.silu, "tanh": jnp.tanh, "softplus": nn.softplus, "gelu": nn.gelu}


class ModelConfig(NamedTuple):
    """Static architecture. hidden: width of every MLP layer and latent; mlp_layers: Dense layers per MLP
    (the last is linear); passes: message-passing steps; activation: a smooth one (∇E is trained);
    edge_velocity: add the edge features v_j − v_i and (v_j − v_i) ⊗ (q_j − q_i) (a node's sum of the latter
    is a velocity-gradient estimate, what stress rates depend on)."""
    hidden: int = 32
    mlp_layers: int = 2
    passes: int = 4
    activation: str = "silu"
    edge_velocity: bool = True


class Rates(NamedTuple):
    """Outputs of the GENERIC model for one graph, in scaled coordinates w = z / s (per step).

    dw: [N,12] increment (clamped q,v rows zero); grad_e, grad_s: [N,12] ∇_w E, ∇_w S;
    deg_l: [N,12] L ∇S; deg_m: [N,12] M ∇E (both zero for an exactly degenerate model);
    entropy_rate: [] ∇Sᵀ dw summed over free and clamped nodes (≥ 0 when degenerate)."""
    dw: jax.Array
    grad_e: jax.Array
    grad_s: jax.Array
    deg_l: jax.Array
    deg_m: jax.Array
    entropy_rate: jax.Array


def step_state(weights, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """One forward-Euler step: z [N,12], f [N,3] (force during the step), node_type [N] → z_next [N,12]."""
    dw, _, _, _ = _generic(weights, config, norm, z, f, node_type, topo)
    return z + dw * state_scale(norm)


def rates(weights, config: ModelConfig, norm: dict, z, f, node_type, topo) -> Rates:
    """The GENERIC increment with gradients, degeneracy residuals and entropy production (for training and
    evaluation; inference uses ``step_state``, which skips the residuals)."""
    dw, g_e, g_s, (l_mat, m_mat) = _generic(weights, config, norm, z, f, node_type, topo)
    deg_l = _apply_l(l_mat, g_s)
    deg_m = _apply_m(m_mat, g_e)
    return Rates(dw=dw, grad_e=g_e, grad_s=g_s, deg_l=deg_l, deg_m=deg_m, entropy_rate=jnp.sum(g_s * dw))


def operators(weights, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """Per-node L [N,12,12] (skew-symmetric) and M [N,12,12] (symmetric PSD) at state z."""
    _, _, (l_mat, m_mat) = _potentials_and_grads(weights, config, norm, z, f, node_type, topo)
    return l_mat - jnp.swapaxes(l_mat, 1, 2), m_mat @ jnp.swapaxes(m_mat, 1, 2)


def energy_entropy(weights, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """Total E and S [2] of the graph at state z (the potentials whose gradients drive the dynamics)."""
    out = _network_out(weights, config, norm, z, f, node_type, topo)
    return jnp.stack([out[:, 0].sum(), out[:, 1].sum()])


def init_weights(key, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """Flax parameters of the network for graphs like the example (z [N,12], f [N,3])."""
    x_node, x_edge = _features(norm, z, f, node_type, topo, config.edge_velocity)
    return Network(config).init(key, x_node, x_edge, topo)["params"]


def state_scale(norm: dict):
    """s [12]: the per-feature scale of the GENERIC coordinates w = z / s."""
    return jnp.sqrt(norm["dz_std"] * norm["z_std"])


def count_params(weights) -> int:
    return int(sum(np.size(x) for x in jax.tree_util.tree_leaves(weights)))


class Topology(NamedTuple):
    """A symmetric directed graph in receiver-major slots, built outside jit by ``topology``.

    nbr [N,K] int32: sender of node i's k-th incoming edge (i itself in padding slots); mask [N,K] float32: 1
    for real edges; rev [N,K] int32: flat slot index (j*K + k') of the reverse edge of slot (i,k)."""
    nbr: jax.Array
    mask: jax.Array
    rev: jax.Array


def topology(senders, receivers, n_nodes: int) -> Topology:
    """Slot layout of a graph whose edges come in both directions (each mesh edge twice), numpy → Topology.

    Raises ValueError when an edge lacks its reverse or appears twice."""
    senders, receivers = np.asarray(senders, np.int64), np.asarray(receivers, np.int64)
    order = np.lexsort((senders, receivers))
    s, r = senders[order], receivers[order]
    deg = np.bincount(r, minlength=n_nodes)
    k_max = max(int(deg.max()) if len(r) else 1, 1)
    start = np.concatenate([[0], np.cumsum(deg)[:-1]])
    slot = np.arange(len(r)) - start[r]
    nbr = np.tile(np.arange(n_nodes)[:, None], (1, k_max))
    mask = np.zeros((n_nodes, k_max), np.float32)
    nbr[r, slot] = s
    mask[r, slot] = 1.0
    keys = r * n_nodes + s
    if len(np.unique(keys)) != len(keys):
        raise ValueError("graph has duplicate edges")
    lookup = dict(zip(keys.tolist(), (r * k_max + slot).tolist()))
    rev = np.zeros((n_nodes, k_max), np.int64)
    try:
        rev[r, slot] = [lookup[int(a) * n_nodes + int(b)] for a, b in zip(s, r)]
    except KeyError as err:
        raise ValueError("graph edges must come in both directions (senders/receivers symmetric)") from err
    return Topology(jnp.asarray(nbr, jnp.int32), jnp.asarray(mask), jnp.asarray(rev, jnp.int32))


@jax.custom_vjp
def gather_neighbors(x, topo: Topology):
    """x [N,F] → [N,K,F]: the sender's row for every incoming-edge slot (zero in padding).

    Its transpose is again a gather (through the reverse-edge index), so gradients of any order avoid
    scatter-adds, which are slow on CPU."""
    return x[topo.nbr] * topo.mask[..., None]


def _gather_fwd(x, topo):
    return gather_neighbors(x, topo), topo


def _gather_bwd(topo, ct):
    return sum_reverse(ct, topo), None


@jax.custom_vjp
def sum_reverse(ct, topo: Topology):
    """The transpose of ``gather_neighbors``: ct [N,K,F] → [N,F], out[j] = Σ over edges j→i of ct[i, slot]."""
    n, k, f = ct.shape
    return jnp.sum(ct.reshape(n * k, f)[topo.rev] * topo.mask[..., None], axis=1)


def _sum_fwd(ct, topo):
    return sum_reverse(ct, topo), topo


def _sum_bwd(topo, g):
    return gather_neighbors(g, topo), None


gather_neighbors.defvjp(_gather_fwd, _gather_bwd)
sum_reverse.defvjp(_sum_fwd, _sum_bwd)


# --- internals -----------------------------------------------------------------------------------------------

def _generic(weights, config, norm, z, f, node_type, topo):
    g_e, g_s, (l_mat, m_mat) = _potentials_and_grads(weights, config, norm, z, f, node_type, topo)
    dw = _apply_l(l_mat, g_e) + _apply_m(m_mat, g_s)
    clamped = (node_type != 0)[:, None] & (jnp.arange(STATE_DIM) < 6)[None, :]
    dw = jnp.where(clamped, 0.0, dw)
    return dw, g_e, g_s, (l_mat, m_mat)


def _potentials_and_grads(weights, config, norm, z, f, node_type, topo):
    """∇_w E, ∇_w S [N,12] from one forward pass and one reverse pass vmapped over the two cotangents."""
    def potentials(z_):
        out = _network_out(weights, config, norm, z_, f, node_type, topo)
        return jnp.stack([out[:, 0].sum(), out[:, 1].sum()]), out[:, 2:]

    (_, pullback, heads) = jax.vjp(potentials, z, has_aux=True)
    (grads,) = jax.vmap(pullback)(jnp.eye(2, dtype=z.dtype))
    scale = state_scale(norm)
    n = z.shape[0]
    l_mat = (heads[:, :N_L] @ _L_EMBED).reshape(n, STATE_DIM, STATE_DIM)
    m_mat = (heads[:, N_L:] @ _M_EMBED).reshape(n, STATE_DIM, STATE_DIM)
    return grads[0] * scale, grads[1] * scale, (l_mat, m_mat)


def _apply_l(l_mat, g):
    """(l - lᵀ) g per node."""
    return jnp.einsum("nij,nj->ni", l_mat, g) - jnp.einsum("nji,nj->ni", l_mat, g)


def _apply_m(m_mat, g):
    """m mᵀ g per node."""
    return jnp.einsum("nij,nj->ni", m_mat, jnp.einsum("nji,nj->ni", m_mat, g))


def _embedding(strict: bool) -> jnp.ndarray:
    rows, cols = np.tril_indices(STATE_DIM, k=-1 if strict else 0)
    e = np.zeros((len(rows), STATE_DIM * STATE_DIM), np.float32)
    e[np.arange(len(rows)), rows * STATE_DIM + cols] = 1.0
    return jnp.asarray(e)


_L_EMBED = _embedding(strict=True)
_M_EMBED = _embedding(strict=False)


def _features(norm, z, f, node_type, topo, edge_velocity=False):
    q, v, sigma = z[:, :3], z[:, 3:6], z[:, 6:]
    mean, std = norm["z_mean"], norm["z_std"]
    one_hot = jax.nn.one_hot(node_type, 2, dtype=z.dtype)
    x_node = jnp.concatenate(
        [(v - mean[3:6]) / std[3:6], (sigma - mean[6:]) / std[6:], one_hot, f / norm["f_std"]], axis=1)
    dq = gather_neighbors(q, topo) - q[:, None, :]
    pad = (1.0 - topo.mask)[..., None]
    length = jnp.sqrt(jnp.sum(dq * dq, axis=-1, keepdims=True) + pad)
    parts = [dq / norm["dq_std"], (length - norm["dqn_mean"]) / norm["dqn_std"]]
    if edge_velocity:
        dv = (gather_neighbors(v, topo) - v[:, None, :]) / norm["dv_std"]
        parts += [dv, (dv[..., :, None] * (dq / norm["dqn_mean"])[..., None, :]).reshape(dv.shape[:2] + (9,))]
    x_edge = jnp.concatenate(parts, axis=-1)
    return x_node, x_edge * topo.mask[..., None]


def _network_out(weights, config, norm, z, f, node_type, topo):
    x_node, x_edge = _features(norm, z, f, node_type, topo, config.edge_velocity)
    return Network(config).apply({"params": weights}, x_node, x_edge, topo)


class MLP(nn.Module):
    """Dense layers of width ``hidden`` with the activation between them; the last layer has ``out`` units."""
    hidden: int
    out: int
    layers: int
    activation: str
    out_scale: float = 1.0

    @nn.compact
    def __call__(self, x):
        act = ACTIVATIONS[self.activation]
        for _ in range(self.layers - 1):
            x = act(nn.Dense(self.hidden)(x))
        init = nn.initializers.variance_scaling(self.out_scale ** 2, "fan_in", "truncated_normal")
        return nn.Dense(self.out, kernel_init=init)(x)


class Network(nn.Module):
    """Encode-process-decode. Returns [N, 2 + 66 + 78]: E_i, S_i, l_i entries, m_i entries.

    Each pass is a residual node update h ← h + φ([h, Σ_j ψ(x_ij, h_i, h_j) / K, f_i]) with a one-hidden-layer
    edge MLP ψ = W₂·act(A x_ij + B h_j + C h_i + b). Its first layer is split per operand: B h and C h are
    computed once per node and gathered (N products instead of E), and the linear W₂ commutes with the sum over
    neighbours, so it is folded into φ's first layer. An edge then costs one gather, an add and an activation;
    all matrix products act on the N nodes. Edges live in the receiver-major slots of ``topo`` ([N,K]); x_ij
    are the (normalised) edge features q_j − q_i and |q_j − q_i| (and, with ``edge_velocity``, v_j − v_i and
    its outer product with q_j − q_i)."""
    config: ModelConfig

    @nn.compact
    def __call__(self, x_node, x_edge, topo):
        c = self.config
        hid, act = c.hidden, ACTIVATIONS[c.activation]
        h = MLP(hid, hid, c.mlp_layers, c.activation)(x_node)
        f = x_node[:, -3:]
        mask = topo.mask[..., None]
        inv_k = 1.0 / topo.mask.shape[1]
        for _ in range(c.passes):
            a = nn.Dense(hid)(x_edge) + gather_neighbors(nn.Dense(hid, use_bias=False)(h), topo) \
                + nn.Dense(hid, use_bias=False)(h)[:, None, :]
            msg = jnp.sum(act(a) * mask, axis=1) * inv_k
            h = h + MLP(hid, hid, c.mlp_layers, c.activation)(jnp.concatenate([h, msg, f], axis=1))
        return MLP(hid, 2 + N_L + N_M, c.mlp_layers, c.activation, out_scale=0.1)(h)
