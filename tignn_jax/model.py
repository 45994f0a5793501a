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

from tignn_jax import convex as CV
from tignn_jax import framesolve as FS

STATE_DIM = 12
N_L = STATE_DIM * (STATE_DIM - 1) // 2   # 66 strictly-lower entries of l
N_M = STATE_DIM * (STATE_DIM + 1) // 2   # 78 lower entries of m
ACTIVATIONS = {"silu": nn.silu, "tanh": jnp.tanh, "softplus": nn.softplus, "gelu": nn.gelu}


class ModelConfig(NamedTuple):
    """Static architecture. hidden: width of every MLP layer and latent; mlp_layers: Dense layers per MLP
    (the last is linear); passes: message-passing steps; activation: a smooth one (∇E is trained);
    edge_velocity: add the edge features v_j − v_i and (v_j − v_i) ⊗ (q_j − q_i) (a node's sum of the latter
    is a velocity-gradient estimate, what stress rates depend on); edge_strain: add (q_j − q_i) − (X_j − X_i)
    and the change of length; node_position: add the node's displacement q − X and rest position X (the
    model is bound to one mesh anyway; message passing alone only sees differences over a few hops, while the
    inertia of a body's global modes depends on its displacement field, which is not local);
    exact_degeneracy: apply L and M through per-node projections, L' = P_S L P_S and M' = P_E M P_E with
    P_g = I − ĝĝᵀ (ĝ = g / |g| for g = ∇S or ∇E at that node), so that L'∇S = 0 and M'∇E = 0 hold exactly
    instead of only as far as the loss enforces them: then dE = 0 and dS = ∇Sᵀ M' ∇S ≥ 0 per node (before the
    clamped rows are zeroed). L' stays skew-symmetric and M' symmetric PSD; global_pool: every pass also
    feeds each node a summary of its whole graph (the mean over the graph's nodes of a projection of the
    latents): one "virtual node" per body, so that information crosses a body in one step instead of one hop
    per pass (a point load on a nearly incompressible solid changes the pressure everywhere within a frame). Cost O(nodes · hidden) per pass; kinematic_prior: add to the learned
    L the canonical coupling of positions and velocities (L₀ with L₀_qv = −L₀_vqᵀ = c·I, c = Δt s_v / s_q in the
    scaled coordinates) and to E the kinetic term ½|w_v|² per node, so that an untrained model already moves
    q by Δt·v and the network's E acts on the velocities through −∇_q E (a learned potential's force); the
    learned l, m, E, S correct the rest. L = L₀ + l − lᵀ stays skew-symmetric. Needs ``norm["dt"]``;
    edge_traction: add the edge features σ_j·n and σ_i·n (n = (q_j − q_i) / mean edge length, σ the node's
    stress tensor over one scalar scale, so the features turn with the body): the tractions whose sum over a
    node's edges estimates the stress divergence, i.e. the internal force. A one-hidden-layer edge MLP of
    additive inputs can only approximate such products, and a narrow one poorly; force_port: the external
    force also acts directly on the velocities, dz/dt = L∇E + M∇S + B f with B f = g_i f_i / f_std in node i's
    velocity rows and g_i = softplus(a decoder output) ≥ 0 a learned per-node gain (an inverse mass): the
    open-system (port) form of GENERIC, so a point load moves its node from the first step instead of only
    through the network's reading of f (where the statistics hold ``port_gain``, g_i is measured in units of
    it and starts at 1: see ``force_term``); load_context: every node also reads where its body is loaded and how
    hard: the body's total force Σf / f_std and the vector from the node to the load centre (the |f|-weighted
    mean of the loaded nodes' rest positions, over x0_std; zero while the body is unloaded) with its length.
    These are functions of the forces and the rest mesh only, not of the state, so ∇E and ∇S keep their
    per-node form. Meant for a body whose far field moves in a pattern set by where a point load acts, which a
    few message passes cannot carry across it (a fingertip's position is known to the application anyway);
    on the bunny it turned the far field's motion towards the load's direction but did not make it fast
    enough (README, bunny session 8); coarse_nodes = C > 0: a second, coarse level of message passing (see
    ``coarse_graph``): the mesh is cut into C connected clusters of nodes, and in every pass the latents are
    averaged per cluster, passed ``coarse_passes`` times between neighbouring clusters (edge features: the
    difference of the clusters' mean displacements and their rest centres' offset) and handed back to every
    node of the cluster. A pass then carries information ~``coarse_passes`` cluster diameters instead of one
    edge: what a backward-Euler frame of a nearly incompressible body needs (its pressure answers a point
    load everywhere within the frame). The cluster means are linear in the state, so ∇E keeps its form (a
    coarse term's force is spread over its cluster's nodes); coarse_mixing: the coarse level also mixes all
    of a body's clusters at once (a learned dense map of the body's C·hidden cluster latents, then the
    activation, added to each cluster's latent) before its message passing: a mesh-specific global coupling
    (the model is bound to its mesh anyway) for bodies whose response to a load is a few global modes (on the
    implicit bunny data a ridge-regressed linear map from 8 clusters' mean u, v, f predicts 85 % of the variance
    of the velocity increment at held-out load positions); rest_equilibrium: the unloaded body at rest is an
    equilibrium by construction: E and S are replaced by E − g_E·w and S − g_S·w, with g_E, g_S the gradients
    at the rest state (q = X, v = σ = 0) under zero force, so ∇E = ∇S = 0 there and the step leaves it in place
    (the port term vanishes with the force). Still a GENERIC model (the shifted E, S are potentials; L, M are
    unchanged); no new weights. The rest gradients depend on the weights only: ``with_rest`` computes them once
    for inference (otherwise every call recomputes them, one more forward and reverse pass); node_embedding =
    D > 0: a learned vector of D numbers per mesh node (zero at initialisation), read by the node encoder
    beside the node's features. The model is bound to its mesh anyway; this lets it learn what the mesh's
    irregular geometry does to each node (its share of the mass and of the stiffness), which a smooth
    function of the rest position cannot: on the implicit bunny data at density 1e-3 the loaded node moves
    as a damped oscillator Δv = a f + b u + c v (per case R² 0.996), but a, b, c vary 2–4× between
    neighbouring load positions, and one shared fit explains 17 %. A node's vector is trained whenever the
    node moves in a training case (as a loaded node or as a neighbour of one); elastic_port (needs force_port
    and the statistics' ``spring_k``): the port also carries an internal force of the body's own, a network of
    springs along the mesh edges, dz/dt = L∇E + M∇S + B (f − ∇_q U) with U = ½ Σ_edges k_e (ℓ_e − ℓ⁰_e)² and
    the same per-node inverse mass B as the external force. The stiffness k_e = k₀ · softplus(ψ(x⁰_e)) / softplus(0)
    is a small MLP ψ of the edge's rest geometry (its length and the absolute values of its rest vector over
    the mean rest edge length: the same for both directions of an edge, so U is one potential), starting at
    k₀, the data's least-squares spring constant (see `data.normalization`). It is a function of q and the rest
    mesh only, so −∇_q U is a conservative force, and it enters the velocities at the physical size the port
    gives a force. Meant for a body whose loaded nodes must recoil: on the bunny the networks got a point
    load's push right but its recoil 4× short (README, sessions 11 and 13): a restoring force that must scale
    with the same inverse mass as the push, which L∇E has no reason to learn. Measured there (session 13, patch
    loads, 16-wide): val u 0.76 against 0.81 without it; free per-edge springs fitted by least squares explain
    65 % of the data's Δv/g − f on train cases and nothing on val, so springs are only a rough internal force;
    port_hops = H > 0 (needs
    force_port): the port's input map reaches H edges: B F = g ⊙ (F + P₁F + P₂P₁F + …) with each P_h a
    learned operator on the mesh edges, (P_h y)_i = Σ_j a_ij y_j + b_ij (ê_ij·y_j) ê_ij, whose coefficients
    a, b come from a small MLP of the edge's rest geometry (zero at initialisation: the plain port). A
    backward-Euler frame answers a force with (M/Δt + Δt K)⁻¹ F, which spreads it over a few edges within
    the frame (the implicit bunny at density 1e-3: 94 % of Δv within 3 edges of the load, and the network's
    first-frame response reached the load's neighbours at 0.5× and the next ring at 0.1–0.5×); P is a
    sparse approximate inverse of that operator, linear in F, so the port stays an input map. Measured there
    (session 13, with elastic_port, 16-wide): val u 0.70 against 0.76 with H = 0; the first-frame response two
    to three edges out reached with slope 0.60 (32-wide) against 0.12; frame_solve: step by a W-method whose
    Jacobian is the rest state's linear dynamics from the FEM, z_{k+1} = z_k + (I − Δt J₀)⁻¹ Δt F (see
    `tignn_jax.framesolve`): the network models the vector field F, the step answers it with the frame's
    non-local linear response (needs the rest linearisation in ``norm``, computed from the data file when
    training); linear_prior (needs frame_solve): F = J₀ z + B f + the network's GENERIC rate, so an untrained
    model is the FEM's linearised backward-Euler frame map and the network learns what the rest linearisation
    misses; correction_scale: with linear_prior, the initial scale of the decoder's output (the correction starts
    this small, so training starts from the prior's map). integrator: how a step answers the GENERIC rate F(z)
    without ``frame_solve``: "euler" (forward Euler, z + Δt F(z), the paper's), "heun" (the explicit trapezoidal
    rule, z + Δt/2 (F(z) + F(z + Δt F(z))): two network evaluations per step, second order) or "rk4" (the
    classical Runge-Kutta method: four evaluations, fourth order; its stability region reaches −2.78 on the
    real axis and ±2.83 on the imaginary one, where forward Euler's disk |1 + λΔt| ≤ 1 excludes every
    undamped oscillation and every decay faster than −2/Δt); a model must be
    trained with the integrator it is used with (training steps with it too); static_l: L is the one the network
    decodes at the rest state (q = X, v = σ = 0, no force), a function of the weights and the rest mesh only,
    instead of L(z) at the current state. Reason (measured on `beam-abaqus`, ``step_growth``): the growth of
    the forward-Euler step (1.89 per step at rest, 1.10–1.21 at loaded states) comes almost entirely from the
    term (∂L/∂z · δz) ∇E of the step's Jacobian, L's change with the state times the energy gradient, not from
    L ∇²E δz (whose eigenvalues are imaginary for a skew L and a convex E) nor from M. A state-independent L
    removes that term (the canonical Poisson bracket of elasticity is constant too). No new weights: a model
    trained with L(z) can be fine-tuned with it (``with_rest`` caches the rest L for inference). Measured
    (``step_growth_terms.md``, session 26): it is not a fix by itself. `beam-abaqus`'s weights with it grow
    1.12–1.19 but lose the dynamics (test u 0.92), and fine-tuned with it the network moved the growth into M
    (M∇²S 0.88 at rest with ``rest_equilibrium``: a learned entropy convex along the mode), its test rollouts
    blown up (relative errors ~1e6). No shipped model uses it; convex: thermodynamic stability built in
    (``tignn_jax.convex``): L and M static (from the rest mesh only) and coupling neighbouring nodes, E convex
    and S concave in the state (input-convex networks over features linear in z, with their minimum / maximum
    at rest), forces through a port. Uses ``hidden`` (the feature and network width), ``mlp_layers`` (the
    convex networks' depth) and ``integrator``; combined with any other architecture option it raises;
    free_energy (with convex): the free-energy form of GENERIC, dz/dt = (L − M)∇F + B f with one convex F
    (what GENERIC reduces to at a fixed temperature under exact degeneracy; stable in continuous time without
    a degeneracy loss, which it does not use: see ``tignn_jax.convex``); dynamic_l (with free_energy): L's edge
    blocks also depend on the two nodes' states through gated bases, skew at every state (the free energy
    stays a Lyapunov function, dF/dt = −∇FᵀM∇F + ∇Fᵀ B f, and at rest ∇F = 0 removes L's change from the
    linearisation), so the brackets can carry state-dependent couplings such as the rotation of the stress;
    relaxation (with free_energy): the relaxation Runge-Kutta step (Ketcheson
    2019; Ranocha et al. 2020) limited to γ ≤ 1, z + γ Δz with γ the largest value in (0, 1] for which the
    free energy obeys the discrete second law F(z + γΔz) ≤ F(z) + γ max(0, Σ b_i ∇F(Z_i)·B f) (no free energy
    beyond the forces' work as the stages estimate it). A step that already obeys it is the Runge-Kutta step
    unchanged; a step that would create free energy (a stiff mode outside the method's stability region) is
    shortened. With a convex F whose minimum is rest, the unloaded state then stays in the sublevel set of its
    initial free energy: bounded by construction (``tignn_jax.convex.relaxation``). Crediting the stages'
    estimated dissipation as well, as relaxation methods do, froze the trained beam after a release (the
    stiff stages promise dissipation the step does not deliver); where a stiff mode dominates, even this
    inequality can only be met by γ = 0, a frozen body, so ``substeps`` is what keeps the dynamics; substeps:
    the integrator's sub-steps per step (each of Δt / substeps, the network's rate unchanged): the step
    integrates the same learned vector field more finely, which brings stiff learned modes into the method's
    stability region (a model is trained with the sub-steps it is used with).
    """
    hidden: int = 32
    mlp_layers: int = 2
    passes: int = 4
    activation: str = "silu"
    edge_velocity: bool = True
    edge_strain: bool = False
    node_position: bool = False
    exact_degeneracy: bool = False
    global_pool: bool = False
    kinematic_prior: bool = False
    edge_traction: bool = False
    force_port: bool = False
    load_context: bool = False
    coarse_nodes: int = 0
    coarse_passes: int = 2
    coarse_mixing: bool = False
    rest_equilibrium: bool = False
    node_embedding: int = 0
    elastic_port: bool = False
    port_hops: int = 0
    frame_solve: bool = False
    linear_prior: bool = False
    correction_scale: float = 0.01
    integrator: str = "euler"
    static_l: bool = False
    convex: bool = False
    free_energy: bool = False
    dynamic_l: bool = False
    relaxation: bool = False
    substeps: int = 1


