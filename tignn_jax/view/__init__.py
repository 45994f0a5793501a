"""``tignn view``: push a simulated body with the mouse in a browser page served on localhost.

* `tignn_jax.view.interaction`: `Interaction`, one page's bodies, fingertip spring, guard and clock (no browser needed).
* `tignn_jax.view.scenes`: `load_scene`, the demo's scenes or any model's own mesh.
* `tignn_jax.view.server`: `serve`, the viser web server, one `Interaction` and physics thread per tab.

The server needs the ``view`` extra (``pip install ".[view]"``: viser); the interaction and scenes do not.
"""
from __future__ import annotations

from tignn_jax.view.scenes import SCENES, load_scene, models_for
from tignn_jax.view.interaction import QUANTITIES, Body, Frame, Scene, Interaction

__all__ = ["SCENES", "QUANTITIES", "Body", "Frame", "Scene", "Interaction", "load_scene", "models_for", "serve"]


def serve(*args, **kwargs):
    """`tignn_jax.view.server.serve` (imported on use: it needs viser)."""
    from tignn_jax.view.server import serve as _serve

    return _serve(*args, **kwargs)
