import os

import pytest

# Kernels compiled without Taichi's advanced IR optimisation (sims.core.backend.init): the suite compiles thousands of
# kernels, and tests check what a step computes, never how fast. Subprocesses of tests inherit it, except the runs
# that compare the bytes of the serial and parallel particle steps, which compile as the lab does: without that
# optimisation the two round differently.
os.environ.setdefault("TISSUE_LAB_QUICK_COMPILE", "1")

from sims.core import backend
from testing import browser


@pytest.fixture(scope="module", autouse=True)
def taichi_cpu():
    """A fresh Taichi runtime on the CPU (CI has no GPU) for every test module: Taichi allows 512 SNode trees
    per runtime (each field made after the first kernel launch is one) and the process dies past that."""
    yield backend.init("cpu")
    backend.shutdown()


@pytest.fixture(scope="module")
def chrome():
    """Debian chromium on a thread of its own (testing.browser.BrowserThread), one per test module that asks for it."""
    thread = browser.BrowserThread()
    yield thread
    thread.close()
