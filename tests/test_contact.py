"""Contact inside the implicit step (`tignn_jax.simulators.contact`, `tignn_jax.contact_stepper`)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tignn_jax
from tignn_jax.simulators.contact import (apply_stiffness, candidate_pairs, coarse_stiffness, contact, energy,
                                         linearise, still_exact)

# the FEM's two beams (`fem.scenes.two_beams_scene`): B turned 90° about z over A's free half, 10 above it
POSE_B = np.array([[0.0, -1.0, 0.0, 36.0], [1.0, 0.0, 0.0, -25.0], [0.0, 0.0, 1.0, 20.0], [0.0, 0.0, 0.0, 1.0]])


def _two_clouds(rng, n=12, m=9):
    """Two small point bodies, b turned and shifted so that some of its points lie within r of a's."""
    qa = rng.uniform(-1.0, 1.0, (n, 3)).astype(np.float32)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    near = qa[:m] + rng.normal(0.0, 0.3, (m, 3))
    qb = ((near - [0.1, 0.2, 0.3]) @ turn).astype(np.float32)        # world: turn qb + (0.1, 0.2, 0.3) = near
    pose_b = np.eye(4)
    pose_b[:3, :3], pose_b[:3, 3] = turn, [0.1, 0.2, 0.3]
    spec = contact([np.eye(4), pose_b], [np.arange(0, n, 2), np.arange(m)], 0.6, 50.0, capacity=16)
    return (jnp.asarray(qa), jnp.asarray(qb)), spec


def test_contact_gradient_is_that_of_its_energy_and_its_stiffness_the_gauss_newton_part():
    # ∂E_c/∂q exactly (autodiff and central differences, in each body's own frame), and H_c w is k n (n · δ) over
    # the touching pairs (δ the pair's relative displacement in the world): the Hessian without its curvature term,
    # symmetric positive semi-definite
    rng = np.random.default_rng(0)
    qs, spec = _two_clouds(rng)
    pairs = candidate_pairs(spec, tuple(jnp.concatenate([q, jnp.zeros_like(q)], 1) for q in qs))
    lin = linearise(spec, pairs, qs)
    auto = jax.grad(lambda q: energy(spec, pairs, q))(qs)
    for g, a in zip(lin.gradient, auto):
        np.testing.assert_allclose(g, a, rtol=1e-4, atol=1e-4)
    e = lambda q: float(energy(spec, pairs, q))  # noqa: E731
    for body, i, c in [(0, 0, 0), (0, 2, 1), (1, 3, 2), (1, 1, 0)]:
        dq = [np.zeros(q.shape, np.float32) for q in qs]
        dq[body][i, c] = 1e-3
        fd = (e(tuple(q + d for q, d in zip(qs, dq))) - e(tuple(q - d for q, d in zip(qs, dq)))) / 2e-3
        assert abs(fd - float(lin.gradient[body][i, c])) < 2e-2 * (1.0 + abs(fd))
    assert float(jnp.abs(lin.gradient[0][1::2]).max()) == 0.0               # a's nodes off its surface feel none
    assert float(lin.active[0].sum()) > 2                                    # the check saw contacts
    w = [jnp.asarray(rng.normal(size=q.shape), jnp.float32) for q in qs]
    x = [jnp.asarray(rng.normal(size=q.shape), jnp.float32) for q in qs]
    hw, hx = apply_stiffness(spec, pairs, lin, w), apply_stiffness(spec, pairs, lin, x)
    dot = lambda a, b: float(sum(jnp.vdot(p, q) for p, q in zip(a, b)))  # noqa: E731
    assert abs(dot(x, hw) - dot(w, hx)) < 1e-4 * (1.0 + abs(dot(x, hw)))     # symmetric
    assert dot(w, hw) >= 0.0 and dot(x, hx) >= 0.0                           # positive semi-definite
    rigid = [jnp.ones_like(q) @ jnp.asarray(r) for q, r in zip(qs, spec.rotations)]   # one world translation
    assert max(float(jnp.abs(t).max()) for t in apply_stiffness(spec, pairs, lin, rigid)) < 1e-3


