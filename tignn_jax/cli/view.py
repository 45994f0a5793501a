"""``tignn view``: a page on localhost where the mouse pushes and pulls a simulated body (`tignn_jax.view`).

Needs the ``view`` extra (viser): ``pip install ".[view]"``.
"""
from __future__ import annotations

import argparse
import math
import signal
import socket
import threading

from tignn_jax.cli import UsageError
from tignn_jax.view.scenes import SCENES

COLOURS = {"von-mises": "von Mises", "sxx": "σxx", "u": "|u|"}   # option value -> `tignn_jax.view.QUANTITIES`


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``view`` subcommand to ``sub`` (the ``tignn`` parser's subparsers)."""
    p = sub.add_parser("view", help="push a simulated body with the mouse, in a browser page on localhost",
                       description="Serve a page where you press on a body and drag to push or pull it; the body "
                                   "is stepped by a learned model (or the FEM's Newton step) and coloured by a "
                                   "chosen quantity. Each browser tab gets its own scene. Needs the view extra: "
                                   "pip install \".[view]\".")
    p.add_argument("--scene", choices=SCENES, default=None,
                   help="one beam clamped at x = 0, two crossed beams (press the upper onto the lower), or the "
                        "bunny (default: beam, or the model's own mesh when --model is given)")
    p.add_argument("--model", default=None,
                   help="a shipped model name, a folder written by tignn train (DIR/model/model.npz or "
                        "DIR/model.npz), a model .npz file, or fem-newton (the FEM's backward-Euler step on the "
                        "scene's mesh; needs --scene or uses beam); default: the scene's shipped model")
    p.add_argument("--port", type=int, default=8080, help="TCP port of the page (default: %(default)s)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on; 0.0.0.0 makes the page reachable from other machines "
                        "(default: %(default)s)")
    p.add_argument("--colour", choices=tuple(COLOURS), default="von-mises",
                   help="the quantity coloured at start: von-mises (von Mises stress), sxx (σxx, S11), u (|u|, "
                        "displacement magnitude); the page can switch (default: %(default)s)")
    p.add_argument("--rate", type=float, default=30.0,
                   help="physics steps per second, each one model frame, 1..240 (default: %(default)s)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Serve the page until interrupted (Ctrl-C or SIGTERM).

    Raises:
      UsageError: a bad option value, or viser is not installed.
    """
    if not 1 <= args.port <= 65535:
        raise UsageError(f"--port must be 1..65535, got {args.port}")
    if not (math.isfinite(args.rate) and 1.0 <= args.rate <= 240.0):
        raise UsageError(f"--rate must be 1..240 steps per second, got {args.rate}")
    from tignn_jax.cli.demo import FEM_NEWTON
    from tignn_jax.view.scenes import resolve_model

    scene = args.scene
    if args.model is not None:
        try:
            resolve_model(args.model)
        except ValueError as err:
            raise UsageError(f"--{err}") from None   # "--model 'NAME': ..."
    if scene is None and (args.model is None or args.model == FEM_NEWTON):
        scene = "beam"
    _check_address(args.host, args.port)
    try:
        import viser  # noqa: F401
    except ImportError:
        raise UsageError('viser is not installed: pip install ".[view]"') from None
    from tignn_jax.view.server import serve

    view = serve(scene, args.model, host=args.host, port=args.port, colour=COLOURS[args.colour], rate=args.rate)
    print(f"tignn view: {view.scene_of(scene, args.model).dynamics}; open http://{args.host}:{args.port} "
          "(Ctrl-C stops)", flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())   # kill: stop as Ctrl-C does
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        view.stop()
    return 0


def _check_address(host: str, port: int) -> None:
    """Refuse a host that does not resolve or a port that is taken (viser would silently move to another)."""
    try:
        family, kind, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
    except OSError as err:
        raise UsageError(f"--host {host} --port {port}: cannot serve there ({err.strerror or err})") from None
