"""`tignn view` (tignn_jax.view): the fingertip spring pushes and pulls a body and lets it go, bad input from the
page is refused without a crash, every tab has its own bodies, and a real browser drags the body with the mouse."""
import importlib.util
import os
import shutil
import socket
import time
import types

import numpy as np
import pytest

from tignn_jax import api, cli
from tignn_jax.view import Interaction, load_scene
from tignn_jax.view.bands import contour_bands

TIP = np.array([38.0, 5.0, 10.0])     # on the beam's top face, near its free end (world = the beam's model frame)


@pytest.fixture(scope="module")
def beam():
    return load_scene("beam")


def _run(interaction, steps):
    for _ in range(steps):
        assert interaction.step()


def _patch_motion(interaction):
    """The grabbed patch's mean displacement [3] (model units)."""
    k, patch = interaction._grab[0], interaction._grab[1]
    return (interaction.zs[k][patch, :3] - interaction.scene.bodies[k].q0[patch]).mean(0)


def test_pressing_down_moves_the_body_down(beam):
    s = Interaction(beam)
    assert s.grab(TIP)
    assert s.drag(TIP - [0.0, 0.0, 10.0])
    _run(s, 20)
    u = _patch_motion(s)
    assert u[2] < -1.0 and abs(u[2]) > 3 * np.abs(u[:2]).max(), u   # along the drag: down, not sideways


def test_pulling_up_moves_the_body_up(beam):
    s = Interaction(beam)
    assert s.grab(TIP) and s.drag(TIP + [0.0, 0.0, 10.0])
    _run(s, 20)
    assert _patch_motion(s)[2] > 1.0   # the same gesture pulls out: the spring acts both ways


def test_the_pull_stays_within_the_training_loads(beam):
    s = Interaction(beam)
    assert s.grab(TIP) and s.drag(TIP - [0.0, 0.0, 500.0])   # the pointer far away
    _run(s, 15)
    per_node = np.linalg.norm(s.forces()[0], axis=1)
    assert per_node.max() <= beam.f_max * (1 + 1e-5) and per_node.max() > 0.5 * beam.f_max
    assert s.resets == 0 and np.all(np.isfinite(s.zs[0]))


def test_release_lets_the_body_spring_back(beam):
    s = Interaction(beam)
    assert s.grab(TIP) and s.drag(TIP - [0.0, 0.0, 10.0])
    _run(s, 20)
    pushed = s.displacement()[0].max()
    s.release()
    assert not s.grabbed and not s.forces()[0].any()
    _run(s, 40)
    assert s.displacement()[0].max() < 0.05 * pushed   # damped: back to rest within 2 s of model time


@pytest.mark.parametrize("point", [[np.nan, 0.0, 0.0], [np.inf, 5.0, 10.0], [1e30, 0.0, 0.0], "abc", [1.0, 2.0],
                                   None, [[1, 2, 3], [4, 5, 6]]])
def test_malformed_or_out_of_range_points_are_refused(beam, point):
    s = Interaction(beam)
    assert not s.grab(point) and not s.grabbed
    assert s.grab(TIP)
    before = s.target.copy()
    assert not s.drag(point)
    assert np.array_equal(s.target, before)          # the previous target stays
    _run(s, 3)
    assert np.all(np.isfinite(s.zs[0])) and s.resets == 0


def test_a_press_beside_the_body_grabs_nothing(beam):
    s = Interaction(beam)
    assert not s.grab([5.0, 5.0, 200.0]) and not s.grabbed   # finite and within reach, but on no body


def test_dragging_without_a_grab_is_refused(beam):
    s = Interaction(beam)
    assert not s.drag(TIP) and not s.grabbed
    s.release()                         # a release without a grab is harmless
    _run(s, 2)
    assert s.displacement()[0].max() == 0.0


def test_reset_returns_to_rest(beam):
    s = Interaction(beam)
    assert s.grab(TIP) and s.drag(TIP - [0.0, 0.0, 10.0])
    _run(s, 10)
    s.reset()
    assert not s.grabbed and s.index == 0
    assert np.array_equal(s.zs[0][:, :3], beam.bodies[0].q0) and not s.zs[0][:, 3:].any()


def test_pause_holds_the_state(beam):
    s = Interaction(beam)
    assert s.grab(TIP) and s.drag(TIP - [0.0, 0.0, 10.0])
    _run(s, 3)
    s.pause(True)
    held = s.zs[0].copy()
    assert not s.step() and np.array_equal(s.zs[0], held)
    s.pause(False)
    assert s.step() and not np.array_equal(s.zs[0], held)


def test_two_sessions_are_independent(beam):
    a, b = Interaction(beam), Interaction(beam)
    assert a.grab(TIP) and a.drag(TIP - [0.0, 0.0, 10.0])
    for _ in range(10):
        a.step()
        b.step()
    assert a.displacement()[0].max() > 1.0 and b.displacement()[0].max() == 0.0 and not b.grabbed


