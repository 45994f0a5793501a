"""The thermodynamics-informed graph network: a GENERIC time step whose potentials and operators a graph network
decodes from the state.

This is the model of Hernández, Badías, Chinesta and Cueto, "Thermodynamics-informed graph neural networks",
IEEE Transactions on Artificial Intelligence (2022), arXiv:2203.01874. A body is a mesh of N nodes with the state
z = (q, v, σ) [N, 12] per node (position, velocity, Cauchy stress S11 S22 S33 S12 S13 S23). An encode-process-
decode graph network reads the state and the external nodal force f and decodes, per node i, an energy density
E_i, an entropy density S_i and the entries of two 12 × 12 matrices: l_i (strictly lower-triangular, 66 entries)
and m_i (lower-triangular, 78 entries). With L_i = l_i − l_iᵀ (skew-symmetric) and M_i = m_i m_iᵀ (symmetric
positive semi-definite) the state evolves by the GENERIC equation::

    dz/dt = L ∇E + M ∇S,      E = Σ_i E_i,   S = Σ_i S_i,

with ∇E, ∇S the gradients of the network's E and S with respect to the whole state (automatic differentiation
through the message passing; both from one reverse pass). The skew L conserves energy and the PSD M produces
entropy wherever the degeneracy conditions L ∇S = 0 and M ∇E = 0 hold; the network meets them as far as its
training penalises their residuals (`rates` returns them).

The operators act in scaled coordinates w = z / s, s = sqrt(dz_std · z_std) per feature (a diagonal change of
variables keeps L skew and M symmetric PSD), with the frame time step Δt absorbed into them, so one step is the
forward-Euler step of a frame::

    z_{k+1} = z_k + s ⊙ (L ∇_w E + M ∇_w S).

Clamped nodes (node_type ≠ 0) keep q and v (their rate is zero); their stress evolves like any other node's.

Network inputs, normalised by the training split's statistics (``norm``, from `tignn_jax.data.normalization`):
per node the velocity, the stress, a one-hot node type and the force f (which also enters every message-passing
update); per directed edge j → i the relative position q_j − q_i and its length, the relative velocity v_j − v_i
and the nine products (v_j − v_i) ⊗ (q_j − q_i) (whose sum over a node's edges estimates the velocity gradient).
Positions enter only through relative positions, so the model is invariant to translations of the body.

Edges are stored receiver-major in rows of K slots (`Topology`); the first layer of each edge MLP is computed in
node-level parts, so every matrix product acts on the N nodes and an edge costs a gather, an add and an
activation (`Network`).

Usage::

    model = GenericGNN(GNNConfig(hidden=64, passes=3))
    stored = model.init(jax.random.PRNGKey(0), norm, mesh)
    arrays = model.prepare(stored, mesh)
    z_next = jax.jit(GenericGNN.step_state, static_argnums=0)(model, arrays, z, f)
"""
from __future__ import annotations

import dataclasses
from functools import partial
from typing import Callable, ClassVar, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

STATE_DIM = 12
N_L = STATE_DIM * (STATE_DIM - 1) // 2   # 66 strictly-lower entries of l
N_M = STATE_DIM * (STATE_DIM + 1) // 2   # 78 lower entries of m
ACTIVATIONS = {"silu": nn.silu, "tanh": jnp.tanh, "softplus": nn.softplus, "gelu": nn.gelu}
NORM_KEYS = ("z_mean", "z_std", "dz_std", "f_std", "dq_std", "dv_std", "dqn_mean", "dqn_std")
MESH_KEYS = ("q0", "senders", "receivers", "node_type")
# edge features, in the order of the first edge layer's kernel rows: q_j − q_i (3), |q_j − q_i| (1),
# v_j − v_i (3), (v_j − v_i) ⊗ (q_j − q_i) (9, a-major)
EDGE_FEATURES = 16
# the kernel rows of the per-slot part of `EdgeInputs` (rest edge vector 0-2, length 3, products 7-15)
SLOT_COLUMNS = np.array([0, 1, 2, 3] + list(range(7, 16)), np.int32)
# the options of the research models whose files share this network (`GNNConfig.from_dict`) and the values
# that make them this model
PAPER_PATH = {"edge_velocity": True, "edge_strain": False, "node_position": False, "exact_degeneracy": False,
              "global_pool": False, "kinematic_prior": False, "edge_traction": False, "force_port": False,
              "load_context": False, "coarse_nodes": 0, "coarse_passes": 2, "coarse_mixing": False,
              "rest_equilibrium": False, "node_embedding": 0, "elastic_port": False, "port_hops": 0,
              "frame_solve": False, "linear_prior": False, "correction_scale": 0.01, "integrator": "euler",
              "static_l": False, "convex": False, "free_energy": False, "dynamic_l": False, "relaxation": False,
              "substeps": 1}
