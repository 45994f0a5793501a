"""Guards for interactive loops: flag forces and states outside a model's training envelope, and step safely.

A learned model has only seen the states and forces of its training data. Its envelope (``params["envelope"]``,
from `tignn_jax.data.normalization`) records them: the mean ``z_mean`` and scale ``z_std`` [12] of every state
feature, the largest deviation ``z_dev_max`` [12] of each (in scales), the largest nodal displacement ``u_max``
and force ``f_max``. A state is out of the envelope where some node's velocity or stress component deviates from
the mean by more than ``tolerance`` × its largest training deviation, or its displacement exceeds
``tolerance`` × ``u_max``; a force where its largest nodal magnitude exceeds ``tolerance`` × ``f_max``.

The guards are safeguards, not physics: a replaced state is no longer the model's prediction.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax import api
from tignn_jax.data import STATE_DIM
from tignn_jax.simulators import LinearGeneric
from tignn_jax.simulators import linear as LG

POLICIES = ("clip", "reset")


def force_check(params: dict, forces, tolerance: float = 1.0) -> dict:
    """Whether ``forces`` lie outside the model's training range.

    Args:
      params: a model.
      forces: [..., N, 3] nodal forces.
      tolerance: the ratio to the largest training force above which the forces are out of distribution.

    Returns:
      {"out_of_distribution": bool, "max_force_ratio": float (largest nodal magnitude over ``f_max``),
      "bound": float (``f_max``)}.

    Raises:
      ValueError: ``forces`` is not [..., N, 3].
    """
    bound = float(np.asarray(params["envelope"]["f_max"]).reshape(-1)[0])
    forces = np.asarray(forces, np.float64)
    if forces.ndim < 2 or forces.shape[-1] != 3:
        raise ValueError(f"forces has shape {forces.shape}, expected [..., nodes, 3]")
    peak = float(np.linalg.norm(forces, axis=-1).max()) if forces.size else 0.0
    ratio = peak / bound if bound > 0 else float("inf") if peak > 0 else 0.0
    return {"out_of_distribution": bool(ratio > tolerance), "max_force_ratio": ratio, "bound": bound}


def state_check(params: dict, z, tolerance: float = 1.5) -> dict:
    """Whether a state has left the model's training envelope, or is not finite.

    Args:
      params: a model.
      z: [..., k·N, 12] states of k stacked bodies of the model's mesh.
      tolerance: the multiple of the envelope (module docstring) beyond which a state is out of distribution.

    Returns:
      {"finite": bool, "envelope_ratio": float (the largest ratio to the envelope), "out_of_distribution": bool}.

    Raises:
      ValueError: ``z`` is not [..., k·N, 12], or ``tolerance`` is not positive.
    """
    z = np.asarray(z, np.float64)
    if z.ndim < 2 or z.shape[-1] != STATE_DIM:
        raise ValueError(f"z has shape {z.shape}, expected [..., nodes, {STATE_DIM}]")
    _check_tolerance(tolerance)
    finite = bool(np.all(np.isfinite(z)))
    ratio = float(np.max(_envelope_ratios(params, z, np))) if finite else float("inf")
    return {"finite": finite, "envelope_ratio": ratio, "out_of_distribution": (not finite) or ratio > tolerance}


def state_guard(params: dict, tolerance: float = 1.5):
    """`state_check` as a jit-able function for loops: ``fn(z [..., k·N, 12]) -> bool`` (True: out of the
    envelope or not finite)."""
    _check_tolerance(tolerance)

    def fn(z):
        s = _envelope_ratios(params, z, jnp)
        return ~jnp.all(jnp.isfinite(z)) | (jnp.max(jnp.where(jnp.isfinite(s), s, jnp.inf)) > tolerance)

    return fn


def guarded_stepper(params: dict, copies: int = 1, policy: str = "reset", tolerance: float = 1.5):
    """A `tignn_jax.stepper` that never returns a non-finite state or one outside the training envelope.

    Each body whose stepped state is flagged (`state_guard`) is replaced; the other bodies keep their step:

    * ``"reset"``: the rest state (q = q0, v = 0, σ = 0);
    * ``"clip"``: non-finite values replaced by the input state's (the rest state's where those are not finite
      either), v and σ clipped to the mean ± ``tolerance`` × the envelope, displacements shortened to
      ``tolerance`` × ``u_max``.

    Args:
      params: a model.
      copies: bodies stacked in the state.
      policy: one of ``POLICIES``.
      tolerance: as `state_check`.

    Returns:
      ``fn(z [copies·N, 12], forces [copies·N, 3]) -> (z_next, flagged [copies] bool)``, jitted.

    Raises:
      ValueError: an unknown ``policy``, or a bad ``copies`` or ``tolerance``.
    """
    if policy not in POLICIES:
        raise ValueError(f"policy must be one of {POLICIES}, got {policy!r}")
    _check_tolerance(tolerance)
    step = api.stepper(params, copies)
    copies = int(copies)
    q0 = jnp.asarray(np.tile(np.asarray(params["mesh"]["q0"], np.float32), (copies, 1)))
    mean, std, dmax, u_max = _envelope_arrays(params)
    lo, hi = mean - tolerance * dmax * std, mean + tolerance * dmax * std
    rest = jnp.concatenate([q0, jnp.zeros((q0.shape[0], STATE_DIM - 3), jnp.float32)], axis=1)
    flag = jax.vmap(state_guard(params, tolerance))
    n = q0.shape[0] // copies

    @jax.jit
    def fn(z, forces):
        nxt = step(z, forces)
        flagged = flag(nxt.reshape(copies, n, STATE_DIM))
        per_node = jnp.repeat(flagged, n)[:, None]
        if policy == "reset":
            return jnp.where(per_node, rest, nxt), flagged
        safe = jnp.where(jnp.isfinite(nxt), nxt, jnp.where(jnp.isfinite(z), z, rest))
        u = safe[:, :3] - q0
        length = jnp.sqrt(jnp.sum(u * u, axis=1, keepdims=True))
        u = u * jnp.minimum(1.0, tolerance * u_max / jnp.maximum(length, 1e-30))
        fixed = jnp.concatenate([q0 + u, jnp.clip(safe[:, 3:], lo, hi)], axis=1)
        return jnp.where(per_node, fixed, nxt), flagged

    return fn


def fallback_step(params: dict, fallback: dict):
    """One body's hand-over step to a linear model.

    Returns ``fn(z [N, 12], forces [N, 3], restart) -> z_next [N, 12]``, jitted: ``fallback``'s backward-Euler
    step (`tignn_jax.simulators.linear`) from z, where ``restart`` (a traced bool) after setting the stress to the
    linear model's stress of the displacement, σ = S u: what a body handed over
    from a learned model starts from (its stress is the first quantity to drift).

    Raises:
      ValueError: ``fallback`` is not a linear model of ``params``' mesh.
    """
    if not isinstance(fallback["model"], LinearGeneric):
        raise ValueError(f"fallback must be a linear model (e.g. 'beam-linear'), got a {fallback['model'].name!r} "
                         "model")
    mesh, fb_mesh = params["mesh"], fallback["mesh"]
    for key in ("node_type", "senders", "receivers"):
        if not np.array_equal(mesh[key], fb_mesh[key]):
            raise ValueError(f"the fallback is on another mesh than the model: its {key} differ")
    if not np.allclose(mesh["q0"], fb_mesh["q0"], atol=1e-5 * np.abs(mesh["q0"]).max()):
        raise ValueError("the fallback is on another mesh than the model: its rest positions q0 differ")
    arrays = fallback["arrays"]

    @jax.jit
    def fn(z, f, restart):
        consistent = z.at[:, 6:].set(LG.stress_of(arrays, z[:, :3] - arrays["q0"]))
        return fallback["model"].step_state(arrays, jnp.where(restart, consistent, z), f)

    return fn


def fallback_stepper(params: dict, fallback: dict, copies: int = 1, hold: int = 30, tolerance: float = 1.5):
    """A guarded step that hands a body to a linear model, instead of resetting it, when the learned model leaves
    its envelope.

    Per body and call: while ``left > 0`` the fallback steps it and ``left`` counts down (the learned model is not
    evaluated for it); else the learned model steps it, and if that state is flagged (`state_guard`) the body is
    handed over from its input state (`fallback_step` with ``restart``) and stays on the fallback for ``hold``
    steps.

    Args:
      params: a model.
      fallback: a linear model of the same mesh, e.g. ``load_pretrained("beam-linear")``.
      copies: bodies stacked in the state.
      hold: frames a handed-over body stays on the fallback.
      tolerance: as `state_check`.

    Returns:
      ``fn(z [copies·N, 12], forces [copies·N, 3], left [copies] int32) -> (z_next, flagged [copies], left)``.

    Raises:
      ValueError: a bad ``hold``, ``tolerance`` or ``copies``, or a fallback that `fallback_step` refuses.
    """
    if not isinstance(hold, (int, np.integer)) or hold < 0:
        raise ValueError(f"hold must be a non-negative integer, got {hold!r}")
    _check_tolerance(tolerance)
    handover = jax.vmap(fallback_step(params, fallback))
    learned = api.stepper(params, copies)
    copies, n = int(copies), len(params["mesh"]["q0"])
    flag = jax.vmap(state_guard(params, tolerance))

    @jax.jit
    def fn(z, forces, left):
        if left.shape != (copies,):
            raise ValueError(f"left must have shape ({copies},), got {left.shape}")
        bodies, loads = z.reshape(copies, n, STATE_DIM), forces.reshape(copies, n, 3)
        on_fallback = left > 0
        nxt = jax.lax.cond(jnp.all(on_fallback), lambda: bodies,
                           lambda: learned(z, forces).reshape(copies, n, STATE_DIM))
        flagged = flag(nxt) & ~on_fallback
        use = on_fallback | flagged
        safe = jax.lax.cond(jnp.any(use), lambda: handover(bodies, loads, flagged), lambda: bodies)
        out = jnp.where(use[:, None, None], safe, nxt)
        left = jnp.where(flagged, hold, jnp.maximum(left - 1, 0)).astype(jnp.int32)
        return out.reshape(copies * n, STATE_DIM), flagged, left

    return fn


def _check_tolerance(tolerance):
    if not (isinstance(tolerance, (int, float, np.floating)) and tolerance > 0):
        raise ValueError(f"tolerance must be a positive number, got {tolerance!r}")


def _envelope_arrays(params):
    """(mean, std, dmax) of the v and σ features, float32 [9] each (dmax floored at 1e-6), and ``u_max``."""
    env = params["envelope"]
    mean, std = (np.asarray(env[k], np.float32)[3:] for k in ("z_mean", "z_std"))
    dmax = np.maximum(np.asarray(env["z_dev_max"], np.float32)[3:], 1e-6)
    return mean, std, dmax, float(np.asarray(env["u_max"]).reshape(-1)[0])


def _envelope_ratios(params, z, xp):
    """[..., nodes, 10]: each node's v and σ deviations over the envelope's, and its displacement over
    ``u_max`` (numpy or jax.numpy as ``xp``)."""
    n = len(params["mesh"]["q0"])
    mean, std, dmax, u_max = _envelope_arrays(params)
    if z.shape[-2] % n:
        raise ValueError(f"z has {z.shape[-2]} nodes, not a multiple of the model's {n}")
    q0 = xp.asarray(np.tile(np.asarray(params["mesh"]["q0"], np.float32), (z.shape[-2] // n, 1)))
    dev = xp.abs((z[..., 3:] - xp.asarray(mean)) / xp.asarray(std)) / xp.asarray(dmax)
    u = xp.sqrt(xp.sum((z[..., :3] - q0) ** 2, axis=-1, keepdims=True)) / max(u_max, 1e-12)
    return xp.concatenate([dev, u], axis=-1)
