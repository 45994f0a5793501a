"""The public simulator: ``step``, ``rollout``, ``load_pretrained``.

A model ("params") is a plain dict:
  config:  dict of ModelConfig fields (static architecture);
  norm:    dict of float32 arrays, the training split's statistics (see ``data.normalization``);
  weights: the flax parameter pytree;
  mesh:    dict with senders [E], receivers [E], node_type [N] and q0 [N,3] of the mesh it was trained on;
  topo:    the mesh's ``model.Topology`` (derived from mesh, not stored in files).
``step`` and ``rollout`` validate their inputs in Python, then call jit-compiled functions; graphs made of k
copies of the model's mesh (``graph.batch``) are accepted, so several bodies step in one call.
"""
from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import jraph
import numpy as np
from flax import traverse_util

from tignn_jax import framesolve as FS
from tignn_jax import graph as G
from tignn_jax import model as M

MODELS_DIR = Path(__file__).resolve().parent / "models"


def step(params: dict, graph: jraph.GraphsTuple, forces) -> jraph.GraphsTuple:
    """Advance the graph's state one frame Δt under ``forces`` [N,3] (external nodal force during the step).

    Returns the graph with the new ``nodes["z"]`` [N,12]. Raises ValueError for wrong shapes, non-finite
    forces or a graph that is not the model's mesh. A graph of several copies of the mesh steps as one graph,
    or on a CPU one body after another (as `stepper`; the same states to rounding)."""
    forces, k = _check(params, graph, forces, seq=False)
    args = params["weights"], _config(params), params["norm"]
    z = graph.nodes["z"]
    if _one_by_one(k):
        z = _bodies_jit(*args, z, forces, jnp.asarray(params["mesh"]["node_type"]), params["topo"])
    else:
        z = _step_jit(*args, z, forces, graph.nodes["node_type"], M.tile_topology(params["topo"], k))
    return G.with_state(graph, z)


def rollout(params: dict, graph: jraph.GraphsTuple, forces_seq) -> jax.Array:
    """States [T+1, N, 12] from the graph's state (first row) under ``forces_seq`` [T, N, 3], by ``lax.scan``
    (several copies of the mesh as one graph, or on a CPU one body after another, as `step`)."""
    forces_seq, k = _check(params, graph, forces_seq, seq=True)
    args = params["weights"], _config(params), params["norm"]
    z0 = graph.nodes["z"]
    if not _one_by_one(k):
        return rollout_states(*args, z0, forces_seq, graph.nodes["node_type"], M.tile_topology(params["topo"], k))
    m, t = len(params["mesh"]["node_type"]), forces_seq.shape[0]
    per_body = _rollout_bodies_jit(*args, jnp.asarray(z0).reshape(k, m, M.STATE_DIM),
                                   jnp.asarray(forces_seq).reshape(t, k, m, 3).swapaxes(0, 1),
                                   jnp.asarray(params["mesh"]["node_type"]), params["topo"])
    return per_body.swapaxes(0, 1).reshape(t + 1, k * m, M.STATE_DIM)


def _one_by_one(copies: int) -> bool:
    """Step ``copies`` bodies of one mesh one after another rather than as one graph: on a CPU, where one graph
    is the slower (``bodies_one_program.md``); an accelerator fills with the one graph."""
    return copies > 1 and jax.default_backend() == "cpu"


def stepper(params: dict, copies: int = 1, one_graph: bool | None = None):
    """A jit-compiled step without per-call checks, for real-time loops: ``z_next = fn(z, forces)``.

    ``z`` [copies·N, 12] and ``forces`` [copies·N, 3] hold ``copies`` bodies of the model's mesh, stacked
    (N = the mesh's nodes). The arguments are checked once here (copies) and by shape at the first call's
    trace; values are not checked per call (use ``step`` for that). The static graph data (topology, node
    types, normalisation) is put on the device once and closed over.

    ``one_graph``: step the copies as one graph of copies·N nodes (True), or one body after another inside the
    program (``lax.map`` over the copies: False; same states to rounding). Default: one graph on an
    accelerator, where it fills the device (128 beams 9.9x cheaper per body than one, ``scaling_gpu.md``), one
    body after another on a CPU, where one graph is the slower (``beam-abaqus`` on this 2-core CPU, session 30,
    ``bodies_one_program.md``: 2, 4, 8 copies 1.52-1.59x, 1.58-1.79x, 1.66-1.97x faster one after another)."""
    if not isinstance(copies, (int, np.integer)) or copies < 1:
        raise ValueError(f"copies must be a positive integer, got {copies!r}")
    config, weights, norm = _config(params), params["weights"], params["norm"]
    if config.frame_solve and copies != 1:
        raise ValueError(f"a frame_solve model steps one body per call (its solve is one body's A₀⁻¹), got "
                         f"copies={copies}: call one stepper per body")
    if one_graph is None:
        one_graph = not _one_by_one(int(copies))
    tiles = int(copies) if one_graph else 1   # copies in the graph the network sees
    topo = M.tile_topology(params["topo"], tiles)
    node_type = jnp.tile(jnp.asarray(params["mesh"]["node_type"], jnp.int32), tiles)
    norm = M.with_rest(weights, config, norm, node_type, topo)   # computed once, not per call
    if network_is_zero(params):   # its rate is exactly zero: only the rest-linearised solve remains
        advance = _linear_step(norm, node_type, jnp.asarray(params["mesh"]["q0"], jnp.float32))
    else:
        def advance(z, forces):
            return M.step_state(weights, config, norm, z, forces, node_type, topo)
    m = len(params["mesh"]["node_type"])   # nodes per body
    n = m * int(copies)
    if tiles != copies:
        advance = partial(_by_body, advance, m)

    @jax.jit
    def fn(z, forces):
        if z.shape != (n, M.STATE_DIM) or forces.shape != (n, 3):
            raise ValueError(f"stepper for {copies} bodies of {n // copies} nodes expects z [{n}, {M.STATE_DIM}]"
                             f" and forces [{n}, 3], got {z.shape} and {forces.shape}")
        return advance(z, forces.astype(z.dtype))   # the state's precision (float64 forces under x64 included)

    return fn


