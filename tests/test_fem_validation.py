"""Input validation at the public boundary, and element inversion reported after a run."""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fem


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def small_problem(n_frames=2, **kw):
    m = fem.mooney_rivlin(1.0, 0.1, 0.1)
    pts, cells = fem.box_hex_mesh((2.0, 1.0, 1.0), (2, 1, 1))
    args = dict(material=m, frame_dt=0.1, n_frames=n_frames, clamped=[0, 3, 6, 9])
    args.update(kw)
    return fem.setup(pts, cells, **args), m, pts, cells


# --- material constants ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, match", [
    (dict(c10=0.0, c01=0.0), r"c10 \+ c01 must be positive.*c10=0\.0"),
    (dict(c10=1.0, c01=-1.5), r"c10 \+ c01 must be positive.*c01=-1\.5"),
    (dict(c10=1.0, d1=0.0), r"d1 must be positive.*d1=0\.0"),
    (dict(c10=1.0, d1=-2e-3), r"d1=-0\.002"),
    (dict(c10=1.0, density=-1.0), r"density=-1\.0"),
    (dict(c10=1.0, g=(0.6, 0.4), tau=(1.0, 2.0)), r"sum\(g\)=(np\.float64\()?1\.0"),
    (dict(c10=1.0, g=(0.7, 0.5), tau=(1.0, 2.0)), r"sum\(g\)=(np\.float64\()?1\.2"),
    (dict(c10=1.0, g=(0.3,), tau=(0.0,)), r"tau must be positive.*\[0\.0\]"),
    (dict(c10=1.0, g=(0.3, 0.2), tau=(0.5, -1.0)), r"tau.*-1\.0"),
    (dict(c10=1.0, g=(0.3, 0.2), tau=(0.5,)), r"same length"),
    (dict(c10=float("nan")), r"c10 must be finite"),
])
def test_bad_material_constants_raise_value_error_naming_the_value(kwargs, match):
    """Non-physical constants (no shear or bulk stiffness, no long-term modulus, non-positive relaxation time)
    are rejected before any tracing, with the offending value in the message."""
    with pytest.raises(ValueError, match=match):
        fem.mooney_rivlin(**kwargs)


# --- problem set-up -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("frame_dt", [0.0, -0.1, float("inf")])
def test_non_positive_frame_dt_raises(frame_dt):
    """The output interval must be a positive finite time."""
    with pytest.raises(ValueError, match=rf"frame_dt={frame_dt!r}"):
        small_problem(frame_dt=frame_dt)


def test_wrong_points_shape_raises():
    """Points must be [N, 3]."""
    m = fem.mooney_rivlin(1.0)
    pts, cells = fem.box_hex_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    with pytest.raises(ValueError, match=r"points must be a finite \[N, 3\] array, got shape \(8, 2\)"):
        fem.setup(pts[:, :2], cells, material=m, frame_dt=0.1, n_frames=1)


@pytest.mark.parametrize("bad", ["five_nodes", "float", "out_of_range"])
def test_wrong_cells_raise(bad):
    """Cells must be integer [K, 8] or [K, 4] node ids inside the node range."""
    m = fem.mooney_rivlin(1.0)
    pts, cells = fem.box_hex_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    cells, match = {"five_nodes": (cells[:, :5], r"\(1, 5\)"),
                    "float": (cells.astype(float), r"float64"),
                    "out_of_range": (cells + 1, r"max 8")}[bad]
    with pytest.raises(ValueError, match=match):
        fem.setup(pts, cells, material=m, frame_dt=0.1, n_frames=1)


@pytest.mark.parametrize("clamped, match", [([0, 12], r"\[12\]"), ([-1, 2], r"\[-1\]")])
def test_clamped_node_ids_out_of_range_raise(clamped, match):
    """Clamped ids must name existing nodes (12 nodes here: ids 0..11)."""
    with pytest.raises(ValueError, match=r"clamped node ids out of range \[0, 11\].*" + match):
        small_problem(clamped=clamped)


def test_inverted_element_in_mesh_raises():
    """A mis-ordered (negative-volume) element is rejected at set-up, naming its id."""
    m = fem.mooney_rivlin(1.0)
    pts, cells = fem.box_hex_mesh((2.0, 1.0, 1.0), (2, 1, 1))
    cells[1] = cells[1][[4, 5, 6, 7, 0, 1, 2, 3]]
    with pytest.raises(ValueError, match=r"non-positive volume.*\[1\]"):
        fem.setup(pts, cells, material=m, frame_dt=0.1, n_frames=1)


@pytest.mark.parametrize("field, shape, match", [
    ("nodal", (2, 11, 3), r"loads.nodal must have shape \[2, 12, 3\], got \(2, 11, 3\)"),
    ("nodal", (3, 12, 3), r"got \(3, 12, 3\)"),
    ("v0", (12, 2), r"loads.v0 must have shape \[12, 3\], got \(12, 2\)"),
])
def test_wrong_load_shapes_raise(field, shape, match):
    """Loads must match the problem: [n_frames, N, 3] nodal forces, [N, 3] initial velocity."""
    prob, m, *_ = small_problem()
    with pytest.raises(ValueError, match=match):
        fem.simulate(prob, m, fem.Loads(**{field: jnp.zeros(shape)}))


def test_nan_load_raises():
    """A NaN force is a user error, not a result."""
    prob, m, pts, _ = small_problem()
    nodal = np.zeros((2, len(pts), 3))
    nodal[1, 5, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fem.simulate(prob, m, fem.Loads(nodal=jnp.asarray(nodal)))


# --- element inversion ----------------------------------------------------------------------------------------

def crushing_run(on_inversion):
    """A point load far beyond the element's strength pulls one free corner through the element."""
    prob, m, pts, _ = small_problem(n_frames=4)
    nodal = np.zeros((4, len(pts), 3))
    nodal[:, 11, :] = [-500.0, -500.0, -500.0]   # node 11 = (2, 1, 1), pushed towards the body's inside
    return fem.simulate(prob, m, fem.Loads(nodal=jnp.asarray(nodal)), on_inversion=on_inversion), prob


def test_element_inversion_raises_with_element_id_and_time():
    """An element whose J drops to ≤ 0 is reported after the run (element id and time) instead of silently
    returning NaN: with on_inversion='raise' as fem.ElementInversionError."""
    with pytest.raises(fem.ElementInversionError, match=r"element 1 inverted \(J <= 0\) at t = 0\.\d+"):
        crushing_run("raise")


def test_element_inversion_warns_and_is_recorded_in_the_result():
    """With on_inversion='warn' the run returns, warns, and the result records the element and time."""
    with pytest.warns(RuntimeWarning, match=r"element 1 inverted"):
        res, prob = crushing_run("warn")
    assert int(res.inverted) == 1
    t = float(res.inversion_time)
    assert 0.0 < t <= float(res.t[-1])


def test_no_inversion_is_recorded_for_a_gentle_run():
    """A small load leaves every element with J > 0: inverted = −1, inversion_time = NaN, no warning."""
    prob, m, pts, _ = small_problem()
    nodal = np.zeros((2, len(pts), 3))
    nodal[:, 11, 2] = -1e-3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = fem.simulate(prob, m, fem.Loads(nodal=jnp.asarray(nodal)), on_inversion="warn")
    assert int(res.inverted) == -1 and np.isnan(float(res.inversion_time))