# explicit Runge-Kutta tableaus: stage i is evaluated at w + Σ_j a[i][j] Δw_j (a[0] is the start), the step's
# increment is Σ_i b[i] Δw_i (each Δw the rate's forward-Euler increment, Δt F, in scaled coordinates)
TABLEAUS = {
    "euler": ((), (1.0,)),
    "heun": (((1.0,),), (0.5, 0.5)),
    "rk4": (((0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)), (1 / 6, 1 / 3, 1 / 3, 1 / 6)),
}
INTEGRATORS = tuple(TABLEAUS)


def runge_kutta(integrator: str, rate, z, scale, bound=lambda dw: dw, substeps: int = 1, limit=None):
    """The explicit Runge-Kutta combination of ``integrator``'s stages over ``substeps`` equal sub-steps of the
    step: ``rate(z)`` returns a stage's output, a tuple whose first element is its scaled increment Δw over the
    whole step (``scale`` maps it to state units); ``bound`` is applied to each stage's and sub-step's increment
    before it moves the state (training with bptt bounds them); ``limit(z, dw, stages)`` (``relaxation``)
    returns a factor γ for each sub-step's increment dw given its stages' outputs.
    Returns (the step's scaled increment, the stages' outputs of every sub-step)."""
    a, b = TABLEAUS[integrator]
    h = 1.0 / substeps
    total, every = 0.0, []
    for _ in range(substeps):
        outs = [rate(z)]
        for row in a:
            shift = sum(c * bound(h * o[0]) for c, o in zip(row, outs) if c != 0.0)
            outs.append(rate(z + shift * scale))
        dw = h * sum(c * o[0] for c, o in zip(b, outs))
        if limit is not None:
            dw = dw * limit(z, dw, outs)
        if substeps > 1:
            dw = bound(dw)
            z = z + dw * scale
        total, every = total + dw, every + outs
    return total, every


def check_integrator(config: ModelConfig) -> None:
    """A clear error for an unknown integrator or one combined with ``frame_solve`` (its own integrator)."""
    if config.integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {config.integrator!r}")
    if config.integrator != "euler" and config.frame_solve:
        raise ValueError(f"integrator={config.integrator!r} with frame_solve: the W-method is the step's integrator")
    if not isinstance(config.substeps, int) or config.substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {config.substeps!r}")
    if config.substeps > 1 and config.frame_solve:
        raise ValueError(f"substeps={config.substeps} with frame_solve: the W-method takes the whole step")
    if config.relaxation and not (config.convex and config.free_energy):
        raise ValueError("relaxation=True needs convex=True and free_energy=True (got convex="
                         f"{config.convex}, free_energy={config.free_energy}): it limits the step by the learned "
                         "free energy, which only that model has")


SPRING_HIDDEN = 16     # width of elastic_port's stiffness MLP ψ
LOAD_CONTEXT_DIM = 7   # Σf (3), load centre − X (3), its length (1)


class Rates(NamedTuple):
    """Outputs of the GENERIC model for one graph, in scaled coordinates w = z / s (per step).

    dw: [N,12] increment (clamped q,v rows zero); grad_e, grad_s: [N,12] ∇_w E, ∇_w S;
    deg_l: [N,12] L ∇S; deg_m: [N,12] M ∇E (both zero for an exactly degenerate model);
    entropy_rate: [] ∇Sᵀ dw summed over free and clamped nodes (≥ 0 when degenerate);
    dissipation: [] ∇Sᵀ M ∇S (≥ 0: M is PSD)."""
    dw: jax.Array
    grad_e: jax.Array
    grad_s: jax.Array
    deg_l: jax.Array
    deg_m: jax.Array
    entropy_rate: jax.Array
    dissipation: jax.Array


