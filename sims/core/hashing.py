"""Counter-based pseudo-random numbers for kernels (deterministic: a function of their integer arguments)."""
import taichi as ti


@ti.func
def hash01(a, b):
    """Deterministic pseudo-random number in [0, 1) from two integers (PCG-style mix): the same on every device and
    thread count."""
    h = ti.cast(a, ti.u32) * ti.u32(747796405) + ti.cast(b, ti.u32) * ti.u32(2891336453) + ti.u32(277803737)
    h = ((h >> ((h >> 28) + ti.u32(4))) ^ h) * ti.u32(277803737)
    h = (h >> 22) ^ h
    return ti.cast(h >> 8, ti.f32) / 16777216.0