def test_a_non_finite_state_is_reset_by_the_guard(beam):
    s = Interaction(beam._replace(step=lambda z, f: np.full_like(z, np.nan)))
    assert s.step()
    assert s.resets == 1 and np.array_equal(s.zs[0][:, :3], beam.bodies[0].q0)


def test_pressing_the_upper_beam_pushes_the_lower_one_through_contact():
    scene = load_scene("two-beams")
    s = Interaction(scene)
    b = scene.bodies[1]
    top = b.rotation @ TIP + b.offset          # B's free end, top face, in the world (A's frame)
    assert s.grab(top) and s._grab[0] == 1
    assert s.drag(top - [0.0, 0.0, 3 * scene.u_max])
    _run(s, 40)
    assert s.displacement()[1].max() > 10.0    # B is pressed through the gap of 10 ...
    assert s.displacement()[0].max() > 1.0     # ... onto A, which bends under it (the contact in the step)


def _bunny_run(tmp_path, monkeypatch, mesh):
    """A run folder of ``tignn train`` whose model is the shipped bunny with ``mesh`` (read without writing the
    model's arrays: `tignn_jax.api.load_pretrained` returns it for that folder)."""
    params, graph = api.load_pretrained("bunny")
    run = tmp_path / "run"
    (run / "model").mkdir(parents=True)
    (run / "model" / "model.npz").touch()
    load = api.load_pretrained
    monkeypatch.setattr(api, "load_pretrained", lambda name: ({**params, "mesh": mesh(params["mesh"])}, graph)
                        if str(run) in str(name) else load(name))
    return run


def test_a_model_on_its_own_mesh_is_shown_from_its_cells(tmp_path, monkeypatch):
    from fem.meshes import bunny_mesh

    cells = np.asarray(bunny_mesh()[1])
    run = _bunny_run(tmp_path, monkeypatch, lambda mesh: {**mesh, "cells": cells})
    scene = load_scene(None, str(run))          # a run folder of tignn train
    assert scene.name == f"{run} (its own mesh)" and len(scene.bodies) == 1
    assert len(np.unique(scene.bodies[0].triangles)) == 1002      # the bunny's surface nodes
    s = Interaction(scene)
    point = scene.bodies[0].q0[917]             # the top of the head
    assert s.grab(point) and s.drag(point + [0.0, 0.0, -scene.u_max])
    _run(s, 10)
    assert s.displacement()[0].max() > 0.05 * scene.u_max


def test_a_model_without_cells_on_an_unknown_mesh_is_refused(tmp_path, monkeypatch):
    moved = lambda mesh: {**{k: v for k, v in mesh.items() if k != "cells"},   # noqa: E731
                          "q0": np.asarray(mesh["q0"]) + 0.1}
    run = _bunny_run(tmp_path, monkeypatch, moved)
    with pytest.raises(ValueError, match="cells"):
        load_scene(None, str(run))


def test_contour_bands_tile_the_surface_with_its_winding():
    from fem.meshes import bunny_mesh
    from tignn_jax.mr.surface import surface_triangles

    q0, cells, _ = bunny_mesh()
    triangles = surface_triangles(cells, q0)
    values = q0[:, 2] + np.random.default_rng(0).normal(0.0, 0.3, len(q0))

    def normals(x, t):
        p = np.asarray(x, np.float64)[t]
        return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])

    pieces = contour_bands(q0, values, triangles, 2.0, 8.0, 12)
    assert len(pieces) == 12 and all(len(f) for _, f in pieces)
    area = sum(np.linalg.norm(normals(v, f), axis=1).sum() for v, f in pieces)
    assert area == pytest.approx(np.linalg.norm(normals(q0, triangles), axis=1).sum(), rel=1e-5)
    assert np.allclose(sum(normals(v, f).sum(0) for v, f in pieces), 0.0, atol=1e-3)   # closed and outward