def network_is_zero(params: dict) -> bool:
    """True where the model's GENERIC network contributes exactly nothing to its step: a ``frame_solve`` +
    ``linear_prior`` model (e.g. 'bunny-linear', 'beam-linear') whose every weight is zero and that has no term
    which is non-zero at zero weights (``force_port``'s softplus gain, ``kinematic_prior``'s kinetic term). Its
    step is then the rest-linearised backward-Euler step alone, and `stepper` does not run the network (a skip
    decided when the program is built, from the weights' values; `step` and `rollout` keep tracing the network)."""
    config = _config(params)
    if not (config.frame_solve and config.linear_prior) or config.force_port or config.kinematic_prior:
        return False
    return all(not np.any(np.asarray(w)) for w in jax.tree_util.tree_leaves(params["weights"]))


def force_check(params: dict, forces, tolerance: float = 1.0) -> dict:
    """Flag forces outside the training range: the largest nodal force magnitude of ``forces`` [..., N, 3]
    against the training split's (``norm["f_max"]``). Returns {"out_of_distribution": bool, "max_force_ratio":
    float, "bound": float}; out of distribution when the ratio exceeds ``tolerance``. The learned simulator
    has not seen such loads: its response is an extrapolation (see benchmarks/results/stability_networks.md)."""
    if "f_max" not in params["norm"]:
        raise ValueError("this model file has no training force bound (norm['f_max']); re-save it with "
                         "data.normalization of its training split")
    bound = float(np.asarray(params["norm"]["f_max"]).reshape(-1)[0])
    forces = np.asarray(forces, np.float64)
    if forces.ndim < 2 or forces.shape[-1] != 3:
        raise ValueError(f"forces has shape {forces.shape}, expected [..., nodes, 3]")
    peak = float(np.linalg.norm(forces, axis=-1).max()) if forces.size else 0.0
    ratio = peak / bound if bound > 0 else float("inf") if peak > 0 else 0.0
    return {"out_of_distribution": bool(ratio > tolerance), "max_force_ratio": ratio, "bound": bound}


def state_check(params: dict, z, bound: float = 8.0, tolerance: float = 1.5) -> dict:
    """Flag a state the model has left its training envelope with, and non-finite values; z [..., nodes, 12]
    of any number of stacked copies of the model's mesh.

    With the envelope in the statistics (``norm``: z_dev_max, u_max; see ``data.envelope``) a state is out of
    distribution when some node's velocity or stress component deviates from the training mean by more than
    ``tolerance`` × the largest deviation of that component in training, or its displacement exceeds
    ``tolerance`` × the largest training displacement. Models saved without the envelope fall back to a fixed
    ``bound`` in training standard deviations (which flags states inside the training data where stresses are
    heavy-tailed). Returns {"finite", "max_deviation" (in standard deviations), "envelope_ratio" (the largest
    ratio to the envelope; None without it), "out_of_distribution"}. Cheap enough to call every frame."""
    z = np.asarray(z, np.float64)
    if z.ndim < 2 or z.shape[-1] != M.STATE_DIM:
        raise ValueError(f"z has shape {z.shape}, expected [..., nodes, {M.STATE_DIM}]")
    if not tolerance > 0:
        raise ValueError(f"tolerance must be positive, got {tolerance!r}")
    norm = params["norm"]
    mean, std = (np.asarray(norm[k], np.float64) for k in ("z_mean", "z_std"))
    finite = bool(np.all(np.isfinite(z)))
    dev = np.abs((z[..., 3:] - mean[3:]) / std[3:])
    max_dev = float(np.nanmax(dev)) if finite else float("inf")
    ratio = None
    if "z_dev_max" in norm:
        ratio = float(np.max(_envelope_ratios(params, z, np))) if finite else float("inf")
        out = (not finite) or ratio > tolerance
    else:
        out = (not finite) or max_dev > bound
    return {"finite": finite, "max_deviation": max_dev, "envelope_ratio": ratio, "out_of_distribution": out}


def state_guard(params: dict, bound: float = 8.0, tolerance: float = 1.5):
    """The jit-able form of ``state_check`` for loops: ``fn(z) -> bool`` (True = out of distribution), z
    [..., nodes, 12] of any number of stacked copies of the model's mesh."""
    if "z_dev_max" in params["norm"]:
        score, limit = (lambda z: _envelope_ratios(params, z, jnp)), tolerance
    else:
        mean, std, _, _ = _envelope_arrays(params)
        score, limit = (lambda z: jnp.abs((z[..., 3:] - mean) / std)), bound

    def fn(z):
        s = score(z)
        return ~jnp.all(jnp.isfinite(z)) | (jnp.max(jnp.where(jnp.isfinite(s), s, jnp.inf)) > limit)

    return fn


