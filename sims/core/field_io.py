"""Many Taichi fields loaded from NumPy arrays or filled with a value in one kernel launch.

Taichi compiles its own copy kernel for every field `from_numpy` or `fill` is called on (the field is a compile-time
argument): 50-80 ms each from nothing on a CPU, 12-25 ms from its kernel cache, and a scene build made about 80 of
them. `load` hands all the fields of one call to one kernel instead (one compile per call site and model).
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
        numpy_type = to_numpy_type(field.dtype)
        if numpy_type not in sizes:
            raise ValueError(f"field_io.load takes fields of {', '.join(t.__name__ for t in BUFFER_TYPES)}, not {numpy_type.__name__}")
        if not field.shape:
            raise ValueError("field_io.load takes fields with at least one axis, not 0-D fields")
        vector = isinstance(field, MatrixField)
        if vector and (field.m != 1 or field.ndim != 1):
            raise ValueError(f"field_io.load takes scalar and vector fields, not a {field.n} x {field.m} matrix field")
        components = field.n if vector else 1
        if np.ndim(value) == 0:
            chunk, fill = np.full(1, value, numpy_type), 1
        else:
            array = np.asarray(value)
            shape = tuple(field.shape) + ((components,) if vector else ())
            if array.shape != shape:
                raise ValueError(f"field_io.load: an array of shape {array.shape} for a field of shape {shape}")
            chunk, fill = np.ascontiguousarray(array, numpy_type).ravel(), 0
        layout.append((BUFFER_TYPES.index(numpy_type), sizes[numpy_type], fill, components, vector))
        chunks[numpy_type].append(chunk)
        sizes[numpy_type] += chunk.size
    if pairs:
        buffers = [np.concatenate(chunks[t]) if chunks[t] else np.zeros(1, t) for t in BUFFER_TYPES]
        _load_kernel(tuple(field for field, _ in pairs), tuple(layout), *buffers)


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
                linear = 0
                for axis in ti.static(range(len(shape))):
                    linear = linear * shape[axis] + index[axis]
                if ti.static(vector):
                    fields[k][index] = ti.Vector([flat[offset + linear * components + c] for c in ti.static(range(components))])
                else:
                    fields[k][index] = flat[offset + linear]
