import pytest


@pytest.fixture(scope="session", autouse=True)
def _quiet_warp():
    import warp as wp

    wp.config.quiet = True
    wp.init()


@pytest.fixture(scope="session")
def hand():
    from sim_backend import HandSpec, Kinematics

    spec = HandSpec()
    return spec, Kinematics(spec)