def test_listed_pairs_give_the_dense_stiffness_and_its_coarse_projection():
    # H_c w over the listed active pairs equals the sum over every candidate pair, and so does the list cut
    # short (then every candidate pair is summed: the overflow branch); Vᵀ H_c V from the list is H_c applied to
    # V's columns, projected
    rng = np.random.default_rng(3)
    qs, spec = _two_clouds(rng)
    pairs = candidate_pairs(spec, tuple(jnp.concatenate([q, jnp.zeros_like(q)], 1) for q in qs))
    lin = linearise(spec, pairs, qs)
    count = int(lin.active[0].sum())
    assert count > 2 and not bool(lin.listed[0].overflow)
    w = [jnp.asarray(rng.normal(size=q.shape), jnp.float32) for q in qs]
    dense = lin._replace(listed=(lin.listed[0]._replace(overflow=jnp.asarray(True)),))
    for a, b in zip(apply_stiffness(spec, pairs, lin, w), apply_stiffness(spec, pairs, dense, w)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)
    bases = [jnp.asarray(rng.normal(size=(q.shape[0], 3, m)), jnp.float32) for q, m in zip(qs, (3, 2))]
    coarse = np.asarray(coarse_stiffness(spec, lin, bases))
    columns = [[v[:, :, c] if k == body else jnp.zeros_like(q) for k, (v, q) in enumerate(zip(bases, qs))]
               for body, v in enumerate(bases) for c in range(v.shape[-1])]
    hv = [apply_stiffness(spec, pairs, lin, col) for col in columns]
    expected = np.array([[float(sum(jnp.vdot(x, y) for x, y in zip(c, h))) for h in hv] for c in columns])
    np.testing.assert_allclose(coarse, expected, rtol=1e-4, atol=1e-3 * np.abs(expected).max())
    assert np.linalg.eigvalsh(coarse).min() > -1e-4 * np.abs(coarse).max()     # positive semi-definite


def test_candidates_stay_exact_only_while_nodes_move_less_than_half_the_spare_reach():
    rng = np.random.default_rng(4)
    qs, spec = _two_clouds(rng)
    pairs = candidate_pairs(spec, tuple(jnp.concatenate([q, jnp.zeros_like(q)], 1) for q in qs))
    half = 0.5 * (spec.reach - spec.radius)
    for step, exact in ((0.9 * half, True), (1.1 * half, False)):
        moved = (qs[0], qs[1].at[2, 1].add(step))
        assert bool(still_exact(spec, pairs, qs, moved)) == exact, step
    full = contact([np.eye(4), np.eye(4)], [np.arange(12), np.arange(9)], 0.6, 50.0, capacity=2, reach=100.0)
    full_pairs = candidate_pairs(full, tuple(jnp.concatenate([q, jnp.zeros_like(q)], 1) for q in qs))
    assert not bool(still_exact(full, full_pairs, qs, qs))                     # a full list may have left some out


def test_candidate_pairs_keep_every_touching_pair():
    # the frame's candidates are only the nodes near the other body's box: their energy and forces are the
    # full pair sum's, and the unused slots never touch anything
    from fem.meshes import beam_mesh
    from tignn_jax.mr.surface import surface_nodes, surface_triangles

    q0, cells, _ = beam_mesh()
    q0 = np.asarray(q0, np.float32)
    surface = surface_nodes(surface_triangles(cells, q0))
    low = POSE_B.copy()
    low[2, 3] = 10.5                                                          # B sunk 0.5 below A's top
    z = jnp.concatenate([jnp.asarray(q0), jnp.zeros((len(q0), 9))], 1)
    qs = (jnp.asarray(q0), jnp.asarray(q0))
    pruned = contact([np.eye(4), low], [surface, surface], 2.0, 1e3, capacity=128)
    full = contact([np.eye(4), low], [surface, surface], 2.0, 1e3, capacity=len(surface), reach=1e3)
    pp, pf = candidate_pairs(pruned, (z, z)), candidate_pairs(full, (z, z))
    taken = [int((ids < len(q0)).sum()) for ids in pp[0]]
    assert all(0 < t < 128 for t in taken) and [int((ids < len(q0)).sum()) for ids in pf[0]] == [len(surface)] * 2
    e_full, e_pruned = float(energy(full, pf, qs)), float(energy(pruned, pp, qs))
    assert e_full > 1.0 and abs(e_pruned - e_full) < 1e-5 * e_full
    for g, h in zip(linearise(pruned, pp, qs).gradient, linearise(full, pf, qs).gradient):
        np.testing.assert_allclose(g, h, rtol=1e-4, atol=1e-2)


