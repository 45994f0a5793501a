"""A GENERIC model with thermodynamic stability built in: convex energy, concave entropy, static brackets.

``ModelConfig(convex=True)``. What the learned beams grew through (README, stability; ``growth_terms``) was
every state dependence the paper's model allows: L(z) turning with the state times a non-zero ∇E, M(z) doing
the same with ∇S, an entropy convex along a mode (so M∇²S amplifies) and an indefinite energy (so L∇²E has a
real eigenvalue above zero). This model closes each of those channels by construction:

* **Brackets from the rest mesh only.** L and M are functions of the weights, the node types and the rest
  geometry, never of the state. Both couple neighbouring nodes, as the canonical brackets of elastodynamics do:

      (L g)_i = L₀ g_i + (l_i − l_iᵀ) g_i + Σ_{j ~ i} C_ij g_j,   C_ij = F(X_j − X_i) − F(X_i − X_j)ᵀ,
      (M g)_i = m_i m_iᵀ g_i + Σ_{j ~ i} P_ij P_ijᵀ (g_i − g_j),

  with F (12×12) and P (12×r) small MLPs of the rest edge vector (P of its absolute components, so P_ij =
  P_ji), l_i, m_i decoded per node from its type and rest position, and L₀ the canonical q–v coupling of
  ``kinematic_prior``. Then C_ji = −C_ijᵀ, so L is skew-symmetric as a whole, and gᵀMg = m-terms + Σ over
  undirected edges |P_ijᵀ (g_i − g_j)|² ≥ 0, so M is symmetric positive semi-definite (a graph Laplacian with
  PSD edge weights: a viscosity on differences between neighbours). An edge block C can hold the discrete
  divergence/gradient pair that couples velocity and stress in linear elastodynamics.
* **Potentials convex / concave in the state.** Per node, features linear in the state,
  h_i = [x_i, Σ_j A(X_j − X_i)(x_j − x_i) / D] with x = (z − z_rest) / z_std (A: D×12 from an MLP of the
  rest edge vector, D the model width, D the graph's largest degree below the bar), feed an input-convex
  network φ (softplus layers, non-negative weights on the hidden path, biases from the node's type and rest
  position) plus a quadratic ½|Q h|²:

      E = ½|w_v|² + Σ_i [φ_E,i(h_i) − φ_E,i(0) − ∇φ_E,i(0)·h_i],
      S = −Σ_i [φ_S,i(h_i) − φ_S,i(0) − ∇φ_S,i(0)·h_i].

  A convex function of an affine map is convex, so E is convex and S concave in z, and their gradients vanish
  at rest: the rest state is E's minimum and S's maximum, and it is a fixed point of the unloaded step.
* **Forces through the port**: B f = g_i f_i in node i's velocity rows with a per-node gain (``force_term``).
* **Clamps as a projection**: the clamped nodes' q and v are prescribed, so both brackets act as P L P and
  P M P, with P zeroing those entries (rows and columns). Zeroing only the rows, as the plain model does,
  lets a clamped node's energy gradient (its reaction) drive the free entries through L, and the linearised
  step then need not keep the structure: a first convex model trained that way grew by 1.22 per step along a
  real eigenvalue at a clamped node's stress. With P on both sides the free block of the linearised rate is
  (P L P − P M P) ∇²F restricted to the free entries, whose eigenvalues have real part ≤ 0 for a convex F.

The rate is dz/dt = L∇E + M∇S + B f as in every model here, stepped by forward Euler, Heun or RK4
(``ModelConfig.integrator``). Linearised at
any state, L∇²E has imaginary eigenvalues (skew times PSD) and M∇²S real ones ≤ 0; what forward Euler's own
amplification of an undamped oscillation, √(1 + (ωΔt)²), leaves is for the learned dissipation to beat: no
term of the step's Jacobian can grow with the state's rotation of an operator. The degeneracy conditions are
still a loss (``rates`` reports L∇S and M∇E as for any model).

**The free-energy form** (``ModelConfig(convex=True, free_energy=True)``). A convex E, a concave S and static
brackets do not make the continuous dynamics stable by themselves: without degeneracy, L∇E + M∇S can have an
eigenvalue with positive real part (a 2×2 example: canonical L, E = ½(k q² + p²), M = 11ᵀ, S = −½(a q² + b p²)
with b > 1 + a/k). Under exact degeneracy (L∇S = M∇E = 0) GENERIC at a fixed temperature T reduces to
dz/dt = (L − M/T)∇F with the free energy F = E − T S, and that form needs no degeneracy to be stable:
dF/dt = −∇Fᵀ M ∇F / T + ∇Fᵀ B f. With ``free_energy`` the model learns F alone (the energy network, T = 1 in the
scaled units) and reports E = F, S = −F: the rate is L∇F − M∇F, the entropy production ∇Sᵀ(dw) = ∇FᵀM∇F ≥ 0
(before the clamped rows and the port), and the degeneracy residuals are not meaningful (E and S are not
separately identified; train with ``deg_weight=0``). Continuous-time stability is then built in: linearised at
rest, the rate's matrix (L − M)∇²F has eigenvalues with real part ≤ 0 (similar to ∇²F^½(L − M)∇²F^½, whose
symmetric part −∇²F^½ M ∇²F^½ is negative semi-definite). Whether a step keeps it is the integrator's business:
forward Euler amplifies every undamped oscillation by √(1 + (ωΔt)²) and overshoots any decay faster than
−2/Δt (the first such model trained, 64 wide, grew by 1.21 per step along a decay at λΔt ≈ −2.2), while RK4's
stability region holds the imaginary axis up to |ωΔt| < 2√2 and the real one down to −2.78, so with
``integrator="rk4"`` every rest mode within that range decays.

All state-independent arrays (the edge blocks, the per-node operators and biases, the rest gradients) are
computed once per mesh by ``static`` (``model.with_rest`` caches them in ``norm`` under ``convex_*`` keys), so a
step costs the linear features, two small per-node networks and one reverse pass through them.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax import model as M

EDGE_HIDDEN = 32     # width of the edge MLPs (F, P, A) and the node MLP
RANK = 6             # columns of an edge's dissipation factor P
CONTEXT = 5          # node context: type one-hot (2), rest position over its std (3)
GATES = 8            # basis blocks of the state-dependent edge blocks of L (``dynamic_l``)
STATIC_KEYS = ("convex_c", "convex_p", "convex_a", "convex_heads", "convex_bias", "convex_grad0", "convex_phi0")
DYNAMIC_KEYS = ("convex_basis_f", "convex_basis_b")   # with ``dynamic_l``: the bases at X_j − X_i and X_i − X_j


# --- parameters ----------------------------------------------------------------------------------------------

def _mlp_init(key, sizes, last_scale):
    keys = jax.random.split(key, len(sizes) - 1)
    out = {}
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        scale = (last_scale if i == len(sizes) - 2 else 1.0) / np.sqrt(a)
        out[f"layer{i}"] = {"w": jax.random.normal(keys[i], (a, b)) * scale, "b": jnp.zeros(b)}
    return out


def _mlp(p, x):
    n = len(p)
    for i in range(n):
        x = x @ p[f"layer{i}"]["w"] + p[f"layer{i}"]["b"]
        if i < n - 1:
            x = jax.nn.silu(x)
    return x


def _icnn_init(key, d_in, width, layers):
    keys = jax.random.split(key, 3 * layers + 2)
    p = {"w0": jax.random.normal(keys[0], (d_in, width)) / np.sqrt(d_in),
         "ctx0": jax.random.normal(keys[1], (CONTEXT, width)) * 0.1,
         "out": jnp.full((width,), -2.0),
         "q": jax.random.normal(keys[2], (d_in, d_in)) * (0.3 / np.sqrt(d_in))}
    for k in range(1, layers):
        p[f"u{k}"] = jax.random.normal(keys[3 * k], (width, width)) * 0.5 - 2.0
        p[f"v{k}"] = jax.random.normal(keys[3 * k + 1], (d_in, width)) / np.sqrt(d_in)
        p[f"ctx{k}"] = jax.random.normal(keys[3 * k + 2], (CONTEXT, width)) * 0.1
    return p


def feature_dim(config) -> int:
    return M.STATE_DIM + config.hidden


def init_weights(key, config) -> dict:
    """The parameters of a ``convex`` model (a plain dict of arrays, saved like a flax tree)."""
    check_config(config)
    d, width = config.hidden, config.hidden
    ks = jax.random.split(key, 8)
    return {
        **({} if config.free_energy else {"entropy": _icnn_init(ks[5], feature_dim(config), width, config.mlp_layers)}),
        "bracket": _mlp_init(ks[0], (4, EDGE_HIDDEN, EDGE_HIDDEN, M.STATE_DIM ** 2), 0.1),
        "dissipation": _mlp_init(ks[1], (4, EDGE_HIDDEN, EDGE_HIDDEN, M.STATE_DIM * RANK), 0.1),
        "features": _mlp_init(ks[2], (4, EDGE_HIDDEN, EDGE_HIDDEN, d * M.STATE_DIM), 1.0),
        "node": _mlp_init(ks[3], (CONTEXT, EDGE_HIDDEN, EDGE_HIDDEN, M.N_L + M.N_M + 1), 0.1),
        "energy": _icnn_init(ks[4], feature_dim(config), width, config.mlp_layers),
        **({"bracket_basis": _mlp_init(ks[6], (4, EDGE_HIDDEN, EDGE_HIDDEN, GATES * 6 * 3), 0.1),
            # zero last layer: an untrained dynamic_l model has the static brackets
            "bracket_gate": _mlp_init(ks[7], (4 + 2 * M.STATE_DIM, EDGE_HIDDEN, GATES), 0.0)}
           if config.dynamic_l else {}),
    }


_ARCHITECTURE_OPTIONS = ("edge_strain", "node_position", "exact_degeneracy", "global_pool", "kinematic_prior",
                         "edge_traction", "force_port", "load_context", "coarse_nodes", "coarse_mixing",
                         "rest_equilibrium", "node_embedding", "elastic_port", "port_hops", "frame_solve",
                         "linear_prior", "static_l")


def check_config(config) -> None:
    """A clear error for an option that a ``convex`` model does not combine with (it has its own brackets,
    features, port, kinetic term and rest equilibrium)."""
    on = [k for k in _ARCHITECTURE_OPTIONS if getattr(config, k)]
    if on:
        raise ValueError(f"convex=True does not combine with {', '.join(on)} (the convex model has its own "
                         "brackets, features, force port, kinetic term and rest equilibrium)")
    if config.free_energy and not config.convex:
        raise ValueError("free_energy=True needs convex=True")
    if config.dynamic_l and not config.free_energy:
        raise ValueError("dynamic_l=True needs convex=True and free_energy=True (only there is the free energy a "
                         "Lyapunov function whatever the skew L: with E and S apart a state-dependent L can grow)")
    if config.mlp_layers < 1 or config.hidden < 1:
        raise ValueError(f"convex needs hidden >= 1 and mlp_layers >= 1, got {config.hidden}, {config.mlp_layers}")


# --- static part: functions of the weights and the rest mesh ------------------------------------------------

def _geometry(topo):
    """Per slot [R,K,4]: (the rest edge vector X_j − X_i, its length) over the mean rest edge length; the same
    with the vector reversed; and with its absolute components (symmetric in i, j)."""
    if topo.dx0 is None or topo.x0 is None:
        raise ValueError("a convex model needs the rest mesh: build its Topology with q0")
    dx, ell, _ = M.scaled_rest_edges(topo)
    return (jnp.concatenate([dx, ell], -1), jnp.concatenate([-dx, ell], -1),
            jnp.concatenate([jnp.abs(dx), ell], -1))


def _context(norm, node_type, topo):
    one_hot = jax.nn.one_hot(node_type, 2, dtype=topo.x0.dtype)
    return jnp.concatenate([one_hot, (topo.x0 - norm["x0_mean"]) / norm["x0_std"]], axis=1)


def _icnn(p, bias, h):
    """φ(h) [N] per node: softplus layers, the hidden path through non-negative weights; bias [layers, N, W]."""
    width = p["w0"].shape[1]
    y = jax.nn.softplus(h @ p["w0"] + bias[0])
    for k in range(1, bias.shape[0]):
        y = jax.nn.softplus(y @ (jax.nn.softplus(p[f"u{k}"]) / width) + h @ p[f"v{k}"] + bias[k])
    return y @ (jax.nn.softplus(p["out"]) / width) + 0.5 * jnp.sum((h @ p["q"]) ** 2, axis=-1)


def _names(config):
    """The learned potentials: (energy, entropy), or the free energy alone with ``free_energy``."""
    return ("energy",) if config.free_energy else ("energy", "entropy")


def static(weights, config, norm, node_type, topo) -> dict:
    """The state-independent arrays of a ``convex`` model on this mesh (keys ``STATIC_KEYS``)."""
    signed, flipped, sym = _geometry(topo)
    r, k = topo.mask.shape
    n, d, s = M.STATE_DIM, config.hidden, RANK
    mask = topo.mask[..., None, None]
    forward = _mlp(weights["bracket"], signed).reshape(r, k, n, n)
    backward = _mlp(weights["bracket"], flipped).reshape(r, k, n, n)
    ctx = _context(norm, node_type, topo)
    names = _names(config)
    bias = jnp.stack([jnp.stack([ctx @ weights[pot][f"ctx{i}"] for i in range(config.mlp_layers)])
                      for pot in names])                                                  # [P, layers, N, W]
    zero = jnp.zeros((ctx.shape[0], feature_dim(config)), ctx.dtype)
    phi = lambda h: jnp.stack([_icnn(weights[pot], bias[i], h) for i, pot in enumerate(names)])
    phi0, pullback = jax.vjp(phi, zero)   # φ_n depends on h_n only: one cotangent per potential gives ∇φ_n(0)
    eye = jnp.eye(len(names), dtype=zero.dtype)
    (grad0,) = jax.vmap(pullback)(eye[:, :, None] * jnp.ones_like(phi0)[None])
    dynamic = {}
    if config.dynamic_l:
        basis = lambda g: _mlp(weights["bracket_basis"], g).reshape(r, k, GATES, 6, 3) * mask[..., None, :, :]
        dynamic = {"convex_basis_f": basis(signed), "convex_basis_b": basis(flipped)}
    return {
        **dynamic,
        "convex_c": (forward - jnp.swapaxes(backward, -1, -2)) * mask,
        "convex_p": _mlp(weights["dissipation"], sym).reshape(r, k, n, s) * mask,
        "convex_a": _mlp(weights["features"], signed).reshape(r, k, d, n) * mask / M.max_degree(topo),
        "convex_heads": _mlp(weights["node"], ctx),
        "convex_bias": bias,
        "convex_grad0": grad0,      # [P, N, F] ∇φ at h = 0
        "convex_phi0": phi0,        # [P, N]
    }


def _static(weights, config, norm, node_type, topo) -> dict:
    keys = STATIC_KEYS + (DYNAMIC_KEYS if config.dynamic_l else ())
    if all(key in norm for key in keys):
        return {key: norm[key] for key in keys}
    return static(weights, config, norm, node_type, topo)


# --- the state-dependent part ---------------------------------------------------------------------------------

def _deviation(norm, z, topo):
    """x [N,12]: the state's deviation from rest over z_std."""
    return (z - jnp.concatenate([topo.x0, jnp.zeros_like(z[:, 3:])], axis=1)) / norm["z_std"]


