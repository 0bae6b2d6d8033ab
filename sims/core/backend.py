"""Taichi start-up: arch choice that never crashes without a GPU, cache dir, one init per process."""
from __future__ import annotations

import linecache
import os
import sys
from pathlib import Path
from textwrap import TextWrapper

ARCH_CHOICES = ("auto", "cpu", "gpu")
CPU_ARCHS = ("x64", "arm64")  # Taichi's names of the CPU backends
_started_arch: str | None = None
# loops over fewer work items run on the launching thread on a CPU (serial(); env TISSUE_LAB_SERIAL_BELOW, 0: never)
SERIAL_BELOW_ITEMS = int(os.environ.get("TISSUE_LAB_SERIAL_BELOW", "8192"))


class ArchUnavailable(RuntimeError):
    """--arch gpu on a machine without a usable GPU."""


OFFLINE_CACHE_BYTES = 1 << 30  # Taichi's compiled kernels on disk: a test run from nothing writes about 270 MB (a kernel
                               # per field); Taichi's default 100 MB evicts kernels that a run then compiles again


def cache_dir() -> Path:
    """Folder for compiled kernels and derived data (env TISSUE_LAB_CACHE, else ~/.cache/tissue-lab)."""
    root = os.environ.get("TISSUE_LAB_CACHE") or Path.home() / ".cache" / "tissue-lab"
    path = Path(root)
    path.mkdir(parents=True, exist_ok=True)
    return path


def save_cached_npz(path: Path, **arrays) -> None:
    """Save a cache entry as .npz under a unique temporary name in the same folder, then rename it: a reader (another
    process, say a second test worker) sees the whole entry or none."""
    import tempfile

    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".npz")
    try:
        with os.fdopen(handle, "wb") as file:
            np.savez(file, **arrays)
        os.replace(temp, path)
    except BaseException:
        Path(temp).unlink(missing_ok=True)
        raise


def read_cached_npz(path: Path, *names: str):
    """The named arrays of a cache entry, in order, or None when there is no entry or it cannot be read
    (truncated, corrupt or missing a name); an unreadable entry is deleted so it is computed again."""
    import zipfile

    import numpy as np

    if not path.is_file():
        return None
    try:
        with np.load(path) as data:
            return tuple(data[name] for name in names)
    except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile):
        path.unlink(missing_ok=True)
        return None


def cache_key(*items) -> str:
    """Hex digest of items: strings, numbers, None and arrays (their shape, dtype and bytes), for a cache entry."""
    import hashlib

    import numpy as np

    digest = hashlib.sha1()
    for item in items:
        if isinstance(item, np.ndarray):
            digest.update(repr((item.shape, item.dtype.str)).encode())
            digest.update(np.ascontiguousarray(item).tobytes())
        else:
            digest.update(repr(item).encode())
    return digest.hexdigest()


def source_digest(module_file: str) -> str:
    """Hex digest of a module's source (pass its __file__): in a cache key, an edit to the code that builds an entry
    builds it anew."""
    import hashlib

    return hashlib.sha1(Path(module_file).read_bytes()).hexdigest()


def cached_arrays(folder: str, key: str, names: tuple[str, ...], build, max_bytes: int) -> dict:
    """{name: array} of the entry `key` of cache_dir()/folder, or build() (a dict with those names) saved there as
    that entry when there is none; entries past max_bytes go, least recently used first (prune_cache)."""
    path = cache_dir() / folder / f"{key}.npz"
    stored = read_cached_npz(path, *names)
    if stored is not None:
        try:
            os.utime(path)  # recently used: pruned last
        except OSError:
            pass
        return dict(zip(names, stored))
    values = build()
    save_cached_npz(path, **{name: values[name] for name in names})
    prune_cache(path.parent, max_bytes)
    return values


def prune_cache(folder: Path, max_bytes: int) -> None:
    """Delete the least recently used entries (oldest modification time) of a cache folder until its files hold at
    most max_bytes; a file another process removes meanwhile is skipped, and one being written (save_cached_npz's
    hidden temporary name) is left alone."""
    entries = []
    for path in folder.iterdir():
        if path.name.startswith("."):
            continue
        try:
            info = path.stat()
        except OSError:
            continue
        entries.append((info.st_mtime, info.st_size, path))
    total = sum(size for _, size, _ in entries)
    for _, size, path in sorted(entries):
        if total <= max_bytes:
            break
        path.unlink(missing_ok=True)
        total -= size


def init(arch: str = "auto") -> str:
    """Start Taichi once per process and return the arch name it runs on ('x64', 'cuda', ...).

    `auto` tries CUDA then Vulkan and falls back to the CPU. `gpu` does the same but fails
    with ArchUnavailable when no GPU is found. `ti.gpu` itself is never used: its OpenGL probe
    segfaults on machines without a GPU. A second call with any arch returns the first arch.
    """
    global _started_arch
    if arch not in ARCH_CHOICES:
        raise ValueError(f"arch must be one of {', '.join(ARCH_CHOICES)}, not {arch!r}")
    if _started_arch is not None:
        return _started_arch
    os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
    import taichi as ti

    candidates = ti.cpu if arch == "cpu" else [ti.cuda, ti.vulkan]
    threads = os.environ.get("TISSUE_LAB_THREADS")  # CPU threads (default: all cores)
    extra = {"cpu_max_num_threads": int(threads)} if threads else {}
    if os.environ.get("TISSUE_LAB_QUICK_COMPILE") == "1":  # the tests: without Taichi's advanced IR optimisation a
        extra["advanced_optimization"] = False             # scene compiles in 2/3 of the time (steps about as fast)
    _remember_source_positions()
    _read_decorating_lines()
    ti.set_logging_level(ti.ERROR)  # the fallback to CPU is expected, not a warning for the user
    ti.init(
        arch=candidates,
        offline_cache=True,
        offline_cache_file_path=str(cache_dir() / "taichi"),
        offline_cache_max_size_of_files=OFFLINE_CACHE_BYTES,
        default_fp=ti.f32,
        log_level=ti.ERROR,
        **extra,
    )
    _started_arch = ti.lang.impl.current_cfg().arch.name
    if arch == "gpu" and _started_arch in CPU_ARCHS:
        raise ArchUnavailable("--arch gpu: no CUDA or Vulkan device found (use --arch auto or cpu)")
    return _started_arch


