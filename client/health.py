"""Container health check: ask the local service's info key over Zenoh; exit 0 when it answers
and is ready (kernels compiled, its tracking loop running).

python -m inhand_tracker.client.health [ENDPOINT]   (default: INHAND_LISTEN with 0.0.0.0 read as 127.0.0.1;
INHAND_ZENOH_CONFIG, when set, is the Zenoh file it connects with, as the service does)
"""

from __future__ import annotations

import os
import sys

from .tracker_client import TrackerClient


def main() -> int:
    endpoint = sys.argv[1] if len(sys.argv) > 1 else os.environ.get("INHAND_LISTEN", "tcp/127.0.0.1:7447")
    endpoint = endpoint.split(",")[0].replace("0.0.0.0", "127.0.0.1")
    service = os.environ.get("INHAND_NAME", "default")
    try:
        zenoh_file = os.environ.get("INHAND_ZENOH_CONFIG") or None
        with TrackerClient(connect=[endpoint], service=service, zenoh_file=zenoh_file) as client:
            info = client.service_info(timeout=5.0)
    except Exception as exc:  # any failure is "unhealthy", with the reason for `docker inspect`
        print(f"unhealthy: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    if not info.ready:
        why = "warming up, or its tracking loop stopped"
        print(f"unhealthy: service '{info.name}' is not ready ({why})", file=sys.stderr)
        return 1
    print(f"healthy: service '{info.name}' on {info.device}, {info.sessions} sessions")
    return 0


if __name__ == "__main__":
    sys.exit(main())
