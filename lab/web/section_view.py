"""The burn cross-section as a picture for the browser: temperature in colour against depth and distance along the
surface, the coagulated zone (Omega >= 1) outlined in white, a millimetre grid with labels, and a colour scale."""
import numpy as np
from matplotlib import colormaps
from PIL import Image, ImageDraw

SHOWN_DEPTH_MM = 3.0          # the picture shows the top 3 mm (liver burns from contact tools reach 1-2 mm)
PIXELS_PER_MM = 40
COLD_C, HOT_C = 37.0, 150.0   # colour scale (temperatures beyond are clipped)
MARGIN_LEFT, MARGIN_TOP, MARGIN_BOTTOM, SCALE_WIDTH = 34, 22, 20, 46
COLOURS = colormaps["inferno"]


def _profile(surface: np.ndarray, layers: np.ndarray, layer_depth_mm: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
    """(D, N) values at the pixel depths: linear between the surface value (depth 0) and the layer centres."""
    z = np.concatenate([[0.0], layer_depth_mm])
    values = np.vstack([surface[None], layers])
    return np.stack([np.interp(depth_mm, z, values[:, column]) for column in range(values.shape[1])], axis=1)


def section_image(section) -> np.ndarray:
    """(H, W, 3) uint8 picture of a sims.heat.section.BurnSection."""
    half = float(section.distance_mm[-1])
    width_px, depth_px = int(round(2 * half * PIXELS_PER_MM)), int(round(SHOWN_DEPTH_MM * PIXELS_PER_MM))
    depth = (np.arange(depth_px) + 0.5) / PIXELS_PER_MM
    columns = np.interp((np.arange(width_px) + 0.5) / PIXELS_PER_MM - half, section.distance_mm, np.arange(len(section.distance_mm)))
    nearest = np.clip(np.round(columns).astype(int), 0, len(section.distance_mm) - 1)
    temperature = _profile(section.surface_temperature_c, section.temperature_c, section.layer_depth_mm, depth)[:, nearest]
    log_omega = _profile(np.log(np.maximum(section.surface_omega, 1e-30)), np.log(np.maximum(section.omega, 1e-30)),
                         section.layer_depth_mm, depth)[:, nearest]
    colour = COLOURS(np.clip((temperature - COLD_C) / (HOT_C - COLD_C), 0.0, 1.0))[..., :3]
    coagulated = log_omega >= 0.0
    edge = np.zeros_like(coagulated)
    edge[1:] |= coagulated[1:] != coagulated[:-1]
    edge[:, 1:] |= coagulated[:, 1:] != coagulated[:, :-1]
    edge[0] |= coagulated[0]
    colour[edge] = 1.0
    canvas = Image.new("RGB", (MARGIN_LEFT + width_px + SCALE_WIDTH, MARGIN_TOP + depth_px + MARGIN_BOTTOM), (24, 24, 28))
    canvas.paste(Image.fromarray((colour * 255).astype(np.uint8)), (MARGIN_LEFT, MARGIN_TOP))
    draw = ImageDraw.Draw(canvas)
    grey = (150, 150, 160)
    for mm in range(int(SHOWN_DEPTH_MM) + 1):
        y = MARGIN_TOP + mm * PIXELS_PER_MM
        draw.line([(MARGIN_LEFT - 4, y), (MARGIN_LEFT, y)], fill=grey)
        draw.text((4, y - 6), f"{mm} mm", fill=grey)
    for mm in range(-int(half), int(half) + 1):
        x = MARGIN_LEFT + (mm + half) * PIXELS_PER_MM
        draw.line([(x, MARGIN_TOP + depth_px), (x, MARGIN_TOP + depth_px + 4)], fill=grey)
        draw.text((x - 6, MARGIN_TOP + depth_px + 6), f"{mm:+d}" if mm else "0", fill=grey)
    deepest = float(section.coagulation_depth_mm.max())
    draw.text((MARGIN_LEFT, 4), f"{section.tool}: coagulated {deepest:.2f} mm deep (white), peak {section.surface_temperature_c.max():.0f} C",
              fill=(230, 230, 230))
    left = MARGIN_LEFT + width_px + 8
    bar = COLOURS(np.linspace(1.0, 0.0, depth_px))[:, :3]
    canvas.paste(Image.fromarray((np.repeat(bar[:, None], 10, axis=1) * 255).astype(np.uint8)), (left, MARGIN_TOP))
    draw.text((left + 12, MARGIN_TOP - 2), f"{HOT_C:.0f}", fill=grey)
    draw.text((left + 12, MARGIN_TOP + depth_px - 10), f"{COLD_C:.0f} C", fill=grey)
    return np.asarray(canvas)