def _state_and_forces(params: dict, z, forces):
    """(z [N,12], forces [N,3]) as float32 arrays, checked: one body of the model's mesh, finite."""
    n = len(params["mesh"]["node_type"])
    z, forces = np.asarray(z, np.float32), np.asarray(forces, np.float32)
    if z.shape != (n, M.STATE_DIM) or forces.shape != (n, 3):
        raise ValueError(f"z and forces must be [{n}, {M.STATE_DIM}] and [{n}, 3] for this model's mesh, got "
                         f"{z.shape} and {forces.shape}")
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(forces))):
        raise ValueError("z and forces must be finite")
    return z, forces


def step_jacobian(params: dict, z, forces, eps: float = 1e-2):
    """``x -> J x``: the learned step's Jacobian at the state ``z`` [N,12] under ``forces`` [N,3] applied to
    x [N,12], both in the training split's state stds, by a finite difference of size ``eps`` along x/‖x‖ (the
    step has custom VJPs, so no forward-mode JVP). The prescribed entries (clamped q, v) are left out of x and
    of J x: a disturbance there would stay as it is, eigenvalue 1 whatever the network."""
    if not (isinstance(eps, (int, float)) and eps > 0):
        raise ValueError(f"eps must be a positive number, got {eps!r}")
    z, forces = _state_and_forces(params, z, forces)
    fn, std = stepper(params), params["norm"]["z_std"]
    z, forces = jnp.asarray(z), jnp.asarray(forces)
    free = (~M.prescribed(params["mesh"]["node_type"])).astype(z.dtype)
    base = fn(z, forces)

    def matvec(x):
        x = jnp.asarray(x, z.dtype) * free
        size = jnp.linalg.norm(x)
        size = jnp.where(size > 0, size, 1.0)
        return (fn(z + eps * (x / size) * std, forces) - base) / (eps * std) * free * size

    return matvec


