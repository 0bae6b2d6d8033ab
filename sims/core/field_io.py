"""Many Taichi fields loaded from NumPy arrays or filled with a value in one kernel launch, or read into arrays in one.

Taichi compiles its own copy kernel for every field `from_numpy`, `to_numpy` or `fill` is called on (the field is a
compile-time argument): 50-80 ms each from nothing on a CPU, 8-25 ms from its kernel cache, and a scene build made
about 80 of them. `load` and `read` hand all the fields of one call to one kernel instead (one compile per call site).
"""
import numpy as np
import taichi as ti
from taichi.lang.matrix import MatrixField
from taichi.lang.util import to_numpy_type

BUFFER_TYPES = (np.float32, np.int32, np.uint8, np.int64)  # the field dtypes load takes, one flat buffer each


def load(pairs) -> None:
    """Set each field of `pairs` [(field, value)]: value a NumPy array of the field's to_numpy shape (field.shape,
    then the vector length for a vector field), or a number every element takes (as field.fill). One launch; the
    fields keep their layouts. Raises ValueError for an array of another shape, a 0-D or matrix field, or a dtype
    outside BUFFER_TYPES."""
    pairs = list(pairs)
    chunks = {numpy_type: [] for numpy_type in BUFFER_TYPES}
    sizes = dict.fromkeys(BUFFER_TYPES, 0)
    layout = []
    for field, value in pairs:
        numpy_type, shape, components, vector = _describe(field, "load")
        if np.ndim(value) == 0:
            chunk, fill = np.full(1, value, numpy_type), 1
        else:
            array = np.asarray(value)
            if array.shape != shape:
                raise ValueError(f"field_io.load: an array of shape {array.shape} for a field of shape {shape}")
            chunk, fill = np.ascontiguousarray(array, numpy_type).ravel(), 0
        layout.append((BUFFER_TYPES.index(numpy_type), sizes[numpy_type], fill, components, vector))
        chunks[numpy_type].append(chunk)
        sizes[numpy_type] += chunk.size
    if pairs:
        buffers = [np.concatenate(chunks[t]) if chunks[t] else np.zeros(1, t) for t in BUFFER_TYPES]
        _load_kernel(tuple(field for field, _ in pairs), tuple(layout), *buffers)


def read(fields) -> list[np.ndarray]:
    """Each field's to_numpy array (the same values, shape and dtype), read in one launch. Raises ValueError as load."""
    fields = list(fields)
    sizes = dict.fromkeys(BUFFER_TYPES, 0)
    layout, views = [], []
    for field in fields:
        numpy_type, shape, components, vector = _describe(field, "read")
        layout.append((BUFFER_TYPES.index(numpy_type), sizes[numpy_type], 0, components, vector))
        views.append((numpy_type, sizes[numpy_type], shape))
        sizes[numpy_type] += int(np.prod(shape))
    if not fields:
        return []
    buffers = {t: np.empty(max(sizes[t], 1), t) for t in BUFFER_TYPES}
    _read_kernel(tuple(fields), tuple(layout), *buffers.values())
    return [buffers[t][offset:offset + int(np.prod(shape))].reshape(shape) for t, offset, shape in views]


def _describe(field, call: str) -> tuple[type, tuple, int, bool]:
    """(NumPy dtype, to_numpy shape, components, vector) of a field load and read take; ValueError for another."""
    numpy_type = to_numpy_type(field.dtype)
    if numpy_type not in BUFFER_TYPES:
        raise ValueError(f"field_io.{call} takes fields of {', '.join(t.__name__ for t in BUFFER_TYPES)}, not {numpy_type.__name__}")
    if not field.shape:
        raise ValueError(f"field_io.{call} takes fields with at least one axis, not 0-D fields")
    vector = isinstance(field, MatrixField)
    if vector and (field.m != 1 or field.ndim != 1):
        raise ValueError(f"field_io.{call} takes scalar and vector fields, not a {field.n} x {field.m} matrix field")
    components = field.n if vector else 1
    return numpy_type, tuple(field.shape) + ((components,) if vector else ()), components, vector


@ti.func
def _flat_index(index, shape):
    """Row-major position of a field's element `index` among the elements of `shape`."""
    linear = 0
    for axis in ti.static(range(len(shape))):
        linear = linear * shape[axis] + index[axis]
    return linear


@ti.kernel
def _read_kernel(fields: ti.template(), layout: ti.template(), f32: ti.types.ndarray(ndim=1),
                 i32: ti.types.ndarray(ndim=1), u8: ti.types.ndarray(ndim=1), i64: ti.types.ndarray(ndim=1)):
    """buffer layout[k] from fields[k], in load's order (row-major, components innermost)."""
    for k in ti.static(range(len(fields))):
        buffer, offset, _, components, vector = ti.static(layout[k])
        flat = ti.static((f32, i32, u8, i64)[buffer])
        shape = ti.static(fields[k].shape)
        for index in ti.grouped(fields[k]):
            linear = _flat_index(index, shape)
            if ti.static(vector):
                for c in ti.static(range(components)):
                    flat[offset + linear * components + c] = fields[k][index][c]
            else:
                flat[offset + linear] = fields[k][index]


@ti.kernel
def _load_kernel(fields: ti.template(), layout: ti.template(), f32: ti.types.ndarray(ndim=1),
                 i32: ti.types.ndarray(ndim=1), u8: ti.types.ndarray(ndim=1), i64: ti.types.ndarray(ndim=1)):
    """fields[k] from buffer layout[k] = (buffer (index into BUFFER_TYPES), offset, fill, components, vector): fill 1
    sets every element (and component) to buffer[offset]; fill 0 copies the field's elements in row-major order,
    components innermost."""
    for k in ti.static(range(len(fields))):
        buffer, offset, fill, components, vector = ti.static(layout[k])
        flat = ti.static((f32, i32, u8, i64)[buffer])
        shape = ti.static(fields[k].shape)
        for index in ti.grouped(fields[k]):
            if ti.static(fill == 1):
                if ti.static(vector):
                    fields[k][index] = ti.Vector([flat[offset] for _ in ti.static(range(components))])
                else:
                    fields[k][index] = flat[offset]
            else:
                linear = _flat_index(index, shape)
                if ti.static(vector):
                    fields[k][index] = ti.Vector([flat[offset + linear * components + c] for c in ti.static(range(components))])
                else:
                    fields[k][index] = flat[offset + linear]
