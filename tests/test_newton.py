"""tignn_jax.newton: the FEM's backward-Euler frame step by a fixed number of Newton iterations, against the
converged FEM on a small hex bar of the beam's nearly incompressible material, on the shipped beam-linear's scene
(`tignn_jax.fem_stepper`) and as the demo's ``--model fem-newton``.

The checks marked ``long`` compile the Newton step several times (its conjugate-gradient iterations are unrolled:
30–80 s per compilation on two shared cores) and run only with ``TIGNN_LONG_TESTS=1``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fem
from fem import implicit
from fem.meshes import mesh_edges
from tignn_jax import newton
from tignn_jax.simulators import LinearGeneric
from tignn_jax.simulators import linear as LG

H = 0.05
long = pytest.mark.long


@pytest.fixture(scope="module")
def bar():
    """A 4×1×1 hex bar of the beam's material clamped at x = 0, its problem, its rest-linearised model's arrays,
    the FEM's force and stress and the nodal rotations."""
    pts, cells = fem.box_hex_mesh((8.0, 2.0, 2.0), (4, 1, 1))
    node_type = (pts[:, 0] < 1e-9).astype(np.int8)
    material = fem.mooney_rivlin(c10=1.5e5, c01=5e3, d1=1e-7, density=7.135e-3)
    problem = fem.setup(pts, cells, material=material, frame_dt=H, n_frames=8, clamped=np.where(node_type)[0],
                        damping=60.0, n_sub=1)
    lin = implicit.rest_linearization(problem, material)
    stored = LG.from_rest_linearization(lin, H)
    arrays = LinearGeneric().prepare(stored, {"q0": pts, "node_type": node_type})   # the linear model's arrays
    force, stress = implicit.force_and_stress(problem, material)
    edges = mesh_edges(cells)
    rotation = newton.rotations(pts, edges[0], edges[1])
    return pts, node_type, problem, material, arrays, force, stress, rotation, stored


def _roll(step, pts, forces):
    z = np.zeros((len(pts), 12), np.float32)
    z[:, :3] = pts
    out = [z]
    for f in forces:
        z = np.asarray(step(jnp.asarray(z), jnp.asarray(f)))
        out.append(z)
    return np.stack(out)


def _tip_case(pts, load):   # a tip load held for 5 frames, then released for 3
    tip = pts[:, 0] > 8 - 1e-9
    f = np.zeros((8, len(pts), 3), np.float32)
    f[:5, tip, 2] = -load / tip.sum()
    return f


@long
def test_one_newton_step_from_v_zero_tracks_the_converged_fem_where_the_velocity_predictor_diverges(bar):
    # A sudden tip load, held, then released: the converged backward-Euler FEM (Newton to 1e-4) against one
    # Newton iteration per frame. From the predictor u + h v the frame after the sudden load overshoots (v = u₁/h
    # doubles the deflection) and one Newton step from there diverges already at a tip deflection of 1.5 % of the
    # bar's length (measured: u error 1.45, growing); from v' = 0 it stays within 1 % of the largest displacement
    # (measured 0.008; the defaults, 2 Newton steps of 3 CG, 0.0019).
    pts, node_type, problem, material, arrays, force, stress, rotation, stored = bar
    f = _tip_case(pts, 1000.0)
    res, _ = implicit.simulate_implicit(problem, material, fem.Loads(nodal=jnp.asarray(f)), tol=1e-4, max_newton=40)
    uf = np.asarray(res.q) - pts
    scale = np.linalg.norm(uf, axis=(1, 2)).max()
    assert np.abs(uf[:, :, 2]).max() > 0.1     # the bar bends (tip 0.12 down), then swings back

    def error(**kw):
        zs = _roll(jax.jit(newton.newton_cg(arrays, node_type, pts, force, stress, rotation, 5, **kw)), pts, f)
        return np.linalg.norm(zs[:, :, :3] - pts - uf, axis=(1, 2)).max() / scale

    assert error(predictor="zero", newton=1) < 0.01
    assert not error(predictor="velocity", newton=1) < 0.5      # diverged (NaN counts as diverged)
    assert error() < 0.005                                       # the defaults: 2 Newton iterations of 3 CG


