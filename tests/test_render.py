"""Software rasteriser and surface extraction (`tignn_jax.mr`), against brute-force and geometric answers; the
scene loop."""

import jax.numpy as jnp
import numpy as np
import pytest

from tignn_jax.mr import draw_mesh, fragment_capacity, rasterize, surface_nodes, surface_triangles

W, H = 64, 48


def _brute_force_coverage(tri, width, height):
    """Pixels whose centre lies strictly inside the 2-D triangle ``tri`` [3,2]."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    def edge(a, b):
        return (b[0] - a[0]) * (v - a[1]) - (b[1] - a[1]) * (u - a[0])
    e = np.stack([edge(tri[0], tri[1]), edge(tri[1], tri[2]), edge(tri[2], tri[0])])
    return np.all(e > 0, axis=0) | np.all(e < 0, axis=0)


def _draw(pixels, depth, colours, triangles, capacity=32768):
    return rasterize(jnp.asarray(pixels, jnp.float32), jnp.asarray(depth, jnp.float32),
                     jnp.asarray(colours, jnp.float32), jnp.asarray(triangles, jnp.int32),
                     width=W, height=H, capacity=capacity)


def test_triangle_pixel_coverage_matches_pixel_centre_rule():
    # A pixel is drawn exactly when its centre is inside the triangle (no vertex lies on a pixel centre).
    tri = np.array([[5.3, 40.7], [50.2, 33.1], [20.6, 3.9]])  # clockwise in pixels = front-facing
    out = _draw(tri, [1.0, 1.0, 1.0], np.ones((3, 3)), [[0, 1, 2]])
    expected = _brute_force_coverage(tri, W, H)
    assert expected.sum() > 300
    np.testing.assert_array_equal(np.asarray(out.triangle) == 0, expected)
    np.testing.assert_array_equal(np.isfinite(np.asarray(out.depth)), expected)
    assert not bool(out.overflow)


def test_back_face_is_culled():
    # The same triangle wound the other way faces away from the camera and is not drawn.
    tri = np.array([[5.3, 40.7], [20.6, 3.9], [50.2, 33.1]])
    out = _draw(tri, [1.0, 1.0, 1.0], np.ones((3, 3)), [[0, 1, 2]])
    assert int((np.asarray(out.triangle) >= 0).sum()) == 0


def test_triangle_behind_camera_is_not_drawn():
    # A vertex at negative depth is behind the eye; the triangle is dropped rather than wrapped around.
    tri = np.array([[5.3, 40.7], [50.2, 33.1], [20.6, 3.9]])
    out = _draw(tri, [1.0, -1.0, 1.0], np.ones((3, 3)), [[0, 1, 2]])
    assert int((np.asarray(out.triangle) >= 0).sum()) == 0


def test_nearer_triangle_wins_the_z_buffer():
    # Two overlapping triangles: the pixel shows the one with the smaller depth, wherever they overlap.
    square = np.array([[2.0, 46.0], [62.0, 46.0], [62.0, 2.0], [2.0, 2.0]])
    pixels = np.concatenate([square, square])
    depth = [2.0, 2.0, 2.0, 2.0, 1.0, 1.0, 3.0, 3.0]      # second quad tilted through the first
    colours = np.concatenate([np.tile([1.0, 0.0, 0.0], (4, 1)), np.tile([0.0, 0.0, 1.0], (4, 1))])
    tris = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]  # clockwise in pixels
    out = _draw(pixels, depth, colours, tris)
    assert not bool(out.overflow)
    d = np.asarray(out.depth)
    rgb = np.asarray(out.rgb)
    drawn = np.isfinite(d)
    # the tilted quad's depth is 1 at v = 46 and 3 at v = 2 (perspective-correct: 1/depth is linear in v)
    v = np.arange(H) + 0.5
    inv = 1.0 / 1.0 + (1.0 / 3.0 - 1.0) * (46.0 - v) / 44.0
    tilted_nearer = (1.0 / inv < 2.0)[:, None] & drawn
    assert tilted_nearer.sum() > 0 and (drawn & ~tilted_nearer).sum() > 0
    np.testing.assert_allclose(rgb[tilted_nearer], np.tile([0.0, 0.0, 1.0], (tilted_nearer.sum(), 1)), atol=1e-5)
    np.testing.assert_allclose(rgb[drawn & ~tilted_nearer], [[1.0, 0.0, 0.0]] * int((drawn & ~tilted_nearer).sum()),
                               atol=1e-5)
    np.testing.assert_allclose(d[drawn], np.minimum(2.0, np.broadcast_to(1.0 / inv[:, None], d.shape)[drawn]),
                               rtol=1e-4)


def test_vertex_colours_interpolate_linearly_at_equal_depth():
    # At constant depth, perspective-correct interpolation is plain barycentric interpolation.
    tri = np.array([[4.0, 44.0], [60.0, 44.0], [4.0, 4.0]])
    colours = np.eye(3)
    out = _draw(tri, [1.5] * 3, colours, [[0, 1, 2]])
    rgb = np.asarray(out.rgb)
    j, i = 30, 10  # pixel centre (10.5, 30.5)
    u, v = i + 0.5, j + 0.5
    b_right = (u - 4.0) / 56.0
    b_top = (44.0 - v) / 40.0
    np.testing.assert_allclose(rgb[j, i], [1.0 - b_right - b_top, b_right, b_top], atol=1e-5)


def test_overflow_is_reported_when_capacity_is_too_small():
    # Fragments beyond the static buffer are dropped, and the caller is told.
    tri = np.array([[5.3, 40.7], [50.2, 33.1], [20.6, 3.9]])
    out = _draw(tri, [1.0, 1.0, 1.0], np.ones((3, 3)), [[0, 1, 2]], capacity=100)
    assert bool(out.overflow)
    assert fragment_capacity(tri, [1.0] * 3, np.array([[0, 1, 2]]), W, H, headroom=1.0, minimum=1) > 100


def _box_hex(nx, ny, nz, h=1.0):
    ijk = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    node = np.arange(ijk[..., 0].size).reshape(ijk.shape[:3])
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    corners = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))
    cells = np.stack([node[i + a, j + b, k + c] for a, b, c in corners], axis=1)
    return ijk.reshape(-1, 3) * h, cells


def _enclosed_volume(points, tris):
    p = points[tris]
    return np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0


def _each_edge_shared_by_two_opposite_triangles(tris):
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    fwd = {tuple(e) for e in directed}
    return len(fwd) == len(directed) and all((b, a) in fwd for a, b in directed)


def test_hex8_boundary_of_the_beam_box():
    # 40x10x10 box, 20x5x5 hex of edge 2: 450 boundary quads -> 900 outward triangles enclosing 4000.
    points, cells = _box_hex(20, 5, 5, 2.0)
    tris = surface_triangles(cells, points)
    assert tris.shape == (900, 3)
    np.testing.assert_allclose(_enclosed_volume(points, tris), 4000.0)
    assert _each_edge_shared_by_two_opposite_triangles(tris)
    assert len(surface_nodes(tris)) == 756 - 19 * 4 * 4


def test_tet4_boundary_of_a_split_cube_is_closed_and_outward():
    # A 2x2x2 hex block split into 6 tets each: 24 unit squares -> 48 outward triangles enclosing 8.
    points, hexes = _box_hex(2, 2, 2)
    split = np.array([[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]])
    tets = hexes[:, split].reshape(-1, 4)
    tets[::2] = tets[::2][:, [0, 2, 1, 3]]  # inverted elements are oriented by geometry
    tris = surface_triangles(tets, points)
    assert tris.shape == (48, 3)
    np.testing.assert_allclose(_enclosed_volume(points, tris), 8.0)
    assert _each_edge_shared_by_two_opposite_triangles(tris)


def test_surface_triangles_rejects_other_cells():
    with pytest.raises(ValueError, match="cells"):
        surface_triangles(np.zeros((3, 6), int), np.zeros((6, 3)))


# ------------------------------------------------------------------------------- scenes and the loop

import jax  # noqa: E402

from tignn_jax import mr  # noqa: E402


def _spring_mass_step(q0, cells, clamped, k=40.0, damping=0.2, dt=0.05, mass=1.0):
    """Stand-in dynamics (not the learned model): damped springs on the mesh edges, clamped nodes fixed.
    State z = [q, v, sigma]; sigma gets the mean spring tension in S11 so the colour map has something to show."""
    edges = np.unique(np.sort(cells[:, [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                                        [0, 4], [1, 5], [2, 6], [3, 7]]].reshape(-1, 2), axis=1), axis=0)
    i, j = jnp.asarray(edges[:, 0]), jnp.asarray(edges[:, 1])
    rest = jnp.linalg.norm(jnp.asarray(q0[edges[:, 1]] - q0[edges[:, 0]]), axis=1)
    free = jnp.asarray(~clamped, jnp.float32)[:, None]

    def step(z, f):
        q, v = z[:, :3], z[:, 3:6]
        d = q[j] - q[i]
        length = jnp.linalg.norm(d, axis=1)
        tension = k * (length - rest)
        fe = (tension / length)[:, None] * d
        f_int = jnp.zeros_like(q).at[i].add(fe).at[j].add(-fe)
        v = free * ((1.0 - damping) * v + dt * (f_int + f) / mass)
        s11 = jnp.zeros(len(q)).at[i].add(tension).at[j].add(tension) / 6.0
        sigma = jnp.zeros((len(q), 6)).at[:, 0].set(s11)
        return jnp.concatenate([q + dt * v, v, sigma], axis=1)

    return step


def _demo_scene(frames=10, width=160, height=120):
    points, cells = _box_hex(4, 2, 2)
    clamped = points[:, 0] == 0.0
    tris = surface_triangles(cells, points)
    model = mr.model_matrix([-0.04, 0.0, -0.02], np.eye(3), 0.02)       # 8 x 4 x 4 cm on the table
    view = np.asarray(mr.look_at([0.02, 0.15, 0.22], [0.0, 0.02, 0.0], [0.0, 1.0, 0.0]))
    cam = mr.Camera(fx=150.0, fy=150.0, cx=width / 2, cy=height / 2, width=width, height=height, near=0.02,
                    far=3.0, view=view)
    z0 = np.concatenate([points, np.zeros((len(points), 9))], axis=1).astype(np.float32)
    top_end = np.asarray(mr.transform_points(model, jnp.array([[4.0, 2.0, 1.0]])))[0]
    body = mr.Body(q0=points, triangles=tris, model=np.asarray(model), z=z0,
                   step_fn=_spring_mass_step(points, cells, clamped), tip_radius=1.2, tip_force=3.0, vmax=5.0)
    track = mr.press_track(cam, top_end, [0.0, 1.0, 0.0], frames)
    return mr.Scene(bodies=(body,), camera=cam, background=mr.table_background(cam), track=track), top_end


def test_scene_loop_compiles_only_on_the_first_frame():
    # Real time needs fixed shapes: after frame 0 no stage (nor the fingertip padding) triggers a compile.
    compiles = []

    def listener(event, duration, **kw):
        if "backend_compile" in event:
            compiles.append(event)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        scene, _ = _demo_scene(frames=6)
        seen = []
        mr.run(scene, write=lambda i, rgb: seen.append(len(compiles)))
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert seen[0] > 0 and seen[-1] == seen[0]


def test_fingertip_press_pushes_the_body_down_and_frames_are_drawn():
    # A fingertip pressing the free end's top face bends the cantilever downwards (-y), and every frame shows it.
    scene, _ = _demo_scene(frames=10)
    frames = []
    zs, timings = mr.run(scene, write=lambda i, rgb: frames.append(rgb))
    q0 = scene.bodies[0].q0
    q = np.asarray(zs[0][:, :3])
    tip_nodes = q0[:, 0] == 4.0
    assert np.all(q[tip_nodes, 1] - q0[tip_nodes, 1] < -1e-3)
    np.testing.assert_array_equal(q[q0[:, 0] == 0.0], q0[q0[:, 0] == 0.0])
    background = (np.asarray(scene.background.rgb) * 255 + 0.5).astype(np.uint8)
    assert len(frames) == 10 and frames[0].shape == (120, 160, 3) and frames[0].dtype == np.uint8
    assert all(np.any(f != background) for f in frames)
    summary = timings.summary()
    assert summary["frames"] == 9 and set(summary) >= {"forces", "step", "render", "write", "frame"}


def test_fused_simulation_frames_match_the_stages_run_one_by_one():
    # Once touched, a scene without devices runs forces, step and guard as one program per frame; its states
    # equal those of the separate forces and step stages applied frame by frame.
    scene, _ = _demo_scene(frames=8)
    scene = scene._replace(skip_rest=False, guard=lambda zs: ~jnp.all(jnp.isfinite(zs[0])))
    zs, t = mr.run(scene)
    forces_fn, step_fn, _, _ = mr.build(scene)
    ref = (jnp.asarray(scene.bodies[0].z, jnp.float32),)
    for tips in scene.track:
        ref = step_fn(ref, forces_fn(ref, tips))
    np.testing.assert_allclose(np.asarray(zs[0]), np.asarray(ref[0]), rtol=1e-6, atol=1e-6)
    assert t.fused_frames == 7 and t.summary()["fused_frames"] == 7 and t.guard_trips == 0
    assert np.all(t.forces == 0.0) and np.all(t.step > 0.0)   # the forces are timed inside the step stage
    assert t.learned.shape == (7,) and t.learned.all() and t.summary()["learned_frames"] == 7


@pytest.mark.long
def test_bodies_on_their_own_devices_step_as_in_one_program():
    # Scene.devices: each body steps on its own (virtual CPU) device, concurrently; the states are those of the
    # serial loop, and the scene with a step over all bodies as well as devices is refused.
    import os
    import subprocess
    import sys
    import textwrap
    from pathlib import Path

    script = textwrap.dedent("""
        import sys
        import numpy as np
        from tignn_jax import mr
        devices = mr.cpu_devices(2)
        assert len(devices) == 2, devices
        sys.path.insert(0, "tests")
        from test_render import _demo_scene
        scene, _ = _demo_scene(frames=6)
        b = scene.bodies[0]
        beside = np.asarray(mr.model_matrix([-0.04, 0.0, 0.08], np.eye(3), 0.02))   # 10 cm further along z
        two = scene._replace(bodies=(b, b._replace(model=beside)))
        serial, _ = mr.run(two)
        parallel, t = mr.run(two._replace(devices=devices))
        for a, c in zip(serial, parallel):
            np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=1e-6, atol=1e-6)
        assert np.abs(np.asarray(parallel[0])[:, :3] - b.q0).max() > 1e-3   # the pressed body moved
        assert all(list(z.devices())[0] == devices[0] for z in parallel)
        # each body's own guard runs in its step's program on its device (Scene.fuse): the same states and
        # trips as the stages awaited one by one, the bad body reset, the good one stepped
        import jax.numpy as jnp
        finite = lambda z: ~jnp.all(jnp.isfinite(z))
        good = b._replace(guard=finite)
        bad = b._replace(model=beside, step_fn=lambda z, f: z * jnp.nan, guard=finite)
        guarded = scene._replace(bodies=(good, bad), devices=devices, skip_rest=False)
        fused, tf = mr.run(guarded)
        staged, ts = mr.run(guarded._replace(fuse=False))
        for a, c in zip(fused, staged):
            np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(np.asarray(fused[1]), b.z)
        assert tf.fused_frames == 5 and ts.fused_frames == 0 and np.all(tf.forces == 0.0)
        assert tf.guard_trips == ts.guard_trips == 6, (tf.guard_trips, ts.guard_trips)   # every frame, warm-up too
        # with a fallback, the fused frame programs hand the bad body over themselves and, while it is held,
        # run only its fallback: restart (+1) at frames 0 and 3, held (+2) at frames 1, 2, 4, 5
        import jax
        fb = jax.jit(lambda z, f, restart: z + jnp.where(restart, 1.0, 2.0))
        handed = guarded._replace(fallback=(None, fb), fallback_hold=2)
        # and with the next-frame hand-over the trip frames (0, 3) keep the state and the next ones catch up
        # (+1 +2): the same states once caught up, one restart step fewer after frame 3
        for mode, after_four in (("same-frame", 6.0), ("next-frame", 5.0)):
            run = handed._replace(handover=mode)
            fused, tf = mr.run(run)
            staged, ts = mr.run(run._replace(fuse=False))
            for a, c in zip(fused, staged):
                np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=1e-6, atol=1e-6)
            np.testing.assert_allclose(np.asarray(fused[1]), b.z + 10.0, rtol=1e-6)
            assert tf.guard_trips == ts.guard_trips == 2, (mode, tf.guard_trips, ts.guard_trips)
            assert tf.fused_frames == 5, (mode, tf.fused_frames)
            short, _ = mr.run(run, frames=4)
            np.testing.assert_allclose(np.asarray(short[1]), b.z + after_four, rtol=1e-6)
        try:
            mr.run(two._replace(devices=devices, step=lambda zs, fs: zs))
        except ValueError as err:
            assert "devices" in str(err)
        else:
            raise AssertionError("devices with a scene step was accepted")
        print("DEVICES OK")
    """)
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600,
                         cwd=str(Path(__file__).resolve().parents[1]))
    assert out.returncode == 0, out.stderr[-3000:]
    assert "DEVICES OK" in out.stdout


def test_track_json_lines_round_trip(tmp_path):
    # A user's tracker output (varying numbers of tips, empty frames) reads back as a NaN-padded array.
    path = tmp_path / "track.jsonl"
    path.write_text('{"frame": 0, "tips": [[320.5, 240.25, 0.41]]}\n'
                    '{"frame": 1, "tips": []}\n'
                    '{"frame": 2, "tips": [[1, 2, 0.5], [3, 4, 0.6]], "hand": "right"}\n')
    track = mr.load_track(path, max_tips=3)
    assert track.shape == (3, 3, 3)
    np.testing.assert_allclose(track[0, 0], [320.5, 240.25, 0.41], rtol=1e-6)
    assert np.isnan(track[1]).all() and np.isnan(track[0, 1:]).all()
    mr.save_track(tmp_path / "again.jsonl", track)
    np.testing.assert_array_equal(mr.load_track(tmp_path / "again.jsonl", max_tips=3), track)


def test_press_track_fingertip_unprojects_onto_the_pressed_point():
    # At mid-track the fingertip is `press` inside the surface along -normal: unprojecting gives that point.
    scene, top_end = _demo_scene(frames=11)
    cam = scene.camera
    vp = jnp.asarray(mr.camera_projection(cam) @ cam.view)
    tip = scene.track[5]
    world = mr.unproject(jnp.asarray(tip[:, :2]), jnp.asarray(tip[:, 2]), vp, (0.0, 0.0, cam.width, cam.height))
    np.testing.assert_allclose(world[0], top_end - np.array([0.0, 0.01, 0.0]), atol=1e-5)


def test_fingertip_proxy_rests_on_the_surface_it_is_pressed_into():
    # A flat surface at depth 0.5 m: a touching sphere of radius r behind it is moved to rest on it (centre r in
    # front: its footprint's deepest point is the centre's d + r); one in front, one behind it that touches no
    # body, a missing one and one over empty space stay where they are.
    cam = mr.Camera(fx=150.0, fy=150.0, cx=80.0, cy=60.0, width=160, height=120, near=0.02, far=3.0,
                    view=np.eye(4))
    r = 0.01
    depth = jnp.full((120, 160), 0.5).at[:, 120:].set(jnp.inf)
    tips = jnp.array([[60.5, 60.5, 0.51], [60.5, 60.5, 0.45], [60.5, 60.5, 0.9], [np.nan] * 3,
                      [150.5, 60.5, 0.7]])     # on pixel centres: the footprint's centre pixel is the sphere's
    touching = jnp.array([True, True, False, True, True])
    moved = np.asarray(mr.rest_on_surface(tips, depth, cam, r, touching))
    np.testing.assert_allclose(moved[0], [60.5, 60.5, 0.5 - r], atol=1e-6)
    np.testing.assert_array_equal(moved[1:3], np.asarray(tips[1:3]))
    assert np.all(np.isnan(moved[3]))
    np.testing.assert_array_equal(moved[4], np.asarray(tips[4]))
    # the deepest part of the sphere then lies on the surface: no pixel of its footprint is behind it
    np.testing.assert_array_equal(np.asarray(mr.rest_on_surface(jnp.asarray(moved[:1]), depth, cam, r)),
                                  moved[:1])


def test_pressing_fingertip_is_drawn_in_front_of_the_deformed_body():
    # At mid-press the track is 1 cm inside the body: the fingertip touches it, and the proxy is drawn on the
    # body's surface, so the pixel under the fingertip shows skin, not the body it would otherwise sink into.
    scene, _ = _demo_scene(frames=11)
    from tignn_jax.mr.scene import make_render_fn

    render = make_render_fn(scene, 65536)
    zs = tuple(jnp.asarray(b.z) for b in scene.bodies)
    tip = jnp.asarray(scene.track[5])
    u, v = np.floor(np.asarray(tip[0, :2])).astype(int)
    rgb, _ = render(zs, tip)
    skin = np.array([0.93, 0.72, 0.6])
    colour = np.asarray(rgb)[v, u] / 255.0
    assert np.allclose(colour / colour.max(), skin / skin.max(), atol=0.05)


def test_scene_validation_names_the_bad_array():
    scene, _ = _demo_scene(frames=2)
    bad = scene._replace(bodies=(scene.bodies[0]._replace(z=np.zeros((3, 12))),))
    with pytest.raises(ValueError, match=r"bodies\[0\].z"):
        mr.run(bad)


def _box_view():
    points, cells = _box_hex(4, 2, 2)
    tris = surface_triangles(cells, points)
    model = mr.model_matrix([-0.04, 0.0, -0.02], np.eye(3), 0.02)
    world = mr.transform_points(model, jnp.asarray(points, jnp.float32))
    view = mr.look_at([0.05, 0.12, 0.2], [0.0, 0.02, 0.0], [0.0, 1.0, 0.0])
    vp = mr.perspective(np.deg2rad(50.0), W / H, 0.02, 2.0) @ view
    return points, tris, model, world, vp


def test_fingertip_at_a_rendered_nodes_pixel_and_depth_lands_on_the_node():
    # A tracker reads a pixel and the depth image there; unprojecting it recovers the surface point it sees,
    # to within the pixel's footprint on the (obliquely seen) surface.
    points, tris, model, world, vp = _box_view()
    width, height = 320, 240
    raster = jax.jit(lambda q: draw_mesh(q, jnp.asarray(tris), jnp.ones_like(q) * 0.5, vp, jnp.zeros(3),
                                         jnp.array([0.0, -1.0, 0.0]), width=width, height=height,
                                         capacity=131072))(world)
    assert not bool(raster.overflow)
    viewport = (0.0, 0.0, width, height)
    pixels, depth = mr.project(world, vp, viewport)
    node = int(np.flatnonzero(np.all(points == [2.0, 2.0, 1.0], axis=1))[0])  # centre of the top face, seen from above
    i, j = np.floor(np.asarray(pixels[node])).astype(int)
    seen = float(raster.depth[j, i])
    footprint = 3 * float(depth[node]) * 2 * np.tan(np.deg2rad(25.0)) / height   # 3 pixels, in metres
    assert abs(seen - float(depth[node])) < footprint
    tip = mr.unproject(jnp.array([[i + 0.5, j + 0.5]]), jnp.array([seen]), vp, viewport)
    assert float(jnp.linalg.norm(tip[0] - world[node])) < footprint


def test_virtual_body_behind_a_real_wall_is_not_drawn():
    # The whole render path: a real wall nearer than the body hides it; moved behind the body, it shows it.
    points, tris, model, world, vp = _box_view()
    raster = draw_mesh(world, jnp.asarray(tris), jnp.ones_like(world), vp, jnp.zeros(3),
                       jnp.array([0.0, -1.0, 0.0]), width=W, height=H, capacity=32768)
    real_rgb = jnp.zeros((H, W, 3))
    drawn = np.isfinite(np.asarray(raster.depth))
    assert drawn.sum() > 50
    hidden = mr.occlude(raster.rgb, raster.depth, real_rgb, jnp.full((H, W), 0.05))   # wall at 5 cm
    shown = mr.occlude(raster.rgb, raster.depth, real_rgb, jnp.full((H, W), 1.5))     # wall at 1.5 m
    assert float(jnp.abs(hidden).max()) == 0.0
    np.testing.assert_array_equal(np.asarray(shown)[drawn], np.asarray(raster.rgb)[drawn])


def test_untouched_bodies_at_rest_are_not_stepped():
    # Skip what the scene does not need: until the fingertip first reaches the body nothing moves, so the
    # step is skipped and the state stays exactly the rest state; stepping resumes at the first touch.
    scene, _ = _demo_scene(frames=4)
    away = np.full_like(scene.track, np.nan)               # no fingertip at all
    body = scene.bodies[0]
    drifting = body._replace(step_fn=lambda z, f: body.step_fn(z, f) + 1e-3)   # a step that never rests
    zs, _ = mr.run(scene._replace(track=away, bodies=(drifting,)))
    np.testing.assert_array_equal(np.asarray(zs[0]), body.z)
    zs_all, _ = mr.run(scene._replace(track=away, bodies=(drifting,), skip_rest=False))
    assert np.abs(np.asarray(zs_all[0]) - body.z).max() > 1e-3   # without the skip it would have stepped
    zs_press, _ = mr.run(scene)                             # the press touches it: it moves
    assert np.abs(np.asarray(zs_press[0])[:, :3] - body.q0).max() > 1e-3


def test_colour_by_displacement_draws_without_stress():
    # coloured by |q − q0|, the frames do not depend on the state's σ (the same run with σ × 100 draws the same
    # pixels); coloured by stress, that run draws other colours
    scene, _ = _demo_scene(frames=3)
    body = scene.bodies[0]
    loud = body._replace(step_fn=lambda z, f: body.step_fn(z, f) * jnp.repeat(jnp.array([1.0, 100.0]), 6))

    def last_frame(colour_by, b):
        frames = []
        mr.run(scene._replace(colour_by=colour_by, bodies=(b,)), write=lambda i, rgb: frames.append(rgb))
        assert len(frames) == 3 and frames[-1].shape == (120, 160, 3)
        return frames[-1].astype(int)

    by_u = last_frame("displacement", loud)
    np.testing.assert_array_equal(last_frame("displacement", body), by_u)
    assert np.abs(last_frame("stress", loud) - by_u).sum(-1).astype(bool).sum() > 100
    with pytest.raises(ValueError, match="colour_by"):
        mr.run(scene._replace(colour_by="temperature"))


def test_clamped_nodes_are_drawn_in_the_clamp_colour_and_the_legend_names_them():
    # the supports show: the box's clamped end (x = 0) is drawn in CLAMP_COLOUR, not the colour map; the pixels it
    # changes turn from the map's blue-purple towards that brick red (shaded, and interpolated over the elements
    # next to the clamp), and the legend's swatch carries the exact colour and its name
    scene, _ = _demo_scene(frames=1)
    body = scene.bodies[0]
    clamped = np.asarray(body.q0)[:, 0] == 0.0
    plain, marked = [], []
    mr.run(scene, write=lambda i, rgb: plain.append(rgb))
    mr.run(scene._replace(bodies=(body._replace(clamped=clamped),)), write=lambda i, rgb: marked.append(rgb))
    changed = np.any(plain[0] != marked[0], axis=-1)
    assert changed.sum() > 20
    red, before = marked[0][changed].astype(float), plain[0][changed].astype(float)
    assert np.mean((red[:, 0] - red[:, 2]) - (before[:, 0] - before[:, 2])) > 30
    framed = mr.with_legend(marked[0], 0.0, body.vmax, "von Mises stress", swatches=(("clamped", mr.CLAMP_COLOUR),))
    swatch = np.round(255 * np.asarray(mr.CLAMP_COLOUR)).astype(np.uint8)
    assert np.all(framed == swatch, axis=-1).sum() >= 100    # a 14 x 14 square less its outline
    with pytest.raises(ValueError, match="clamped"):
        mr.validate(scene._replace(bodies=(body._replace(clamped=clamped[:-1]),)))


def test_guard_resets_bodies_whose_state_goes_bad():
    # A step that produces NaN once touched: the guard rejects the state and the body shows its rest state.
    scene, _ = _demo_scene(frames=6)
    body = scene.bodies[0]
    bad = body._replace(step_fn=lambda z, f: z * jnp.nan)
    zs, t = mr.run(scene._replace(bodies=(bad,), guard=lambda zs: ~jnp.all(jnp.isfinite(zs[0]))))
    np.testing.assert_array_equal(np.asarray(zs[0]), body.z)
    assert t.guard_trips > 0 and t.summary()["guard_trips"] == t.guard_trips


@pytest.mark.long   # CI time: test_guard_resets_bodies_whose_state_goes_bad covers the guard
def test_guard_with_one_flag_per_body_resets_only_the_flagged_body():
    # Two bodies, one whose step goes bad: a guard that returns one flag per body resets that body alone and
    # counts one trip per reset body; the other keeps stepping.
    scene, _ = _demo_scene(frames=6)
    body = scene.bodies[0]
    bad = body._replace(step_fn=lambda z, f: z * jnp.nan)
    guard = lambda zs: jnp.stack([~jnp.all(jnp.isfinite(z)) for z in zs])
    zs, t = mr.run(scene._replace(bodies=(body, bad), guard=guard))
    np.testing.assert_array_equal(np.asarray(zs[1]), body.z)
    assert np.abs(np.asarray(zs[0])[:, :3] - body.q0).max() > 1e-3    # the good body was pressed and moved
    assert t.guard_trips > 0
    # the same with each body's own guard (Body.guard) instead of one over all bodies; both at once is refused
    finite = lambda z: ~jnp.all(jnp.isfinite(z))
    own = scene._replace(bodies=(body._replace(guard=finite), bad._replace(guard=finite)))
    zs_own, t_own = mr.run(own)
    for a, c in zip(zs, zs_own):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
    assert t_own.guard_trips == t.guard_trips
    with pytest.raises(ValueError, match="not both"):
        mr.run(own._replace(guard=guard))


def test_one_program_per_frame_runs_a_held_body_on_its_fallback_alone():
    # Without devices, bodies with their own step and guard run their whole frame in one program per frame:
    # the hand-over inside it and, for a body held on its fallback, only the fallback (lax.cond): its learned
    # step is not executed (counted by a callback in it). States and trips equal the stages run one by one.
    scene, _ = _demo_scene(frames=6)
    body = scene.bodies[0]
    calls = []

    def bad_step(z, f):
        jax.debug.callback(lambda: calls.append(1))
        return z * jnp.nan

    finite = lambda z: ~jnp.all(jnp.isfinite(z))
    fb = jax.jit(lambda z, f, restart: z + jnp.where(restart, 1.0, 2.0))
    handed = scene._replace(bodies=(body._replace(guard=finite), body._replace(step_fn=bad_step, guard=finite)),
                            skip_rest=False, fallback=(None, fb), fallback_hold=2)
    fused, tf = mr.run(handed)
    fused_calls, calls[:] = len(calls), []
    staged, ts = mr.run(handed._replace(fuse=False))
    for a, c in zip(fused, staged):
        np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=1e-6, atol=1e-6)
    # restart (+1) at frames 0 and 3, held (+2) at frames 1, 2, 4, 5
    np.testing.assert_allclose(np.asarray(fused[1]), body.z + 10.0, rtol=1e-6)
    assert tf.guard_trips == ts.guard_trips == 2 and tf.fused_frames == 5
    # learned step of the bad body: the warm-up compile run, then frames 0 and 3 only (the staged loop's
    # one step over all bodies also runs it while the other body is not held: every frame)
    assert fused_calls == 1 + 2, fused_calls
    assert len(calls) > fused_calls


def test_guard_hands_flagged_bodies_to_their_fallback_for_the_hold():
    # Two bodies whose step goes bad once touched; the second has a fallback (here: a step that moves every
    # node by one unit in x and marks σ11 with the restart flag). A flagged body is stepped by its fallback from
    # its previous state (restart True at the hand-over, False after) for fallback_hold more frames, then its
    # step resumes and is flagged again; the body without a fallback is reset. One trip per hand-over or reset.
    scene, _ = _demo_scene(frames=6)
    body = scene.bodies[0]
    bad = body._replace(step_fn=lambda z, f: z * jnp.nan)

    def fallback(z, f, restart):
        return z.at[:, 0].add(1.0).at[:, 6].set(jnp.where(restart, 7.0, 0.0))

    guard = lambda zs: jnp.stack([~jnp.all(jnp.isfinite(z)) for z in zs])
    hold = 2
    run = scene._replace(bodies=(bad, bad), guard=guard, fallback=(None, jax.jit(fallback)), fallback_hold=hold)
    zs, t = mr.run(run, frames=7)
    np.testing.assert_array_equal(np.asarray(zs[0]), body.z)                      # reset
    z1 = np.asarray(zs[1])
    assert np.all(np.isfinite(z1))
    steps = round(float(np.mean(z1[:, 0] - body.q0[:, 0])))   # one unit per fallback step
    touched = steps   # every touched frame was a fallback frame: a hand-over then the hold, repeated
    assert touched >= hold + 1
    hand_overs = -(-touched // (hold + 1))
    assert t.guard_trips == hand_overs + touched   # the reset body trips on every touched frame
    last_restart = (touched - 1) % (hold + 1) == 0
    assert np.all(z1[:, 6] == (7.0 if last_restart else 0.0))
    # per frame: both bodies ran the learned step at a hand-over, one while the second is held; the reset body
    # trips on every touched frame, so every touched frame is a hand-over frame
    lb = t.learned_bodies[t.learned]
    assert len(lb) == touched and (lb == 2).sum() == hand_overs and (lb == 1).sum() == touched - hand_overs
    assert t.handed.sum() == touched and not t.handed[~t.learned].any()
    by_class = t.summary(bodies=2)["simulation_by_class"]
    assert list(by_class) == ["hand-over"] and by_class["hand-over"]["frames"] == touched
    with pytest.raises(ValueError, match="fallback"):
        mr.run(scene._replace(fallback=(None, None)))
    with pytest.raises(ValueError, match="fallback_hold"):
        mr.run(scene._replace(fallback_hold=-1))


def _resting_fallback_scene(bodies=1, frames=6):
    # Bodies whose learned step always goes bad, each with a fallback that leaves q where it is (so the forces
    # depend on the fingertip track alone), adds each frame's forces to v and 1 (restarted) or 2 to σ11; held
    # for 2 frames after each trip. A second body sits 10 cm beside the first, out of the fingertip's reach.
    scene, _ = _demo_scene(frames=frames)
    body = scene.bodies[0]
    finite = lambda z: ~jnp.all(jnp.isfinite(z))
    bad = body._replace(step_fn=lambda z, f: z * jnp.nan, guard=finite)
    beside = np.asarray(mr.model_matrix([-0.04, 0.0, 0.08], np.eye(3), 0.02))
    fb = jax.jit(lambda z, f, restart: z.at[:, 3:6].add(f).at[:, 6].add(jnp.where(restart, 1.0, 2.0)))
    return scene._replace(bodies=(bad, bad._replace(model=beside))[:bodies], skip_rest=False,
                          fallback=(fb,) * bodies, fallback_hold=2)


def test_next_frame_handover_shows_the_previous_state_then_catches_up():
    # handover="next-frame": the trip frame shows the body's previous state and the next frame runs the fallback
    # twice (restarted, under the trip frame's forces, then under its own). Trips at frames 0 and 3 as with
    # "same-frame"; once caught up the states are the same (here the forces do not depend on the state), the
    # fingertip's forces of every frame in v.
    scene = _resting_fallback_scene()
    z0 = scene.bodies[0].z
    same, ts = mr.run(scene, frames=6)
    later, tn = mr.run(scene._replace(handover="next-frame"), frames=6)
    np.testing.assert_allclose(np.asarray(later[0]), np.asarray(same[0]), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(later[0])[:, 6], z0[:, 6] + 10.0)   # 6 fallback steps, 2 restarted
    assert np.abs(np.asarray(later[0])[:, 3:6]).max() > 1e-3                   # the press reached v
    assert ts.guard_trips == tn.guard_trips == 2
    assert tn.handed.sum() == ts.handed.sum() == 1                             # frame 3 (frame 0 is warm-up)
    # after frame 3, the second trip: "same-frame" restarted the fallback there (+1), "next-frame" shows frame 2's
    part_same, _ = mr.run(scene, frames=4)
    part_later, _ = mr.run(scene._replace(handover="next-frame"), frames=4)
    np.testing.assert_allclose(np.asarray(part_same[0])[:, 6], z0[:, 6] + 6.0)
    np.testing.assert_allclose(np.asarray(part_later[0])[:, 6], z0[:, 6] + 5.0)
    # a hold of 0 still leaves the catch-up frame to the fallback; a body without one is reset at once
    zero, tz = mr.run(scene._replace(handover="next-frame", fallback_hold=0), frames=6)
    np.testing.assert_allclose(np.asarray(zero[0])[:, 6], z0[:, 6] + 9.0)       # trips 0, 2, 4: 3 catch-ups
    assert tz.guard_trips == 3
    reset, _ = mr.run(scene._replace(handover="next-frame", fallback=()), frames=3)
    np.testing.assert_array_equal(np.asarray(reset[0]), z0)
    with pytest.raises(ValueError, match="handover"):
        mr.run(scene._replace(handover="later"))


def test_next_frame_handover_in_one_program_per_frame_matches_the_stages():
    # Two bodies without devices: each body's frame is a lax.switch over its learned frame, its fallback and its
    # catch-up inside one program; the states and trips equal those of the stages run one by one, and the bad
    # body's learned step runs only at its trips (counted by a callback in it).
    scene = _resting_fallback_scene(bodies=2)
    calls = []

    def bad_step(z, f):
        jax.debug.callback(lambda: calls.append(1))
        return z * jnp.nan

    good, bad = scene.bodies
    good = good._replace(step_fn=_demo_scene()[0].bodies[0].step_fn)
    two = scene._replace(bodies=(good, bad._replace(step_fn=bad_step)), handover="next-frame")
    fused, tf = mr.run(two)
    fused_calls, calls[:] = len(calls), []
    staged, ts = mr.run(two._replace(fuse=False))
    for a, c in zip(fused, staged):
        np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(fused[1])[:, 6], bad.z[:, 6] + 10.0)
    assert np.abs(np.asarray(fused[0])[:, :3] - good.q0).max() > 1e-3          # the pressed body moved
    assert tf.guard_trips == ts.guard_trips == 2 and tf.fused_frames == 5
    assert fused_calls == 1 + 2, fused_calls   # the warm-up's learned call, then frames 0 and 3


def test_timings_split_the_learned_frames_by_what_the_bodies_did():
    ms = np.array([10.0, 11.0, 5.0, 6.0, 20.0, 1.0])
    t = mr.Timings(forces=np.zeros(6), step=ms, render=ms, write=ms, frame=ms, reallocations=0,
                   learned=np.array([1, 1, 1, 1, 1, 0], bool), learned_bodies=np.array([2, 2, 1, 1, 2, 0]),
                   handed=np.array([0, 0, 0, 0, 1, 0], bool))
    c = t.summary(bodies=2)["simulation_by_class"]
    assert {k: v["frames"] for k, v in c.items()} == {"every body learned": 2, "a body held": 2, "hand-over": 1}
    assert c["every body learned"]["p50_ms"] == 10.5 and c["a body held"]["p50_ms"] == 5.5
    assert c["hand-over"]["p50_ms"] == 20.0
    assert "simulation_by_class" not in t.summary()       # without the body count: not split


def test_loop_pauses_garbage_collection_and_restores_it():
    # The loop runs with automatic collection off (young-generation collections between frames instead) and
    # gives the same states as with it on; the caller's setting comes back, also after an error.
    import gc

    scene, _ = _demo_scene(frames=4)
    seen = []
    assert gc.isenabled()
    zs, _ = mr.run(scene, write=lambda i, rgb: seen.append(gc.isenabled()))
    assert seen == [False] * 4 and gc.isenabled()
    zs_on, _ = mr.run(scene, gc_pause=False, write=lambda i, rgb: seen.append(gc.isenabled()))
    assert seen[4:] == [True] * 4
    np.testing.assert_array_equal(np.asarray(zs[0]), np.asarray(zs_on[0]))

    def fail(i, rgb):
        raise RuntimeError("writer failed")

    with pytest.raises(RuntimeError, match="writer failed"):
        mr.run(scene, write=fail)
    assert gc.isenabled()


def test_real_time_xla_flags_add_the_loop_option_once_and_respect_the_user():
    # The real-time loop's XLA:CPU option (YNNPACK fusions off) is appended to XLA_FLAGS, after what is there,
    # once; a user's own choice of that option is left as it is.
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert mr.real_time_xla_flags(env)
    assert env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2 " + mr.REAL_TIME_XLA_FLAG
    assert not mr.real_time_xla_flags(env) and env["XLA_FLAGS"].count("ynn_fusion_type") == 1
    empty = {}
    assert mr.real_time_xla_flags(empty) and empty["XLA_FLAGS"] == mr.REAL_TIME_XLA_FLAG
    mine = {"XLA_FLAGS": "--xla_cpu_experimental_ynn_fusion_type=dot"}
    assert not mr.real_time_xla_flags(mine) and mine["XLA_FLAGS"] == "--xla_cpu_experimental_ynn_fusion_type=dot"


def test_demo_beams_are_the_corotational_beam_pressed_onto_the_lower_one_keeping_their_volume():
    # the demo's default beams: the shipped `beam-corot`, stepped raw, the contact inside their one implicit frame;
    # its spring fingertip bends the upper beam B down (model z, the load axis) onto the lower beam A, which bends
    # visibly under it, at the deepest press of the 120-frame track (frame 60), with no guard trip, no bounce, the
    # surfaces apart, and each beam's volume kept
    from fem.meshes import beam_mesh, cell_volumes
    from tignn_jax.cli.demo import DEFAULT_MODELS, build_scene

    assert DEFAULT_MODELS["beam"] == DEFAULT_MODELS["two-beams"] == "beam-corot"
    scene, dynamics = build_scene("two-beams", 120)
    assert dynamics == "model beam-corot (contact in the implicit step)"
    zs, timings = mr.run(scene, frames=60)
    zs = [np.asarray(z, np.float64) for z in zs]
    assert all(np.all(np.isfinite(z)) for z in zs)
    assert timings.guard_trips == 0
    uz = [z[:, 2] - b.q0[:, 2] for z, b in zip(zs, scene.bodies)]
    assert uz[1].min() < -14.0 and uz[1].max() < 0.5        # B bent by over a third of its length, downwards
    assert uz[0].min() < -5.0 and uz[0].max() < 0.1         # A bent down under it, through the contact alone
    assert max(np.abs(z[:, 3:6]).max() for z in zs) < 20.0  # settled, not bouncing
    world = [np.asarray(mr.transform_points(b.model, z[:, :3].astype(np.float32))) for b, z in zip(scene.bodies, zs)]
    assert np.linalg.norm(world[0][:, None] - world[1][None], axis=-1).min() > 0.002   # apart (metres)
    _, cells, _ = beam_mesh()
    rest = cell_volumes(np.asarray(scene.bodies[0].q0, np.float64), cells).sum()
    for z in zs:
        assert abs(cell_volumes(z[:, :3], cells).sum() / rest - 1.0) < 5e-3


def test_demo_bunny_is_the_corotational_bunny_dented_by_its_fingertip_keeping_its_volume():
    # the demo's default bunny: the shipped `bunny-corot`, stepped raw; its spring fingertip dents the top of the
    # head (model z, up) by about 7 % of the bunny's height at the deepest press (frame 60), the stress colours
    # reach their top there, with no guard trip, no bounce, and the volume kept
    from fem.meshes import bunny_mesh, cell_volumes
    from tignn_jax.cli.demo import BUNNY_PRESS_NODE, DEFAULT_MODELS, build_scene

    assert DEFAULT_MODELS["bunny"] == "bunny-corot"
    scene, dynamics = build_scene("bunny", 120, size=(160, 120))
    assert dynamics == "model bunny-corot"
    (z,), timings = mr.run(scene, frames=60)
    z, body = np.asarray(z, np.float64), scene.bodies[0]
    assert np.all(np.isfinite(z)) and timings.guard_trips == 0
    q0 = np.asarray(body.q0, np.float64)
    height = np.ptp(q0[:, 2])
    uz = z[:, 2] - q0[:, 2]
    assert -0.09 * height < uz.min() < -0.05 * height                 # dented by 5-9 % of the height,
    assert np.linalg.norm(q0[uz.argmin()] - q0[BUNNY_PRESS_NODE]) < 0.15 * height   # on the head
    assert uz.max() < 0.02 * height                                   # nothing pushed up
    assert np.abs(z[:, 3:6]).max() < 0.2 * height                     # settled, not bouncing
    assert np.asarray(mr.von_mises(z[:, 6:12])).max() > body.vmax      # the colour scale saturates at the dent
    _, cells, _ = bunny_mesh()
    rest = cell_volumes(q0, cells).sum()
    assert abs(cell_volumes(z[:, :3], cells).sum() / rest - 1.0) < 5e-3
