"""Shared pieces of the benchmark sections: a test surface, the lab's display updates, device description, plotting setup."""
import math
import platform
import socket
import time
from pathlib import Path

from lab.session import TEXTURE_INTERVAL_S

BODY_C = 37.0
TEXTURE_UPDATES_PER_S = round(1.0 / TEXTURE_INTERVAL_S)  # display updates per (simulated) second, as the lab makes them


def free_port() -> int:
    """A TCP port on 127.0.0.1 free now (the system picks it), for a lab server of a bench section or a test."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def json_finite(value):
    """NaN and infinities become None (JSON null), recursively."""
    if isinstance(value, dict):
        return {key: json_finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_finite(item) for item in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def build_plane(side_mm: float, size: int):
    """A flat square of side_mm centred at the origin, rasterised at size^2 texels (sims.surface.texels.TissueSurface)."""
    from lab.reference.meshes import plane_mesh
    from sims.surface.texels import build_surface

    return build_surface(plane_mesh(side_mm, side_mm), size)


def lab_stream(server, scene, name: str):
    """A lab.web.stream.TextureStream made as the lab makes one (lab.web.app: its defaults, so the same tiles, maps and rate
    limit), on the scene's simulated clock: per simulated second it publishes what the lab publishes per second."""
    from lab.web.stream import TextureStream

    return TextureStream(server, scene.surface, name=name, clock=lambda: scene.time_s)


def stream_frame(scene, stream) -> tuple[float, float, int]:
    """One display update as the lab makes it (lab.web.stream.TextureStream.show, the lab's own frame path). Returns
    (wall s copying the maps off the device, wall s in the stream, GLB bytes published); composing is timed by the
    scene's profile as `compose`."""
    seconds = {}
    sent = stream.show(scene, seconds)["bytes"]
    return seconds["copying maps"], seconds["in the stream"], sent


def device_description(arch: str) -> dict:
    """Where the numbers were taken: Taichi arch, CPU, threads, Python, Taichi version."""
    import os

    import taichi as ti

    return {
        "arch": arch,
        "machine": platform.machine(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count() or 1,
        "threads": int(os.environ.get("TISSUE_LAB_THREADS", 0)) or (os.cpu_count() or 1),
        "python": platform.python_version(),
        "taichi": ".".join(str(v) for v in ti.__version__),
    }


def cpu_ticks() -> tuple[int, int] | None:
    """(all, stolen) CPU ticks of the machine so far from /proc/stat (Linux), None elsewhere."""
    try:
        fields = [int(value) for value in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return None
    return sum(fields[:8]), fields[7] if len(fields) > 7 else 0


def stolen_share(before, after) -> float | None:
    """Share of the machine's CPU time the hypervisor took for other guests between two cpu_ticks() (steal)."""
    if before is None or after is None or after[0] <= before[0]:
        return None
    return (after[1] - before[1]) / (after[0] - before[0])


def synced_seconds(fn, repeats: int = 1, chunks: int = 5) -> float:
    """Wall seconds for `repeats` calls of fn: the calls are timed in up to `chunks` equal runs (Taichi device
    synchronised at both ends of each) and the fastest run's time per call is scaled to `repeats`, so a burst of
    other load on the machine does not count."""
    import taichi as ti

    chunks = max(1, min(chunks, repeats))
    best = float("inf")
    done = 0
    for index in range(chunks):
        size = (repeats * (index + 1)) // chunks - done
        ti.sync()
        start = time.perf_counter()
        for _ in range(size):
            fn()
        ti.sync()
        best = min(best, (time.perf_counter() - start) / size)
        done += size
    return best * repeats


def pyplot():
    """matplotlib.pyplot with the file-only Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"figure.dpi": 110, "axes.grid": True, "grid.alpha": 0.3, "font.size": 9})
    return plt


def save(fig, out_dir, name: str) -> str:
    """Lay out, write out_dir/name as PNG, free the figure; returns name."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(Path(out_dir) / name)
    plt.close(fig)
    return name


def pareto(rows: list[dict], cost, error) -> list[dict]:
    """The rows no other row beats in both cost(row) and error(row), cheapest first."""
    best, front = float("inf"), []
    for row in sorted(rows, key=lambda r: (cost(r), error(r))):
        if error(row) < best:
            best = error(row)
            front.append(row)
    return front