@long
def test_the_step_keeps_rest_and_a_rigidly_turned_body_unstressed(bar):
    # From rest under no load the residual is exactly zero: CG must not divide 0 by 0. A free body turned rigidly
    # by 1 rad (far outside the rest linearisation's range) is left where it is, unstressed.
    pts, node_type, problem, material, arrays, force, stress, rotation, stored = bar
    z = np.zeros((len(pts), 12), np.float32)
    z[:, :3] = pts
    zero = np.zeros((len(pts), 3), np.float32)
    free = np.zeros_like(node_type)   # the bar's operators with no node clamped (A = K + c M stays invertible)
    unclamped = LinearGeneric().prepare(stored, {"q0": pts, "node_type": free})
    c = pts.mean(0)
    th = 1.0
    rot = np.array([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0], [0.0, 0.0, 1.0]])
    turned = z.copy()
    turned[:, :3] = (pts - c) @ rot.T + c
    for pred in newton.PREDICTORS:
        step = jax.jit(newton.newton_cg(unclamped, free, pts, force, stress, rotation, predictor=pred))
        np.testing.assert_array_equal(np.asarray(step(jnp.asarray(z), jnp.asarray(zero))), z)
        out = np.asarray(step(jnp.asarray(turned), jnp.asarray(zero)), np.float64)
        assert np.abs(out[:, :3] - turned[:, :3]).max() < 1e-4 * np.abs(pts).max(), pred
        assert np.abs(out[:, 6:]).max() < 1e-3 * 1.5e5, pred


def test_bad_arguments_are_named():
    # the iteration counts and the predictor are checked before anything is built
    for kw, word in (({"iterations": 0}, "iterations"), ({"newton": 0}, "newton"), ({"predictor": "guess"},
                                                                                      "predictor")):
        with pytest.raises(ValueError, match=word):
            newton.newton_cg({}, None, np.zeros((1, 3)), None, None, None, **kw)


@pytest.mark.long
def test_fallback_step_for_the_shipped_beam_fallback():
    # beam-linear with the FEM's beam scene: in the linear range (a small tip load from rest) the Newton step lands
    # where the rest-linearised step does, to the float32 conditioning of the solve (measured 1.2 % apart in v
    # whether CG runs 5 or 60 iterations; each leaves 0.5–0.7 % of the load as residual: A₀ of this nearly
    # incompressible beam is ill-conditioned); from a bent state its stress σ(u') differs from the linear step's by
    # far more than that; in a state with an inverted element the FEM's force is not defined and the step is not
    # finite; a scene of another mesh is refused.
    import tignn_jax
    from fem import scenes

    linear, graph = tignn_jax.load_pretrained("beam-linear")
    scene = scenes.beam_scene()
    step = newton.fallback_step(linear, scene)
    z = graph.nodes["z"]
    q0 = np.asarray(linear["mesh"]["q0"])
    f = np.zeros((len(q0), 3), np.float32)
    tip = q0[:, 0] > q0[:, 0].max() - 1e-3
    f[tip, 2] = -1e3 / tip.sum()
    lin_step = tignn_jax.fallback_step(linear, linear)
    a = np.asarray(step(z, jnp.asarray(f)), np.float64)
    b = np.asarray(lin_step(z, jnp.asarray(f), False), np.float64)
    assert np.linalg.norm(a[:, :3] - q0) > 0
    assert np.linalg.norm(a[:, 3:6] - b[:, 3:6]) < 0.03 * np.linalg.norm(b[:, 3:6])
    bent = np.asarray(z).copy()
    bent[:, 2] += 2.0 * (q0[:, 0] / 40.0) ** 2
    bent = jnp.asarray(bent)
    a = np.asarray(step(bent, jnp.asarray(f)), np.float64)
    b = np.asarray(lin_step(bent, jnp.asarray(f), False), np.float64)
    rel = lambda x, y, k: np.linalg.norm(x[:, k] - y[:, k]) / np.linalg.norm(y[:, k])
    assert rel(b, a, slice(6, 12)) > 0.5
    broken = np.asarray(bent).copy()
    corner = int(np.argmax(q0[:, 0] + q0[:, 1] + q0[:, 2]))
    broken[corner, :3] -= 6.0                       # pushed through its element
    assert not np.all(np.isfinite(np.asarray(step(jnp.asarray(broken), jnp.asarray(f)))))
    with pytest.raises(ValueError, match="mesh"):
        newton.fallback_step(linear, scenes.bunny_scene())