def features(st, norm, z, topo):
    """h [N, 12 + D]: the node's state deviation from rest over z_std and the A-weighted sum of its
    neighbours' differences (both linear in z)."""
    return _linear_features(st, _deviation(norm, z, topo), topo)


def _linear_features(st, x, topo):
    """h of a deviation x [N,12] (already over z_std): the linear map of ``features``."""
    diff = M.gather_neighbors(x, topo) - M.expand_rows(x, topo)[:, None, :]
    a = M.reduce_rows(jnp.einsum("rkdc,rkc->rd", st["convex_a"], diff), topo)
    return jnp.concatenate([x, a], axis=1)


def potentials(weights, config, st, norm, z, topo):
    """[2]: the total E (convex) and S (concave) at state z; with ``free_energy``, F and −F."""
    h = features(st, norm, z, topo)
    bias, grad0, phi0 = st["convex_bias"], st["convex_grad0"], st["convex_phi0"]
    shifted = [jnp.sum(_icnn(weights[pot], bias[i], h) - phi0[i] - jnp.sum(grad0[i] * h, axis=1))
               for i, pot in enumerate(_names(config))]
    e = shifted[0] + 0.5 * jnp.sum((z[:, 3:6] / M.state_scale(norm)[3:6]) ** 2)
    return jnp.stack([e, -e if config.free_energy else -shifted[1]])


