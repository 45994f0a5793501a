"""The mixed-reality layer (`tignn_jax.mr`): camera maths, forcing, colour, shading and occlusion, against known
answers."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tignn_jax import mr

W, H = 640, 480
VIEWPORT = (0.0, 0.0, float(W), float(H))


def _camera():
    projection = mr.perspective(np.deg2rad(60.0), W / H, 0.1, 5.0)
    view = mr.look_at([0.3, 0.4, 1.2], [0.0, 0.05, 0.0], [0.0, 1.0, 0.0])
    model = mr.model_matrix([0.05, 0.0, -0.1], mr.rotation_matrix([0.2, 1.0, 0.1], 0.7), 0.01)
    return projection, view, model


def _points(n=200, seed=0):
    return jnp.asarray(np.random.default_rng(seed).uniform(-10, 10, size=(n, 3)), jnp.float32)


def test_project_unproject_round_trip():
    # unproject is the inverse of the chain clip = P·V·M·x given the depth the camera measures.
    projection, view, model = _camera()
    mvp = mr.mvp_matrix(projection, view, model)
    x = _points()
    pixels, depth = jax.jit(mr.project)(x, mvp, VIEWPORT)
    back = jax.jit(mr.unproject)(pixels, depth, mvp, VIEWPORT)
    scale = float(jnp.max(jnp.abs(x)))
    assert float(jnp.max(jnp.abs(back - x))) / scale < 1e-5


def test_near_and_far_planes_map_to_clip_limits():
    # OpenGL convention: the near plane is z_ndc = -1, the far plane z_ndc = +1, and depth = -z_eye.
    near, far = 0.1, 5.0
    projection = mr.perspective(np.deg2rad(50.0), 4 / 3, near, far)
    points = jnp.array([[0.01, -0.02, -near], [1.0, 0.5, -far]])
    clip = mr.clip_coordinates(points, projection)
    np.testing.assert_allclose(clip[:, 2] / clip[:, 3], [-1.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(clip[:, 3], [near, far], rtol=1e-6)


def test_frustum_corner_maps_to_image_corner():
    # The top-left corner of the near plane lands on pixel (0, 0): v grows downwards.
    fov, near = np.deg2rad(60.0), 0.2
    projection = mr.perspective(fov, W / H, near, 10.0)
    top = near * np.tan(fov / 2)
    pixels, depth = mr.project(jnp.array([[-top * W / H, top, -near]]), projection, VIEWPORT)
    np.testing.assert_allclose(pixels[0], [0.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(depth, [near], rtol=1e-6)


def test_intrinsics_projection_is_the_pinhole_model():
    # With P from intrinsics, project gives u = fx·x/d + cx and v = -fy·y/d + cy at depth d = -z.
    fx, fy, cx, cy = 520.0, 515.0, 330.0, 245.0
    projection = mr.projection_from_intrinsics(fx, fy, cx, cy, W, H, 0.1, 10.0)
    p = jnp.array([[0.1, -0.2, -1.5], [-0.3, 0.25, -0.8]])
    pixels, depth = mr.project(p, projection, VIEWPORT)
    d = -p[:, 2]
    np.testing.assert_allclose(pixels[:, 0], fx * p[:, 0] / d + cx, rtol=1e-5)
    np.testing.assert_allclose(pixels[:, 1], -fy * p[:, 1] / d + cy, rtol=1e-5)
    np.testing.assert_allclose(depth, d, rtol=1e-6)


def test_look_at_maps_eye_to_origin_and_target_onto_negative_z():
    # A camera looks down its -z axis; the target lies there at its distance from the eye.
    eye, target = jnp.array([1.0, 2.0, 3.0]), jnp.array([-0.5, 0.2, 0.4])
    view = mr.look_at(eye, target, [0.0, 1.0, 0.0])
    # float32: a few ulps of the coordinates' size (|eye| ≈ 3.7) summed over three products
    np.testing.assert_allclose(mr.transform_points(view, eye[None])[0], 0.0, atol=1e-5)
    t = mr.transform_points(view, target[None])[0]
    np.testing.assert_allclose(t[:2], 0.0, atol=1e-5)
    np.testing.assert_allclose(t[2], -jnp.linalg.norm(target - eye), rtol=1e-6)
    np.testing.assert_allclose(view[:3, :3] @ view[:3, :3].T, np.eye(3), atol=1e-6)


def test_model_matrix_scales_then_rotates_then_translates():
    # x_world = t + R·(s·x): a quarter turn about z sends s·e_x to s·e_y.
    m = mr.model_matrix([1.0, 2.0, 3.0], mr.rotation_matrix([0.0, 0.0, 1.0], np.pi / 2), 2.0)
    np.testing.assert_allclose(mr.transform_points(m, jnp.array([[1.0, 0.0, 0.0]]))[0], [1.0, 4.0, 3.0],
                               atol=1e-6)


def test_fingertip_unprojected_from_projected_node_lands_on_node():
    # A tracker that reports a node's pixel and camera depth puts the fingertip on that node.
    projection, view, model = _camera()
    mvp = mr.mvp_matrix(projection, view, model)
    node = jnp.array([[3.0, -2.0, 5.0]])
    pixels, depth = mr.project(node, mvp, VIEWPORT)
    world = mr.unproject(pixels, depth, projection @ view, VIEWPORT)  # the track knows no model
    tip = mr.transform_points(jnp.linalg.inv(model), world)
    np.testing.assert_allclose(tip, node, atol=1e-4)


def test_fingertip_forces_push_inwards_within_radius_only():
    # Nodes within the radius get `magnitude` along -n; all others (and missing NaN tips) get nothing.
    positions = jnp.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.9, 0.0]])
    normals = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    tips = jnp.array([[0.0, 0.0, 0.2], [np.nan, np.nan, np.nan]])
    f = jax.jit(mr.fingertip_forces)(tips, positions, normals, 1.0, 7.0)
    np.testing.assert_allclose(f, [[0, 0, -7.0], [0, 0, -7.0], [0, 0, 0], [0, 0, 0]], atol=0)


def test_a_spring_fingertip_pushes_its_pad_with_stiffness_times_depth_and_never_the_far_side():
    # a 3 x 3 x 2 block of nodes (top layer z = 2, bottom z = 0), pressed down (−z) at its centre
    x, y, z = np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0], [0.0, 2.0], indexing="ij")
    positions = jnp.asarray(np.stack([x.ravel(), y.ravel(), z.ravel()], 1), jnp.float32)
    surface = jnp.ones(len(positions), bool)
    down = jnp.asarray([0.0, 0.0, -1.0])
    tips = jnp.asarray([[0.0, 0.0, 1.25], [0.0, 0.0, 2.5], [np.nan] * 3], jnp.float32)   # 0.75 deep, above, missing
    pad, depth = jax.jit(mr.fingertip_pads)(tips, positions, surface, down, 1.1)
    top_near = np.asarray((positions[:, 2] == 2.0) & (jnp.linalg.norm(positions[:, :2], axis=1) < 1.1))
    np.testing.assert_array_equal(np.asarray(pad[0]), top_near)        # the centre and its 4 neighbours, top only
    np.testing.assert_allclose(np.asarray(depth[:2]), [0.75, -0.5], atol=1e-6)
    assert not np.asarray(pad[2]).any()
    f = np.asarray(jax.jit(mr.fingertip_spring_forces)(tips, positions, surface, down, 1.1, 40.0))
    np.testing.assert_allclose(f.sum(0), [0.0, 0.0, -40.0 * 0.75], rtol=1e-6)   # F = stiffness · depth
    np.testing.assert_allclose(f[top_near], np.tile([0.0, 0.0, -6.0], (5, 1)), rtol=1e-6)
    assert np.all(f[~top_near] == 0.0)
    # past the whole block the finger still pushes the top layer down, harder: it cannot pass through
    deep = np.asarray(mr.fingertip_spring_forces(jnp.asarray([[0.0, 0.0, -3.0]]), positions, surface, down, 1.1,
                                                 40.0))
    np.testing.assert_allclose(deep.sum(0), [0.0, 0.0, -200.0], rtol=1e-6)
    assert np.all(deep[:, 2] <= 0.0)


def test_contact_forces_are_equal_and_opposite():
    # Newton's third law: internal contact forces of the pair sum to zero.
    a = _points(300, 1) * 0.1
    b = _points(250, 2) * 0.1 + 0.5
    fa, fb = jax.jit(mr.contact_forces)(a, b, 0.3, 100.0)
    assert float(jnp.max(jnp.abs(fa))) > 0.0
    total = fa.sum(0) + fb.sum(0)
    assert float(jnp.max(jnp.abs(total))) < 1e-5 * float(jnp.abs(fa).sum())


def test_contact_forces_are_minus_energy_gradient():
    # The hand-derived penalty force is -dE/dx of E = Σ ½ k max(r0 - r, 0)².
    a = _points(60, 3) * 0.1
    b = _points(50, 4) * 0.1 + 0.3
    fa, fb = mr.contact_forces(a, b, 0.4, 10.0)
    ga, gb = jax.grad(mr.contact_energy, argnums=(0, 1))(a, b, 0.4, 10.0)
    np.testing.assert_allclose(fa, -ga, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(fb, -gb, rtol=1e-4, atol=1e-5)


def test_contact_forces_zero_when_far_apart():
    # No pair closer than the radius: no force, whether or not the bounding boxes overlap.
    a = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    fa, fb = mr.contact_forces(a, a + 5.0, 0.5, 1e3)
    fa2, fb2 = mr.contact_forces(a, jnp.array([[0.5, 0.0, 0.8]]), 0.5, 1e3)  # boxes overlap, nodes do not
    for f in (fa, fb, fa2, fb2):
        np.testing.assert_array_equal(f, 0.0)


def test_contact_force_of_one_pair_is_the_linear_spring():
    # Two nodes at distance 0.3 with radius 0.5 repel with k·(0.5 - 0.3) along their line.
    fa, fb = mr.contact_forces(jnp.array([[0.0, 0.0, 0.0]]), jnp.array([[0.0, 0.3, 0.0]]), 0.5, 10.0)
    np.testing.assert_allclose(fa, [[0.0, -2.0, 0.0]], rtol=1e-5)
    np.testing.assert_allclose(fb, [[0.0, 2.0, 0.0]], rtol=1e-5)


def test_colour_map_ends_and_clipping():
    # vmin is the first colour of the fixed map, vmax the last; values outside are clipped.
    c = mr.colour_map(jnp.array([-1.0, 0.0, 10.0, 20.0]), 0.0, 10.0)
    np.testing.assert_allclose(c[0], c[1])
    np.testing.assert_allclose(c[2], c[3])
    np.testing.assert_allclose(c[1], mr.render._COLOUR_TABLE[0], atol=1e-6)
    np.testing.assert_allclose(c[2], mr.render._COLOUR_TABLE[-1], atol=1e-6)


def test_vertex_normals_of_a_cube_corner_point_along_the_diagonal():
    # A unit cube's corner touches three faces of equal area: its normal is the outward diagonal.
    points = jnp.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
                       jnp.float32)
    tris = mr.surface_triangles(np.arange(8)[None], np.asarray(points))
    n = mr.vertex_normals(points, jnp.asarray(tris))
    centre = points - 0.5
    np.testing.assert_allclose(n, centre / jnp.linalg.norm(centre, axis=1, keepdims=True), atol=1e-6)


def test_phong_terms():
    # Light along -n: ambient + diffuse + full specular towards an eye on the normal; light behind: ambient only.
    p, n, c = jnp.zeros((1, 3)), jnp.array([[0.0, 0.0, 1.0]]), jnp.array([[0.5, 0.2, 0.1]])
    front = mr.phong(p, n, c, eye=[0.0, 0.0, 2.0], light_dir=[0.0, 0.0, -1.0], ambient=0.2, diffuse=0.5,
                     specular=0.1)
    back = mr.phong(p, n, c, eye=[0.0, 0.0, 2.0], light_dir=[0.0, 0.0, 1.0], ambient=0.2, diffuse=0.5,
                    specular=0.1)
    np.testing.assert_allclose(front, 0.7 * c + 0.1, rtol=1e-6)
    np.testing.assert_allclose(back, 0.2 * c, rtol=1e-6)


def test_virtual_object_behind_real_wall_is_not_drawn():
    # A real wall at 1 m hides a virtual pixel at 1.5 m and shows one at 0.5 m.
    virtual = jnp.ones((2, 2, 3))
    real = jnp.zeros((2, 2, 3))
    virtual_depth = jnp.array([[1.5, 0.5], [jnp.inf, 1.5]])
    real_depth = jnp.array([[1.0, 1.0], [1.0, 0.0]])  # 0 = no depth measured
    out = mr.occlude(virtual, virtual_depth, real, real_depth)
    np.testing.assert_array_equal(out[..., 0], [[0.0, 1.0], [0.0, 1.0]])


def test_camera_inputs_are_validated():
    with pytest.raises(ValueError, match="near"):
        mr.perspective(1.0, 1.0, -0.1, 1.0)
    with pytest.raises(ValueError, match="far"):
        mr.perspective(1.0, 1.0, 2.0, 1.0)
    with pytest.raises(ValueError, match="eye"):
        mr.look_at([0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0])


def test_pruned_contact_matches_all_pairs_and_falls_back_when_full():
    # Restricting to nodes inside the other body's grown box loses no pair; an overfull buffer falls back.
    a = _points(300, 5) * 0.1
    b = _points(250, 6) * 0.1 + jnp.array([1.6, 0.0, 0.0])
    fa, fb = mr.contact_forces(a, b, 0.3, 100.0)
    assert float(jnp.abs(fa).max()) > 0.0
    for capacity in (200, 4):
        pa, pb = jax.jit(lambda a, b: mr.contact_forces(a, b, 0.3, 100.0, capacity=capacity))(a, b)
        np.testing.assert_allclose(pa, fa, rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(pb, fb, rtol=1e-5, atol=1e-4)
