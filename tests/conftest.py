import pytest

import inhand_tracker.sim_backend  # noqa: F401  (before collection imports newton: it switches Warp's adjoints off)


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