def _port(st):
    """[N,1]: the force port's per-node column of the node heads (after the l and m entries)."""
    return st["convex_heads"][:, M.N_L + M.N_M:]


RELAX_ITERS = 12   # bisection steps of ``relaxation`` on (0, 1]: γ to 2⁻¹² of the step


def relaxation(weights, config, norm, z, f, dw, stages, node_type, topo):
    """γ ∈ [0, 1] [] of the limited relaxation step z + γ Δz (``ModelConfig.relaxation``).

    dw [N,12] is the step's scaled increment Σ b_i ΔW_i and ``stages`` the stages' ``_generic`` outputs (their
    ΔW_i and ∇_w F). With W = max(0, Σ b_i ∇F(Z_i)·B f), the forces' work over the step as the stages estimate
    it where it is positive (where it is negative, F must not rise: the stages of a step beyond the method's
    stability region are far from the path, and their estimate can be large either way),
    r(γ) = F(z + γΔz) − F(z) − γW is convex in γ with r(0) = 0, so its chord slope r(γ)/γ is non-decreasing and
    {γ > 0: r(γ) ≤ 0} is an interval (0, γ*]. Returns 1 when r(1) ≤ 0 (the step unchanged), else γ* from below
    by bisection (0 where r'(0) ≥ 0: no step along this direction obeys the inequality). The features are
    linear in z, so F along the line costs the per-node convex networks only; the change of F is summed node
    by node (not as a difference of two totals), and the kinetic term's change is exact."""
    st = _static(weights, config, norm, node_type, topo)
    scale = M.state_scale(norm)
    b = M.TABLEAUS[config.integrator][1]
    force = jnp.where(M.prescribed(node_type), 0.0, M.force_term(_port(st), f, norm))
    work = jnp.maximum(sum(c * jnp.sum(out[1] * force) for c, out in zip(b, stages)), 0.0)
    d = dw * scale
    h0, hd = features(st, norm, z, topo), _linear_features(st, d / norm["z_std"], topo)
    p, bias, grad0 = weights["energy"], st["convex_bias"][0], st["convex_grad0"][0]
    phi_0 = _icnn(p, bias, h0)
    w_v, d_v = z[:, 3:6] / scale[3:6], dw[:, 3:6]
    lin, quad = jnp.sum(w_v * d_v) - jnp.sum(grad0 * hd), 0.5 * jnp.sum(d_v ** 2)

    def slope(g):   # r(γ)/γ
        return jnp.sum(_icnn(p, bias, h0 + g * hd) - phi_0) / g + lin + g * quad - work

    def bisect(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        ok = slope(mid) <= 0
        return jnp.where(ok, mid, lo), jnp.where(ok, hi, mid)

    one = jnp.ones((), z.dtype)
    search = lambda: jax.lax.fori_loop(0, RELAX_ITERS, bisect, (jnp.zeros((), z.dtype), one))[0]
    return jax.lax.cond(slope(one) <= 0, lambda: one, search)


class Ops:
    """What the appliers need: the static arrays, the topology, the statistics (for L₀) and which state entries
    are prescribed. A convex model's ``model._potentials_and_grads`` hands it on twice, in the places of the
    plain model's (l, m) pair."""

    def __init__(self, st, topo, norm, node_type, dynamic=None):
        self.st, self.topo, self.norm = st, topo, norm
        self.dynamic = dynamic     # with dynamic_l: the state's stress–velocity edge blocks (``dynamic_blocks``)
        self.free = (~M.prescribed(node_type)).astype(norm["z_std"].dtype)
        self.l_mat, self.m_mat = M._matrices(st["convex_heads"][:, :M.N_L + M.N_M])


def potentials_and_grads(weights, config, norm, z, f, node_type, topo):
    """(∇_w E, ∇_w S [N,12], Ops, port [N,1]) as ``model._potentials_and_grads`` returns them."""
    st = _static(weights, config, norm, node_type, topo)
    _, pullback = jax.vjp(lambda z_: potentials(weights, config, st, norm, z_, topo), z)
    (grads,) = jax.vmap(pullback)(jnp.eye(2, dtype=z.dtype))
    scale = M.state_scale(norm)
    ops = Ops(st, topo, norm, node_type, dynamic_blocks(weights, st, norm, z, topo) if config.dynamic_l else None)
    return grads[0] * scale, grads[1] * scale, (ops, ops), _port(st)


def dynamic_blocks(weights, st, norm, z, topo):
    """With ``dynamic_l``, (D_f, D_b) [R,K,6,3] per edge slot: L's edge blocks at state z are the static C_ij
    plus E_ij − E_jiᵀ, where E_ij holds D_ij = Σ_a s_a(X_j − X_i, x_i, x_j) B_a(X_j − X_i) in its stress rows
    and velocity columns (D_f is D_ij, D_b is D_ji seen from slot ij), with the bases B_a (6×3) from the rest
    edge and the gates s_a from an MLP of the edge and both nodes' deviations from rest (``apply_l`` applies
    them). Swapping i and j gives minus the transpose, so L(z) is skew-symmetric at every state. The
    stress–velocity coupling is where the state enters the bracket of finite elasticity (the stress rate's
    rotation terms, Wσ − σW with W from the velocity gradient, and their transpose in the momentum balance);
    restricting the bases to it keeps the per-edge work at the static blocks' size."""
    signed, flipped, _ = _geometry(topo)
    x = _deviation(norm, z, topo)
    x_i = jnp.broadcast_to(M.expand_rows(x, topo)[:, None, :], topo.mask.shape + (M.STATE_DIM,))
    x_j = M.gather_neighbors(x, topo)
    gate_f = _mlp(weights["bracket_gate"], jnp.concatenate([signed, x_i, x_j], -1))
    gate_b = _mlp(weights["bracket_gate"], jnp.concatenate([flipped, x_j, x_i], -1))
    return (jnp.einsum("rkg,rkgij->rkij", gate_f, st["convex_basis_f"]),
            jnp.einsum("rkg,rkgij->rkij", gate_b, st["convex_basis_b"]))


def apply_l(ops: Ops, g):
    """L g [N,12]: canonical + per-node skew blocks + the skew edge blocks, applied as P L P with P the
    projection onto the evolved entries (module docstring: clamps as a projection)."""
    g = g * ops.free
    out = M._apply_l(ops.l_mat, g) + g @ M._canonical_matrix(ops.norm).T
    g_j = M.gather_neighbors(g, ops.topo)
    edge = jnp.einsum("rkij,rkj->ri", ops.st["convex_c"], g_j)
    if ops.dynamic is not None:   # σ_i ← D_f v_j and v_i ← −D_bᵀ σ_j
        d_f, d_b = ops.dynamic
        edge = (edge.at[:, 6:].add(jnp.einsum("rkij,rkj->ri", d_f, g_j[..., 3:6]))
                .at[:, 3:6].add(-jnp.einsum("rkji,rkj->ri", d_b, g_j[..., 6:])))
    return (out + M.reduce_rows(edge, ops.topo)) * ops.free


def apply_m(ops: Ops, g):
    """M g [N,12]: per-node m mᵀ + the edge Laplacian Σ_j P Pᵀ (g_i − g_j), applied as P M P."""
    g = g * ops.free
    p = ops.st["convex_p"]
    diff = M.expand_rows(g, ops.topo)[:, None, :] - M.gather_neighbors(g, ops.topo)
    edge = jnp.einsum("rkcs,rks->rc", p, jnp.einsum("rkcs,rkc->rks", p, diff))
    return (M._apply_m(ops.m_mat, g) + M.reduce_rows(edge, ops.topo)) * ops.free


def energy_entropy(weights, config, norm, z, node_type, topo):
    return potentials(weights, config, _static(weights, config, norm, node_type, topo), norm, z, topo)
