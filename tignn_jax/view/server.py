"""The viewer's web server: each browser tab pushes its own bodies with the mouse (viser, served on localhost).

`serve` starts a `viser.ViserServer` (its web client ships inside the package: no network is needed). Every
connecting tab gets a `Page`: its own `tignn_jax.view.interaction.Interaction`, a physics thread that steps it
at a fixed ``rate`` whatever the tab does, and a drawing thread that sends the newest state at most once per step. Sends
never block: viser queues a mesh's property updates and keeps only the newest unsent one, so a slow tab is sent
fewer frames and the physics does not wait for it. A tab's threads stop and its interaction is dropped when it
closes.

Drawing: viser meshes take one colour each, so a body is drawn as ``BANDS`` meshes, band j holding the pieces of
the surface triangles where the quantity lies in the j-th twelfth of the legend's range
(`tignn_jax.view.bands.contour_bands`: contour bands, as FEM post-processors show them), coloured by
`tignn_jax.mr.colour_map` at the band's centre; the legend shows the same bands. Pressing the left button on a
body and dragging pulls it (`Interaction.grab`/`drag`/`release`, through viser's scene-node drag events, which give
the pressed surface point and the pointer projected onto the camera-facing plane through it); dragging elsewhere
turns the camera. A red line from the grab point to a red ball at the pointer shows the spring.

On screen: ``step`` (one model step with the spring, contact and guard, ms), ``physics`` (steps per second),
``frame`` (building and queueing one frame, ms) and ``queued`` (frames per second queued for the tab).
"""
from __future__ import annotations

import threading
import time

import numpy as np

from tignn_jax.view.bands import contour_bands
from tignn_jax.view.scenes import SCENES, load_scene, models_for
from tignn_jax.view.interaction import QUANTITIES, Interaction

BANDS = 12
_EMPTY = np.array([[0, 1, 2]], np.uint32)
VIEW_DIRECTION = np.array([0.25, -1.0, 0.55])  # from the target to the camera (world, z up)
FOV = np.radians(50.0)                          # the camera's vertical field of view


def serve(scene: str | None = "beam", model: str | None = None, host: str = "127.0.0.1", port: int = 8080,
          colour: str = "von Mises", rate: float = 30.0, verbose: bool = False) -> "ViewServer":
    """Start the viewer in background threads and return its `ViewServer` (``stop()`` ends it).

    Args:
      scene: one of `tignn_jax.view.scenes.SCENES`, or None for ``model``'s own mesh.
      model: a shipped model name, a model folder or file, or ``fem-newton`` (default: the scene's own).
      host, port: where to serve the page (http://host:port).
      colour: the quantity first shown, one of `tignn_jax.view.interaction.QUANTITIES`.
      rate: physics steps per second of every tab (each step one model frame).
      verbose: let viser print its banner and connections.

    Returns:
      The running `ViewServer`.

    Raises:
      ValueError: a bad scene, model, colour or rate (checked before the server starts, the scene loaded once).
    """
    if colour not in QUANTITIES:
        raise ValueError(f"colour must be one of {QUANTITIES}, got {colour!r}")
    if not (np.isfinite(rate) and 1.0 <= rate <= 240.0):
        raise ValueError(f"rate must be 1..240 steps per second, got {rate}")
    view = ViewServer(scene, model, colour, rate)
    first = Interaction(view.scene_of(scene, model))     # load (and compile) before the first tab arrives
    view.start(host, port, verbose)
    frame_camera(view.server.initial_camera, first.centre, first.size)
    return view


class ViewServer:
    """The server: the viser server, the scenes loaded so far (shared, read-only) and the open pages."""

    def __init__(self, scene, model, colour, rate):
        self.scene, self.model, self.colour, self.rate = scene, model, colour, float(rate)
        self.pages: dict[int, Page] = {}
        self._scenes: dict = {}
        self._lock = threading.Lock()
        self.server = None

    def start(self, host: str, port: int, verbose: bool) -> None:
        import viser

        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.server.scene.set_up_direction("+z")
        self.server.gui.configure_theme(show_share_button=False)
        self.server.gui.main_panel.dock_right()        # the panel beside the view, not over the body
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    def stop(self) -> None:
        """Stop every page's threads and the server."""
        for page in list(self.pages.values()):
            page.close()
        self.pages.clear()
        if self.server is not None:
            self.server.stop()

    def scene_of(self, scene, model):
        """The `Scene` of (scene, model), loaded once and shared by the pages (scenes hold no state)."""
        key = (scene, model)
        with self._lock:
            if key not in self._scenes:
                loaded = load_scene(scene, model)
                Interaction(loaded).step()        # compile the step now, not in a tab's first frame
                self._scenes[key] = loaded
            return self._scenes[key]

    def _connect(self, client) -> None:
        self.pages[client.client_id] = Page(self, client)

    def _disconnect(self, client) -> None:
        page = self.pages.pop(client.client_id, None)
        if page is not None:
            page.close()


