"""The FEM's own frame step, cheap enough to hand a body to: a fixed number of Newton iterations of backward
Euler, each solved by a few conjugate-gradient iterations preconditioned with the rest operator turned with the body.

The rest-linearised step (`tignn_jax.simulators.linear` with the FEM's operators, the model ``beam-linear``) is
unconditionally stable and costs one dense product, but for a nearly incompressible body its linear pressure
(2/D1)·div u is wrong at second order in the rotation: a rigidly turned body is pressed where it is unstressed.
Keeping the FEM's exact internal force f_int(u) and stress σ(u) but stepping with the rest tangent is unstable
(see docs/research_log.md): once an element rotates, its stiff volumetric modes act along directions the rest
solve does not hold implicitly.

Backward Euler with step h, lumped mass M and mass damping α, on the free degrees of freedom, for Δv = v' − v::

    r(Δv) = h [f − f_int(u + h (v + Δv)) − α M (v + Δv)] − M Δv = 0,   u' = u + h v',   σ' = σ(u'),

by ``newton`` Newton iterations Δv ← Δv + A⁻¹ r(Δv), A = (1 + αh) M + h² K(ũ) with K(ũ) the exact tangent at the
iterate ũ (applied matrix-free as Kᵀw by ``jax.vjp`` of f_int: K is symmetric but for the hourglass forces'
co-rotation, 7e-4 apart on a random beam state, and the reverse pass is the cheaper product; docs/research_log.md),
each solved by ``iterations`` conjugate-gradient
iterations preconditioned with R A₀⁻¹ Rᵀ / h², where A₀ = (1 + αh) M / h² + K₀ is the rest operator (its dense
inverse is the linear model's A⁻¹) and R block-diagonal with each node's rotation (`rotations`: the polar
factor of the node's least-squares deformation gradient). The iteration starts from v' = 0 (``predictor="zero"``,
ũ = u) or from v' = v (``"velocity"``, ũ = u + h v). After a sudden load the velocity predictor overshoots and
one Newton step from it diverges (a hex bar of the beam material: at a tip deflection of 1.5 % of its length,
`tests/test_newton.py`); from v' = 0 it does not. A rigidly turned body is left at rest: f_int and σ vanish, so
the residual does. The input state's σ is not read: the stress is the FEM's at the new displacement.

Accuracy and cost against the learned and rest-linearised steps: ``benchmarks/pareto.py``. Use it as a reference
simulator (`fem_stepper`, ``tignn demo --model fem-newton``) or as the step a loop hands a body to.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tignn_jax.simulators import LinearGeneric
from tignn_jax.simulators import linear as LG

PREDICTORS = ("zero", "velocity")   # the Newton iteration starts from v' = 0 (u' = u) or v' = v (u' = u + h v)


def rotations(x0, senders, receivers, iterations: int = 6):
    """x [N,3] → [N,3,3], the rotation of each node's neighbourhood: the polar factor R of the least-squares
    deformation gradient F_i = (Σ_j dx dXᵀ)(Σ_j dX dXᵀ)⁻¹ over the node's edges (dx = x_j − x_i, dX = X_j − X_i),
    by Higham's iteration R ← (R + R⁻ᵀ)/2 from R = F (``iterations`` of it: quadratic convergence, exact at once for
    a rigid motion; element-wise, cheaper than a batched SVD). The rest factor
    (Σ_j dX dXᵀ)⁻¹ is computed here, once per mesh."""
    x0 = jnp.asarray(x0, jnp.float32)
    senders, receivers = jnp.asarray(senders, jnp.int32), jnp.asarray(receivers, jnp.int32)
    n = x0.shape[0]
    dX = x0[receivers] - x0[senders]
    rest_inv = jnp.linalg.inv(jax.ops.segment_sum(dX[:, :, None] * dX[:, None, :], senders, n))

    def inverse_transpose(a):   # columns c_k: A⁻ᵀ = [c1 × c2, c2 × c0, c0 × c1] / det A
        c0, c1, c2 = a[:, :, 0], a[:, :, 1], a[:, :, 2]
        x = jnp.stack([jnp.cross(c1, c2), jnp.cross(c2, c0), jnp.cross(c0, c1)], axis=-1)
        return x / jnp.sum(c0 * x[:, :, 0], axis=-1)[:, None, None]

    def rotation(x):
        dx = x[receivers] - x[senders]
        r = jax.ops.segment_sum(dx[:, :, None] * dX[:, None, :], senders, n) @ rest_inv
        for _ in range(int(iterations)):
            r = 0.5 * (r + inverse_transpose(r))
        return r

    return rotation


def newton_cg(arrays: dict, node_type, x0, force, stress, rotation, iterations: int = 3, newton: int = 2,
              predictor: str = "zero"):
    """``step(z [N,12], f [N,3]) -> z_next``, not jitted: the module's step with a linear model's ``arrays``
    (its A⁻¹ the preconditioner's, its masses, α and Δt the step's), the FEM's internal force ``force`` and nodal stress
    ``stress`` (u [N,3] → [N,3] / [N,6], `fem.implicit.force_and_stress`) and a nodal ``rotation`` (`rotations`).
    A converged or zero residual stops the CG updates without dividing 0 by 0 (the rest state is kept exactly)."""
    if not isinstance(iterations, (int, np.integer)) or iterations < 1:
        raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
    if not isinstance(newton, (int, np.integer)) or newton < 1:
        raise ValueError(f"newton must be a positive integer, got {newton!r}")
    if predictor not in PREDICTORS:
        raise ValueError(f"predictor must be one of {PREDICTORS}, got {predictor!r}")
    x0 = jnp.asarray(x0, jnp.float32)
    h, alpha, free, m = LG._constants(arrays, jnp.float32)

    def step(z, f):
        u, v = (z[:, :3] - x0) * free, z[:, 3:6] * free
        rot = rotation(z[:, :3])

        def _cg(u_at, v_at, dv_at):   # the Newton correction of Δv at the iterate u_at = u + h (v + Δv)
            f_up, pullback = jax.vjp(force, u_at)   # the force and its tangent there, applied as Kᵀ w (a
            tangent = lambda w: pullback(w)[0]       # reverse pass: 5× cheaper than jax.linearize's forward one)
            apply_a = lambda w: (m * (1 + alpha * h) * w + h * h * tangent(w * free)) * free
            res = (h * (f - f_up - alpha * m * v_at) - m * dv_at) * free

            def update(x, res, d, rz):   # one CG step along d (a converged or zero residual: no 0/0, no move)
                ad = apply_a(d)
                dad = jnp.vdot(d, ad)
                a = jnp.where(dad > 0, rz / jnp.where(dad > 0, dad, 1.0), 0.0)
                return x + a * d, res - a * ad

            def body(_, carry):
                x, res, d, rz = carry
                x, res = update(x, res, d, rz)
                pz = prec(res)
                rz_new = jnp.vdot(res, pz)
                return x, res, pz + jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0) * d, rz_new

            pz = prec(res)
            carry = (jnp.zeros_like(v), res, pz, jnp.vdot(res, pz))
            for k in range(int(iterations) - 1):   # unrolled: 1.5× faster here than a lax.fori_loop
                carry = body(k, carry)
            return update(*carry)[0]     # the last step needs no new direction (saves a preconditioner product)

        def prec(w):   # R A₀⁻¹ Rᵀ w / h² on the free degrees of freedom
            back = jnp.einsum("nji,nj->ni", rot, w * free)
            return jnp.einsum("nij,nj->ni", rot, LG.apply_ainv(arrays, back.reshape(-1)).reshape(-1, 3)) * free / h ** 2

        dv = jnp.zeros_like(v) if predictor == "velocity" else -v   # start from v' = v, or from v' = 0
        for _ in range(int(newton)):
            dv = dv + _cg(u + h * (v + dv), v + dv, dv)
        u_next = u + h * (v + dv)
        return jnp.concatenate([x0 + u_next, v + dv, stress(u_next).astype(z.dtype)], axis=1)

    return step


def fallback_step(fallback: dict, scene, iterations: int = 3, newton: int = 2, predictor: str = "zero"):
    """The module's step (``newton`` Newton iterations of ``iterations`` CG each from ``predictor``), jitted.

    Args:
      fallback: the rest-linearised linear model of the scene (e.g. ``load_pretrained("beam-linear")``): its A⁻¹
        preconditions the CG iterations.
      scene: the `fem.scenes.Scene` it was built from (its damping is taken from ``fallback``'s
        ``info["fem_damping"]`` where recorded).

    Returns:
      ``fn(z [N,12], f [N,3]) -> z_next``.

    Raises:
      ValueError: the scene's mesh, clamps, damping or frame step are not the fallback's, or the scene is not
        elastic (`fem.implicit.check_scope`).
    """
    from fem import implicit, scenes

    if not isinstance(fallback["model"], LinearGeneric):
        raise ValueError(f"fallback must be a linear model (e.g. 'beam-linear'), got a {fallback['model'].name!r} "
                         "model")
    mesh, info = fallback["mesh"], fallback.get("info", {})
    q0 = np.asarray(mesh["q0"], np.float32)
    if q0.shape != scene.points.shape or not np.allclose(q0, scene.points, atol=1e-4 * np.abs(q0).max()):
        raise ValueError(f"the fallback is not on the {scene.name} scene's mesh (nodes, order or units differ)")
    node_type = np.asarray(mesh["node_type"])
    if not np.array_equal(node_type != 0, np.asarray(scene.node_type) != 0):
        raise ValueError(f"the fallback clamps other nodes than the {scene.name} scene")
    if "fem_damping" in info:
        scene = scene._replace(damping=float(info["fem_damping"]))
    arrays = fallback["arrays"]
    dt = float(np.asarray(arrays["dt"]).reshape(-1)[0])
    if not np.isclose(dt, scene.frame_dt, rtol=1e-6):
        raise ValueError(f"the fallback steps dt = {dt}, the {scene.name} scene's frame is {scene.frame_dt}")
    problem = scenes.setup_scene(scene._replace(n_frames=1))
    alpha = float(np.asarray(arrays["alpha"]).reshape(-1)[0])
    if not np.isclose(alpha, float(problem.arrays.damping_alpha), rtol=1e-4):
        raise ValueError(f"the fallback's mass damping α = {alpha} is not the scene's "
                         f"{float(problem.arrays.damping_alpha)}")
    force, stress = implicit.force_and_stress(problem, scene.material)
    rotation = rotations(q0, mesh["senders"], mesh["receivers"])
    return jax.jit(newton_cg(arrays, node_type, q0, force, stress, rotation, iterations, newton, predictor))


def fem_scene(fallback: dict):
    """The `fem.scenes.Scene` a rest-linearised model ``fallback`` was built from: the shipped scene (beam or
    bunny) whose mesh is the model's, with the density and mass damping the model records (``info["fem_density"]``,
    ``info["fem_damping"]``). ValueError where no shipped scene has the model's mesh."""
    from fem import scenes

    q0 = np.asarray(fallback["mesh"]["q0"], np.float64)
    info = fallback.get("info", {})
    for make in (scenes.beam_scene, scenes.bunny_scene):
        kwargs = {k: float(info[f"fem_{k}"]) for k in ("density", "damping") if f"fem_{k}" in info}
        scene = make(**kwargs)
        if scene.points.shape == q0.shape and np.allclose(scene.points, q0, atol=1e-4 * np.abs(q0).max()):
            return scene
    raise ValueError(f"no shipped FEM scene has this model's mesh ({q0.shape[0]} nodes): build the "
                     "fem.scenes.Scene yourself and call fallback_step(fallback, scene)")


def fem_stepper(fallback: dict, iterations: int = 3, newton: int = 2, predictor: str = "zero"):
    """``fallback_step`` on the FEM scene the rest-linearised model ``fallback`` was built from (`fem_scene`):
    the FEM's own backward-Euler frame step, not learned, ``fn(z [N,12], f [N,3]) -> z_next`` (jitted)."""
    return fallback_step(fallback, fem_scene(fallback), iterations, newton, predictor)
