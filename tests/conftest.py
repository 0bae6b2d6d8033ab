import pytest

from sims import backend


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    """One Taichi init per test process, on the CPU (CI has no GPU)."""
    return backend.init("cpu")