class Page:
    """One tab: its interaction, its GUI, its meshes, and its physics and drawing threads.

    Attributes:
      interaction: the tab's `Interaction` (replaced when the tab picks another scene or model).
      physics_rate: physics steps per second over the last second.
      frame_rate: frames built and queued for the tab per second over the last second (viser sends the newest
        and drops older unsent ones, so a slow tab receives fewer).
      frame_ms: the last frame's time to build and queue (positions, bands, messages).
    """

    def __init__(self, view: ViewServer, client):
        self.view, self.client = view, client
        self.scene_name, self.model = view.scene, view.model
        self.colour = view.colour
        self.physics_rate = self.frame_rate = self.frame_ms = 0.0
        self._stop = threading.Event()
        self._stepped = threading.Condition()
        self._drawing = threading.Lock()      # held while a frame is sent and while the scene is replaced
        self._request = None                  # (scene, model) the tab asked for, loaded by the physics thread
        self._meshes = []
        self.interaction = Interaction(view.scene_of(self.scene_name, self.model))
        self._framed = False     # framed by the server's initial camera, and again once the tab reports its own
        self._build_gui()
        self._build_scene()
        client.camera.on_update(self._on_camera)
        self._threads = [threading.Thread(target=f, daemon=True, name=f"tignn-view-{n}-{client.client_id}")
                         for n, f in (("physics", self._physics), ("draw", self._draw))]
        for t in self._threads:
            t.start()

    def close(self) -> None:
        """Stop the tab's threads (its interaction is dropped with the page)."""
        self._stop.set()
        with self._stepped:
            self._stepped.notify_all()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=10.0)

    # GUI ---------------------------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.client.gui
        custom = self.view.scene is None
        scenes = ([self.interaction.scene.name] if custom else []) + list(SCENES)
        self._scene_menu = gui.add_dropdown("scene", scenes, initial_value=scenes[0] if custom else self.scene_name)
        self._model_menu = gui.add_dropdown("model", self._models(self.scene_name),
                                            initial_value=self._model_label())
        self._colour_menu = gui.add_dropdown("colour", QUANTITIES, initial_value=self.colour)
        self._pause = gui.add_checkbox("pause", False)
        reset = gui.add_button("reset")
        self._status = gui.add_markdown("")
        self._legend = gui.add_image(_legend(self.interaction.scene.ranges[self.colour], self.colour), format="png")
        self._about = gui.add_markdown("")
        self._scene_menu.on_update(lambda _: self._pick_scene())
        self._model_menu.on_update(lambda _: self._pick_model())
        self._colour_menu.on_update(lambda _: self._pick_colour())
        self._pause.on_update(lambda _: self.interaction.pause(bool(self._pause.value)))
        reset.on_click(lambda _: self.interaction.reset())

    def _models(self, scene) -> tuple:
        models = models_for(scene)
        if self.view.model and self.view.model not in models and (scene == self.view.scene):
            models = [self.view.model] + models
        return tuple(models) or (self._model_label(),)

    def _model_label(self) -> str:
        from tignn_jax.cli.demo import DEFAULT_MODELS

        return self.model or DEFAULT_MODELS.get(self.scene_name, self.interaction.scene.name)

    def _pick_scene(self) -> None:
        value = self._scene_menu.value
        if value not in SCENES:        # the model's own mesh
            self._ask(None, self.view.model)
        else:
            self._ask(value, None if value != self.view.scene else self.view.model)

    def _pick_model(self) -> None:
        value = self._model_menu.value
        if self.scene_name is not None and value in self._models(self.scene_name):
            self._ask(self.scene_name, value)

    def _ask(self, scene, model) -> None:
        """Have the physics thread load (scene, model) unless the tab shows it already."""
        from tignn_jax.cli.demo import DEFAULT_MODELS

        default = DEFAULT_MODELS.get(scene)
        if (scene, model or default) != (self.scene_name, self.model or DEFAULT_MODELS.get(self.scene_name)):
            self._request = (scene, model)

    def _pick_colour(self) -> None:
        value = self._colour_menu.value
        if value in QUANTITIES:
            self.colour = value
            self._legend.image = _legend(self.interaction.scene.ranges[value], value)

    # scene -------------------------------------------------------------------------------------------------

    def _build_scene(self) -> None:
        """Add the interaction's meshes and frame the camera on them."""
        for handle in self._meshes:
            handle.remove()
        scene = self.interaction.scene
        self._meshes = []
        self._empty = [True] * (BANDS * len(scene.bodies))
        frame = self.interaction.frame()
        for k, body in enumerate(scene.bodies):
            vertices = np.repeat(frame.positions[k][:1], 3, 0).astype(np.float32)
            for j in range(BANDS):
                handle = self.client.scene.add_mesh_simple(
                    f"/body{k}/band{j}", vertices, _EMPTY, color=_band_colour(j), side="double",
                    cast_shadow=False, receive_shadow=False)
                handle.on_drag("left")(self._on_drag)
                self._meshes.append(handle)
        from tignn_jax.mr.legend import rgb255
        from tignn_jax.mr.scene import CLAMP_COLOUR

        for k, body in enumerate(scene.bodies):    # the supports: the clamped nodes, which never move
            fixed = frame.positions[k][~np.asarray(body.free, bool)]
            if len(fixed):
                self._meshes.append(self.client.scene.add_point_cloud(
                    f"/body{k}/clamps", fixed.astype(np.float32),
                    colors=rgb255(CLAMP_COLOUR),
                    point_size=0.012 * self.interaction.size, point_shape="square", point_shading="flat"))
        self._tip = self.client.scene.add_icosphere("/fingertip", radius=0.015 * self.interaction.size,
                                                    color=(230, 60, 40), visible=False)
        self._spring = self.client.scene.add_line_segments("/spring", np.zeros((1, 2, 3), np.float32),
                                                           colors=(230, 60, 40), thickness=3.0,
                                                           thickness_units="screen", visible=False)
        self._meshes += [self._tip, self._spring]
        size, centre = self.interaction.size, self.interaction.centre
        low = min(float(b.q0[:, 2].min()) for b in scene.bodies)   # the floor, just below the lowest node
        self.client.scene.add_grid("/floor", width=1.5 * size, height=1.5 * size, cell_size=size / 20,
                                   position=(centre[0], centre[1], low - 0.5 * scene.u_max - 0.01 * size))
        self._legend.image = _legend(scene.ranges[self.colour], self.colour)
        self._about.content = (f"**{scene.name}**: {scene.dynamics}. Press the left button on the body and drag "
                               "to pull it; drag elsewhere to turn the view.")
        self._sent = None

    def _on_camera(self, _) -> None:
        if not self._framed:
            self._framed = True
            self._frame_camera(self.client.camera)

    def _frame_camera(self, camera) -> None:
        """Point ``camera`` (a tab's, or the server's initial one) at the scene, from its size."""
        frame_camera(camera, self.interaction.centre, self.interaction.size)

    def _on_drag(self, event) -> None:
        if event.phase == "start":
            self.interaction.grab(event.start_position)
        elif event.phase == "update":
            self.interaction.drag(event.end_position)
        else:
            self.interaction.release()

    # threads -----------------------------------------------------------------------------------------------

    def _physics(self) -> None:
        """Step the interaction every 1/rate s (catching up at most one step, never piling up)."""
        period = 1.0 / self.view.rate
        next_t = time.perf_counter()
        count, since = 0, time.perf_counter()
        while not self._stop.is_set():
            if self._request is not None:
                self._switch()
                next_t = time.perf_counter()
            try:
                stepped = self.interaction.step()
            except Exception as err:          # a model error must not kill the tab's physics
                self._status.content = f"step failed: {type(err).__name__}: {err}"
                self.interaction.reset()
                stepped = False
            count += stepped
            with self._stepped:
                self._stepped.notify_all()
            now = time.perf_counter()
            if now - since >= 1.0:
                self.physics_rate, count, since = count / (now - since), 0, now
            next_t = max(next_t + period, now)
            self._stop.wait(max(next_t - now, 0.0))

    def _switch(self) -> None:
        scene, model = self._request
        self._request = None
        self._status.content = "loading…"
        try:
            loaded = self.view.scene_of(scene, model)
        except (ValueError, OSError) as err:
            self._status.content = f"cannot load {model or scene}: {err}"
            return
        with self._drawing, self.client.atomic():     # not while a frame of the old scene is being sent
            self.scene_name, self.model = scene, model
            paused = self.interaction.paused
            self.interaction = Interaction(loaded)
            self.interaction.pause(paused)
            self._build_scene()
            self._framed = True               # the tab has long reported its camera: move it
            self._frame_camera(self.client.camera)
            self._scene_menu.value = scene if scene is not None else self._scene_menu.options[0]
            if scene is not None:
                self._model_menu.options = self._models(scene)
                self._model_menu.value = self._model_label()

    def _draw(self) -> None:
        """Send the newest state after each step (at most one frame per step; a blocked send skips states)."""
        count, since = 0, time.perf_counter()
        while not self._stop.is_set():
            with self._stepped:
                self._stepped.wait(timeout=0.25)
            now = time.perf_counter()
            with self._drawing:
                interaction = self.interaction
                if (interaction.index, self.colour, id(interaction)) != self._sent:
                    try:
                        self._send(interaction)
                    except Exception as err:      # the tab closed while sending, or a bad frame: go on
                        if self._stop.is_set():
                            return
                        self._status.content = f"drawing failed: {type(err).__name__}: {err}"
                        self._sent = (interaction.index, self.colour, id(interaction))
                        continue
                    self.frame_ms = 1e3 * (time.perf_counter() - now)
                    count += 1
            if now - since >= 0.5:
                self.frame_rate, count, since = count / (now - since), 0, now
                self._status.content = (
                    f"step **{interaction.step_ms:.1f} ms** · physics **{self.physics_rate:.0f}/s** · "
                    f"frame **{self.frame_ms:.1f} ms** · queued **{self.frame_rate:.0f} frames/s**"
                    + (f" · guard resets {interaction.resets}" if interaction.resets else "")
                    + (" · paused" if interaction.paused else ""))

    def _send(self, interaction: Interaction) -> None:
        frame, colour = interaction.frame(), self.colour
        lo, hi = interaction.scene.ranges[colour]
        with self.client.atomic():
            for k, (positions, values) in enumerate(zip(frame.positions, frame.values[colour])):
                pieces = contour_bands(positions, values, interaction.scene.bodies[k].triangles, lo, hi, BANDS)
                for j, (vertices, faces) in enumerate(pieces):
                    m = k * BANDS + j
                    if not len(faces) and self._empty[m]:
                        continue
                    self._empty[m] = not len(faces)
                    if not len(faces):                  # nothing in this band: one degenerate triangle
                        vertices, faces = np.repeat(positions[:1], 3, 0).astype(np.float32), _EMPTY
                    self._meshes[m].vertices = vertices
                    self._meshes[m].faces = faces
            spring = interaction.spring()
            if spring is not None:
                self._tip.position = tuple(float(x) for x in spring[1])
                self._spring.points = np.asarray([spring], np.float32)
            if self._tip.visible != (spring is not None):
                self._tip.visible = self._spring.visible = spring is not None
        self._sent = (frame.index, colour, id(interaction))


