"""Generate the static assets of tissue-lab: tissue textures and meshes.

Run from anywhere as ``python tools/make_static.py``.  Output is written to
``static/`` next to this ``tools/`` folder and is byte-for-byte deterministic.

Conventions
-----------
* Lengths are millimetres, z is up.
* Textures are 1024x1024 RGB PNGs that tile seamlessly (every noise field is
  periodic on the tile).  The tissue states share the same noise fields
  and vessel layout, so blending between them reads as one tissue changing.
* OBJ ``vt`` follows the OBJ/OpenGL convention: v=0 is the BOTTOM row of the
  image, i.e. image row = (1 - v) * height.
"""

from __future__ import annotations

import heapq
import time
from pathlib import Path

import numpy as np
import trimesh
import xatlas
from PIL import Image
from scipy import ndimage
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parent.parent
STATIC = ROOT / "static"
TEX_SIZE = 1024
SEED = 20240611

# Mean sRGB of each tissue state. Native liver: "liver" (108, 46, 31) (docs/model/look.md "Healthy liver", a weak source). No measured
# colour of coagulated liver was found; the coagulum takes the CIELAB of cooked pork (Jang et al. 2019, Food Sci Anim
# Resour 39:756, table 5): the pale crest at the margin the interior cooked medium (L* 66.4, a* 11.0, b* 11.5), the
# coagulum well done (57.4, 7.7, 12.6), a deep burn the well-done surface (49.9, 6.9, 15.1). The hyperaemic rim (the
# "red zone" of ablation pathology, Ng et al. 2005, Radiology 235:478) and char are chosen by eye.
LIVER_HEALTHY_RGB = (108.0, 46.0, 31.0)
LIVER_HYPERAEMIC_RGB = (128.0, 32.0, 33.0)
LIVER_PALE_RGB = (189.0, 154.0, 141.0)
LIVER_COAGULATED_RGB = (159.0, 133.0, 116.0)
LIVER_BROWNED_RGB = (139.0, 114.0, 93.0)
LIVER_CHARRED_RGB = (33.0, 23.0, 17.0)


# --------------------------------------------------------------------------
# Periodic noise primitives (all fields are float64 arrays of shape (n, n))
# --------------------------------------------------------------------------

def band_noise(rng: np.random.Generator, n: int, f_lo: float, f_hi: float,
               slope: float = 1.0) -> np.ndarray:
    """Periodic noise with energy between f_lo and f_hi cycles per tile.

    White noise is filtered in the Fourier domain with a soft band-pass whose
    amplitude falls as f**-slope.  Returns an (n, n) field, mean 0, std 1.
    """
    k = np.fft.fftfreq(n, 1.0 / n)
    f = np.hypot(k[:, None], k[None, :])
    f[0, 0] = 1.0
    band = (1.0 / (1.0 + (f_lo / f) ** 8)) * (1.0 / (1.0 + (f / f_hi) ** 8))
    spectrum = np.fft.fft2(rng.standard_normal((n, n))) * band * f ** -slope
    spectrum[0, 0] = 0.0
    field = np.fft.ifft2(spectrum).real
    return field / field.std()


