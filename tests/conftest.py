import gc
from collections.abc import Iterator

import pytest

import inhand_tracker.sim_backend  # noqa: F401  (before collection imports newton: it switches Warp's adjoints off)


def pytest_addoption(parser: pytest.Parser) -> None:
    # An option rather than `-m "not alone"`: a user's own `-m` replaces an earlier one.
    parser.addoption(
        "--alone", choices=("with", "skip", "only"), default="with",
        help="the tests marked alone (they need an idle core): with the others, skipped, or only them",
    )  # fmt: skip


@pytest.hookimpl(wrapper=True)
def pytest_collection(session: pytest.Session) -> Iterator[object]:
    # Collecting imports the GPU stack: over a million objects that every full collection would walk
    # again, for every test; they load with the collector paused and are then frozen out of its view
    # (as the command line's gpu_stack does).
    gc.disable()
    try:
        return (yield)
    finally:
        gc.freeze()
        gc.enable()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    mode = config.getoption("--alone")
    if mode == "with":
        return
    keep = [item for item in items if (item.get_closest_marker("alone") is not None) == (mode == "only")]
    config.hook.pytest_deselected(items=[item for item in items if item not in keep])
    items[:] = keep


@pytest.fixture(scope="session", autouse=True)
def _quiet_warp():
    import warp as wp

    from inhand_tracker.service.logs import quiet_warp

    quiet_warp()
    wp.init()


@pytest.fixture(scope="session")
def hand():
    from inhand_tracker.sim_backend import HandSpec, Kinematics

    spec = HandSpec()
    return spec, Kinematics(spec)