def step_state(weights, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """One step (forward Euler, Heun or classical Runge-Kutta, see ``ModelConfig.integrator``, or the W-method
    of ``frame_solve``): z [N,12], f [N,3] (force during the step), node_type [N] → z_next [N,12]."""
    dw, _ = runge_kutta(config.integrator, lambda x: _generic(weights, config, norm, x, f, node_type, topo), z,
                        state_scale(norm), substeps=config.substeps, limit=relaxation_limit(weights, config, norm, f,
                                                                                            node_type, topo))
    return z + increment(config, norm, dw, z, f, node_type, topo)


def relaxation_limit(weights, config: ModelConfig, norm: dict, f, node_type, topo):
    """``runge_kutta``'s ``limit`` for a model with ``relaxation`` (None otherwise): each sub-step's γ from
    ``convex.relaxation``, with the forces' work over that sub-step."""
    if not config.relaxation:
        return None
    h = 1.0 / config.substeps
    return lambda z, dw, stages: CV.relaxation(weights, config, norm, z, h * f, dw, stages, node_type, topo)


def increment(config: ModelConfig, norm: dict, dw, z, f, node_type, topo):
    """The state increment [N,12] of a step from z under f whose network increment is ``dw`` (the GENERIC
    rate's forward-Euler increment in scaled coordinates): dw · s, or with ``frame_solve`` the W-method's
    W⁻¹(dw · s), to which ``linear_prior`` adds the rest linearisation's rate inside the solve."""
    e = dw * state_scale(norm)
    if config.linear_prior:
        return FS.prior_step(norm, z, f, e, node_type, topo.x0)
    return FS.solve(norm, e, node_type) if config.frame_solve else e


def rates(weights, config: ModelConfig, norm: dict, z, f, node_type, topo) -> Rates:
    """The GENERIC increment with gradients, degeneracy residuals and entropy production (for training and
    evaluation; inference uses ``step_state``, which skips the residuals)."""
    dw, g_e, g_s, (l_mat, m_mat) = _generic(weights, config, norm, z, f, node_type, topo)
    apply_l, apply_m = _appliers(config, norm, g_e, g_s)
    deg_l = apply_l(l_mat, g_s)
    m_s = apply_m(m_mat, g_s)
    return Rates(dw=dw, grad_e=g_e, grad_s=g_s, deg_l=deg_l, deg_m=apply_m(m_mat, g_e),
                 entropy_rate=jnp.sum(g_s * dw), dissipation=jnp.sum(g_s * m_s))


def operators(weights, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """Per-node L [N,12,12] (skew-symmetric) and M [N,12,12] (symmetric PSD) at state z (projected when
    ``config.exact_degeneracy``). A ``convex`` model's operators also couple neighbouring nodes: see
    ``dense_operators``."""
    if config.convex:
        raise ValueError("a convex model's L and M couple neighbouring nodes, so they have no per-node form; "
                         "use dense_operators")
    g_e, g_s, (l_mat, m_mat), _ = _potentials_and_grads(weights, config, norm, z, f, node_type, topo)
    l_op, m_op = l_mat - jnp.swapaxes(l_mat, 1, 2), m_mat @ jnp.swapaxes(m_mat, 1, 2)
    if config.kinematic_prior:
        l_op = l_op + _canonical_matrix(norm)
    if config.exact_degeneracy:
        p_s, p_e = _projector(g_s), _projector(g_e)
        l_op, m_op = p_s @ l_op @ p_s, p_e @ m_op @ p_e
    return l_op, m_op


def dense_operators(weights, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """The whole graph's L and M [N·12, N·12] at state z, in the scaled coordinates (node-major), by applying
    the model's operators to every unit vector: for tests and diagnostics on small meshes."""
    g_e, g_s, (l_mat, m_mat), _ = _potentials_and_grads(weights, config, norm, z, f, node_type, topo)
    apply_l, apply_m = _appliers(config, norm, g_e, g_s)
    n = z.shape[0] * STATE_DIM
    basis = jnp.eye(n, dtype=z.dtype).reshape(n, -1, STATE_DIM)
    cols = lambda apply, ops: jax.vmap(lambda e: apply(ops, e).reshape(-1))(basis).T
    return cols(apply_l, l_mat), cols(apply_m, m_mat)


def energy_entropy(weights, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """Total E and S [2] of the graph at state z (the potentials whose gradients drive the dynamics)."""
    if config.convex:
        return CV.energy_entropy(weights, config, norm, z, node_type, topo)
    out = _network_out(weights, config, norm, z, f, node_type, topo)
    e, s_ = out[:, 0].sum(), out[:, 1].sum()
    if config.kinematic_prior:
        e = e + 0.5 * jnp.sum((z[:, 3:6] / state_scale(norm)[3:6]) ** 2)
    if config.rest_equilibrium:
        rest, w = _rest(weights, config, norm, node_type, topo), z / state_scale(norm)
        e, s_ = e - jnp.sum(rest[0] * w), s_ - jnp.sum(rest[1] * w)
    return jnp.stack([e, s_])


def rest_gradients(weights, config: ModelConfig, norm: dict, node_type, topo):
    """[2,N,12]: ∇_w E and ∇_w S of the unshifted network at the rest state (q = X, v = σ = 0) with zero force."""
    z, f = _rest_state(norm, topo, "rest_equilibrium")
    g_e, g_s, _, _ = _potentials_and_grads(weights, config._replace(rest_equilibrium=False), norm, z, f,
                                           node_type, topo)
    return jnp.stack([g_e, g_s])


def with_rest(weights, config: ModelConfig, norm: dict, node_type, topo) -> dict:
    """``norm`` with the model's constants of the rest mesh added, so that steps on this topology do not
    recompute them: the rest gradients of a ``rest_equilibrium`` model ("rest_grads"), ``elastic_port``'s edge
    stiffnesses ("spring_edges" [R,K]) and ``port_hops``' edge coefficients ("spread_edges" [H,R,K,2]). They
    depend on the weights and the rest mesh only; ``norm`` is unchanged for models without these options."""
    extra = {}
    if config.convex:
        extra.update(CV.static(weights, config, norm, node_type, topo))
    if config.rest_equilibrium:
        extra["rest_grads"] = rest_gradients(weights, config, norm, node_type, topo)
    if config.force_port and config.elastic_port:
        extra["spring_edges"] = spring_stiffness(weights, norm, topo)
    if config.force_port and config.port_hops:
        extra["spread_edges"] = _spread_coefficients(weights, topo, config.port_hops)
    if config.static_l:
        extra["rest_l"] = rest_l_entries(weights, config, norm, node_type, topo)
    return {**norm, **extra} if extra else norm


def _rest(weights, config, norm, node_type, topo):
    rest = norm.get("rest_grads")
    return rest_gradients(weights, config, norm, node_type, topo) if rest is None else rest


def rest_l_entries(weights, config: ModelConfig, norm: dict, node_type, topo):
    """[N, 66]: the entries of l that the network decodes at the rest state (q = X, v = σ = 0) under zero force,
    ``static_l``'s state-independent L."""
    z, f = _rest_state(norm, topo, "static_l")
    _, heads = _network_out(weights, config, norm, z, f, node_type, topo, split=True)
    return heads[:, :N_L]


def _rest_state(norm: dict, topo, option: str):
    """(z [N,12], f [N,3]): the rest state (q = X, v = σ = 0) and zero force, in the precision the model runs in;
    ``option`` names the model option that needs it, for the error when the topology has no rest positions."""
    if topo.x0 is None:
        raise ValueError(f"{option} needs the rest positions: build the Topology with q0")
    n, dtype = topo.x0.shape[0], jnp.result_type(norm["z_mean"])
    z = jnp.concatenate([topo.x0.astype(dtype), jnp.zeros((n, STATE_DIM - 3), dtype)], axis=1)
    return z, jnp.zeros((n, 3), dtype)


def init_weights(key, config: ModelConfig, norm: dict, z, f, node_type, topo):
    """Flax parameters of the network for graphs like the example (z [N,12], f [N,3])."""
    if config.convex or config.free_energy:   # (free_energy alone: the convex module's error)
        return CV.init_weights(key, config)
    return Network(config).init(key, *_inputs(config, norm, z, f, node_type, topo), topo,
                                _coarse_inputs(config, norm, z, topo))["params"]


def state_scale(norm: dict):
    """s [12]: the per-feature scale of the GENERIC coordinates w = z / s."""
    return jnp.sqrt(norm["dz_std"] * norm["z_std"])


def count_params(weights) -> int:
    return int(sum(np.size(x) for x in jax.tree_util.tree_leaves(weights)))


class Topology(NamedTuple):
    """A symmetric directed graph in receiver-major rows of K slots, built outside jit by ``topology``.

    Every node owns at least one row; a node with more than K incoming edges owns extra rows (so K can be
    near the mean degree instead of the maximum: an irregular tet mesh wastes fewer padding slots). Rows
    0..N-1 are the nodes' first rows; extra rows follow.
    nbr [R,K] int32: sender of the row's k-th incoming edge (the row's node itself in padding slots);
    mask [R,K] float32: 1 for real edges; rev [R,K] int32: flat slot index (r'*K + k') of the reverse edge of
    slot (r,k); dx0 [R,K,3] float32: rest edge vector X_j − X_i (zero in padding; None without a rest mesh);
    row_node [R] int32: the node that owns each row; node_rows [N,X] int32: each node's extra rows (R = a
    zero row in padding; X = 0 when every node has one row, R = N); x0 [N,3] float32: rest positions (None
    without a rest mesh); member [G,N] float32: which of G disjoint graphs each node belongs to (None: one
    graph; set by ``tile_topology``, read by global pooling); degree_max [] float32: the largest number of
    incoming edges of a node (the same for every layout of the graph; the network's message scale);
    coarse: the ``CoarseGraph`` of the mesh's clusters (None unless built with ``coarse`` > 0)."""
    nbr: jax.Array
    mask: jax.Array
    rev: jax.Array
    dx0: jax.Array | None = None
    row_node: jax.Array | None = None
    node_rows: jax.Array | None = None
    x0: jax.Array | None = None
    member: jax.Array | None = None
    degree_max: jax.Array | None = None
    coarse: "CoarseGraph | None" = None


class CoarseGraph(NamedTuple):
    """Clusters of a mesh's nodes for coarse message passing (dense: C is small).

    assign [N,C] float32: 1 where node n belongs to cluster c (each node to one); pool [C,N] float32: the
    cluster means (assignᵀ over the cluster sizes); adj [C,C] float32: 1 where two different clusters are joined
    by a mesh edge; dx0 [C,C,3] float32: rest centre of cluster j minus that of cluster i at [i, j] (zero
    where not adjacent); degree_max [] float32: the most neighbours of a cluster (the coarse message scale)."""
    assign: jax.Array
    pool: jax.Array
    adj: jax.Array
    dx0: jax.Array
    degree_max: jax.Array


def coarse_clusters(senders, receivers, q0, n_clusters: int) -> np.ndarray:
    """Cluster of every node [N] int: ``n_clusters`` seeds by farthest-point sampling in the distance along
    the mesh's edges (an unreached component counts as infinitely far, so every component gets a seed),
    each node joined to its nearest seed along the mesh. Deterministic (the first seed is node 0), and the
    clusters follow the mesh (two ears that touch in space but not in the mesh stay apart)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    q0 = np.asarray(q0, np.float64)
    n = len(q0)
    if not 1 <= int(n_clusters) <= n:
        raise ValueError(f"coarse_nodes must be between 1 and the {n} nodes of the mesh, got {n_clusters}")
    senders, receivers = np.asarray(senders, np.int64), np.asarray(receivers, np.int64)
    length = np.linalg.norm(q0[senders] - q0[receivers], axis=1) + 1e-12
    graph = csr_matrix((length, (senders, receivers)), shape=(n, n))
    dist = np.full(n, np.inf)
    nearest = np.zeros(n, np.int64)
    seed = 0
    for c in range(int(n_clusters)):
        d = dijkstra(graph, directed=False, indices=seed)
        closer = d < dist
        nearest[closer], dist[closer] = c, d[closer]
        seed = int(np.argmax(dist))   # the farthest node (an unreached component is at +inf)
    return nearest


def coarse_graph(senders, receivers, q0, n_clusters: int) -> CoarseGraph:
    """The ``CoarseGraph`` of ``coarse_clusters`` (numpy, outside jit)."""
    cluster = coarse_clusters(senders, receivers, q0, n_clusters)
    n, c = len(cluster), int(n_clusters)
    assign = np.zeros((n, c), np.float32)
    assign[np.arange(n), cluster] = 1.0
    size = assign.sum(0)
    if np.any(size == 0):
        raise ValueError(f"coarse_nodes {n_clusters}: {int(np.sum(size == 0))} clusters are empty")
    pool = assign.T / size[:, None]
    adj = np.zeros((c, c), np.float32)
    a, b = cluster[np.asarray(senders)], cluster[np.asarray(receivers)]
    adj[a[a != b], b[a != b]] = 1.0
    adj = np.maximum(adj, adj.T)
    centre = pool.astype(np.float64) @ np.asarray(q0, np.float64)
    dx0 = (centre[None, :, :] - centre[:, None, :]) * adj[..., None]
    return CoarseGraph(jnp.asarray(assign), jnp.asarray(pool, jnp.float32), jnp.asarray(adj),
                       jnp.asarray(dx0, jnp.float32), jnp.asarray(max(float(adj.sum(1).max()), 1.0), jnp.float32))


def tile_coarse(cg: CoarseGraph, copies: int) -> CoarseGraph:
    """The CoarseGraph of ``copies`` disjoint copies (block-diagonal)."""
    eye = np.eye(copies, dtype=np.float32)
    dx0 = np.asarray(cg.dx0)
    c = dx0.shape[0]
    tiled = np.zeros((copies * c, copies * c, 3), np.float32)
    for k in range(copies):
        tiled[k * c:(k + 1) * c, k * c:(k + 1) * c] = dx0
    return CoarseGraph(*(jnp.asarray(np.kron(eye, np.asarray(a))) for a in (cg.assign, cg.pool, cg.adj)),
                       jnp.asarray(tiled), cg.degree_max)


def model_topology(config: ModelConfig, senders, receivers, n_nodes: int, q0=None) -> Topology:
    """``topology`` with what ``config`` needs (the coarse clusters of ``config.coarse_nodes``)."""
    return topology(senders, receivers, n_nodes, q0, coarse=int(config.coarse_nodes))


def topology(senders, receivers, n_nodes: int, q0=None, slots: int | None = None, coarse: int = 0) -> Topology:
    """Row/slot layout of a graph whose edges come in both directions (each mesh edge twice), numpy → Topology.

    ``slots`` (K) defaults to the maximum degree or a power of two below it, whichever minimises the slot
    work (the maximum degree on a structured hex mesh, 4 on the bunny's tet mesh). With the rest positions
    ``q0`` [N,3] the rest edge vectors are stored too (needed by ``edge_strain``); ``coarse`` > 0 (needs q0)
    adds the ``coarse_graph`` of that many clusters. Raises ValueError when an edge lacks its reverse or
    appears twice."""
    senders, receivers = np.asarray(senders, np.int64), np.asarray(receivers, np.int64)
    order = np.lexsort((senders, receivers))
    s, r = senders[order], receivers[order]
    deg = np.bincount(r, minlength=n_nodes)
    k_max = max(int(deg.max()) if len(r) else 1, 1)
    if slots is None:   # slot work R·K plus half a slot per node and extra row (the gather that sums rows),
        # over K = the maximum degree and the powers of two below it: measured on this CPU, a power-of-two K
        # vectorises better than its neighbours (bunny 16x3 step, one core: K = 4 12.8 ms, 5 15.5, 6 15.8,
        # 8 14.0, 9 15.6, 13 16.8; beam: K = 6 = max degree 12.0, 4 13.3, 8 14.3)
        candidates = {k_max} | {2 ** p for p in range(1, 8) if 2 ** p < k_max}
        cost = {k: int(np.sum(np.maximum(1, -(-deg // k)))) * k + n_nodes * int(np.max(-(-deg // k)) - 1) / 2
                for k in candidates}
        slots = min(cost, key=lambda k: (cost[k], -k))
    k_w = int(slots)
    if k_w < 1:
        raise ValueError(f"slots must be positive, got {slots}")
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
    dx0 = x0 = None
    if q0 is not None:
        q0 = np.asarray(q0, np.float64)
        if q0.shape != (n_nodes, 3):
            raise ValueError(f"q0 has shape {q0.shape}, expected ({n_nodes}, 3)")
        dx0 = jnp.asarray((q0[nbr] - q0[row_node][:, None, :]) * mask[..., None], jnp.float32)
        x0 = jnp.asarray(q0, jnp.float32)
    cg = None
    if coarse:
        if q0 is None:
            raise ValueError("coarse clusters need the rest positions q0")
        cg = coarse_graph(senders, receivers, q0, int(coarse))
    return Topology(jnp.asarray(nbr, jnp.int32), jnp.asarray(mask), jnp.asarray(rev, jnp.int32), dx0,
                    jnp.asarray(row_node, jnp.int32), jnp.asarray(node_rows, jnp.int32), x0,
                    degree_max=jnp.asarray(k_max, jnp.float32), coarse=cg)


def tile_topology(topo: Topology, copies: int) -> Topology:
    """The Topology of ``copies`` disjoint copies of a graph (nodes of copy c offset by c·N), laid out so that
    the nodes' first rows still come first: [first rows of every copy, then the extra rows of every copy]."""
    if copies == 1:
        return topo
    nbr, mask, rev = (np.asarray(a) for a in (topo.nbr, topo.mask, topo.rev))
    rows, k_w = nbr.shape
    n = rows if topo.row_node is None else int(np.asarray(topo.node_rows).shape[0])
    e = rows - n
    c = np.arange(copies)[:, None]

    def new_row(r):   # [copies, ...] new index of old row r in each copy
        r = np.asarray(r)
        c_ = c.reshape((copies,) + (1,) * r.ndim)
        return np.where(r < n, c_ * n + r, copies * n + c_ * e + (r - n))

    def stack(a):     # per-row array [copies, R, ...] (or [R, ...], the same in every copy) → new row order
        a = np.asarray(a)
        if a.shape[:2] != (copies, rows):
            a = np.broadcast_to(a, (copies,) + a.shape)
        return np.concatenate([a[:, :n].reshape((-1,) + a.shape[2:]), a[:, n:].reshape((-1,) + a.shape[2:])])

    offsets = (c * n).reshape(copies, 1, 1)
    nbr_t = stack(nbr[None] + offsets)
    rev_t = stack(new_row(rev // k_w) * k_w + (rev % k_w)[None])
    row_node = np.arange(rows) if topo.row_node is None else np.asarray(topo.row_node)
    row_node_t = stack(row_node[None] + c * n)   # [copies, R]
    node_rows = np.asarray(topo.node_rows) if topo.node_rows is not None else np.zeros((n, 0), np.int64)
    padded = np.where(node_rows >= rows, copies * rows, new_row(np.minimum(node_rows, rows - 1)))
    node_rows_t = padded.reshape(copies * n, -1)
    dx0 = None if topo.dx0 is None else jnp.asarray(stack(np.asarray(topo.dx0)))
    x0 = None if topo.x0 is None else jnp.asarray(np.tile(np.asarray(topo.x0), (copies, 1)))
    if topo.member is not None:
        raise ValueError("tile_topology: the topology is already tiled; tile the single graph instead")
    member = np.kron(np.eye(copies, dtype=np.float32), np.ones((1, n), np.float32))
    return Topology(jnp.asarray(nbr_t, jnp.int32), jnp.asarray(stack(mask)), jnp.asarray(rev_t, jnp.int32), dx0,
                    jnp.asarray(row_node_t, jnp.int32), jnp.asarray(node_rows_t, jnp.int32), x0,
                    jnp.asarray(member), topo.degree_max,
                    None if topo.coarse is None else tile_coarse(topo.coarse, copies))


def max_degree(topo: Topology):
    """The largest number of incoming edges of a node (a scalar array, stored by ``topology``; the same for
    every row/slot layout of the graph). The network divides its message sums by it, a fixed scale that must
    not depend on the slot width."""
    return topo.degree_max


def _one_row_per_node(topo: Topology, n: int) -> bool:
    return topo.nbr.shape[0] == n


@jax.custom_vjp
def expand_rows(x, topo: Topology):
    """x [N,F] → [R,F]: each row gets its node's value (identity when R = N)."""
    return x if _one_row_per_node(topo, x.shape[0]) else x[topo.row_node]


@jax.custom_vjp
def reduce_rows(y, topo: Topology):
    """The transpose of ``expand_rows``: y [R,F] → [N,F], each node's rows summed (gathers only)."""
    n = topo.node_rows.shape[0] if topo.node_rows is not None else y.shape[0]
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
    """x [N,F] → [R,K,F]: the sender's row for every incoming-edge slot (zero in padding).

    Its transpose is again a gather (through the reverse-edge index), so gradients of any order avoid
    scatter-adds, which are slow on CPU."""
    return x[topo.nbr] * topo.mask[..., None]


def _gather_fwd(x, topo):
    return gather_neighbors(x, topo), topo


def _gather_bwd(topo, ct):
    return sum_reverse(ct, topo), None


@jax.custom_vjp
def sum_reverse(ct, topo: Topology):
    """The transpose of ``gather_neighbors``: ct [R,K,F] → [N,F], out[j] = Σ over edges j→i of ct[slot]."""
    r, k, f = ct.shape
    per_row = jnp.sum(ct.reshape(r * k, f)[topo.rev] * topo.mask[..., None], axis=1)
    return reduce_rows(per_row, topo)


def _sum_fwd(ct, topo):
    return sum_reverse(ct, topo), topo


def _sum_bwd(topo, g):
    return gather_neighbors(g, topo), None


gather_neighbors.defvjp(_gather_fwd, _gather_bwd)
sum_reverse.defvjp(_sum_fwd, _sum_bwd)


# --- internals -----------------------------------------------------------------------------------------------

def _generic(weights, config, norm, z, f, node_type, topo):
    g_e, g_s, (l_mat, m_mat), port = _potentials_and_grads(weights, config, norm, z, f, node_type, topo)
    apply_l, apply_m = _appliers(config, norm, g_e, g_s)
    dw = apply_l(l_mat, g_e) + apply_m(m_mat, g_s)
    if config.force_port or config.convex:
        if config.elastic_port:
            f = f + spring_force(weights, norm, z, topo)
        if config.port_hops:
            f = spread_forces(weights, f, topo, config.port_hops, norm.get("spread_edges"))
        dw = dw + force_term(port, f, norm)
    dw = jnp.where(prescribed(node_type), 0.0, dw)
    return dw, g_e, g_s, (l_mat, m_mat)


def prescribed(node_type):
    """[N,12] bool: the state entries that are prescribed rather than evolved, the clamped nodes' q and v."""
    return (jnp.asarray(node_type) != 0)[:, None] & (jnp.arange(STATE_DIM) < 6)[None, :]


def _potentials_and_grads(weights, config, norm, z, f, node_type, topo):
    """∇_w E, ∇_w S [N,12] from one forward pass and one reverse pass vmapped over the two cotangents.

    The decoder's last layer is applied in two parts (E, S columns | l, m columns) so the reverse pass only
    runs through the two potential columns; l and m are read out of the heads with a gather (no matmul)."""
    if config.convex:
        return CV.potentials_and_grads(weights, config, norm, z, f, node_type, topo)
    def potentials(z_):
        es, heads = _network_out(weights, config, norm, z_, f, node_type, topo, split=True)
        return jnp.stack([es[:, 0].sum(), es[:, 1].sum()]), heads

    (_, pullback, heads) = jax.vjp(potentials, z, has_aux=True)
    (grads,) = jax.vmap(pullback)(jnp.eye(2, dtype=z.dtype))
    scale = state_scale(norm)
    g_e, g_s = grads[0] * scale, grads[1] * scale
    if config.kinematic_prior:   # ∇_w of ½|w_v|²: w_v in the velocity columns
        g_e = g_e + jnp.pad(z[:, 3:6] / scale[3:6], ((0, 0), (3, 6)))
    if config.rest_equilibrium:
        rest = _rest(weights, config, norm, node_type, topo)
        g_e, g_s = g_e - rest[0], g_s - rest[1]
    if config.static_l:   # L from the rest state's heads: the same for every state
        rest_l = norm.get("rest_l")
        if rest_l is None:
            rest_l = rest_l_entries(weights, config, norm, node_type, topo)
        heads = jnp.concatenate([rest_l, heads[:, N_L:]], axis=1)
    return g_e, g_s, _matrices(heads), heads[:, N_L + N_M:]


def force_term(port, f, norm):
    """B f [N,12] in the velocity rows, zero elsewhere. With the data's ``port_gain`` (the velocity a unit force
    adds per frame from rest, ≈ Δt / nodal mass; see `data.normalization`) it is
    softplus(port[:, 0]) / softplus(0) · port_gain · f / s_v: the learned per-node factor starts at 1 and the
    term starts at the physical size. Without it (older models), softplus(port[:, 0]) · f / f_std, whose scale
    can be orders of magnitude short: the bunny's first-frame Δv needs a gain of ~160 in those units."""
    if "port_gain" in norm:
        gain = jax.nn.softplus(port[:, :1]) / np.log(2.0) * (norm["port_gain"] / state_scale(norm)[3:6])
        return jnp.pad(gain * f, ((0, 0), (3, 6)))
    gain = jax.nn.softplus(port[:, :1])
    return jnp.pad(gain * f / norm["f_std"], ((0, 0), (3, 6)))


def spring_stiffness(weights, norm, topo: Topology, x=None):
    """k [R,K]: elastic_port's stiffness of every edge slot, k₀ · softplus(ψ(x⁰)) / softplus(0) (0 in padding).
    x⁰ = (|X_j − X_i|, |X_j − X_i|ₓ, |·|ᵧ, |·|_z) / mean rest edge length: symmetric in i, j (``x``: x⁰ if the
    caller has it)."""
    if "spring_k" not in norm:
        raise ValueError("elastic_port needs the statistics' spring_k (data.normalization of data whose cases "
                         "start at rest under a load)")
    if x is None:
        x, _ = _rest_edge_geometry(topo)
    out = _edge_mlp(weights["spring"], x, 1)
    return norm["spring_k"][0] * jax.nn.softplus(out[..., 0]) / np.log(2.0) * topo.mask


def _edge_mlp(w, x, n_out):
    """A one-hidden-layer MLP packed as [W1 (4 rows); b1; W2 (SPRING_HIDDEN rows); b2], on x [...,4]."""
    h = jax.nn.silu(x @ w[:4] + w[4])
    return h @ w[5:5 + SPRING_HIDDEN, :n_out] + w[5 + SPRING_HIDDEN, :n_out]


def scaled_rest_edges(topo: Topology):
    """([R,K,3] X_j − X_i and [R,K,1] |X_j − X_i|, both over the mean rest edge length; [R,K,1] rest lengths)."""
    if topo.dx0 is None:
        raise ValueError("this model needs the rest edge vectors: build the Topology with q0")
    rest = _last_norm(topo.dx0)
    mean_len = jnp.sum(rest[..., 0] * topo.mask) / jnp.sum(topo.mask)
    return topo.dx0 / mean_len, rest / mean_len, rest


def _rest_edge_geometry(topo: Topology):
    """([R,K,4] |X_j − X_i| and its absolute components over the mean rest edge length (symmetric in i, j),
    [R,K,1] rest lengths)."""
    dx, ell, rest = scaled_rest_edges(topo)
    return jnp.concatenate([ell, jnp.abs(dx)], axis=-1), rest


def _spread_coefficients(weights, topo: Topology, hops: int):
    """[H,R,K,2]: port_hops' edge coefficients (a, b) of every slot, from the rest edge geometry."""
    x, _ = _rest_edge_geometry(topo)
    return jnp.stack([_edge_mlp(weights["port_spread"][h], x, 2) for h in range(hops)])


def spread_forces(weights, f, topo: Topology, hops: int, coeffs=None):
    """port_hops' input map without the per-node gain: F + P₁F + P₂P₁F + … [N,3] (see ModelConfig).
    ``coeffs``: the edge coefficients from ``_spread_coefficients`` where the caller has cached them."""
    _, rest = _rest_edge_geometry(topo)
    unit = topo.dx0 / jnp.maximum(rest, 1e-12)
    mask = topo.mask[..., None]
    if coeffs is None:
        coeffs = _spread_coefficients(weights, topo, hops)
    out, y = f, f
    for h in range(hops):
        c = coeffs[h]
        yj = gather_neighbors(y, topo)
        along = jnp.sum(unit * yj, axis=-1, keepdims=True) * unit
        y = reduce_rows(jnp.sum((c[..., :1] * yj + c[..., 1:] * along) * mask, axis=1), topo)
        out = out + y
    return out


def spring_force(weights, norm, z, topo: Topology):
    """−∇_q U [N,3] of elastic_port's spring network at positions z[:, :3]: Σ over a node's edges of
    k (ℓ − ℓ⁰) (q_j − q_i) / ℓ (a stretched edge pulls its nodes together)."""
    q = z[:, :3]
    x, rest = _rest_edge_geometry(topo)
    k = norm["spring_edges"] if "spring_edges" in norm else spring_stiffness(weights, norm, topo, x)
    d = gather_neighbors(q, topo) - expand_rows(q, topo)[:, None, :]
    length = _last_norm(d)
    per_slot = (k[..., None] * (length - rest) / jnp.maximum(length, 1e-12)) * d * topo.mask[..., None]
    return reduce_rows(jnp.sum(per_slot, axis=1), topo)


def _matrices(heads):
    """heads [N, 66 + 78] → (l, m) [N,12,12]: strictly-lower l and lower m filled from the entries."""
    n = heads.shape[0]
    padded = jnp.concatenate([jnp.zeros((n, 1), heads.dtype), heads], axis=1)
    l_mat = jnp.take(padded, _L_INDEX, axis=1).reshape(n, STATE_DIM, STATE_DIM)
    m_mat = jnp.take(padded, _M_INDEX, axis=1).reshape(n, STATE_DIM, STATE_DIM)
    return l_mat, m_mat


def _apply_l(l_mat, g):
    """(l - lᵀ) g per node."""
    return jnp.einsum("nij,nj->ni", l_mat, g) - jnp.einsum("nji,nj->ni", l_mat, g)


def _apply_m(m_mat, g):
    """m mᵀ g per node."""
    return jnp.einsum("nij,nj->ni", m_mat, jnp.einsum("nji,nj->ni", m_mat, g))


_TINY = 1e-30   # keeps ĝ finite where a node's gradient vanishes (the projection is then the identity)


def _project(g, x):
    """(I − ĝĝᵀ) x per node, ĝ = g / |g|: removes from x its component along g."""
    return x - g * (jnp.sum(g * x, axis=-1, keepdims=True) / (jnp.sum(g * g, axis=-1, keepdims=True) + _TINY))


def _projector(g):
    """Per-node matrices I − ĝĝᵀ [N,12,12]: ``_project`` applied to the unit vectors (the matrix is symmetric)."""
    return _project(g[:, None, :], jnp.eye(g.shape[-1], dtype=g.dtype))


def _canonical_matrix(norm):
    """L₀ [12,12]: c·I in the (q, v) block, −c·I in the (v, q) block, zero elsewhere (skew-symmetric), with
    c = Δt s_v / s_q per axis, the q–v coupling in the scaled coordinates (so that Δq = Δt v)."""
    if "dt" not in norm:
        raise ValueError("kinematic_prior needs the frame time step in the normalisation (norm['dt']); "
                         "recompute it with tignn_jax.data.normalization")
    scale = state_scale(norm)
    c = jnp.diag(norm["dt"][0] * scale[3:6] / scale[:3])
    zero3, zero6 = jnp.zeros((3, 3), c.dtype), jnp.zeros((6, 6), c.dtype)
    top = jnp.concatenate([jnp.concatenate([zero3, c], 1), jnp.concatenate([-c, zero3], 1)], 0)
    return jax.scipy.linalg.block_diag(top, zero6)


def _appliers(config, norm, g_e, g_s):
    """(l, g) -> L g and (m, g) -> M g, with the canonical L₀ added for ``kinematic_prior`` and through the
    degeneracy projections when the config asks for them. A ``convex`` model's operator data is its
    ``convex.Ops`` (in both places of the pair) and its appliers are its own."""
    if config.convex:
        return CV.apply_l, CV.apply_m
    base_l = _apply_l
    if config.kinematic_prior:
        l_0 = _canonical_matrix(norm)
        base_l = lambda l_mat, g: _apply_l(l_mat, g) + g @ l_0.T
    if not config.exact_degeneracy:
        return base_l, _apply_m
    return (lambda l_mat, g: _project(g_s, base_l(l_mat, _project(g_s, g))),
            lambda m_mat, g: _project(g_e, _apply_m(m_mat, _project(g_e, g))))


def _embedding(strict: bool, offset: int) -> np.ndarray:
    """Column of the padded heads (0 = the zero column) for each of the 144 entries of a 12x12 matrix."""
    rows, cols = np.tril_indices(STATE_DIM, k=-1 if strict else 0)
    index = np.zeros(STATE_DIM * STATE_DIM, np.int32)
    index[rows * STATE_DIM + cols] = offset + 1 + np.arange(len(rows))
    return index


_L_INDEX = _embedding(strict=True, offset=0)
_M_INDEX = _embedding(strict=False, offset=N_L)


def load_context(norm, f, topo: Topology):
    """[N, 7] per-node load context (see ModelConfig.load_context): each graph's Σf / f_std, then
    (c − X_i) / x0_std and its length, c = Σ|f_j| X_j / Σ|f_j| the graph's load centre (zero when unloaded)."""
    if topo.x0 is None:
        raise ValueError("load_context needs the rest positions: build the Topology with q0")
    member = jnp.ones((1, f.shape[0]), f.dtype) if topo.member is None else topo.member.astype(f.dtype)
    w = _last_norm(f)                                                        # [N,1] |f_i|
    total = member @ f                                                       # [G,3]
    weight = member @ w                                                      # [G,1]
    centre = (member @ (w * topo.x0)) / jnp.where(weight > 0, weight, 1.0)   # [G,3]
    loaded = (member.T @ (weight > 0).astype(f.dtype)) > 0                   # [N,1]
    d = jnp.where(loaded, (member.T @ centre - topo.x0) / norm["x0_std"], 0.0)
    return jnp.concatenate([member.T @ total / norm["f_std"], d, _last_norm(d)], 1)


def _last_norm(x):
    """Norms over the last axis, kept as a size-1 axis ([N,3] → [N,1]), with gradient 0 (not NaN) at a zero
    vector (an unloaded node, the load centre itself, a padding slot)."""
    sq = jnp.sum(x * x, axis=-1, keepdims=True)
    return jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)


def _features(norm, z, f, node_type, topo, edge_velocity=False, edge_strain=False, node_position=False,
              with_edges=True, edge_traction=False, context=False):
    """(x_node [N,F_n], x_edge [R,K,F_e]): the edge features assembled per slot from ``_edge_inputs`` (the
    model itself uses that factored form); x_edge is None without ``with_edges``."""
    q, v, sigma = z[:, :3], z[:, 3:6], z[:, 6:]
    mean, std = norm["z_mean"], norm["z_std"]
    one_hot = jax.nn.one_hot(node_type, 2, dtype=z.dtype)
    position = []
    if node_position:
        if topo.x0 is None:
            raise ValueError("this model needs the rest positions: build its Topology with q0")
        position = [(q - topo.x0) / norm["u_std"], (topo.x0 - norm["x0_mean"]) / norm["x0_std"]]
    context = [load_context(norm, f, topo)] if context else []
    x_node = jnp.concatenate(   # the force inputs stay last: every pass reads them as x_node[:, -force_inputs:]
        [(v - mean[3:6]) / std[3:6], (sigma - mean[6:]) / std[6:], one_hot, *position, *context,
         f / norm["f_std"]], axis=1)
    if not with_edges:
        return x_node, None
    edges = _edge_inputs(norm, z, topo, edge_velocity, edge_strain, edge_traction)
    _, cols = edge_columns(edge_velocity, edge_strain, rest=topo.x0 is not None, edge_traction=edge_traction)
    x_edge = gather_neighbors(edges.lin, topo) - expand_rows(edges.lin, topo)[:, None, :]
    return x_node, x_edge.at[..., cols].add(edges.slot) * topo.mask[..., None]


class EdgeInputs(NamedTuple):
    """The edge features of ``_features`` in factored form, for the fast path of ``Network``:
    x_edge[r,k] = (lin[sender] − lin[receiver]) + slot[r,k] placed in the feature columns ``edge_columns``
    gives for the slot part. The features linear in q and v (q_j − q_i, v_j − v_i and the strain's q part)
    live in ``lin`` [N,F] at node level, so their share of the edge MLP's first layer is a node-level product
    that rides on the gathers the layer does anyway; only the nonlinear ones (lengths, the products
    (v_j − v_i)(q_j − q_i)) and the rest-state constants are computed per slot ([R,K,S])."""
    lin: jax.Array
    slot: jax.Array


def _tractions(norm, sigma, dq, topo):
    """[R,K,6]: S(σ_j)·n and S(σ_i)·n per slot (S the symmetric tensor of the Voigt vector σ, order 11, 22, 33,
    12, 13, 23, over one scalar stress scale; n = dq / mean edge length)."""
    scale = jnp.sqrt(jnp.mean(norm["z_std"][6:] ** 2))
    n = dq / norm["dqn_mean"]

    def apply(sv):   # sv [..., 6] broadcast against n [R,K,3]
        s11, s22, s33, s12, s13, s23 = (sv[..., a:a + 1] for a in range(6))
        nx, ny, nz = n[..., 0:1], n[..., 1:2], n[..., 2:3]
        return [s11 * nx + s12 * ny + s13 * nz, s12 * nx + s22 * ny + s23 * nz, s13 * nx + s23 * ny + s33 * nz]

    sender = gather_neighbors(sigma / scale, topo)
    receiver = expand_rows(sigma / scale, topo)[:, None, :]
    return jnp.concatenate(apply(sender) + apply(receiver), axis=-1)


def edge_columns(edge_velocity=False, edge_strain=False, rest=False, edge_traction=False) -> tuple[int, np.ndarray]:
    """(F, cols): the number of edge features and, for each column of ``EdgeInputs.slot``, the feature it
    adds to (the order of ``_features``: dq 3, length 1 [, dv 3, dv⊗dq 9] [, strain 3, length change 1]).
    With ``rest`` (a Topology with rest positions) the slot part starts with the rest edge vector's share of dq."""
    cols, width = ([0, 1, 2] if rest else []) + [3], 4
    if edge_velocity:
        cols += list(range(width + 3, width + 12))
        width += 12
    if edge_strain:
        cols += [width + 3]
        width += 4
    if edge_traction:
        cols += list(range(width, width + 6))
        width += 6
    return width, np.asarray(cols, np.int32)


def _edge_inputs(norm, z, topo, edge_velocity=False, edge_strain=False, edge_traction=False) -> EdgeInputs:
    """The factored form of ``_features``' x_edge (the same numbers once assembled; see ``EdgeInputs``).

    With rest positions the node-level part is built from displacements q − X (q_j − q_i = (u_j − u_i) +
    (X_j − X_i), the rest edge vector a per-slot constant), so the difference of node values loses no
    precision to large coordinates."""
    q, v = z[:, :3], z[:, 3:6]
    n = q.shape[0]
    rest = topo.x0 is not None
    u = q - topo.x0 if rest else q
    dq = gather_neighbors(q, topo) - expand_rows(q, topo)[:, None, :]
    pad = (1.0 - topo.mask)[..., None]
    length = jnp.sqrt(jnp.sum(dq * dq, axis=-1, keepdims=True) + pad)
    lin = [u / norm["dq_std"], jnp.zeros((n, 1), z.dtype)]
    slot = ([topo.dx0 / norm["dq_std"]] if rest else []) + [(length - norm["dqn_mean"]) / norm["dqn_std"]]
    if edge_velocity:
        dv = (gather_neighbors(v, topo) - expand_rows(v, topo)[:, None, :]) / norm["dv_std"]
        dq_unit = dq / norm["dqn_mean"]
        lin += [v / norm["dv_std"], jnp.zeros((n, 9), z.dtype)]
        # the nine products dv_a dq_b (a-major) as one broadcast: one kernel and one in the reverse pass, where
        # nine sliced products cost XLA:CPU eighteen small pad kernels (measured: the beam's step 1.07x faster)
        slot += [(dv[..., :, None] * dq_unit[..., None, :]).reshape(dv.shape[:-1] + (9,))]
    if edge_strain:
        if topo.dx0 is None:
            raise ValueError("this model needs the rest edge vectors: build its Topology with q0")
        length0 = jnp.sqrt(jnp.sum(topo.dx0 * topo.dx0, axis=-1, keepdims=True) + pad)
        lin += [u / norm["du_std"], jnp.zeros((n, 1), z.dtype)]   # (q_j − q_i) − (X_j − X_i) = u_j − u_i
        slot += [(length - length0) / norm["du_std"][:1]]
    if edge_traction:
        lin += [jnp.zeros((n, 6), z.dtype)]
        slot += [_tractions(norm, z[:, 6:], dq, topo)]
    return EdgeInputs(jnp.concatenate(lin, axis=1), jnp.concatenate(slot, axis=-1) * topo.mask[..., None])


def _inputs(config, norm, z, f, node_type, topo):
    """(x_node, EdgeInputs): what the network reads, in the factored form the model uses."""
    x_node, _ = _features(norm, z, f, node_type, topo, node_position=config.node_position, with_edges=False,
                          context=config.load_context)
    return x_node, _edge_inputs(norm, z, topo, config.edge_velocity, config.edge_strain, config.edge_traction)


def _coarse_inputs(config, norm, z, topo):
    """[C,C,6] the coarse edge features, once per network call (None without ``coarse_nodes``): the difference
    of two adjacent clusters' mean displacements over u_std and their rest centres' offset over its RMS."""
    if not config.coarse_nodes:
        return None
    if topo.coarse is None or topo.x0 is None:
        raise ValueError(f"this model has coarse_nodes={config.coarse_nodes}: build its Topology with "
                         "model_topology (rest positions and clusters)")
    if topo.coarse.pool.shape[0] % config.coarse_nodes:
        raise ValueError(f"the Topology has {topo.coarse.pool.shape[0]} clusters, not a multiple of the "
                         f"model's coarse_nodes={config.coarse_nodes}")
    u_c = topo.coarse.pool @ ((z[:, :3] - topo.x0) / norm["u_std"])
    cg = topo.coarse
    du = (u_c[None, :, :] - u_c[:, None, :]) * cg.adj[..., None]            # [C,C,3] receiver i, sender j
    scale = jnp.sqrt(jnp.sum(cg.dx0 ** 2, axis=-1).sum() / jnp.maximum(cg.adj.sum(), 1.0))
    return jnp.concatenate([du, cg.dx0 / scale], axis=-1)


def _network_out(weights, config, norm, z, f, node_type, topo, split=False):
    """[N, 2 + 66 + 78 (+ 1 port gain with ``force_port``)] decoder outputs, or with ``split`` the pair
    ([N,2] E_i, S_i; the rest)."""
    es, heads = Network(config).apply({"params": weights}, *_inputs(config, norm, z, f, node_type, topo), topo,
                                      _coarse_inputs(config, norm, z, topo))
    return (es, heads) if split else jnp.concatenate([es, heads], axis=1)


def graph_pool(values, topo: Topology):
    """Each graph's mean of ``values`` [N,F], broadcast back to its nodes [N,F].

    A mean (not an attention-weighted sum) keeps ∂E/∂z_i = Σ_j ∂E_j/∂z_i of order one: every node's energy
    depends on node i only through a 1/N share. An attention variant that could single out the loaded node made
    ∇E there of order N, and its first bunny training diverged (loss 1e3 in epoch 1)."""
    member = jnp.ones((1, values.shape[0]), values.dtype) if topo.member is None else topo.member
    return member.T @ (member @ values / jnp.sum(member, axis=1, keepdims=True))


class MLP(nn.Module):
    """Dense layers of width ``hidden`` with the activation between them; the last layer has ``out`` units.
    With ``split`` = k the output is returned as the pair (first k columns, the rest), computed as two
    products with the two column blocks of the same last-layer parameters."""
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
    """A Dense layer (parameters ``kernel`` [in, features], ``bias`` [features], as ``nn.Dense``) whose output
    is returned in two column blocks (first ``split`` | rest), each its own product."""
    features: int
    split: int
    kernel_init: callable = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(self, x):
        kernel = self.param("kernel", self.kernel_init, (x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        k = self.split
        return x @ kernel[:, :k] + bias[:k], x @ kernel[:, k:] + bias[k:]


class DenseParams(nn.Module):
    """The parameters of an ``nn.Dense`` (same names, shapes and initialisers), returned instead of applied,
    for a layer whose product is computed in parts."""
    features: int
    inputs: int

    @nn.compact
    def __call__(self):
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (self.inputs, self.features))
        return kernel, self.param("bias", nn.initializers.zeros_init(), (self.features,))


class CoarsePass(nn.Module):
    """The coarse level of one pass: cluster means of a projection of the latents h [N,H], ``passes`` residual
    message-passing steps between adjacent clusters (dense [C,C], C small; edge features: the difference of
    the clusters' mean displacements u_c [C,3] and of their rest centres, the same one-hidden-layer edge MLP
    form as the fine level; given as e [C,C,6] by ``_coarse_inputs``), and each node's cluster latent back
    [N,H]. With ``mixing`` = C (a body's clusters) the cluster latents of each body are first mixed by one dense
    layer over all C·H of them."""
    hidden: int
    passes: int
    mlp_layers: int
    activation: str
    mixing: int = 0

    @nn.compact
    def __call__(self, h, e, cg: CoarseGraph):
        hid, act = self.hidden, ACTIVATIONS[self.activation]
        hc = cg.pool @ nn.Dense(hid, name="down")(h)
        if self.mixing:
            bodies = hc.shape[0] // self.mixing
            mixed = nn.Dense(self.mixing * hid, name="mix")(hc.reshape(bodies, self.mixing * hid))
            hc = hc + act(mixed.reshape(hc.shape))
        inv_k = 1.0 / cg.degree_max
        for k in range(self.passes):
            a = (nn.Dense(hid, name=f"edge_{k}")(e) + nn.Dense(hid, use_bias=False, name=f"send_{k}")(hc)[None]
                 + nn.Dense(hid, use_bias=False, name=f"recv_{k}")(hc)[:, None])
            msg = jnp.sum(act(a) * cg.adj[..., None], axis=1) * inv_k
            hc = hc + MLP(hid, hid, self.mlp_layers, self.activation, name=f"node_{k}")(
                jnp.concatenate([hc, msg], axis=1))
        return cg.assign @ nn.Dense(hid, name="up")(hc)


class Network(nn.Module):
    """Encode-process-decode. Returns ([N, 2] E_i, S_i; [N, 66 + 78] l_i entries, m_i entries, then the port
    gain's column with ``force_port``).

    Each pass is a residual node update h ← h + φ([h, Σ_j ψ(x_ij, h_i, h_j) / D, f_i]) (D the graph's maximum
    degree, whatever the slot layout) with a one-hidden-layer edge MLP ψ = W₂·act(A x_ij + B h_j + C h_i + b).
    Its first layer is split per operand: B h and C h are computed once per node and gathered (N products instead of E), and the linear W₂ commutes with the sum over
    neighbours, so it is folded into φ's first layer. An edge then costs one gather, an add and an activation;
    all matrix products act on the N nodes. Edges live in the receiver-major slots of ``topo`` ([R,K]); x_ij
    are the (normalised) edge features q_j − q_i and |q_j − q_i| (and, with ``edge_velocity``, v_j − v_i and
    its outer product with q_j − q_i).

    The edge features come either as the array x_edge [R,K,F] or factored (``EdgeInputs``, what the model
    uses): then A x_ij = (A lin)_j − (A lin)_i + A_slot slot_ij, the node-level part joins B h_j and C h_i
    before their gathers, and only the slot part is a per-slot product. Both give the same numbers with
    the same parameters."""
    config: ModelConfig

    @nn.compact
    def __call__(self, x_node, x_edge, topo, x_coarse=None):
        c = self.config
        hid, act = c.hidden, ACTIVATIONS[c.activation]
        x_in = x_node
        if c.node_embedding:
            copies = 1 if topo.member is None else topo.member.shape[0]
            if x_node.shape[0] % copies:
                raise ValueError(f"{x_node.shape[0]} nodes do not split into {copies} copies of one mesh")
            table = self.param("node_embedding", nn.initializers.zeros,
                               (x_node.shape[0] // copies, c.node_embedding), x_node.dtype)
            x_in = jnp.concatenate([jnp.tile(table, (copies, 1)), x_node], axis=1)
        if c.elastic_port and not c.force_port:
            raise ValueError("elastic_port=True needs force_port=True (the spring force enters through the port)")
        if c.port_hops and not c.force_port:
            raise ValueError(f"port_hops={c.port_hops} needs force_port=True")
        if c.port_hops < 0:
            raise ValueError(f"port_hops must be >= 0, got {c.port_hops}")

        def init_edge_mlp(key, shape, dtype):   # [..., W1 (4 rows); b1; W2; b2] with W2 = b2 = 0: output ≡ 0
            w1 = nn.initializers.lecun_normal()(key, shape[:-2] + (4, SPRING_HIDDEN), dtype)
            return jnp.concatenate([w1, jnp.zeros(shape[:-2] + (2 + SPRING_HIDDEN, SPRING_HIDDEN), dtype)], -2)

        if c.elastic_port:   # ψ of spring_stiffness
            self.param("spring", init_edge_mlp, (6 + SPRING_HIDDEN, SPRING_HIDDEN), x_node.dtype)
        if c.port_hops:      # one edge MLP per hop of spread_forces
            self.param("port_spread", init_edge_mlp, (c.port_hops, 6 + SPRING_HIDDEN, SPRING_HIDDEN), x_node.dtype)
        h = MLP(hid, hid, c.mlp_layers, c.activation)(x_in)
        f = x_node[:, -(3 + LOAD_CONTEXT_DIM * c.load_context):]   # the force (and its context) feed every pass
        mask = topo.mask[..., None]
        inv_k = (1.0 / max_degree(topo)).astype(mask.dtype)
        per_pass = 4 if c.global_pool else 3   # Dense layers per pass (the names nn.Dense would get)
        factored = isinstance(x_edge, EdgeInputs)
        width, cols = edge_columns(c.edge_velocity, c.edge_strain, rest=factored and topo.x0 is not None,
                                   edge_traction=c.edge_traction)
        if not factored and x_edge.shape[-1] != width:
            raise ValueError(f"x_edge has {x_edge.shape[-1]} features, the config needs {width}")
        first = [DenseParams(hid, width, name=f"Dense_{p * per_pass}")() for p in range(c.passes)]
        for p in range(c.passes):
            kernel, bias = first[p]
            b_h = nn.Dense(hid, use_bias=False, name=f"Dense_{p * per_pass + 1}")(h)
            c_h = nn.Dense(hid, use_bias=False, name=f"Dense_{p * per_pass + 2}")(h)
            if factored:
                lin = x_edge.lin @ kernel
                a = gather_neighbors(b_h + lin, topo) + expand_rows(c_h - lin, topo)[:, None, :] \
                    + x_edge.slot @ kernel[cols] + bias
            else:
                a = x_edge @ kernel + bias + gather_neighbors(b_h, topo) + expand_rows(c_h, topo)[:, None, :]
            msg = reduce_rows(jnp.sum(act(a) * mask, axis=1), topo) * inv_k
            parts = [h, msg, f]
            if c.global_pool:
                parts.append(graph_pool(nn.Dense(hid, name=f"Dense_{p * per_pass + 3}")(h), topo))
            if c.coarse_nodes:
                parts.append(CoarsePass(hid, c.coarse_passes, c.mlp_layers, c.activation,
                                        c.coarse_nodes if c.coarse_mixing else 0, name=f"coarse_{p}")(
                    h, x_coarse, topo.coarse))
            h = h + MLP(hid, hid, c.mlp_layers, c.activation)(jnp.concatenate(parts, axis=1))
        # with linear_prior the network is a correction: it starts small, so training starts from the prior's map
        return MLP(hid, 2 + N_L + N_M + int(c.force_port), c.mlp_layers, c.activation,
                   out_scale=c.correction_scale if c.linear_prior else 0.1, split=2)(h)
