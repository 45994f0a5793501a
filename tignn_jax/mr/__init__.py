"""The mixed-reality layer: fingertips tracked in a camera image push virtual solids drawn over the real image.

Modules, one concept each:

* `tignn_jax.mr.camera`: the pinhole `Camera`, projection, view and model matrices, `project` and `unproject`.
* `tignn_jax.mr.surface`: a volume mesh's outward surface triangles, their nodes, vertex normals.
* `tignn_jax.mr.forcing`: fingertip forces on a body and penalty contact between bodies.
* `tignn_jax.mr.render`: colour map, Phong shading, a software rasteriser, occlusion by a real depth image.
* `tignn_jax.mr.legend`: the colour legend drawn onto finished frames.
* `tignn_jax.mr.background`: the real RGB and depth image, a synthetic table, the hand proxy.
* `tignn_jax.mr.track`: fingertip tracks (the JSON-lines format, a synthetic press); `tignn_jax.mr.hands`:
  MediaPipe hand landmarks into tracks (depth from the hand's size).
* `tignn_jax.mr.scene`: `Scene`, `Body` and the real-time loop `run`.
* `tignn_jax.mr.runtime`: process set-up of the loop (CPU pinning, CPU devices, XLA:CPU options).

Everything is exported here, e.g. ``from tignn_jax import mr; mr.run(scene)``. The CLI's scenes are built by
`tignn_jax.cli.demo.build_scene`.
"""
from __future__ import annotations

from tignn_jax.mr.background import Background, hand_proxy, rest_on_surface, table_background
from tignn_jax.mr.camera import (Camera, camera_projection, clip_coordinates, look_at, model_matrix, mvp_matrix,
                                 perspective, project, projection_from_intrinsics, rotation_matrix,
                                 transform_points, unproject)
from tignn_jax.mr.forcing import (contact_energy, contact_forces, fingertip_forces, fingertip_pads,
                                  fingertip_spring_forces)
from tignn_jax.mr.legend import with_legend
from tignn_jax.mr.render import (Raster, colour_map, draw_mesh, fragment_capacity, occlude, phong, rasterize,
                                 von_mises)
from tignn_jax.mr.runtime import REAL_TIME_XLA_FLAG, cpu_devices, pin_cores, real_time_cores, real_time_xla_flags
from tignn_jax.mr.scene import CLAMP_COLOUR, Body, Scene, StepFn, Timings, build, make_render_fn, run, validate
from tignn_jax.mr.surface import HEX8_FACES, TET4_FACES, surface_nodes, surface_triangles, vertex_normals
from tignn_jax.mr.hands import hand_to_tips
from tignn_jax.mr.track import load_track, press_track, save_track

__all__ = [
    # camera
    "Camera", "camera_projection", "clip_coordinates", "look_at", "model_matrix", "mvp_matrix", "perspective",
    "project", "projection_from_intrinsics", "rotation_matrix", "transform_points", "unproject",
    # surface
    "HEX8_FACES", "TET4_FACES", "surface_nodes", "surface_triangles", "vertex_normals",
    # forcing
    "contact_energy", "contact_forces", "fingertip_forces", "fingertip_pads", "fingertip_spring_forces",
    # render
    "Raster", "colour_map", "draw_mesh", "fragment_capacity", "occlude", "phong", "rasterize", "von_mises",
    "with_legend",
    # background
    "Background", "hand_proxy", "rest_on_surface", "table_background",
    # track
    "load_track", "press_track", "save_track", "hand_to_tips",
    # scene
    "CLAMP_COLOUR", "Body", "Scene", "StepFn", "Timings", "build", "make_render_fn", "run", "validate",
    # runtime
    "REAL_TIME_XLA_FLAG", "cpu_devices", "pin_cores", "real_time_cores", "real_time_xla_flags",
]