def _world_energy(params, zs, poses, radius, stiffness):
    """Σ_b E_b(z_b) + E_c of all surface pairs (dense), in the models' work units (pose scale 1)."""
    from tignn_jax.mr.surface import surface_nodes, surface_triangles
    from tignn_jax.simulators.corotational import energy

    arrays = params["arrays"]
    surface = surface_nodes(surface_triangles(np.asarray(arrays["cells"]), np.asarray(params["mesh"]["q0"])))
    x = [np.asarray(z[surface, :3], np.float64) @ p[:3, :3].T + p[:3, 3] for z, p in zip(zs, poses)]
    d = np.linalg.norm(x[0][:, None] - x[1][None], axis=-1)
    e_c = 0.5 * stiffness * np.sum(np.maximum(radius - d, 0.0) ** 2)
    return sum(float(energy(arrays, z)) for z in zs) + e_c, d.min()


def test_two_beams_in_contact_never_gain_energy_and_the_lower_one_is_bent_through_the_contact():
    # the FEM's two beams, B pressed down at its free end onto A with the FEM's contact (r = 2, k = 2.5e5): the
    # sum of both beams' energies and the contact's never exceeds what the force has put in, frame by frame;
    # the surfaces stay apart and A, never touched by the load, bends under B
    params, _ = tignn_jax.load_pretrained("beam-corot")
    poses = [np.eye(4), POSE_B]
    radius, stiffness = 2.0, 2.5e5
    fn = tignn_jax.contact_stepper(params, poses, radius, stiffness)
    q0 = np.asarray(params["mesh"]["q0"], np.float32)
    z0 = jnp.concatenate([jnp.asarray(q0), jnp.zeros((len(q0), 9))], axis=1)
    tip = (q0[:, 0] > 39.0) & (q0[:, 2] > 9.0)
    f_b = np.zeros_like(q0)
    f_b[tip, 2] = -6e5 / tip.sum()
    zs, forces = (z0, z0), (jnp.zeros_like(jnp.asarray(q0)), jnp.asarray(f_b))
    e, _ = _world_energy(params, zs, poses, radius, stiffness)
    for _ in range(12):
        nxt = fn(zs, forces)
        work = float(jnp.sum(forces[1] * (nxt[1][:, :3] - zs[1][:, :3])))
        e_next, gap = _world_energy(params, nxt, poses, radius, stiffness)
        assert e_next <= e + work + 1e-4 * (abs(e) + abs(work)) + 1e-3
        assert gap > 0.25 * radius
        zs, e = nxt, e_next
    assert all(np.all(np.isfinite(np.asarray(z))) for z in zs)
    u_a = np.asarray(zs[0][:, 2]) - q0[:, 2]
    u_b = np.asarray(zs[1][:, 2]) - q0[:, 2]
    assert u_b.min() < -10.0 and u_a.min() < -2.0 and u_a.max() < 0.2


def test_contact_stepper_rejects_bad_input_naming_it():
    params, _ = tignn_jax.load_pretrained("beam-corot")
    linear, _ = tignn_jax.load_pretrained("beam-linear")
    with pytest.raises(ValueError, match="two or more bodies"):
        tignn_jax.contact_stepper(params, [np.eye(4)], 1.0, 1.0)
    with pytest.raises(ValueError, match="rotation times a positive scale"):
        tignn_jax.contact_stepper(params, [np.eye(4), np.diag([1.0, 2.0, 1.0, 1.0])], 1.0, 1.0)
    with pytest.raises(ValueError, match="same scale"):
        tignn_jax.contact_stepper(params, [np.eye(4), np.diag([2.0, 2.0, 2.0, 1.0])], 1.0, 1.0)
    with pytest.raises(ValueError, match="radius must be a positive number, got -1"):
        tignn_jax.contact_stepper(params, [np.eye(4), POSE_B], -1.0, 1.0)
    with pytest.raises(ValueError, match="capacity must be a positive integer"):
        tignn_jax.contact_stepper(params, [np.eye(4), POSE_B], 1.0, 1.0, capacity=0)
    with pytest.raises(ValueError, match="cannot be stepped together"):
        tignn_jax.contact_stepper(linear, [np.eye(4), POSE_B], 1.0, 1.0)
    fn = tignn_jax.contact_stepper(params, [np.eye(4), POSE_B], 1.0, 1.0)
    z = jnp.zeros((756, 12))
    with pytest.raises(ValueError, match="takes 2 states"):
        fn((z,), (z[:, :3],))
