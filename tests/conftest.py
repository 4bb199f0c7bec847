import pytest

from service.cli import forward_only_kernels

# Before collection imports a test module that imports newton: Warp reads it per kernel module.
forward_only_kernels()


@pytest.fixture(scope="session", autouse=True)
def _quiet_warp():
    import warp as wp

    from service.logs import quiet_warp

    quiet_warp()
    wp.init()


@pytest.fixture(scope="session")
def hand():
    from sim_backend import HandSpec, Kinematics

    spec = HandSpec()
    return spec, Kinematics(spec)
