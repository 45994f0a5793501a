"""Identify the beam parameters the paper does not publish by gradient descent through the FEM.

Unknowns: density ρ, Rayleigh mass damping α, and a time-scale factor s on the Prony relaxation times
(τ_i → s·τ_i; s → ∞ means no relaxation within the run). The loss is the mean over frames and cases of the
relative L2 error of the displacement u = q − q0 against the Abaqus reference, on train-split cases only.
Parameters are optimised in log space with Adam (optax); ρ is kept above ``rho_min``, for which the sub-step
count is fixed, so every iterate is stable.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .scenes import beam_reference_forces, beam_scene, setup_scene
from .solver import Loads, _simulate


def identify_beam(reference_path, sim_ids, *, n_frames: int = 10, steps: int = 8, rho_min: float = 7e-3,
                  init=(1.2e-2, 20.0, 1.0), lr: float = 0.3, log_path=None):
    """Return (params dict, history list). sim_ids must come from the train split."""
    ref = np.load(reference_path)
    train = set(ref["split_train"].tolist())
    bad = [s for s in sim_ids if s not in train]
    if bad:
        raise ValueError(f"identification must use train-split cases only; not in the train split: {bad}")
    scene = beam_scene(density=rho_min, damping=1.0, tau_scale=1.0)._replace(n_frames=n_frames)
    problem = setup_scene(scene)
    forces = jnp.asarray(beam_reference_forces(scene, sim_ids), jnp.float32)
    q0 = jnp.asarray(ref["q0"], jnp.float32)
    u_ref = jnp.asarray(ref["z"][np.asarray(sim_ids) - 1, 1:n_frames + 1, :, :3]) - q0
    base = scene.material

    def unpack(theta):
        rho = rho_min + jnp.exp(theta[0])
        return rho, jnp.exp(theta[1]), jnp.exp(theta[2])

    def loss_fn(theta):
        rho, alpha, s = unpack(theta)
        mat = base._replace(density=rho, tau=base.tau * s)
        arr = problem.arrays._replace(damping_alpha=alpha)
        res = jax.vmap(lambda f: _simulate(arr, mat, Loads(nodal=f), problem.config))(forces)
        u = res.q[:, 1:] - q0
        err = jnp.sqrt(jnp.sum((u - u_ref) ** 2, axis=(-2, -1)) / jnp.sum(u_ref ** 2, axis=(-2, -1)))
        return jnp.mean(err)

    theta = jnp.array([math.log(init[0] - rho_min), math.log(init[1]), math.log(init[2])])
    opt = optax.adam(lr)
    state = opt.init(theta)
    step = jax.jit(jax.value_and_grad(loss_fn))
    history = []
    for it in range(steps):
        t0 = time.perf_counter()
        loss, grad = step(theta)
        rho, alpha, s = (float(v) for v in unpack(theta))
        history.append({"iter": it, "loss": float(loss), "density": rho, "damping": alpha, "tau_scale": s,
                        "grad": np.asarray(grad).tolist(), "seconds": time.perf_counter() - t0})
        print(json.dumps(history[-1]), flush=True)
        if log_path:
            Path(log_path).write_text(json.dumps(history, indent=1))
        updates, state = opt.update(grad, state)
        theta = optax.apply_updates(theta, updates)
    best = min(history, key=lambda h: h["loss"])
    return {k: best[k] for k in ("density", "damping", "tau_scale", "loss")}, history
