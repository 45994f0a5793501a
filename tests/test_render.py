"""Software rasteriser and surface extraction, against brute-force and geometric answers."""
import jax.numpy as jnp
import numpy as np
import pytest

from tignn_jax.render import rasterize, fragment_capacity, surface_nodes, surface_triangles

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