def _remember_source_positions() -> None:
    """Make Taichi build each kernel line's source-position text once per process instead of at every compile.

    Taichi's front end renders, for every statement and expression of a kernel it compiles, a caret-marked copy of the
    source line for its error messages (`get_pos_info`, wrapped to 80 columns by textwrap), and compiles each kernel
    again for every field it is handed and after every runtime restart: that text was 30-40 % of the time a warm-cache
    test module spent compiling. The text depends only on the node's place in the file, so it is kept by that place;
    the messages are unchanged."""
    from taichi.lang.ast import ast_transformer_utils as utils

    context = utils.ASTTransformerContext
    if getattr(context.get_pos_info, "remembers", False):
        return
    render, texts = context.get_pos_info, {}

    def get_pos_info(self, node):
        body = getattr(node, "body", None)
        place = (self.file, self.lineno_offset, self.func.func.__name__, self.indent, type(node).__name__, node.lineno,
                 node.end_lineno, node.col_offset, node.end_col_offset, body[0].lineno if isinstance(body, list) and body else None)
        text = texts.get(place)
        if text is None:
            text = texts[place] = render(self, node)
        return text

    get_pos_info.remembers = True
    context.get_pos_info = get_pos_info
    utils.TextWrapper = _LineWrapper


class _LineWrapper(TextWrapper):
    """TextWrapper with a shortcut for what Taichi's source-position text mostly wraps: a line (or caret hint) of at
    most `width` printable ASCII characters comes back as TextWrapper gives it, itself less its trailing spaces, without
    TextWrapper's regular-expression split into words (a fresh process wrapped 7,000 such lines: 0.2-0.3 s)."""

    def wrap(self, text: str) -> list[str]:
        if (len(text) <= self.width and text.isascii() and text.isprintable() and self.drop_whitespace
                and not (self.initial_indent or self.max_lines or self.fix_sentence_endings)):
            return [text.rstrip(" ")] if text.strip(" ") else []
        return super().wrap(text)


def _read_decorating_lines() -> None:
    """Make Taichi's test of whether a kernel or ti.func is decorated in a class body read the decorating frame's line
    from linecache. Taichi reads it through inspect.getframeinfo, which looks for the frame's module through every
    loaded module (about 1,300 in a run; 1-4 ms a call, and decorations made inside kernels being compiled call it
    for each): the same line, so the same answer (False where the source cannot be read)."""
    from taichi.lang import kernel_impl

    if getattr(kernel_impl._inside_class, "reads_lines", False):
        return
    patterns = kernel_impl._KERNEL_CLASS_STACKFRAME_STMT_RES

    def inside_class(level_of_class_stackframe):
        try:
            frame = sys._getframe(level_of_class_stackframe)  # this function replaces Taichi's at its depth
        except ValueError:
            return False
        if frame.f_lineno is None:
            return False
        line = linecache.getline(frame.f_code.co_filename, frame.f_lineno, frame.f_globals).strip()
        return any(pattern.match(line) for pattern in patterns)

    inside_class.reads_lines = True
    kernel_impl._inside_class = inside_class


def on_cpu() -> bool:
    """Whether kernels run on the CPU (also before the runtime starts)."""
    return _started_arch is None or _started_arch in CPU_ARCHS


def serial(items: int) -> bool:
    """Whether a kernel's loops over `items` work items (texels, particles) should run on the launching thread instead
    of Taichi's CPU thread pool: each parallel loop wakes the pool's threads and waits for them, measured at 40-60 us
    per loop on a 2-core virtual machine (25 us on another), whatever the loop does, more than the whole work of a
    loop over a few thousand texels. Kernels take it as a template argument (`ti.loop_config(serialize=serial)` before
    each loop), so both versions give the same bytes. Never on a GPU."""
    return on_cpu() and items < SERIAL_BELOW_ITEMS


def row_span(width: int) -> int:
    """Texels one thread of a light texture pass takes along a row (kernels loop `for r, q in ti.ndrange(height,
    width // span)`, then over the span's columns): the whole row on a CPU, where a thread walking a row measured 1.5-1.9
    times cheaper per texel than a loop over texels for a few loads and a square root (the normal map), though 1.1-1.3
    times dearer for heavy texels (the tissue's stages, the blood layer); one texel on a GPU, where every texel wants
    its own thread."""
    return width if _started_arch is None or _started_arch in CPU_ARCHS else 1


def started_arch() -> str | None:
    """The arch Taichi runs on, or None before init()."""
    return _started_arch


def shutdown() -> None:
    """Release every Taichi field and kernel of this process; the next init() starts a fresh runtime. Taichi allows
    512 SNode trees per runtime and each field made after the first kernel launch is one."""
    global _started_arch
    if _started_arch is not None:
        import taichi as ti

        ti.reset()
        _started_arch = None


def restart() -> None:
    """shutdown(), then a fresh runtime on the device the last one ran on (a CPU stays a CPU, a GPU a GPU)."""
    arch = _started_arch
    shutdown()
    if arch is not None:
        init("cpu" if arch in CPU_ARCHS else "gpu")