def step_growth(params: dict, z, forces, iterations: int = 150, eps: float = 1e-2, seed: int = 0) -> dict:
    """How much the learned step amplifies a small disturbance of the state ``z`` [N,12] under ``forces``
    [N,3]: the largest eigenvalue modulus of the step's Jacobian there, by power iteration on finite
    differences, in the training split's state stds, over the state entries that evolve (the clamped nodes' q
    and v are prescribed, so they are left out).

    The Jacobian is ``step_jacobian``'s. A value above 1 means the learned step is linearly unstable at that
    state: a disturbance along the
    returned mode grows by that factor per step however small it starts (the true, damped dynamics contracts).
    Returns {"growth": the geometric mean of the last third of the iterations' ratios (also right for a complex
    pair), "history": [iterations] the ratios, "mode": [N,12] the last unit direction, "feature_share": [12]
    its squared weight per state feature, "top_node": the node where it is largest}."""
    if not isinstance(iterations, (int, np.integer)) or iterations < 3:
        raise ValueError(f"iterations must be an integer >= 3, got {iterations!r}")
    jac = step_jacobian(params, z, forces, eps)
    free = ~M.prescribed(params["mesh"]["node_type"])
    x = jax.random.normal(jax.random.PRNGKey(seed), free.shape) * free
    x = x / jnp.linalg.norm(x)
    history = []
    for _ in range(iterations):
        y = jac(x)
        ratio = float(jnp.linalg.norm(y))
        history.append(ratio)
        if not ratio > 0 or not np.isfinite(ratio):
            break
        x = y / ratio
    history = np.asarray(history)
    tail = history[-max(len(history) // 3, 1):]
    mode = np.asarray(x)
    share = np.sum(mode ** 2, axis=0)
    return {"growth": float(np.exp(np.mean(np.log(tail)))) if np.all(tail > 0) else float("nan"),
            "history": history, "mode": mode, "feature_share": share / max(share.sum(), 1e-30),
            "top_node": int(np.argmax(np.sum(mode ** 2, axis=1)))}


GROWTH_TERMS = ("L_hessian", "L_change", "M_hessian", "M_change")


def growth_terms(params: dict, z, forces, mode) -> dict:
    """Where a disturbance's growth comes from: the forward-Euler step z' = z + Δt (L(z) ∇E(z) + M(z) ∇S(z))
    of a plain model (no ``frame_solve``, no ``exact_degeneracy``, Euler) has the Jacobian
    I + Δt (L ∇²E + (∂L·)∇E + M ∇²S + (∂M·)∇S) (+ the port's terms), and for a unit ``mode`` x [N,12] in the
    training split's state stds (e.g. ``step_growth``'s) this returns xᵀ T x for each term T (the product rule's
    split of the rate's Jacobian at z under ``forces``, in the same units as ``step_jacobian``):

    * ``L_hessian``: L ∇²E, the reversible part with L frozen (for a skew L and a convex E an oscillation,
      whose forward-Euler growth is √(1 + (ωΔt)²));
    * ``L_change``: L's change with the state times the energy gradient, (∂L/∂z · x) ∇E;
    * ``M_hessian``: M ∇²S (≤ 0 when S is concave, a decay; > 0 means the entropy is convex along x and the
      dissipative part amplifies it);
    * ``M_change``: (∂M/∂z · x) ∇S;
    * ``total``: xᵀ (J − I) x of the whole step (reverse mode), so that the four terms can be checked against it
      (the remainder is the port's terms, zero without ``force_port``).

    For x the dominant mode with a real eigenvalue μ, ``total`` ≈ μ − 1, so the terms say which part of the
    model makes the step unstable. Measured on `beam-abaqus` (``step_growth_terms.md``): at rest ``L_change``
    is 0.888 of the growth's 0.888, the other terms < 1e-3."""
    config = _config(params)
    if config.frame_solve or config.exact_degeneracy or config.integrator != "euler":
        raise ValueError("growth_terms needs a plain forward-Euler model (no frame_solve, exact_degeneracy or "
                         f"Heun), got frame_solve={config.frame_solve}, exact_degeneracy="
                         f"{config.exact_degeneracy}, integrator={config.integrator!r}")
    z, forces = _state_and_forces(params, z, forces)
    n, mode = len(z), np.asarray(mode, np.float32)
    if mode.shape != (n, M.STATE_DIM):
        raise ValueError(f"mode must be [{n}, {M.STATE_DIM}] for this model's mesh, got {mode.shape}")
    if not np.all(np.isfinite(mode)):
        raise ValueError("mode must be finite")
    z, forces, mode = jnp.asarray(z), jnp.asarray(forces), jnp.asarray(mode)
    weights, norm, node_type, topo = params["weights"], params["norm"], jnp.asarray(params["mesh"]["node_type"]), \
        params["topo"]
    norm = M.with_rest(weights, config, norm, node_type, topo)
    std, scale = jnp.asarray(norm["z_std"]), M.state_scale(norm)
    free = (~M.prescribed(node_type)).astype(z.dtype)
    mode = mode * free
    size = jnp.linalg.norm(mode)
    if not float(size) > 0:
        raise ValueError("mode must have a non-zero entry where the state evolves")
    mode = mode / size

    def parts(z_):
        g_e, g_s, (l_mat, m_mat), _ = M._potentials_and_grads(weights, config, norm, z_, forces, node_type, topo)
        return g_e, g_s, l_mat, m_mat

    at_z, parts_pullback = jax.vjp(parts, z)     # one forward pass; each term's row pulls back through it
    g_e0, g_s0, l0, m0 = at_z
    apply_l, apply_m = M._appliers(config, norm, g_e0, g_s0)

    def terms(p):   # bilinear in (L, ∇E) and (M, ∇S): one factor varies, the other is held at z
        g_e, g_s, l_mat, m_mat = p
        # (the kinematic prior's constant L₀ adds nothing to the change term's derivative)
        return apply_l(l0, g_e), apply_l(l_mat, g_e0), apply_m(m0, g_s), apply_m(m_mat, g_s0)

    out, terms_pullback = jax.vjp(terms, at_z)
    cotangent = mode * scale / std * free          # the rate in scaled units → state stds, evolved entries only
    result = {}
    for i, name in enumerate(GROWTH_TERMS):
        cts = tuple(cotangent if j == i else jnp.zeros_like(o) for j, o in enumerate(out))
        (row,) = parts_pullback(terms_pullback(cts)[0])
        result[name] = float(jnp.sum(row * mode * std))
    fn = stepper(params)
    _, step_pullback = jax.vjp(lambda d: fn(z + d * std, forces) / std, jnp.zeros_like(z))
    (row,) = step_pullback(mode)
    result["total"] = float(jnp.sum(row * mode)) - 1.0
    return result


GUARD_POLICIES = ("clip", "reset")


def guarded_stepper(params: dict, copies: int = 1, policy: str = "reset", tolerance: float = 1.5,
                    bound: float = 8.0):
    """A ``stepper`` that never returns a non-finite state or one outside the model's training envelope:
    ``z_next, flagged = fn(z, forces)`` for ``copies`` stacked bodies, with ``flagged`` [copies] True for each
    body whose plain-step state was out of distribution (as ``state_guard`` measures it) or non-finite, and that
    body's state then replaced (the other bodies keep their plain step):

    * ``policy="clip"``: each node's v and σ components are clipped to the training mean ± ``tolerance`` ×
      the envelope (the largest deviation of that component in training; ``bound`` standard deviations for
      models saved without it), and a displacement longer than ``tolerance`` × the largest training
      displacement is shortened to it; non-finite values are first replaced by the input state's (by the rest
      state's where those are non-finite too). The body keeps its shape, bounded.
    * ``policy="reset"`` (default): the rest state (q = q0, v = 0, σ = 0), the demo's reaction.

    Measured (``stability_networks.md``, the explicit beam networks, 1000 steps under five loadings): with "reset" 16–66 steps
    are flagged; with "clip" the model pushes the clipped state out again at nearly every step once it has
    left (956–981 of 1000 steps flagged) and the body stays at the envelope's edge, 2–6× the FEM's displacement
    away, so "clip" keeps a picture bounded but not plausible.

    This is a safeguard for interactive loops, not physics: a flagged step's state is no longer the model's
    prediction, and ``benchmarks/stability.py`` reports how far guarded rollouts are from the FEM. A step that
    is not flagged returns the plain step's state unchanged."""
    if policy not in GUARD_POLICIES:
        raise ValueError(f"policy must be one of {GUARD_POLICIES}, got {policy!r}")
    if not tolerance > 0:
        raise ValueError(f"tolerance must be positive, got {tolerance!r}")
    if not bound > 0:
        raise ValueError(f"bound must be positive, got {bound!r}")
    step = stepper(params, copies)
    q0 = jnp.asarray(np.tile(np.asarray(params["mesh"]["q0"], np.float32), (int(copies), 1)))
    mean, std, dmax, u_max = _envelope_arrays(params)
    if dmax is not None:
        half, u_cap = tolerance * dmax * std, tolerance * u_max
    else:
        half, u_cap = bound * std, None
    lo, hi = mean - half, mean + half
    rest = jnp.concatenate([q0, jnp.zeros((q0.shape[0], M.STATE_DIM - 3), jnp.float32)], axis=1)
    flag = jax.vmap(state_guard(params, bound=bound, tolerance=tolerance))
    n = q0.shape[0] // int(copies)

    @jax.jit
    def fn(z, forces):
        nxt = step(z, forces)
        flagged = flag(nxt.reshape(int(copies), n, M.STATE_DIM))      # one flag per body
        per_node = jnp.repeat(flagged, n)[:, None]
        if policy == "reset":
            return jnp.where(per_node, rest, nxt), flagged
        safe = jnp.where(jnp.isfinite(nxt), nxt, jnp.where(jnp.isfinite(z), z, rest))
        u = safe[:, :3] - q0
        if u_cap is not None:
            length = jnp.sqrt(jnp.sum(u * u, axis=1, keepdims=True))
            u = u * jnp.minimum(1.0, u_cap / jnp.maximum(length, 1e-30))
        fixed = jnp.concatenate([q0 + u, jnp.clip(safe[:, 3:], lo, hi)], axis=1)
        return jnp.where(per_node, fixed, nxt), flagged

    return fn


def fallback_step(params: dict, fallback: dict):
    """One body's fallback step for loops that keep their own bookkeeping (``scene.run``): ``z_next = fn(z,
    forces, restart)`` is the rest-linearised backward-Euler step of ``fallback`` (see ``fallback_stepper``)
    from z [N,12], after setting the stress to S₀u where ``restart`` (a bool scalar, traced: one compilation) is
    True, as a hand-over from the learned model does. Checks that ``fallback`` is a rest-linearised model of
    ``params``' mesh."""
    return jax.jit(_handover(params, fallback))


def consistency_bound(params: dict, fallback: dict, z, forces) -> np.ndarray:
    """[12]: per state component, the largest departure of the learned step from ``fallback``'s rest-linearised
    step over the transitions from states z [..., N, 12] under forces [..., N, 3] (free nodes; in training
    standard deviations, floored at 1e-6): the calibration of ``fallback_stepper(..., consistency=...)``, e.g.
    over a model's training split (``data.z[rows, :-1]``, ``data.f[rows]``)."""
    z, forces = np.asarray(z, np.float32), np.asarray(forces, np.float32)
    n = len(params["mesh"]["q0"])
    if z.shape[-2:] != (n, M.STATE_DIM) or forces.shape != z.shape[:-1] + (3,):
        raise ValueError(f"z must be [..., {n}, {M.STATE_DIM}] and forces [..., {n}, 3] of the same transitions, "
                         f"got {z.shape} and {forces.shape}")
    handover, step = _handover(params, fallback), stepper(params)
    std = jnp.asarray(params["norm"]["z_std"])
    free = (jnp.asarray(params["mesh"]["node_type"]) == 0)[:, None]
    departure = jax.jit(lambda a, b: jnp.max(jnp.where(free, jnp.abs(step(a, b) - handover(a, b, False)) / std,
                                                       0.0), axis=0))
    out = np.zeros(M.STATE_DIM)
    for a, b in zip(z.reshape(-1, n, M.STATE_DIM), forces.reshape(-1, n, 3)):
        out = np.maximum(out, np.asarray(departure(jnp.asarray(a), jnp.asarray(b))))
    return np.maximum(out, 1e-6).astype(np.float32)


def fallback_stepper(params: dict, fallback: dict, copies: int = 1, hold: int = 30, tolerance: float = 1.5,
                     bound: float = 8.0, consistency=None, step=None):
    """A guarded step that hands a body to a physically consistent, unconditionally stable step when the learned
    model leaves its training envelope, instead of resetting it: ``z_next, flagged, left = fn(z, forces, left)``
    for ``copies`` stacked bodies, with ``left`` int32 [copies] (start from zeros) the steps each body still has
    to spend on the fallback.

    ``fallback`` is a rest-linearised FEM model of the same mesh (a ``frame_solve`` + ``linear_prior`` model,
    e.g. ``load_pretrained("beam-linear")``, built by ``framesolve.linear_model``); only its rest linearisation
    is used (backward Euler on u̇ = v, M v̇ = f − K₀u − αMv, σ̇ = S₀v; its network is not run). Per body and step:

    * ``left > 0``: the fallback steps the body and ``left`` counts down; the network is not evaluated for it
      (nor at all while every body is on the fallback);
    * else the network steps it; if that state is out of the envelope (``state_guard`` at ``tolerance`` /
      ``bound``) or non-finite, the body is ``flagged``: its input state's stress is replaced by the linear
      stress of its displacement, σ = S₀u (the network's stress drifts before anything else, see
      ``step_growth.md``; the fallback carries σ on from a consistent value), the fallback steps it from there,
      and it stays on the fallback for the next ``hold`` steps, which lets it settle before the network resumes.

    ``consistency`` ([12], from ``consistency_bound``): a body is also flagged where its network step departs
    from the fallback's step by more than ``tolerance`` × that bound in some component (free nodes, in
    standard deviations): the learned model is trusted only as far from the physics as it was on its training
    data. The envelope alone flags late (the state has to drift out first); this catches a departure at once,
    at the cost of the fallback's step every call.

    ``step``: a step ``fn(z [N,12], f [N,3]) -> z_next`` of one body of the fallback's mesh that replaces the
    rest-linearised one where a body is on the fallback, e.g. ``newton.fallback_step(fallback, scene)`` (the
    FEM's non-linear backward-Euler step by Newton–CG iterations: it keeps a rotated body unstressed, at about
    eight times the rest-linearised step's cost); where its result is not finite (a learned state with inverted
    elements, where the FEM's force is undefined) the rest-linearised step is taken instead. The consistency check
    still compares with the rest-linearised step.

    Measured (``stability_networks.md``, ``beam-abaqus`` with ``beam-linear``, 1000 steps under five loadings): finite
    everywhere, with the u error against the FEM at step 100 far below the "reset" policy's. The fallback's
    steps are the rest linearisation's, so away from rest (large rotations, loads beyond the training range)
    they carry its error; a flagged step is no longer the learned model's prediction."""
    if not isinstance(hold, (int, np.integer)) or hold < 0:
        raise ValueError(f"hold must be a non-negative integer, got {hold!r}")
    if not tolerance > 0:
        raise ValueError(f"tolerance must be positive, got {tolerance!r}")
    if not bound > 0:
        raise ValueError(f"bound must be positive, got {bound!r}")
    linear_handover = jax.vmap(_handover(params, fallback))    # validates the fallback's kind and mesh
    handover = linear_handover if step is None else _custom_handover(step, linear_handover)
    learned = stepper(params, copies)     # validates copies
    copies, n = int(copies), len(params["mesh"]["q0"])
    flag = jax.vmap(state_guard(params, bound=bound, tolerance=tolerance))
    if consistency is not None:
        consistency = np.asarray(consistency, np.float32)
        if consistency.shape != (M.STATE_DIM,) or not np.all(consistency > 0):
            raise ValueError(f"consistency must be {M.STATE_DIM} positive bounds (consistency_bound), got "
                             f"{consistency!r}")
        limit = jnp.asarray(consistency * np.asarray(params["norm"]["z_std"], np.float32) * tolerance)
        free = (jnp.asarray(params["mesh"]["node_type"]) == 0)[:, None]

    @jax.jit
    def fn(z, forces, left):
        if left.shape != (copies,):
            raise ValueError(f"left must have shape ({copies},), got {left.shape}")
        bodies, loads = z.reshape(copies, n, M.STATE_DIM), forces.reshape(copies, n, 3)
        on_fallback = left > 0
        nxt = jax.lax.cond(jnp.all(on_fallback), lambda: bodies,
                           lambda: learned(z, forces).reshape(copies, n, M.STATE_DIM))
        out_of_envelope = flag(nxt)
        if consistency is not None:   # the network step against the fallback's from the same state
            linear_next = linear_handover(bodies, loads, jnp.zeros(copies, bool))
            departs = jnp.any((jnp.abs(nxt - linear_next) > limit) & free, axis=(1, 2))
            out_of_envelope = out_of_envelope | departs
        flagged = out_of_envelope & ~on_fallback
        use = on_fallback | flagged
        safe = jax.lax.cond(jnp.any(use), lambda: handover(bodies, loads, flagged), lambda: bodies)
        out = jnp.where(use[:, None, None], safe, nxt)
        left = jnp.where(flagged, hold, jnp.maximum(left - 1, 0)).astype(jnp.int32)
        return out.reshape(copies * n, M.STATE_DIM), flagged, left

    return fn


def _handover(params: dict, fallback: dict):
    """``fn(z, f, restart) -> z_next`` for one body of ``params``' mesh: ``fallback``'s rest-linearised
    backward-Euler step (its network not run) from z, or, where ``restart``, from z with σ = S₀u; ValueError
    where ``fallback`` is not a rest-linearised model of that mesh."""
    fb_config = _config(fallback)
    if not (fb_config.frame_solve and fb_config.linear_prior):
        raise ValueError("fallback must be a rest-linearised model (frame_solve and linear_prior, e.g. "
                         f"'beam-linear'), got one with frame_solve={fb_config.frame_solve}, "
                         f"linear_prior={fb_config.linear_prior}")
    mesh, fb_mesh = params["mesh"], fallback["mesh"]
    for key in ("node_type", "senders", "receivers"):
        if not np.array_equal(np.asarray(mesh[key]), np.asarray(fb_mesh[key])):
            raise ValueError(f"the fallback is on another mesh than the model: its {key} differ")
    q0 = np.asarray(mesh["q0"], np.float32)
    if not np.allclose(q0, np.asarray(fb_mesh["q0"], np.float32), atol=1e-5 * np.abs(q0).max()):
        raise ValueError("the fallback is on another mesh than the model: its rest positions q0 differ")
    norm = FS.with_inverse(fallback["norm"], fb_mesh["node_type"])
    node_type, x0 = jnp.asarray(mesh["node_type"], jnp.int32), jnp.asarray(q0)
    free = (node_type == 0)[:, None]

    linear = _linear_step(norm, node_type, x0)

    def consistent(z):
        return z.at[:, 6:].set(FS.apply_s(norm, jnp.where(free, z[:, :3] - x0, 0.0)))

    def fn(z, f, restart):
        return linear(jnp.where(restart, consistent(z), z), f)

    return fn


def _custom_handover(step, linear):
    """``fn(z, f, restart)`` over stacked bodies z [B,N,12], f [B,N,3]: ``step`` on each body (a fallback step that
    needs no consistent stress to start from, e.g. `newton`'s, which computes σ from the displacement), or the
    batched rest-linearised hand-over ``linear(z, f, restart)`` for a body whose result is not finite: a learned
    model's state can hold inverted elements (measured: J down to −0.30 in `beam-abaqus`'s state at its first
    flagged step under a constant load), where the FEM's internal force is not defined, while the linear step is.
    The linear step runs only when some body needs it (the condition is over the batch, so it stays a branch)."""
    if not callable(step):
        raise ValueError(f"step must be a function (z, f) -> z_next, got {step!r}")
    step = jax.vmap(step)

    def fn(z, f, restart):
        out = step(z, f)
        ok = jnp.all(jnp.isfinite(out), axis=(1, 2))
        return jax.lax.cond(jnp.all(ok), lambda: out,
                            lambda: jnp.where(ok[:, None, None], out, linear(z, f, restart)))

    return fn


def _linear_step(norm, node_type, x0):
    """``fn(z, f) -> z_next``: the rest-linearised backward-Euler step of a ``frame_solve`` normalisation (with
    its A₀⁻¹), without a network: `framesolve.linear_step`, which needs no product by K₀."""
    def fn(z, f):
        return z + FS.linear_step(norm, z, f, node_type, x0)

    return fn


def _envelope_arrays(params):
    """(mean, std, dmax, u_max) of the v and σ features, float32 [9] each (dmax floored at 1e-6), and the
    largest training displacement; dmax and u_max are None for models saved without the envelope."""
    norm = params["norm"]
    mean, std = (np.asarray(norm[k], np.float32)[3:] for k in ("z_mean", "z_std"))
    if "z_dev_max" not in norm:
        return mean, std, None, None
    return (mean, std, np.maximum(np.asarray(norm["z_dev_max"], np.float32)[3:], 1e-6),
            float(np.asarray(norm["u_max"]).reshape(-1)[0]))


def _envelope_ratios(params, z, xp):
    """[..., nodes, 10]: each node's v and σ deviations over the training envelope's, and its displacement over
    the largest training displacement (numpy or jax.numpy as ``xp``)."""
    n = len(params["mesh"]["q0"])
    mean, std, dmax, u_max = (xp.asarray(a) if isinstance(a, np.ndarray) else a for a in _envelope_arrays(params))
    if z.shape[-2] % n:
        raise ValueError(f"z has {z.shape[-2]} nodes, not a multiple of the model's {n}")
    q0 = xp.asarray(np.tile(np.asarray(params["mesh"]["q0"], np.float32), (z.shape[-2] // n, 1)))
    dev = xp.abs((z[..., 3:] - mean) / std) / dmax
    u = xp.sqrt(xp.sum((z[..., :3] - q0) ** 2, axis=-1, keepdims=True)) / max(u_max, 1e-12)
    return xp.concatenate([dev, u], axis=-1)


def load_pretrained(name: str = "beam-abaqus"):
    """A shipped model by name (a folder of ``tignn_jax/models``) or a path to a model folder/file.

    Returns (params, graph): the model and the rest-state graph of its mesh (q = q0, v = 0, sigma = 0)."""
    path = Path(name)
    if not path.exists():
        path = MODELS_DIR / name
    if path.is_dir():
        path = path / "model.npz"
    if not path.exists():
        shipped = sorted(p.name for p in MODELS_DIR.iterdir() if (p / "model.npz").exists()) \
            if MODELS_DIR.exists() else []
        raise ValueError(f"no model named {name!r}; shipped models: {shipped}")
    params = load_model(path)
    mesh = params["mesh"]
    return params, G.rest_graph(mesh["q0"], np.stack([mesh["senders"], mesh["receivers"]]), mesh["node_type"])


def make_params(config: M.ModelConfig, norm: dict, weights, q0, edges, node_type) -> dict:
    """Bundle a model: architecture, normalisation, weights and its mesh."""
    edges = np.asarray(edges)
    M.check_integrator(config)
    if config.linear_prior and not config.frame_solve:
        raise ValueError("linear_prior needs frame_solve (forward Euler on the stiff rest dynamics is unstable)")
    if config.frame_solve:
        norm = FS.with_inverse(norm, node_type)   # the dense A₀⁻¹ of the W-method step, built once per model
    return {
        "config": dict(config._asdict()),
        "norm": {k: jnp.asarray(v, jnp.float32) for k, v in norm.items()},
        "weights": weights,
        "mesh": {"senders": np.asarray(edges[0], np.int32), "receivers": np.asarray(edges[1], np.int32),
                 "node_type": np.asarray(node_type, np.int32), "q0": np.asarray(q0, np.float32)},
        "topo": M.model_topology(config, edges[0], edges[1], len(node_type), q0),
    }


def save_model(params: dict, path: str | Path, info: dict | None = None) -> Path:
    """Write a model to one compressed ``.npz`` (float32 weights; config and ``info`` as JSON)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {f"weights/{k}": np.asarray(v, np.float32)
              for k, v in traverse_util.flatten_dict(jax.device_get(params["weights"]), sep="/").items()}
    arrays.update({f"norm/{k}": np.asarray(v, np.float32) for k, v in params["norm"].items()
                   if k not in FS.DERIVED})
    arrays.update({f"mesh/{k}": np.asarray(v) for k, v in params["mesh"].items()})
    arrays["config"] = np.array(json.dumps(params["config"]))
    arrays["info"] = np.array(json.dumps(info or {}))
    np.savez_compressed(path, **arrays)
    return path


def load_model(path: str | Path) -> dict:
    """Read a model written by ``save_model``."""
    with np.load(path, allow_pickle=False) as npz:
        flat = {k: npz[k] for k in npz.files}
    group = lambda p: {k[len(p) + 1:]: v for k, v in flat.items() if k.startswith(p + "/")}
    weights = traverse_util.unflatten_dict({tuple(k.split("/")): jnp.asarray(v)
                                            for k, v in group("weights").items()})
    mesh = group("mesh")
    params = make_params(M.ModelConfig(**json.loads(str(flat["config"]))), group("norm"), weights, mesh["q0"],
                         np.stack([mesh["senders"], mesh["receivers"]]), mesh["node_type"])
    params["info"] = json.loads(str(flat["info"])) if "info" in flat else {}
    return params


@partial(jax.jit, static_argnames="config")
def rollout_states(weights, config, norm, z0, forces_seq, node_type, topo):
    """Unvalidated jit-compiled rollout: z0 [N,12], forces_seq [T,N,3] → [T+1,N,12]."""
    norm = M.with_rest(weights, config, norm, node_type, topo)   # once per rollout

    def body(z, f):
        z_next = M.step_state(weights, config, norm, z, f, node_type, topo)
        return z_next, z_next

    _, zs = jax.lax.scan(body, z0, forces_seq)
    return jnp.concatenate([z0[None], zs])


@partial(jax.jit, static_argnames="config")
def _step_jit(weights, config, norm, z, f, node_type, topo):
    return M.step_state(weights, config, norm, z, f, node_type, topo)


@partial(jax.jit, static_argnames="config")
def _rollout_bodies_jit(weights, config, norm, zs, fs, node_type, topo):
    """Rollouts [k,T+1,N,12] of the bodies zs [k,N,12] under fs [k,T,N,3], one after another."""
    return jax.lax.map(lambda zf: rollout_states(weights, config, norm, zf[0], zf[1], node_type, topo), (zs, fs))


@partial(jax.jit, static_argnames="config")
def _bodies_jit(weights, config, norm, z, f, node_type, topo):
    """One step of the stacked bodies z [k·N,12] under f [k·N,3], one after another (one body's N, topology)."""
    return _by_body(lambda zb, fb: M.step_state(weights, config, norm, zb, fb, node_type, topo),
                    node_type.shape[0], z, f)


def _by_body(step_fn, m: int, z, f):
    """``step_fn`` (one body of m nodes: z [m,12], f [m,3] → z [m,12]) applied to the stacked bodies z [k·m,12],
    f [k·m,3] one after another (``lax.map``), restacked."""
    out = jax.lax.map(lambda zf: step_fn(*zf), (z.reshape(-1, m, M.STATE_DIM), f.reshape(-1, m, 3)))
    return out.reshape(z.shape)


def _config(params) -> M.ModelConfig:
    return M.ModelConfig(**params["config"])


def _check(params, graph, forces, seq: bool):
    """Validate a graph against the model's mesh and the forces' shape and values.

    Returns forces (float32) and k, the graph's number of copies of the mesh."""
    if not isinstance(graph, jraph.GraphsTuple) or not isinstance(graph.nodes, dict) \
            or "z" not in graph.nodes or "node_type" not in graph.nodes:
        raise ValueError("graph must be a jraph.GraphsTuple with nodes {'z': [N,12], 'node_type': [N]}")
    mesh = params["mesh"]
    n_mesh = len(mesh["node_type"])
    n_node = np.asarray(graph.n_node).reshape(-1)
    z = graph.nodes["z"]
    n = z.shape[0]
    if np.any(n_node != n_mesh) or n != n_mesh * len(n_node):
        raise ValueError(f"graph has n_node {n_node.tolist()}, but the model's mesh has {n_mesh} nodes")
    if tuple(z.shape) != (n, M.STATE_DIM):
        raise ValueError(f"graph.nodes['z'] has shape {tuple(z.shape)}, expected ({n}, {M.STATE_DIM})")
    k = len(n_node)
    offsets = np.repeat(np.arange(k) * n_mesh, len(mesh["senders"]))
    senders, receivers = np.asarray(graph.senders), np.asarray(graph.receivers)
    if senders.shape != offsets.shape or not np.array_equal(senders, np.tile(mesh["senders"], k) + offsets) \
            or not np.array_equal(receivers, np.tile(mesh["receivers"], k) + offsets):
        raise ValueError("graph senders/receivers are not the edges of the model's mesh")
    if not np.array_equal(np.asarray(graph.nodes["node_type"]), np.tile(mesh["node_type"], k)):
        raise ValueError("graph.nodes['node_type'] differs from the model's mesh")
    expected = (n, 3) if not seq else (None, n, 3)
    shape = tuple(np.shape(forces))
    if len(shape) != len(expected) or any(e is not None and e != s for e, s in zip(expected, shape)):
        name = "forces_seq" if seq else "forces"
        raise ValueError(f"{name} has shape {shape}, expected {'[T, ' if seq else '['}{n}, 3]")
    forces = np.asarray(forces, np.float32)
    if not np.all(np.isfinite(forces)):
        name = "forces_seq" if seq else "forces"
        raise ValueError(f"{name} contains NaN or infinite values")
    if not np.all(np.isfinite(np.asarray(z))):
        raise ValueError("graph.nodes['z'] contains NaN or infinite values")
    return forces, k

