"""sims.core.backend's shortcuts in Taichi's Python front end give what Taichi's own code gives."""
import textwrap
from pathlib import Path

import pytest
import taichi as ti
from taichi.lang.exception import TaichiSyntaxError

from sims.core import backend

SOURCES = Path(backend.__file__).parents[1]  # every module of sims


def test_line_wrapper_wraps_as_textwrap():
    lines = [line for path in sorted(SOURCES.rglob("*.py")) for line in path.read_text().splitlines()]
    hints = [" " * start + "^" * length + " " * 3 for start in (0, 4, 40, 79) for length in (0, 1, 30, 60)]
    edges = ["", " ", " " * 80, "x" * 80, "x" * 81, "a b " * 20, "a b " * 21, "\tx = 1", "x = 'é'", "a\x1cb", "a-b-c " * 14]
    wrapper, plain = backend._LineWrapper(width=80), textwrap.TextWrapper(width=80)
    assert len(lines) > 1000
    for text in lines + hints + edges:
        assert wrapper.wrap(text) == plain.wrap(text), repr(text)


def test_kernels_are_told_apart_in_classes_and_modules():
    backend.init("cpu")

    @ti.data_oriented
    class Counter:
        def __init__(self):
            self.count = ti.field(ti.i32, ())

        @ti.kernel
        def add(self, amount: ti.i32):
            self.count[None] += amount

    class Undecorated:
        @ti.kernel
        def add(self):
            pass

    @ti.kernel
    def twice(value: ti.i32) -> ti.i32:
        return 2 * value

    counter = Counter()
    counter.add(3)
    assert counter.count[None] == 3 and twice(4) == 8
    with pytest.raises(TaichiSyntaxError, match="data_oriented"):  # Taichi saw the kernel was defined in a class
        Undecorated().add()