def _turn(th):
    return np.array([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0], [0.0, 0.0, 1.0]])


def test_rotations_recover_a_rigid_rotation():
    pts, cells = fem.box_hex_mesh((8.0, 2.0, 2.0), (4, 1, 1))
    edges = np.asarray(mesh_edges(cells))
    rot = _turn(0.7) @ np.array([[1.0, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]])
    x = pts @ rot.T + np.array([1.0, -2.0, 0.5])
    rotation = newton.rotations(jnp.asarray(pts, jnp.float32), jnp.asarray(edges[0]), jnp.asarray(edges[1]))
    r = np.asarray(rotation(jnp.asarray(x, jnp.float32)))
    np.testing.assert_allclose(r, np.broadcast_to(rot, r.shape), atol=1e-5)
    stretched = pts * np.array([1.1, 1.0, 1.0])          # a pure stretch has no rotation
    r = np.asarray(rotation(jnp.asarray(stretched, jnp.float32)))
    np.testing.assert_allclose(r, np.broadcast_to(np.eye(3), r.shape), atol=1e-5)


def test_fem_scene_of_the_shipped_linear_models():
    # each shipped rest-linearised model names its FEM scene by its mesh, with the density and damping it records;
    # a model on no shipped scene's mesh is refused
    import tignn_jax

    for name, scene_name in (("beam-linear", "beam"), ("bunny-linear", "bunny")):
        linear, _ = tignn_jax.load_pretrained(name)
        scene = newton.fem_scene(linear)
        assert scene.name == scene_name
        assert scene.damping == pytest.approx(linear["info"]["fem_damping"])
        assert scene.material.density == pytest.approx(linear["info"]["fem_density"])
    other = dict(linear, mesh=dict(linear["mesh"], q0=np.asarray(linear["mesh"]["q0"]) * 2.0))
    with pytest.raises(ValueError, match="no shipped FEM scene"):
        newton.fem_scene(other)


@long
def test_the_demo_dynamics_of_fem_newton():
    # `tignn demo --model fem-newton` steps the beam with its scene's Newton step (not learned), which pushes a
    # pressed tip down, is labelled as the FEM and is not taken for the stand-in; it is `tignn_jax.fem_stepper`
    import tignn_jax
    from tignn_jax.cli.demo import build_scene

    linear, _ = tignn_jax.load_pretrained("beam-linear")
    scene, dynamics = build_scene("beam", 4, "fem-newton")
    assert dynamics.startswith("FEM backward Euler") and "not learned" in dynamics
    body = scene.bodies[0]
    q0 = np.asarray(body.q0)
    f = np.zeros((len(q0), 3), np.float32)
    tip = q0[:, 0] > q0[:, 0].max() - 1e-3
    f[tip, 2] = -1e3 / tip.sum()
    z = body.step_fn(jnp.asarray(body.z), jnp.asarray(f))
    assert np.all(np.isfinite(np.asarray(z))) and float(np.mean(np.asarray(z)[tip, 2] - q0[tip, 2])) < 0
    assert not bool(body.guard(z)) and bool(body.guard(z.at[0, 0].set(jnp.nan)))
    np.testing.assert_allclose(np.asarray(z), np.asarray(tignn_jax.fem_stepper(linear)(body.z, jnp.asarray(f))),
                               rtol=1e-5, atol=1e-5)