def frame_camera(camera, centre, size: float) -> None:
    """Aim a viser camera at a scene of diameter ``size`` (world units) around ``centre`` [3], from
    ``VIEW_DIRECTION`` with z up, at the distance where the scene spans about 60 % of the view's height."""
    camera.fov = float(FOV)
    camera.near, camera.far = 1e-3 * size, 50.0 * size
    direction = VIEW_DIRECTION / np.linalg.norm(VIEW_DIRECTION)
    position = tuple(float(x) for x in centre + direction * 0.85 * size / np.tan(FOV / 2))
    look_at = tuple(float(x) for x in centre)
    if hasattr(camera, "up_direction"):       # a tab's camera
        camera.up_direction = (0.0, 0.0, 1.0)
    else:                                     # the server's initial camera
        camera.up = (0.0, 0.0, 1.0)
    camera.position = position
    camera.look_at = look_at


def _band_colour(j: int) -> tuple:
    from tignn_jax.mr.legend import rgb255
    from tignn_jax.mr.render import colour_map

    return rgb255(np.asarray(colour_map(np.asarray((j + 0.5) / BANDS), 0.0, 1.0)))


def _legend(value_range, quantity: str, width: int = 300, height: int = 58) -> np.ndarray:
    """The legend as an RGB image [height, width, 3] uint8: the ``BANDS`` colours over ``value_range`` with
    its ends and middle labelled, the quantity's name (model units) and the clamped nodes' colour."""
    from PIL import Image, ImageDraw, ImageFont

    lo, hi = value_range
    image = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    try:
        font = ImageFont.load_default(size=12)
    except TypeError:
        font = ImageFont.load_default()
    left, right, top, bottom = 8, width - 8, 18, 36
    step = (right - left) / BANDS
    for j in range(BANDS):
        draw.rectangle([left + j * step, top, left + (j + 1) * step, bottom], fill=_band_colour(j))
    draw.rectangle([left, top, right, bottom], outline=(0, 0, 0))
    draw.text((left, 2), f"{quantity} (model units)", fill=(0, 0, 0), font=font)
    from tignn_jax.mr.legend import rgb255
    from tignn_jax.mr.scene import CLAMP_COLOUR   # the supports' markers (`_build_scene`)

    draw.rectangle([right - 62, 4, right - 52, 14], fill=rgb255(CLAMP_COLOUR), outline=(0, 0, 0))
    draw.text((right - 48, 2), "clamped", fill=(0, 0, 0), font=font)
    for x, v, anchor in ((left, lo, "la"), ((left + right) / 2, (lo + hi) / 2, "ma"), (right, hi, "ra")):
        draw.text((x, bottom + 4), f"{v:.3g}", fill=(0, 0, 0), font=font, anchor=anchor)
    return np.asarray(image)