# options whose value does not matter while the option that uses them is off
_UNUSED_WHEN_OFF = {"coarse_passes": "coarse_nodes", "correction_scale": "linear_prior"}


class GNNConfig(NamedTuple):
    """The network's architecture.

    Attributes:
      hidden: width of every MLP layer and of the node latents.
      mlp_layers: Dense layers per MLP (the last one linear).
      passes: message-passing steps.
      activation: one of ``ACTIVATIONS``; a smooth one, since ∇E and ∇S are trained.
    """
    hidden: int = 64
    mlp_layers: int = 2
    passes: int = 3
    activation: str = "silu"

    def check(self) -> GNNConfig:
        """Returns the config unchanged.

        Raises:
          ValueError: naming the field and its value, for a width, depth or pass count that is not a positive
            integer, or an unknown activation.
        """
        for field in ("hidden", "mlp_layers", "passes"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{field} must be a positive integer, got {value!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {tuple(ACTIVATIONS)}, got {self.activation!r}")
        return self

    @classmethod
    def from_dict(cls, config: dict) -> GNNConfig:
        """The config of a dict of its fields, or of a model file's flat architecture record (that of the older
        `ModelConfig`, with the research options), checked.

        Raises:
          ValueError: an unknown key, or a research option set to a value other than this model's (``PAPER_PATH``):
            the file holds another model.
        """
        unknown = sorted(set(config) - set(cls._fields) - set(PAPER_PATH))
        if unknown:
            raise ValueError(f"unknown architecture options {unknown}")
        off = {k: v for k, v in config.items()
               if k in PAPER_PATH and v != PAPER_PATH[k] and not (k in _UNUSED_WHEN_OFF and not
                                                                  config.get(_UNUSED_WHEN_OFF[k]))}
        if off:
            raise ValueError(f"not a {GenericGNN.name} model: the options {off} differ from its {PAPER_PATH}")
        return cls(**{k: config[k] for k in cls._fields if k in config}).check()


class Topology(NamedTuple):
    """A mesh's directed edges (each mesh edge in both directions) in receiver-major rows of K slots.

    Built outside jit by `topology`. Every node owns at least one row; a node with more than K incoming edges owns
    extra rows, so K can be near the mean degree instead of the maximum. Rows 0..N-1 are the nodes' first rows;
    extra rows follow.

    Attributes:
      nbr: [R, K] int32, the sender of the row's k-th incoming edge (the row's own node in padding slots).
      mask: [R, K] float32, 1 for real edges, 0 for padding.
      rev: [R, K] int32, flat slot index r' K + k' of the reverse edge of slot (r, k).
      dx0: [R, K, 3] float32, the rest edge vector X_j − X_i (zero in padding), in length units.
      row_node: [R] int32, the node that owns each row.
      node_rows: [N, X] int32, each node's extra rows (R, a zero row, in padding; X = 0 when R = N).
      x0: [N, 3] float32, the rest positions X, in length units.
      degree_max: [] float32, the largest number of incoming edges of a node: the network's message scale, the
        same for every slot layout of the graph.
    """
    nbr: jax.Array
    mask: jax.Array
    rev: jax.Array
    dx0: jax.Array
    row_node: jax.Array
    node_rows: jax.Array
    x0: jax.Array
    degree_max: jax.Array


class EdgeInputs(NamedTuple):
    """The edge features in factored form: x_edge[r, k] = (lin[sender] − lin[receiver]) + slot[r, k], with slot
    placed in the feature columns ``SLOT_COLUMNS``.

    The features linear in q and v (q_j − q_i through the displacement u = q − X, and v_j − v_i) live at node level
    in ``lin``, so their share of the first edge layer rides on the gathers the layer does anyway; only the
    nonlinear features (the length, the products) and the rest edge vectors are per slot.

    Attributes:
      lin: [N, EDGE_FEATURES] node-level part.
      slot: [R, K, len(SLOT_COLUMNS)] per-slot part (zero in padding).
    """
    lin: jax.Array
    slot: jax.Array


class Rates(NamedTuple):
    """The GENERIC rate of one body with its parts, in scaled coordinates w = z / s, per frame.

    Attributes:
      dw: [N, 12] the step's increment L ∇E + M ∇S (clamped nodes' q, v rows zero).
      grad_e, grad_s: [N, 12] ∇_w E and ∇_w S.
      deg_l: [N, 12] the degeneracy residual L ∇S.
      deg_m: [N, 12] the degeneracy residual M ∇E.
      entropy_rate: [] ∇Sᵀ dw (≥ 0 where the degeneracy holds).
      dissipation: [] ∇Sᵀ M ∇S (≥ 0: M is PSD).
    """
    dw: jax.Array
    grad_e: jax.Array
    grad_s: jax.Array
    deg_l: jax.Array
    deg_m: jax.Array
    entropy_rate: jax.Array
    dissipation: jax.Array


@dataclasses.dataclass(frozen=True)
class GenericGNN:
    """The thermodynamics-informed graph network (module docstring) as a model class.

    Stored arrays (``stored``): ``weights``, the flax parameters of `Network`, and ``norm``, the training split's
    statistics (`tignn_jax.data.normalization`; the step reads ``NORM_KEYS``, the others are kept for the guards
    and provenance). ``prepare`` adds ``topo`` (the mesh's `Topology`) and ``node_type`` [N] int32.

    Raises:
      ValueError: for an invalid ``config`` (`GNNConfig.check`).
    """
    config: GNNConfig = GNNConfig()
    name: ClassVar[str] = "generic_gnn"

    def __post_init__(self):
        if not isinstance(self.config, GNNConfig):
            raise ValueError(f"config must be a GNNConfig, got {self.config!r}")
        self.config.check()

    def init(self, key: jax.Array, norm: dict, mesh: dict) -> dict:
        """The stored arrays of a new, untrained model.

        Args:
          key: PRNG key of the weights' initialisation.
          norm: the training split's statistics (`tignn_jax.data.normalization`), numpy or jax arrays.
          mesh: ``{"q0": [N, 3] rest positions, "senders": [E], "receivers": [E], "node_type": [N]}`` (numpy).

        Returns:
          ``{"weights": flax parameters, "norm": norm as float32 numpy arrays}``.
        """
        _check_norm(norm)
        topo = mesh_topology(mesh)
        jnorm = {k: jnp.asarray(v, jnp.float32) for k, v in norm.items()}
        weights = _initial_weights(self.config, key, jnorm, jnp.asarray(mesh["node_type"], jnp.int32), topo)
        return {"weights": weights, "norm": {k: np.asarray(v, np.float32) for k, v in norm.items()}}

    def prepare(self, stored: dict, mesh: dict) -> dict:
        """The arrays the step reads: ``weights`` and ``norm`` (jax arrays, ``norm`` in float32), ``topo`` (the
        mesh's `Topology`) and ``node_type`` [N] int32.

        Args:
          stored: ``{"weights", "norm"}`` as ``init`` or a model file gives them.
          mesh: as in ``init``.

        Raises:
          ValueError: a statistic or mesh entry is missing, or the weights do not have this config's parameter
            tree (names and shapes).
        """
        for key in ("weights", "norm"):
            if key not in stored:
                raise ValueError(f"a {self.name} model needs the stored arrays 'weights' and 'norm', missing {key!r}")
        _check_norm(stored["norm"])
        topo = mesh_topology(mesh)
        norm = {k: jnp.asarray(v, jnp.float32) for k, v in stored["norm"].items()}
        weights = jax.tree_util.tree_map(jnp.asarray, stored["weights"])
        node_type = jnp.asarray(mesh["node_type"], jnp.int32)
        self._check_weights(weights, norm, node_type, topo)
        return {"weights": weights, "norm": norm, "topo": topo, "node_type": node_type}

    def stored(self, arrays: dict) -> dict:
        """The arrays a model file keeps: ``{"weights", "norm"}`` as numpy arrays (``topo`` and ``node_type`` are
        derived from the mesh)."""
        return {"weights": jax.tree_util.tree_map(np.asarray, arrays["weights"]),
                "norm": {k: np.asarray(v) for k, v in arrays["norm"].items()}}

    def step_state(self, arrays: dict, z, f):
        """One frame of one body (forward Euler of the GENERIC rate).

        Args:
          arrays: from ``prepare``.
          z: [N, 12] state (q, v, σ) in the data's units.
          f: [N, 3] external nodal forces, constant during the frame.

        Returns:
          [N, 12] the state one frame later; clamped nodes keep q and v.
        """
        dw, _, _, _ = generic_rate(self.config, arrays, z, f.astype(z.dtype))
        return z + dw * state_scale(arrays["norm"])

    def rates(self, arrays: dict, z, f) -> Rates:
        """The GENERIC rate of state z [N, 12] under f [N, 3] with its gradients, degeneracy residuals and entropy
        production (`Rates`), for training and diagnostics; ``step_state`` skips the residuals."""
        dw, g_e, g_s, (l_mat, m_mat) = generic_rate(self.config, arrays, z, f.astype(z.dtype))
        m_s = apply_m(m_mat, g_s)
        return Rates(dw=dw, grad_e=g_e, grad_s=g_s, deg_l=apply_l(l_mat, g_s), deg_m=apply_m(m_mat, g_e),
                     entropy_rate=jnp.sum(g_s * dw), dissipation=jnp.sum(g_s * m_s))

    def diagnostics(self, arrays: dict, z, f, z_next) -> dict:
        """The structure of one step from z [N, 12] under f [N, 3] (``z_next`` is not needed: the rate is local):
        {"deg_l_rel", "deg_m_rel": ‖L∇S‖ and ‖M∇E‖ over ‖Δw‖, "entropy_rate": ∇Sᵀ Δw, "dissipation": ∇Sᵀ M ∇S}."""
        r = self.rates(arrays, z, f)
        size = jnp.linalg.norm(r.dw) + 1e-12
        return {"deg_l_rel": jnp.linalg.norm(r.deg_l) / size, "deg_m_rel": jnp.linalg.norm(r.deg_m) / size,
                "entropy_rate": r.entropy_rate, "dissipation": r.dissipation}

    def operators(self, arrays: dict, z, f):
        """Per-node L [N, 12, 12] (skew-symmetric) and M [N, 12, 12] (symmetric PSD) at state z [N, 12] under
        f [N, 3], in the scaled coordinates w = z / s."""
        _, _, (l_mat, m_mat) = potentials_and_grads(self.config, arrays, z, f.astype(z.dtype))
        return l_mat - jnp.swapaxes(l_mat, 1, 2), m_mat @ jnp.swapaxes(m_mat, 1, 2)

    def energy_entropy(self, arrays: dict, z, f):
        """[2]: the total energy E and entropy S of the body at state z [N, 12] under f [N, 3] (the potentials
        whose gradients with respect to w = z / s drive the step; in the network's units)."""
        es, _ = network_out(self.config, arrays, z, f.astype(z.dtype))
        return jnp.stack([es[:, 0].sum(), es[:, 1].sum()])

    def _check_weights(self, weights, norm, node_type, topo):
        z, f = rest_state(topo), jnp.zeros((topo.x0.shape[0], 3), jnp.float32)
        want = jax.eval_shape(lambda: Network(self.config).init(jax.random.PRNGKey(0), *inputs(
            norm, z, f, node_type, topo), topo)["params"])
        shapes = lambda tree: {"/".join(str(getattr(k, "key", k)) for k in path): tuple(np.shape(leaf))
                               for path, leaf in jax.tree_util.tree_leaves_with_path(tree)}
        have, need = shapes(weights), shapes(want)
        if have != need:
            diff = sorted(k for k in set(have) | set(need) if have.get(k) != need.get(k))
            raise ValueError(f"the weights do not fit {self.config}: parameters that differ (name: stored, "
                             f"expected) {[(k, have.get(k), need.get(k)) for k in diff[:6]]}")


@partial(jax.jit, static_argnums=0)
def _initial_weights(config: GNNConfig, key, norm: dict, node_type, topo: Topology):
    """`Network.init` at the rest state under zero force, compiled as one program (the same numbers as the eager
    init; XLA drops the forward pass, whose outputs are not used)."""
    z, f = rest_state(topo), jnp.zeros((topo.x0.shape[0], 3), jnp.float32)
    return Network(config).init(key, *inputs(norm, z, f, node_type, topo), topo)["params"]


def _check_norm(norm: dict) -> None:
    missing = [k for k in NORM_KEYS if k not in norm]
    if missing:
        raise ValueError(f"the statistics lack {missing} (compute them with tignn_jax.data.normalization)")


# --- the GENERIC rate ------------------------------------------------------------------------------------------

def state_scale(norm: dict):
    """s [12]: the per-feature scale of the GENERIC coordinates w = z / s, sqrt(dz_std · z_std)."""
    return jnp.sqrt(norm["dz_std"] * norm["z_std"])


def prescribed(node_type):
    """[N, 12] bool: the state entries that are prescribed rather than evolved, the clamped nodes' q and v."""
    return (jnp.asarray(node_type) != 0)[:, None] & (jnp.arange(STATE_DIM) < 6)[None, :]


def generic_rate(config: GNNConfig, arrays: dict, z, f):
    """(dw [N, 12], ∇_w E, ∇_w S, (l, m) [N, 12, 12]): the step's scaled increment L ∇E + M ∇S with the clamped
    nodes' q, v rows zeroed, the gradients, and the decoded matrices (L = l − lᵀ, M = m mᵀ)."""
    g_e, g_s, (l_mat, m_mat) = potentials_and_grads(config, arrays, z, f)
    dw = apply_l(l_mat, g_e) + apply_m(m_mat, g_s)
    dw = jnp.where(prescribed(arrays["node_type"]), 0.0, dw)
    return dw, g_e, g_s, (l_mat, m_mat)


def potentials_and_grads(config: GNNConfig, arrays: dict, z, f):
    """(∇_w E, ∇_w S [N, 12], (l, m) [N, 12, 12]) from one forward pass and one reverse pass vmapped over the two
    cotangents. The decoder's last layer is applied in two column blocks (E, S | l, m), so the reverse pass runs
    through the two potential columns only."""
    def potentials(z_):
        es, heads = network_out(config, arrays, z_, f)
        return jnp.stack([es[:, 0].sum(), es[:, 1].sum()]), heads

    _, pullback, heads = jax.vjp(potentials, z, has_aux=True)
    (grads,) = jax.vmap(pullback)(jnp.eye(2, dtype=z.dtype))
    scale = state_scale(arrays["norm"])
    return grads[0] * scale, grads[1] * scale, matrices(heads)


def network_out(config: GNNConfig, arrays: dict, z, f):
    """The decoder's outputs ([N, 2] E_i, S_i; [N, 66 + 78] the entries of l_i, then of m_i) at state z under f."""
    norm, topo = arrays["norm"], arrays["topo"]
    return Network(config).apply({"params": arrays["weights"]}, *inputs(norm, z, f, arrays["node_type"], topo),
                                 topo)


def matrices(heads):
    """heads [N, 66 + 78] → (l, m) [N, 12, 12]: strictly-lower l and lower m filled row-major from the entries."""
    n = heads.shape[0]
    padded = jnp.concatenate([jnp.zeros((n, 1), heads.dtype), heads], axis=1)
    l_mat = jnp.take(padded, _L_INDEX, axis=1).reshape(n, STATE_DIM, STATE_DIM)
    m_mat = jnp.take(padded, _M_INDEX, axis=1).reshape(n, STATE_DIM, STATE_DIM)
    return l_mat, m_mat


def apply_l(l_mat, g):
    """(l − lᵀ) g per node: l [N, 12, 12], g [N, 12] → [N, 12]."""
    return jnp.einsum("nij,nj->ni", l_mat, g) - jnp.einsum("nji,nj->ni", l_mat, g)


def apply_m(m_mat, g):
    """m mᵀ g per node: m [N, 12, 12], g [N, 12] → [N, 12]."""
    return jnp.einsum("nij,nj->ni", m_mat, jnp.einsum("nji,nj->ni", m_mat, g))


def _embedding(strict: bool, offset: int) -> np.ndarray:
    """For each of the 144 entries of a 12 × 12 matrix, its column in the zero-padded heads (0: the zero)."""
    rows, cols = np.tril_indices(STATE_DIM, k=-1 if strict else 0)
    index = np.zeros(STATE_DIM * STATE_DIM, np.int32)
    index[rows * STATE_DIM + cols] = offset + 1 + np.arange(len(rows))
    return index


_L_INDEX = _embedding(strict=True, offset=0)
_M_INDEX = _embedding(strict=False, offset=N_L)


# --- inputs ----------------------------------------------------------------------------------------------------

def rest_state(topo: Topology):
    """[N, 12] the rest state of the topology's mesh: q = X, v = 0, σ = 0 (float32)."""
    n = topo.x0.shape[0]
    return jnp.concatenate([topo.x0.astype(jnp.float32), jnp.zeros((n, STATE_DIM - 3), jnp.float32)], axis=1)


def inputs(norm: dict, z, f, node_type, topo: Topology):
    """(x_node [N, 14], `EdgeInputs`): what the network reads at state z [N, 12] under forces f [N, 3].

    x_node = ((v − v̄) / v_std, (σ − σ̄) / σ_std, one-hot node type (2), f / f_std); the force stays last, where
    every pass reads it."""
    v, sigma = z[:, 3:6], z[:, 6:]
    mean, std = norm["z_mean"], norm["z_std"]
    one_hot = jax.nn.one_hot(node_type, 2, dtype=z.dtype)
    x_node = jnp.concatenate([(v - mean[3:6]) / std[3:6], (sigma - mean[6:]) / std[6:], one_hot, f / norm["f_std"]],
                             axis=1)
    return x_node, edge_inputs(norm, z, topo)


def edge_inputs(norm: dict, z, topo: Topology) -> EdgeInputs:
    """The edge features of state z [N, 12] in factored form (`EdgeInputs`): (q_j − q_i) / dq_std,
    (|q_j − q_i| − dqn_mean) / dqn_std, (v_j − v_i) / dv_std and its products with (q_j − q_i) / dqn_mean.

    The position part is built from displacements u = q − X (q_j − q_i = (u_j − u_i) + (X_j − X_i), the rest edge
    vector a per-slot constant), so the difference of node values loses no precision to large coordinates."""
    q, v = z[:, :3], z[:, 3:6]
    n = q.shape[0]
    dq = gather_neighbors(q, topo) - expand_rows(q, topo)[:, None, :]
    pad = (1.0 - topo.mask)[..., None]
    length = jnp.sqrt(jnp.sum(dq * dq, axis=-1, keepdims=True) + pad)
    dv = (gather_neighbors(v, topo) - expand_rows(v, topo)[:, None, :]) / norm["dv_std"]
    dq_unit = dq / norm["dqn_mean"]
    # the nine products dv_a dq_b (a-major) as one broadcast, one kernel forward and one in the reverse pass
    products = (dv[..., :, None] * dq_unit[..., None, :]).reshape(dv.shape[:-1] + (9,))
    lin = [(q - topo.x0) / norm["dq_std"], jnp.zeros((n, 1), z.dtype), v / norm["dv_std"], jnp.zeros((n, 9), z.dtype)]
    slot = [topo.dx0 / norm["dq_std"], (length - norm["dqn_mean"]) / norm["dqn_std"], products]
    return EdgeInputs(jnp.concatenate(lin, axis=1), jnp.concatenate(slot, axis=-1) * topo.mask[..., None])


# --- the network -----------------------------------------------------------------------------------------------

class MLP(nn.Module):
    """Dense layers of width ``hidden`` with the activation between them; the last has ``out`` units and
    kernels drawn with variance ``out_scale``² / fan-in. With ``split`` = k the output is the pair (first k
    columns, the rest), two products with the column blocks of one layer's parameters."""
    hidden: int
    out: int
    layers: int
    activation: str
    out_scale: float = 1.0
    split: int = 0

    @nn.compact
    def __call__(self, x):
        act = ACTIVATIONS[self.activation]
        for _ in range(self.layers - 1):
            x = act(nn.Dense(self.hidden)(x))
        init = nn.initializers.variance_scaling(self.out_scale ** 2, "fan_in", "truncated_normal")
        if not self.split:
            return nn.Dense(self.out, kernel_init=init)(x)
        return SplitDense(self.out, self.split, kernel_init=init, name=f"Dense_{self.layers - 1}")(x)


class SplitDense(nn.Module):
    """A Dense layer (``kernel`` [in, features], ``bias`` [features], as ``nn.Dense``) whose output comes in two
    column blocks (first ``split`` | rest), each its own product."""
    features: int
    split: int
    kernel_init: Callable = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(self, x):
        kernel = self.param("kernel", self.kernel_init, (x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        k = self.split
        return x @ kernel[:, :k] + bias[:k], x @ kernel[:, k:] + bias[k:]


class DenseParams(nn.Module):
    """The parameters of an ``nn.Dense`` (same names, shapes and initialisers), returned instead of applied, for a
    layer whose product is computed in parts."""
    features: int
    inputs: int

    @nn.compact
    def __call__(self):
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (self.inputs, self.features))
        return kernel, self.param("bias", nn.initializers.zeros_init(), (self.features,))


class Network(nn.Module):
    """Encode-process-decode over one body's graph.

    Encoder: h = MLP(x_node). Each of the ``passes`` passes is a residual node update

        h_i ← h_i + φ([h_i, Σ_j ψ(x_ij, h_i, h_j) / D, f_i]),

    D the mesh's largest degree, with a one-hidden-layer edge MLP ψ = W₂ act(A x_ij + B h_j + C h_i + b). Its first
    layer is computed per operand: B h and C h once per node, then gathered, and A x_ij from `EdgeInputs` (the
    node-level part joins B h_j and C h_i before their gathers); the linear W₂ commutes with the sum over
    neighbours, so it is folded into φ's first layer. Decoder: an MLP to [N, 2 + 66 + 78] (E_i, S_i, l_i, m_i),
    its last layer initialised at a tenth of the usual scale.

    Parameter names (those of the model files): ``MLP_0`` the encoder, ``Dense_{3p}`` (A and b: ``kernel``
    [16, hidden], ``bias``), ``Dense_{3p+1}`` (B) and ``Dense_{3p+2}`` (C) of pass p, ``MLP_{p+1}`` its φ and
    ``MLP_{passes+1}`` the decoder; each MLP's layers are ``Dense_0``, ``Dense_1``, ...

    Returns:
      ([N, 2] E_i, S_i; [N, 66 + 78] the entries of l_i and m_i).
    """
    config: GNNConfig

    @nn.compact
    def __call__(self, x_node, edges: EdgeInputs, topo: Topology):
        c = self.config
        hid, act = c.hidden, ACTIVATIONS[c.activation]
        h = MLP(hid, hid, c.mlp_layers, c.activation)(x_node)
        f = x_node[:, -3:]
        mask = topo.mask[..., None]
        inv_k = (1.0 / topo.degree_max).astype(mask.dtype)
        first = [DenseParams(hid, EDGE_FEATURES, name=f"Dense_{3 * p}")() for p in range(c.passes)]
        for p in range(c.passes):
            kernel, bias = first[p]
            b_h = nn.Dense(hid, use_bias=False, name=f"Dense_{3 * p + 1}")(h)
            c_h = nn.Dense(hid, use_bias=False, name=f"Dense_{3 * p + 2}")(h)
            lin = edges.lin @ kernel
            a = gather_neighbors(b_h + lin, topo) + expand_rows(c_h - lin, topo)[:, None, :] \
                + edges.slot @ kernel[SLOT_COLUMNS] + bias
            msg = reduce_rows(jnp.sum(act(a) * mask, axis=1), topo) * inv_k
            h = h + MLP(hid, hid, c.mlp_layers, c.activation)(jnp.concatenate([h, msg, f], axis=1))
        return MLP(hid, 2 + N_L + N_M, c.mlp_layers, c.activation, out_scale=0.1, split=2)(h)


# --- the graph layout ------------------------------------------------------------------------------------------

def mesh_topology(mesh: dict) -> Topology:
    """The `Topology` of a mesh dict ``{"q0" [N, 3], "senders" [E], "receivers" [E], "node_type" [N]}`` (rest
    positions taken in float32, as a model file stores them).

    Raises:
      ValueError: a key is missing, or an edge lacks its reverse (see `topology`).
    """
    missing = [k for k in MESH_KEYS if k not in mesh]
    if missing:
        raise ValueError(f"the mesh lacks {missing} (needs {list(MESH_KEYS)})")
    q0 = np.asarray(mesh["q0"], np.float32)
    if len(np.asarray(mesh["node_type"]).reshape(-1)) != len(q0):
        raise ValueError(f"the mesh has {len(q0)} rest positions but {np.size(mesh['node_type'])} node types")
    return topology(mesh["senders"], mesh["receivers"], len(q0), q0)


def topology(senders, receivers, n_nodes: int, q0, slots: int | None = None) -> Topology:
    """The row/slot layout (`Topology`) of a graph whose edges come in both directions, built with numpy.

    Args:
      senders, receivers: [E] the directed edges j → i.
      n_nodes: N.
      q0: [N, 3] rest positions (length units).
      slots: K; by default the maximum degree or a power of two below it, whichever gives the least slot work
        (slots R·K plus half a slot per node and extra row, for the gather that sums a node's rows). Powers of two
        vectorise well, so an irregular mesh (a tet mesh) gets K near its mean degree and a few extra rows.

    Raises:
      ValueError: an edge lacks its reverse or appears twice, ``slots`` < 1, or q0 has the wrong shape.
    """
    senders, receivers = np.asarray(senders, np.int64), np.asarray(receivers, np.int64)
    order = np.lexsort((senders, receivers))
    s, r = senders[order], receivers[order]
    deg = np.bincount(r, minlength=n_nodes)
    k_max = max(int(deg.max()) if len(r) else 1, 1)
    if slots is None:
        candidates = {k_max} | {2 ** p for p in range(1, 8) if 2 ** p < k_max}
        cost = {k: int(np.sum(np.maximum(1, -(-deg // k)))) * k + n_nodes * int(np.max(-(-deg // k)) - 1) / 2
                for k in candidates}
        slots = min(cost, key=lambda k: (cost[k], -k))
    k_w = int(slots)
    if k_w < 1:
        raise ValueError(f"slots must be positive, got {slots}")
    q0 = np.asarray(q0, np.float64)
    if q0.shape != (n_nodes, 3):
        raise ValueError(f"q0 has shape {q0.shape}, expected ({n_nodes}, 3)")
    n_rows = np.maximum(1, -(-deg // k_w))
    extra = n_rows - 1
    extra_start = n_nodes + np.concatenate([[0], np.cumsum(extra)[:-1]])
    rank = np.arange(len(r)) - np.concatenate([[0], np.cumsum(deg)[:-1]])[r]   # position among r's edges
    chunk, slot = rank // k_w, rank % k_w
    row = np.where(chunk == 0, r, extra_start[r] + chunk - 1)
    total_rows = n_nodes + int(extra.sum())
    row_node = np.concatenate([np.arange(n_nodes), np.repeat(np.arange(n_nodes), extra)])
    nbr = np.tile(row_node[:, None], (1, k_w))
    mask = np.zeros((total_rows, k_w), np.float32)
    nbr[row, slot] = s
    mask[row, slot] = 1.0
    keys = r * n_nodes + s
    if len(np.unique(keys)) != len(keys):
        raise ValueError("graph has duplicate edges")
    lookup = dict(zip(keys.tolist(), (row * k_w + slot).tolist()))
    rev = np.zeros((total_rows, k_w), np.int64)
    try:
        rev[row, slot] = [lookup[int(a) * n_nodes + int(b)] for a, b in zip(s, r)]
    except KeyError as err:
        raise ValueError("graph edges must come in both directions (senders/receivers symmetric)") from err
    x_max = int(extra.max()) if n_nodes else 0
    node_rows = np.full((n_nodes, x_max), total_rows, np.int64)
    for x in range(x_max):
        has = extra > x
        node_rows[has, x] = extra_start[has] + x
    dx0 = (q0[nbr] - q0[row_node][:, None, :]) * mask[..., None]
    return Topology(jnp.asarray(nbr, jnp.int32), jnp.asarray(mask), jnp.asarray(rev, jnp.int32),
                    jnp.asarray(dx0, jnp.float32), jnp.asarray(row_node, jnp.int32),
                    jnp.asarray(node_rows, jnp.int32), jnp.asarray(q0, jnp.float32),
                    jnp.asarray(k_max, jnp.float32))


def _one_row_per_node(topo: Topology, n: int) -> bool:
    return topo.nbr.shape[0] == n


@jax.custom_vjp
def expand_rows(x, topo: Topology):
    """x [N, F] → [R, F]: each row gets its node's value (the identity when R = N)."""
    return x if _one_row_per_node(topo, x.shape[0]) else x[topo.row_node]


@jax.custom_vjp
def reduce_rows(y, topo: Topology):
    """The transpose of `expand_rows`: y [R, F] → [N, F], each node's rows summed (by gathers only)."""
    n = topo.node_rows.shape[0]
    if y.shape[0] == n:
        return y
    padded = jnp.concatenate([y, jnp.zeros((1,) + y.shape[1:], y.dtype)])
    return y[:n] + jnp.sum(padded[topo.node_rows], axis=1)


expand_rows.defvjp(lambda x, topo: (expand_rows(x, topo), topo),
                   lambda topo, ct: (reduce_rows(ct, topo), None))
reduce_rows.defvjp(lambda y, topo: (reduce_rows(y, topo), topo),
                   lambda topo, g: (expand_rows(g, topo), None))


@jax.custom_vjp
def gather_neighbors(x, topo: Topology):
    """x [N, F] → [R, K, F]: the sender's row for every incoming-edge slot (zero in padding).

    Its transpose is again a gather (through the reverse-edge index, `sum_reverse`), so gradients of any order
    avoid scatter-adds."""
    return x[topo.nbr] * topo.mask[..., None]


@jax.custom_vjp
def sum_reverse(ct, topo: Topology):
    """The transpose of `gather_neighbors`: ct [R, K, F] → [N, F], out[j] = Σ over the edges j → i of ct[slot]."""
    r, k, f = ct.shape
    per_row = jnp.sum(ct.reshape(r * k, f)[topo.rev] * topo.mask[..., None], axis=1)
    return reduce_rows(per_row, topo)


gather_neighbors.defvjp(lambda x, topo: (gather_neighbors(x, topo), topo),
                        lambda topo, ct: (sum_reverse(ct, topo), None))
sum_reverse.defvjp(lambda ct, topo: (sum_reverse(ct, topo), topo),
                   lambda topo, g: (gather_neighbors(g, topo), None))
