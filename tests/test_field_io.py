"""sims.core.field_io: many fields set (load) or read (read) in one launch, the same values as Taichi's own from_numpy,
fill and to_numpy."""
import numpy as np
import pytest
import taichi as ti

from sims.core import backend, field_io


@pytest.fixture(scope="module", autouse=True)
def runtime():
    backend.init("cpu")


def twin_fields():
    """Fields of every dtype load takes, scalar and vector, both layouts, 1 to 3 axes."""
    return [ti.field(ti.f32, (5, 7)), ti.Vector.field(3, ti.f32, (4, 6), layout=ti.Layout.SOA),
            ti.Vector.field(2, ti.f32, 11), ti.field(ti.i32, 9), ti.Vector.field(8, ti.i32, (3, 2)),
            ti.field(ti.u8, (3, 4)), ti.field(ti.i64, 3), ti.field(ti.f32, (2, 3, 4)), ti.field(ti.i32, 6)]


def test_load_sets_what_from_numpy_and_fill_set_in_one_kernel():
    rng = np.random.default_rng(3)
    ours, theirs = twin_fields(), twin_fields()
    values = [rng.random((5, 7)), rng.random((4, 6, 3)).astype(np.float32), 2.5, np.arange(9) - 4,
              rng.integers(-99, 99, (3, 2, 8)), 7, np.array([2 ** 40, -3, 5]), rng.random((2, 3, 4)), -1]
    for field, value in zip(theirs, values):
        if np.ndim(value):
            field.from_numpy(np.asarray(value).astype(field.to_numpy().dtype))
        else:
            field.fill(value)
    compiled = len(field_io._load_kernel._primal.compiled_kernels)
    field_io.load(zip(ours, values))
    assert len(field_io._load_kernel._primal.compiled_kernels) == compiled + 1  # one kernel for all nine fields
    for mine, reference in zip(ours, theirs):
        assert mine.to_numpy().dtype == reference.to_numpy().dtype
        assert np.array_equal(mine.to_numpy(), reference.to_numpy())


def test_read_returns_what_to_numpy_returns_in_one_kernel():
    rng = np.random.default_rng(4)
    fields = twin_fields()
    for field in fields:
        shape = field.to_numpy().shape
        field.from_numpy((rng.random(shape) * 200 - 100).astype(field.to_numpy().dtype) if field.dtype != ti.u8
                         else rng.integers(0, 256, shape).astype(np.uint8))
    compiled = len(field_io._read_kernel._primal.compiled_kernels)
    arrays = field_io.read(fields)
    assert len(field_io._read_kernel._primal.compiled_kernels) == compiled + 1  # one kernel for all nine fields
    for array, field in zip(arrays, fields):
        reference = field.to_numpy()
        assert array.dtype == reference.dtype and array.shape == reference.shape and np.array_equal(array, reference)
    with pytest.raises(ValueError, match="matrix field"):
        field_io.read([ti.Matrix.field(2, 2, ti.f32, 3)])


def test_load_refuses_what_it_cannot_copy_exactly():
    with pytest.raises(ValueError, match=r"shape \(7, 5\) for a field of shape \(5, 7\)"):
        field_io.load([(ti.field(ti.f32, (5, 7)), np.zeros((7, 5)))])
    with pytest.raises(ValueError, match="shape"):
        field_io.load([(ti.Vector.field(3, ti.f32, 4), np.zeros(4))])  # the components are missing
    with pytest.raises(ValueError, match="0-D"):
        field_io.load([(ti.field(ti.f32, ()), 1.0)])
    with pytest.raises(ValueError, match="matrix field"):
        field_io.load([(ti.Matrix.field(2, 2, ti.f32, 3), 0.0)])
    with pytest.raises(ValueError, match="float64"):
        field_io.load([(ti.field(ti.f64, 3), 0.0)])