@pytest.mark.parametrize("argv, names", [
    (["--rate", "0"], ["--rate", "0"]),
    (["--rate", "nan"], ["--rate", "nan"]),
    (["--port", "70000"], ["--port", "70000"]),
    (["--model", "no-such-model"], ["--model", "'no-such-model'"]),
    (["--host", "999.1.1.1"], ["--host 999.1.1.1"]),
])
def test_bad_options_are_one_line_naming_the_value_and_exit_2(argv, names, capsys):
    assert cli.main(["view", *argv]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("tignn view: error: ") and all(n in err for n in names), err


def test_a_taken_port_is_refused_rather_than_moved(capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert cli.main(["view", "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert err.strip() == (f"tignn view: error: --host 127.0.0.1 --port {port}: cannot serve there "
                           "(Address already in use)")


def test_without_viser_the_error_says_how_to_install_it(monkeypatch, capsys):
    import sys

    monkeypatch.setitem(sys.modules, "viser", None)     # import viser -> ImportError
    assert cli.main(["view", "--port", str(_free_port())]) == 2
    assert capsys.readouterr().err.strip() == 'tignn view: error: viser is not installed: pip install ".[view]"'


def test_help_names_every_option(capsys):
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["view", "--help"])
    text = capsys.readouterr().out
    for option in ("--scene", "--model", "--port", "--host", "--colour", "--rate"):
        assert option in text


# --- a real browser -----------------------------------------------------------------------------------------------

CHROMIUM = "/usr/bin/chromium"
# Chrome's notice for a preventDefault() in a passive listener, which viser's client (SceneTree.tsx) calls on every
# press of a draggable scene node; it is logged at the error level but changes nothing
BENIGN = ("Unable to preventDefault inside passive event listener",)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _screen(camera, point):
    """The pixel (u, v) of a world point in a tab's view, from the camera the tab reports (OpenCV convention)."""
    import viser.transforms as tf

    r = tf.SO3(np.asarray(camera.wxyz)).as_matrix()              # camera -> world
    x = r.T @ (np.asarray(point, np.float64) - np.asarray(camera.position))
    f = 0.5 * camera.image_height / np.tan(0.5 * camera.fov)
    return f * x[0] / x[2] + 0.5 * camera.image_width, f * x[1] / x[2] + 0.5 * camera.image_height


def _wait(condition, timeout, what):
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def test_a_mouse_drag_in_chromium_pushes_the_beam():
    for module in ("viser", "playwright"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} is not installed (pip install -e \".[dev]\")")
    if not (os.path.exists(CHROMIUM) or shutil.which("chromium")):
        pytest.skip("Debian's chromium is not installed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    from tignn_jax.view import serve
    from tignn_jax.view.server import frame_camera

    port = _free_port()
    view = serve("beam", port=port)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM if os.path.exists(CHROMIUM)
                                        else shutil.which("chromium"),
                                        args=["--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 900, "height": 600})
            errors = []
            page.on("console", lambda m: m.type == "error" and errors.append(m.text))
            page.on("pageerror", lambda e: errors.append(str(e)))
            local = (f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}", "data:", "blob:")
            outside = []                                            # viser's client is served by the package
            page.on("request", lambda r: r.url.startswith(local) or outside.append(r.url))
            page.goto(f"http://127.0.0.1:{port}")
            _wait(lambda: view.pages, 20, "the tab to connect")
            tab = next(iter(view.pages.values()))
            camera = tab.client.camera
            framed = types.SimpleNamespace(up_direction=None)       # where frame_camera puts the camera
            frame_camera(framed, tab.interaction.centre, tab.interaction.size)
            _wait(lambda: camera.update_timestamp and np.allclose(camera.position, framed.position, atol=1e-3),
                  20, "the tab's camera to be framed")
            _wait(lambda: "physics" in tab._status.content, 20, "the first frames")
            time.sleep(1.0)
            canvas = page.locator("canvas").first.bounding_box()
            rest = np.asarray(_png(page.screenshot()), np.float64)

            u, v = _screen(camera, TIP)
            page.mouse.move(canvas["x"] + u, canvas["y"] + v)
            page.mouse.down()
            for i in range(1, 21):                                   # pull the tip down on the screen
                page.mouse.move(canvas["x"] + u, canvas["y"] + v + 6 * i)
                time.sleep(0.02)
            _wait(lambda: tab.interaction.displacement()[0].max() > 2.0, 15, "the beam to move")
            assert tab.interaction.grabbed
            k, patch = tab.interaction._grab[:2]
            assert np.linalg.norm(tab.interaction.scene.bodies[k].q0[patch].mean(0) - TIP) < 3.0   # grabbed at the tip
            moved = tab.interaction.zs[0][patch, 2] - tab.interaction.scene.bodies[0].q0[patch, 2]
            assert moved.mean() < -1.0                                # down, as dragged
            time.sleep(0.5)
            pushed = np.asarray(_png(page.screenshot()), np.float64)
            page.mouse.up()
            _wait(lambda: not tab.interaction.grabbed, 10, "the release")
            second = browser.new_page(viewport={"width": 640, "height": 480})   # a second tab: its own scene
            second.goto(f"http://127.0.0.1:{port}")
            _wait(lambda: len(view.pages) == 2, 20, "the second tab to connect")
            other = next(t for t in view.pages.values() if t is not tab)
            _wait(lambda: "physics" in other._status.content, 20, "the second tab's frames")
            assert other.interaction is not tab.interaction                    # its own scene, at rest
            assert other.interaction.displacement()[0].max() < 1e-3
            second.close()
            _wait(lambda: list(view.pages.values()) == [tab], 20, "the closed tab to be dropped")
            browser.close()
        _wait(lambda: not view.pages, 20, "the closed browser's tab to be dropped")
        assert np.abs(pushed - rest).mean() > 1.0                    # the page shows the bent, coloured beam
        from tignn_jax.mr.scene import CLAMP_COLOUR                   # and its clamped end, marked in that colour
        clamp = np.all(np.abs(rest - 255 * np.asarray(CLAMP_COLOUR)) < 40, axis=-1)
        assert clamp.sum() > 20, clamp.sum()
        assert not [e for e in errors if not any(b in e for b in BENIGN)], errors
        assert not outside, outside                                   # nothing fetched from the network
    finally:
        view.stop()


def _png(data: bytes):
    import io

    from PIL import Image

    return Image.open(io.BytesIO(data)).convert("RGB")
