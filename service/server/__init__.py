"""The service on Zenoh: its configuration, the sessions (each a group of a shared population)
and the node whose one loop thread owns the GPU.

Its names load on first use (lazy_loader), so that a configuration is read and refused in a
fraction of a second, before torch, warp and newton load."""

import lazy_loader as lazy

__getattr__, __dir__, __all__ = lazy.attach(
    __name__,
    submod_attrs={
        "admission": ["ServiceError"],
        "config": ["ServiceConfig", "load_config"],
        "node": ["TrackerNode"],
        "sessions": ["SessionManager"],
    },
)