def warp(field: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Sample an (n, n) periodic field at (col + dx, row + dy), offsets in px."""
    n = field.shape[0]
    rows, cols = np.mgrid[0:n, 0:n].astype(np.float64)
    return ndimage.map_coordinates(field, [rows + dy, cols + dx], order=1,
                                   mode="grid-wrap")


def periodic_blur(field: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (sigma in px) with wrap-around borders."""
    return ndimage.gaussian_filter(field, sigma, mode="wrap")


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at x=e0 to 1 at x=e1 (elementwise)."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def hex_cells(rng: np.random.Generator, n: int, cols: int, jitter: float,
              dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Periodic Worley distances on a jittered hexagonal lattice.

    cols cells across the tile (rows chosen to keep cells near-regular);
    jitter is in cell widths; (dx, dy) domain-warp the lookup in px.
    Returns (F1, F2 - F1), both (n, n) in units of the cell width.
    """
    rows = 2 * int(round(cols / np.sqrt(3.0)))
    j, i = np.mgrid[0:rows, 0:cols].astype(np.float64)
    seeds = np.stack([(i + 0.5 * (j % 2) + 0.25) / cols, (j + 0.5) / rows], -1)
    seeds = seeds.reshape(-1, 2) + rng.normal(0.0, jitter / cols, (rows * cols, 2))
    tree = cKDTree(np.mod(seeds, 1.0) * n, boxsize=n)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    pts = np.stack([np.mod(xx + 0.5 + dx, n), np.mod(yy + 0.5 + dy, n)], -1)
    dist, _ = tree.query(pts.reshape(-1, 2), k=2, workers=-1)
    cell = n / cols
    f1 = dist[:, 0].reshape(n, n) / cell
    f2 = dist[:, 1].reshape(n, n) / cell
    return f1, f2 - f1


# --------------------------------------------------------------------------
# Branching vessels
# --------------------------------------------------------------------------

def grow_vessels(rng: np.random.Generator, n: int, roots: int) -> np.ndarray:
    """Random branching vessel trees on an n x n torus.

    Each tree is a trunk of radius 3-4.5 px growing both ways from a random
    point; it wanders with small turns, tapering and splitting until the
    radius drops below 0.45 px.
    Returns segments as an (m, 6) array: x0, y0, x1, y1, r0, r1 (px).
    """
    segments, stack = [], []
    for _ in range(roots):
        x, y = rng.uniform(0, n, 2)
        angle, radius = rng.uniform(0, 2 * np.pi), rng.uniform(3.0, 4.5)
        stack += [(x, y, angle, radius, 0), (x, y, angle + np.pi, radius, 0)]
    while stack:
        x, y, angle, radius, depth = stack.pop()
        heading = angle
        while radius > 0.45:
            heading += rng.normal(0.0, 0.10) + 0.05 * (angle - heading)
            step = 2.0 + radius
            nx, ny = x + step * np.cos(heading), y + step * np.sin(heading)
            r_next = radius * (0.992 if depth == 0 else 0.985)
            segments.append((x, y, nx, ny, radius, r_next))
            x, y, radius = nx, ny, r_next
            if depth < 5 and radius > 0.9 and rng.random() < 0.035:
                side = 1.0 if rng.random() < 0.5 else -1.0
                child = radius * rng.uniform(0.45, 0.8)
                stack.append((x, y, heading + side * rng.uniform(0.5, 1.1),
                              child, depth + 1))
                radius *= 0.92
                heading -= side * 0.25
                angle = heading
    return np.asarray(segments)


def rasterise_vessels(segments: np.ndarray, n: int) -> np.ndarray:
    """Anti-aliased coverage (0..1) of tapered capsule segments, wrapped.

    segments: (m, 6) array from grow_vessels.  Returns an (n, n) field whose
    value is the max over segments of a rounded profile, highest on the axis
    of a vessel and falling toward its wall (so wide vessels look
    cylindrical); vessels thinner than 2 px are proportionally fainter.
    """
    out = np.zeros((n, n))
    for x0, y0, x1, y1, r0, r1 in segments:
        pad = max(r0, r1) + 1.5
        xs = np.arange(int(np.floor(min(x0, x1) - pad)), int(np.ceil(max(x0, x1) + pad)))
        ys = np.arange(int(np.floor(min(y0, y1) - pad)), int(np.ceil(max(y0, y1) + pad)))
        px, py = np.meshgrid(xs + 0.5, ys + 0.5)
        ex, ey = x1 - x0, y1 - y0
        t = np.clip(((px - x0) * ex + (py - y0) * ey) / (ex * ex + ey * ey), 0.0, 1.0)
        d = np.hypot(px - x0 - t * ex, py - y0 - t * ey)
        r = r0 + t * (r1 - r0)
        edge = np.clip(r - d + 0.5, 0.0, 1.0)
        core = np.sqrt(np.clip(1.0 - (d / (r + 0.5)) ** 2, 0.0, 1.0))
        value = edge * (0.35 + 0.65 * core) * np.clip(r / 2.0, 0.3, 1.0)
        idx = np.ix_(ys % n, xs % n)
        out[idx] = np.maximum(out[idx], value)
    return out


# --------------------------------------------------------------------------
# Tissue textures
# --------------------------------------------------------------------------

def tissue_fields(n: int, seed: int) -> dict[str, np.ndarray]:
    """Shared (n, n) fields that every tissue state is built from.

    Keys: 'large', 'mid', 'fine', 'grain' (fBm bands, std ~1), 'hue' (slow
    colour drift), 'gloss' (0..1 soft sheen), 'lobule_edge' / 'lobule_centre'
    (0..1 hexagonal lobule pattern), 'vessel' (0..1 sharp vessel profile),
    'vessel_halo' (0..1 blurred vessels), 'blotch', 'cracks', 'crack_rim',
    'ash' (0..1 char features).
    """
    rng = np.random.default_rng(seed)
    f = {
        "large": band_noise(rng, n, 1.5, 6.0, 0.5),
        "mid": band_noise(rng, n, 6.0, 24.0, 0.8),
        "fine": band_noise(rng, n, 24.0, 110.0, 0.8),
        "grain": band_noise(rng, n, 110.0, 400.0, 0.3),
        "hue": band_noise(rng, n, 1.0, 5.0, 0.5),
    }
    sheen = band_noise(rng, n, 2.0, 8.0, 1.0) + 0.35 * band_noise(rng, n, 8.0, 20.0, 1.0)
    f["gloss"] = smoothstep(0.6, 2.2, sheen)

    wx = 6.0 * band_noise(rng, n, 8.0, 30.0, 1.0)
    wy = 6.0 * band_noise(rng, n, 8.0, 30.0, 1.0)
    f1, edge = hex_cells(rng, n, cols=44, jitter=0.22, dx=wx, dy=wy)
    f["lobule_edge"] = 1.0 - smoothstep(0.0, 0.12, edge)
    f["lobule_centre"] = 1.0 - smoothstep(0.05, 0.22, f1)

    vessel = rasterise_vessels(grow_vessels(rng, n, roots=3), n)
    f["vessel"] = vessel
    halo = periodic_blur(vessel, 4.0)
    f["vessel_halo"] = halo / halo.max()

    f["blotch"] = smoothstep(-2.2, 2.2, 0.6 * f["large"] + 0.8 * f["mid"]
                             + 0.45 * band_noise(rng, n, 20.0, 60.0, 0.5))
    cx = 2.5 * band_noise(rng, n, 16.0, 60.0, 1.0)
    cy = 2.5 * band_noise(rng, n, 16.0, 60.0, 1.0)
    # a crackle of crust plates about 1.2 mm across (48 cells over the 60 mm patch), drawn 2-3 texels wide: a few
    # long 1-texel lines of larger cells read as stray diagonal strokes across a small char spot
    _, crack_gap = hex_cells(rng, n, cols=48, jitter=0.35, dx=cx, dy=cy)
    crack_on = smoothstep(-1.2, 0.0, band_noise(rng, n, 3.0, 10.0, 1.0))
    cracks = (1.0 - smoothstep(0.04, 0.12, crack_gap)) * crack_on
    f["cracks"] = cracks
    f["crack_rim"] = np.clip(periodic_blur(cracks, 2.0) * 2.0 - cracks, 0.0, 1.0)
    specks = band_noise(rng, n, 150.0, 400.0, 0.0) + 0.5 * f["fine"]
    f["ash"] = smoothstep(2.9, 3.8, specks) * smoothstep(-0.5, 0.8, f["mid"])
    return f


def mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear blend of (n, n, 3) colours a, b with (n, n) weight t."""
    return a + (b - a) * t[..., None]


def rgb(colour: tuple[float, float, float], n: int) -> np.ndarray:
    """Constant (n, n, 3) colour image."""
    return np.broadcast_to(np.asarray(colour, dtype=np.float64), (n, n, 3))


def finish(img: np.ndarray, target: tuple[float, float, float]) -> np.ndarray:
    """Scale channels so the mean RGB equals target, clip to uint8 (n, n, 3)."""
    gain = np.asarray(target) / img.reshape(-1, 3).mean(axis=0)
    return np.clip(np.rint(img * gain), 0, 255).astype(np.uint8)


def healthy_liver(f: dict[str, np.ndarray]) -> np.ndarray:
    """Fresh liver: red-brown capsule, mottled, lobules, darker vessels (the sheen is the renderer's: no highlight
    baked in)."""
    n = f["large"].shape[0]
    hue = smoothstep(-2.0, 2.0, f["hue"])
    base = mix(rgb((100, 40, 36), n), rgb((114, 50, 28), n), hue)
    tone = (1.0 + 0.05 * f["large"] + 0.05 * f["mid"] + 0.035 * f["fine"]
            + 0.03 * f["grain"] + 0.08 * f["lobule_edge"] - 0.10 * f["lobule_centre"])
    img = base * tone[..., None]
    img = mix(img, rgb((80, 24, 32), n), 0.35 * f["vessel_halo"])
    img = mix(img, rgb((78, 12, 24), n), 0.75 * f["vessel"])
    return finish(img, LIVER_HEALTHY_RGB)


def hyperaemic_liver(f: dict[str, np.ndarray]) -> np.ndarray:
    """The congested rim around a burn: redder, vessels and lobule borders filled with blood."""
    n = f["large"].shape[0]
    tone = 1.0 + 0.06 * f["mid"] + 0.04 * f["fine"] + 0.10 * f["lobule_edge"] - 0.06 * f["lobule_centre"]
    img = rgb((128, 32, 33), n) * tone[..., None]
    img = mix(img, rgb((100, 14, 26), n), 0.5 * f["vessel_halo"] + 0.3 * f["lobule_edge"])
    return finish(img, LIVER_HYPERAEMIC_RGB)


def cooked_liver(f: dict[str, np.ndarray], target: tuple[float, float, float], mottle: float) -> np.ndarray:
    """Coagulated liver of mean colour target: grey-tan, mottled by `mottle`, ghost lobules and vessels."""
    n = f["large"].shape[0]
    hue = smoothstep(-2.0, 2.0, f["hue"] + 0.6 * f["mid"])
    base = mix(rgb(target, n) * (1.02, 0.99, 0.97), rgb(target, n) * (0.97, 1.0, 1.04), hue)
    tone = (1.0 + mottle * (f["large"] + f["mid"]) + 0.03 * f["fine"] + 0.02 * f["grain"]
            + 0.04 * f["lobule_edge"] - 0.07 * f["lobule_centre"])
    img = base * tone[..., None]
    img = mix(img, rgb(target, n) * (0.86, 0.82, 0.8), 0.30 * f["vessel"] + 0.15 * f["vessel_halo"])
    img = mix(img, rgb(target, n) * (0.9, 0.78, 0.74), 0.35 * f["blotch"] ** 2)  # reddish-brown patches
    return finish(img, target)


def charred_liver(f: dict[str, np.ndarray]) -> np.ndarray:
    """Carbonised tissue: blotchy black-brown crust, black cracks with brown rims, pale ash specks."""
    n = f["large"].shape[0]
    img = mix(rgb((10, 8, 6), n), rgb((58, 38, 26), n), f["blotch"])
    tone = 1.0 + 0.10 * f["fine"] + 0.06 * f["grain"] - 0.10 * f["lobule_centre"]
    img = img * tone[..., None]
    img = img * (1.0 - 0.25 * f["vessel_halo"])[..., None]
    img = mix(img, rgb((74, 50, 34), n), 0.35 * f["crack_rim"])
    img = mix(img, rgb((3, 2, 2), n), 0.95 * f["cracks"])
    return finish(mix(img, rgb((140, 130, 118), n), 0.7 * f["ash"]), LIVER_CHARRED_RGB)


def surface_map(height: np.ndarray, roughness: np.ndarray) -> np.ndarray:
    """(n, n, 3) uint8 surface map of the look (sims.look.compose): red the height rescaled to 0-1, green the roughness."""
    h = (height - height.min()) / max(float(np.ptp(height)), 1e-9)
    out = np.zeros(height.shape + (3,))
    out[..., 0], out[..., 1] = h, np.clip(roughness, 0.0, 1.0)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def healthy_surface(f: dict[str, np.ndarray]) -> np.ndarray:
    """Capsule: lobules bulge slightly between their borders, vessels run in shallow ridges, fine grain; moist, with a
    broad sheen (roughness 0.45-0.6, lowest where the gloss field is; chosen while the lab still flat-shaded the patch
    mesh, whose triangles then showed in sharper highlights)."""
    height = (0.6 * f["lobule_centre"] - 0.8 * f["lobule_edge"] + 0.5 * f["vessel_halo"]
              + 0.1 * f["fine"] + 0.03 * f["grain"])
    return surface_map(height, 0.6 - 0.15 * f["gloss"] + 0.02 * f["fine"])


def coagulated_surface(f: dict[str, np.ndarray]) -> np.ndarray:
    """Coagulum: mottled, puckered around the lobule centres; drier (roughness 0.65-0.8)."""
    height = 0.5 * f["mid"] + 0.3 * f["fine"] + 0.1 * f["grain"] - 0.6 * f["lobule_centre"]
    return surface_map(height, 0.72 + 0.04 * f["mid"] + 0.02 * f["grain"])


def charred_surface(f: dict[str, np.ndarray]) -> np.ndarray:
    """Char: a crust raised in blotches, cut by deep cracks; matte (roughness 0.85-0.95)."""
    height = 1.2 * f["blotch"] + 0.25 * f["fine"] + 0.1 * f["grain"] - 1.5 * f["cracks"] - 0.4 * f["crack_rim"]
    return surface_map(height, 0.9 + 0.03 * f["fine"])


def make_textures(out_dir: Path) -> list[Path]:
    """Write the liver's colour textures and surface maps (1024x1024 RGB PNG); return paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    fields = tissue_fields(TEX_SIZE, SEED)
    paths = []
    for name, build in (("liver_healthy", healthy_liver),
                        ("liver_hyperaemic", hyperaemic_liver),
                        ("liver_pale", lambda f: cooked_liver(f, LIVER_PALE_RGB, 0.025)),
                        ("liver_coagulated", lambda f: cooked_liver(f, LIVER_COAGULATED_RGB, 0.035)),
                        ("liver_browned", lambda f: cooked_liver(f, LIVER_BROWNED_RGB, 0.045)),
                        ("liver_charred", charred_liver),
                        ("liver_healthy_surface", healthy_surface),
                        ("liver_coagulated_surface", coagulated_surface),
                        ("liver_charred_surface", charred_surface)):
        path = out_dir / f"{name}.png"
        Image.fromarray(build(fields), "RGB").save(path, optimize=True)
        paths.append(path)
    return paths


# --------------------------------------------------------------------------
# OBJ output
# --------------------------------------------------------------------------

def write_obj(path: Path, positions: np.ndarray, normals: np.ndarray,
              uvs: np.ndarray, faces_v: np.ndarray, faces_vt: np.ndarray,
              comment: str) -> None:
    """Write an OBJ with v (mm), vt, vn and 1-based 'v/vt/vn' faces.

    positions, normals: (nv, 3); uvs: (nt, 2); faces_v: (nf, 3) indices into
    positions and normals; faces_vt: (nf, 3) indices into uvs.
    """
    fmt = lambda rows, spec: "\n".join(spec % tuple(r) for r in rows + 0.0)
    corners = np.stack([faces_v + 1, faces_vt + 1, faces_v + 1], axis=-1)
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [fmt(positions, "v %.5f %.5f %.5f"),
              fmt(uvs, "vt %.6f %.6f"),
              fmt(normals, "vn %.5f %.5f %.5f"),
              "\n".join("f %d/%d/%d %d/%d/%d %d/%d/%d" % tuple(c.ravel()) for c in corners)]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------
# Tissue patch
# --------------------------------------------------------------------------

PATCH_SIZE = (60.0, 40.0)   # mm in x, y
PATCH_QUADS = (120, 80)
PATCH_SLOPE_DEG = 15.0
# (x, y, height, radius) in mm; negative height is a hollow.
PATCH_FEATURES = ((-15.0, -8.0, 2.5, 5.0),
                  (13.0, -11.0, 1.8, 5.0),
                  (19.0, 7.0, 1.2, 4.5),
                  (-7.0, 10.0, -2.0, 6.0))


def smooth_bump(x: np.ndarray, y: np.ndarray, cx: float, cy: float,
                radius: float) -> np.ndarray:
    """C2 compact bump (1 - r^2/R^2)^3, 1 at (cx, cy), 0 beyond radius (mm)."""
    s2 = ((x - cx) ** 2 + (y - cy) ** 2) / radius ** 2
    return np.clip(1.0 - s2, 0.0, None) ** 3


def patch_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Patch surface z(x, y) in mm: slope down toward -y, dome, bumps, hollow."""
    z = np.tan(np.radians(PATCH_SLOPE_DEG)) * y
    z += -x ** 2 / (2.0 * 150.0) - y ** 2 / (2.0 * 400.0) + 0.4 * np.sin(0.09 * x + 0.5)
    for cx, cy, h, r in PATCH_FEATURES:
        z += h * smooth_bump(x, y, cx, cy, r)
    return z


def pool_depth(z: np.ndarray) -> np.ndarray:
    """Depth (mm) of water each grid node (ny, nx) holds when the edge drains.

    Priority-flood from the border; returns filled level minus z.
    """
    ny, nx = z.shape
    level = np.full_like(z, np.inf)
    heap = []
    for j in range(ny):
        for i in range(nx):
            if j in (0, ny - 1) or i in (0, nx - 1):
                level[j, i] = z[j, i]
                heap.append((z[j, i], j, i))
    heapq.heapify(heap)
    while heap:
        h, j, i = heapq.heappop(heap)
        for dj, di in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            a, b = j + dj, i + di
            if 0 <= a < ny and 0 <= b < nx and level[a, b] == np.inf:
                level[a, b] = max(z[a, b], h)
                heapq.heappush(heap, (level[a, b], a, b))
    return level - z


def make_patch(path: Path) -> dict[str, float]:
    """Write the curved tissue patch OBJ; return stats for the summary."""
    (sx, sy), (qx, qy) = PATCH_SIZE, PATCH_QUADS
    xs = np.linspace(-sx / 2, sx / 2, qx + 1)
    ys = np.linspace(-sy / 2, sy / 2, qy + 1)
    x, y = np.meshgrid(xs, ys)                      # (qy+1, qx+1), row = y
    z = patch_height(x, y)
    dzdy, dzdx = np.gradient(z, ys, xs, edge_order=2)
    normals = np.stack([-dzdx, -dzdy, np.ones_like(z)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    uvs = np.stack([(x - xs[0]) / sx, (y - ys[0]) / sy], -1)

    idx = np.arange(x.size).reshape(x.shape)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.stack([np.stack([a, b, c], 1), np.stack([a, c, d], 1)], 1).reshape(-1, 3)

    depth = pool_depth(z)
    pooled = depth > 1e-6
    assert pooled.any() and (y[pooled] > 0).all(), "hollow must hold fluid in +y half"
    write_obj(path, np.stack([x, y, z], -1).reshape(-1, 3), normals.reshape(-1, 3),
              uvs.reshape(-1, 2), faces, faces,
              "tissue-lab patch, mm, z up; downhill toward -y\n"
              "uv: u=(x-xmin)/60, v=(y-ymin)/40 (OBJ: v=0 is the image bottom)")
    cell = (xs[1] - xs[0]) * (ys[1] - ys[0])
    return {"verts": x.size, "faces": len(faces), "z_min": z.min(), "z_max": z.max(),
            "pool_depth": depth.max(), "pool_volume": depth.sum() * cell}


# --------------------------------------------------------------------------
# Liver lobe
# --------------------------------------------------------------------------

LOBE_EXTENTS = np.array([110.0, 70.0, 35.0])   # mm


def lobe_shape(p: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Deform unit-sphere points (nv, 3) into a liver-lobe wedge (mm).

    Thick, domed at -x; thinning to a rounded edge at +x; flatter underside;
    gentle banana bend in plan; low-frequency bumps; scaled to LOBE_EXTENTS.
    """
    x, y, z = p.T.copy()
    t = (x + 1.0) / 2.0
    z *= 1.0 - 0.72 * t ** 1.3
    z *= 0.82 + 0.18 * np.tanh(4.0 * z)            # flatter inferior surface
    y *= (1.0 - 0.45 * t ** 1.5) * (0.92 + 0.08 * np.tanh(3.0 * y))
    z *= 1.0 - 0.25 * smoothstep(0.0, 1.0, -y)     # sharper anterior border
    x *= 1.0 + 0.12 * (1.0 - x ** 2) * y           # skewed, D-shaped plan
    y += 0.15 * x ** 2 - 0.05 * x
    z += -0.10 * x ** 2 + 0.04 * x * y
    q = np.stack([x, y, z], -1)
    for _ in range(6):
        k = rng.normal(0.0, 2.2, 3)
        q += (0.018 * np.sin(p @ k + rng.uniform(0, 2 * np.pi)))[:, None] * p
    q -= (q.max(0) + q.min(0)) / 2.0
    return q * (LOBE_EXTENTS / (q.max(0) - q.min(0)))


def uv_overlap(uvs: np.ndarray, faces: np.ndarray, res: int = 512) -> int:
    """Count texel centres of a res^2 grid strictly inside two or more UV tris."""
    count = np.zeros((res, res), dtype=np.int32)
    for tri in uvs[faces] * res:
        lo = np.floor(tri.min(0) - 0.5).astype(int).clip(0, res - 1)
        hi = np.ceil(tri.max(0) - 0.5).astype(int).clip(0, res - 1)
        px, py = np.meshgrid(np.arange(lo[0], hi[0] + 1) + 0.5,
                             np.arange(lo[1], hi[1] + 1) + 0.5)
        (x0, y0), (x1, y1), (x2, y2) = tri
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
        w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
        inside = (w0 > 1e-6) & (w1 > 1e-6) & (1.0 - w0 - w1 > 1e-6)
        count[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1] += inside
    return int((count > 1).sum())


def make_liver_lobe(path: Path) -> dict[str, float]:
    """Write the watertight liver-lobe OBJ with an xatlas UV atlas; check it."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    rng = np.random.default_rng(SEED + 1)
    mesh = trimesh.Trimesh(lobe_shape(np.asarray(sphere.vertices), rng),
                           sphere.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0

    atlas = xatlas.Atlas()
    atlas.add_mesh(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32),
                   mesh.vertex_normals.astype(np.float32))
    pack = xatlas.PackOptions()
    pack.resolution = TEX_SIZE
    pack.padding = 4
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    vmapping, uv_faces, uvs = atlas[0]
    uv_faces = uv_faces.astype(np.int64)
    assert np.array_equal(vmapping[uv_faces], mesh.faces), "xatlas reordered faces"
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0

    write_obj(path, mesh.vertices, mesh.vertex_normals, uvs.astype(np.float64),
              mesh.faces, uv_faces,
              "tissue-lab liver lobe, mm, z up; closed mesh, xatlas UV atlas\n"
              "v indices are shared (watertight); vt indices split at chart seams")

    loaded = trimesh.load(path, process=False)
    assert len(loaded.visual.uv) == len(loaded.vertices) == len(uvs)
    welded = loaded.copy()
    welded.merge_vertices(merge_tex=True, merge_norm=True)
    assert welded.is_watertight
    overlap = uv_overlap(uvs.astype(np.float64), uv_faces)
    assert overlap == 0, f"{overlap} overlapping UV texels"
    return {"verts": len(mesh.vertices), "uv_verts": len(uvs), "faces": len(mesh.faces),
            "charts": atlas.chart_count, "utilization": atlas.utilization,
            "overlap": overlap, "volume_ml": mesh.volume / 1000.0}


# --------------------------------------------------------------------------
# Blade electrode
# --------------------------------------------------------------------------

BLADE_LENGTH, BLADE_WIDTH, BLADE_THICKNESS = 12.0, 2.4, 0.6   # mm


def make_blade(path: Path) -> dict[str, float]:
    """Write the blade electrode OBJ in its local frame.

    Tip at the origin, shaft along +z to z=BLADE_LENGTH; a capsule of radius
    BLADE_WIDTH/2 flattened in y to BLADE_THICKNESS (elliptic cross-section,
    semicircular tip in the x-z plane).  UVs are u = x/width + 0.5,
    v = z/length (a simple planar map; the blade is untextured in practice).
    """
    radius = BLADE_WIDTH / 2.0
    mesh = trimesh.creation.capsule(height=BLADE_LENGTH - BLADE_WIDTH, radius=radius,
                                    count=[32, 16])
    v = np.asarray(mesh.vertices) * [1.0, BLADE_THICKNESS / BLADE_WIDTH, 1.0]
    v[:, 2] -= v[:, 2].min()
    blade = trimesh.Trimesh(v, mesh.faces, process=False)
    assert blade.is_watertight and blade.volume > 0
    uvs = np.stack([v[:, 0] / BLADE_WIDTH + 0.5, v[:, 2] / BLADE_LENGTH], -1)
    write_obj(path, v, blade.vertex_normals, uvs, blade.faces, blade.faces,
              "tissue-lab blade electrode, local frame, mm\n"
              "tip at origin, tool axis +z toward the handle, blade plane x-z")
    return {"verts": len(v), "faces": len(blade.faces)}


# --------------------------------------------------------------------------

def main() -> None:
    """Build every asset under static/ and print a summary."""
    start = time.perf_counter()
    textures = make_textures(STATIC / "textures")
    patch = make_patch(STATIC / "meshes" / "patch.obj")
    lobe = make_liver_lobe(STATIC / "meshes" / "liver_lobe.obj")
    blade = make_blade(STATIC / "instruments" / "blade.obj")

    def size(p: Path) -> str:
        return f"{p.stat().st_size / 1024:7.0f} KiB"

    for p in textures:
        mean = np.asarray(Image.open(p)).reshape(-1, 3).mean(0)
        print(f"{p.relative_to(ROOT)}  {size(p)}  mean RGB {np.round(mean).astype(int)}")
    print(f"static/meshes/patch.obj  {size(STATIC / 'meshes/patch.obj')}  "
          f"{patch['verts']} v, {patch['faces']} f, z {patch['z_min']:.1f}..{patch['z_max']:.1f} mm, "
          f"hollow holds {patch['pool_volume']:.1f} mm^3 (max depth {patch['pool_depth']:.2f} mm)")
    print(f"static/meshes/liver_lobe.obj  {size(STATIC / 'meshes/liver_lobe.obj')}  "
          f"{lobe['verts']} v ({lobe['uv_verts']} uv), {lobe['faces']} f, "
          f"{lobe['charts']} UV charts, utilisation {lobe['utilization']:.2f}, "
          f"UV overlap texels {lobe['overlap']}, volume {lobe['volume_ml']:.0f} ml")
    print(f"static/instruments/blade.obj  {size(STATIC / 'instruments/blade.obj')}  "
          f"{blade['verts']} v, {blade['faces']} f")
    print(f"done in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
