"""A browser's side of the live view's wire, without its rendering: it connects with viser's
subprotocol, reports a camera (viser counts a client once it has one) and reads every message the
view sends, until SIGTERM; then it reads what is still on its way and prints how many draws came:
the view's updates after the scene it had when the stand-in connected, each carrying the real
fingertips. It prints "connected" once the view counts it as a client. It stands for a browser on
another machine, where the rendering's cost falls."""

from __future__ import annotations

import os
import signal
import sys
import time

import msgspec
import viser
import zstandard
from viser._messages import ViewerCameraMessage
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

_QUIET_S = 1.0
"""How long the wire stays quiet, once told to stop, before the stand-in is sure it read all [s]."""
_DRAIN_S = 15.0
"""The most it reads for once told to stop, should the view go on sending [s]."""


def watch(url: str) -> None:
    draws, replayed, stopping = 0, False, []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(time.monotonic()))
    try:
        with connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None) as ws:
            camera = ViewerCameraMessage(
                wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.5, -0.5, 0.4), fov=1.0, near=0.01, far=100.0,
                image_height=700, image_width=1000, look_at=(0.0, 0.0, 0.0), up_direction=(0.0, 0.0, 1.0),
            )  # fmt: skip
            ws.send(msgspec.msgpack.encode({"type": "ViewerCameraMessage", **camera.as_serializable_dict()}))
            print("connected", flush=True)
            _step_aside()
            while True:
                try:
                    data = ws.recv(timeout=_QUIET_S)
                except TimeoutError:
                    if stopping:  # drained: at idle priority on a busy runner, reading falls behind
                        break
                    continue
                kinds = _kinds(data)
                draws += replayed and "PointCloudMessage" in kinds
                replayed = replayed or "ReplayDoneMessage" in kinds
                if stopping and time.monotonic() - stopping[0] > _DRAIN_S:
                    break
    except ConnectionClosed:
        pass
    finally:
        print(draws, flush=True)


def _kinds(data: bytes) -> set[str]:
    """The types of the messages in one of viser's windows: two sizes (8 bytes each), then the
    zstd-compressed msgpack of the messages, then their binary arrays."""
    size, compressed = int.from_bytes(data[:8], "little"), int.from_bytes(data[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(data[16 : 16 + compressed], max_output_size=size)
    return {message["type"] for message in msgspec.msgpack.decode(inner)["messages"]}


def _step_aside() -> None:
    """From now on run only on a core the service leaves idle: the stand-in is a browser on another
    machine, so what the test measures is the view's cost to the service, not this process's share
    of a 2-core runner. What it falls behind in reading, it reads once told to stop."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except OSError:  # a sandbox that refuses the policy: the lowest priority it allows
        os.nice(19)


if __name__ == "__main__":
    watch(sys.argv[1])
