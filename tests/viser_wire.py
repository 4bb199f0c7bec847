"""A browser's side of the live view's wire, without its rendering: it connects with viser's
subprotocol, reports a camera (viser counts a client once it has one) and reads every message the
view sends, until SIGTERM; then it prints how many came. It stands for a browser on another
machine, where the rendering's cost falls."""

from __future__ import annotations

import os
import signal
import sys

import msgspec
import viser
from viser._messages import ViewerCameraMessage
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect


def watch(url: str) -> None:
    # The browser stands for one on another machine: here it runs only on a core the service
    # leaves idle, so that what the test measures is the view's cost to the service, not this
    # stand-in's share of a 2-core runner.
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except OSError:  # a sandbox that refuses the policy: the lowest priority it allows
        os.nice(19)
    received = 0
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        with connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None) as ws:
            camera = ViewerCameraMessage(
                wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.5, -0.5, 0.4), fov=1.0, near=0.01, far=100.0,
                image_height=700, image_width=1000, look_at=(0.0, 0.0, 0.0), up_direction=(0.0, 0.0, 1.0),
            )  # fmt: skip
            ws.send(msgspec.msgpack.encode({"type": "ViewerCameraMessage", **camera.as_serializable_dict()}))
            while True:
                ws.recv()
                received += 1
    except ConnectionClosed:
        pass
    finally:
        print(received, flush=True)


if __name__ == "__main__":
    watch(sys.argv[1])
