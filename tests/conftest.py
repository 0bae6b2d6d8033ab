import pytest

from sims import backend


@pytest.fixture(scope="module", autouse=True)
def taichi_cpu():
    """A fresh Taichi runtime on the CPU (CI has no GPU) for every test module: Taichi allows 512 SNode trees
    per runtime (each field made after the first kernel launch is one) and the process dies past that."""
    yield backend.init("cpu")
    backend.shutdown()
