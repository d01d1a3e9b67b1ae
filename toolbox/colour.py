"""False colour and legends: arrays in, RGB arrays out (the writers put them in files).

Every picture RVS writes carries a legend: a colour bar with its range and unit, and what grey or
black means (no data), so a PNG can be read without the code that made it.
"""
from __future__ import annotations

import cv2
import numpy as np

NO_DATA_RGB = (40, 40, 40)
_COLORMAPS = {"turbo": cv2.COLORMAP_TURBO, "viridis": cv2.COLORMAP_VIRIDIS, "gray": None,
              "inferno": cv2.COLORMAP_INFERNO, "jet": cv2.COLORMAP_JET}


def colourise(values: np.ndarray, low: float, high: float, cmap: str = "turbo",
              valid: np.ndarray | None = None) -> np.ndarray:
    """Map values in [low, high] to RGB uint8; NaN and invalid pixels become dark grey."""
    values = np.asarray(values, dtype=np.float64)
    span = high - low if high > low else 1.0
    scaled = np.clip((values - low) / span, 0.0, 1.0)
    grey = np.nan_to_num(scaled * 255.0, nan=0.0).astype(np.uint8)
    if _COLORMAPS[cmap] is None:
        rgb = np.repeat(grey[..., None], 3, axis=2)
    else:
        rgb = cv2.applyColorMap(grey, _COLORMAPS[cmap])[..., ::-1]
    missing = ~np.isfinite(values)
    if valid is not None:
        missing |= ~valid
    rgb = np.ascontiguousarray(rgb)
    rgb[missing] = NO_DATA_RGB
    return rgb


def categorical(codes: np.ndarray, palette: dict[int, tuple[int, int, int]]) -> np.ndarray:
    """Map integer codes to colours (for hazard classes); unknown codes are black."""
    rgb = np.zeros((*codes.shape, 3), dtype=np.uint8)
    for code, colour in palette.items():
        rgb[codes == code] = colour
    return rgb


def _text(image: np.ndarray, text: str, origin: tuple[int, int], scale: float = 0.45) -> None:
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (235, 235, 235), 1, cv2.LINE_AA)


def with_colour_bar(rgb: np.ndarray, low: float, high: float, label: str, cmap: str = "turbo",
                    no_data: str | None = "no data", min_width: int = 360) -> np.ndarray:
    """The image with a strip below it: a colour bar from low to high, its label and the no-data swatch."""
    height, width = rgb.shape[:2]
    width_out = max(width, min_width)
    strip = np.full((56, width_out, 3), 20, dtype=np.uint8)
    bar_width = width_out - 140 if no_data else width_out - 20
    ramp = np.linspace(low, high, max(bar_width, 2))[None, :].repeat(14, axis=0)
    strip[22:36, 10:10 + bar_width] = colourise(ramp, low, high, cmap)
    _text(strip, label, (10, 16))
    _text(strip, f"{low:.3g}", (10, 52), 0.4)
    end = f"{high:.3g}"
    _text(strip, end, (10 + bar_width - 9 * len(end), 52), 0.4)
    if no_data:
        strip[22:36, width_out - 120:width_out - 106] = NO_DATA_RGB
        _text(strip, no_data, (width_out - 100, 34), 0.4)
    return _stack(rgb, strip)


def with_key(rgb: np.ndarray, entries: list[tuple[str, tuple[int, int, int]]], title: str = "",
             min_width: int = 360) -> np.ndarray:
    """The image with a strip of coloured swatches and their names below it (categorical legend)."""
    width_out = max(rgb.shape[1], min_width)
    rows = 1 + (len(entries) - 1) // 3
    strip = np.full((24 + 20 * rows, width_out, 3), 20, dtype=np.uint8)
    if title:
        _text(strip, title, (10, 16))
    column = (width_out - 20) // 3
    for index, (name, colour) in enumerate(entries):
        x = 10 + (index % 3) * column
        y = 22 + 20 * (index // 3)
        strip[y:y + 12, x:x + 12] = colour
        _text(strip, name, (x + 18, y + 11), 0.4)
    return _stack(rgb, strip)


def with_title(rgb: np.ndarray, title: str) -> np.ndarray:
    strip = np.full((22, rgb.shape[1], 3), 20, dtype=np.uint8)
    _text(strip, title, (6, 16))
    return np.concatenate([strip, rgb], axis=0)


def upscale(rgb: np.ndarray, min_size: int = 480) -> np.ndarray:
    """Enlarge a small image by an integer factor (nearest), so a 176x144 frame is readable."""
    factor = max(1, int(np.ceil(min_size / max(rgb.shape[:2]))))
    if factor == 1:
        return rgb
    # The same pixels as np.repeat along both axes; OpenCV lets go of the interpreter while it copies
    # (a product's pictures are drawn in the server beside the transports).
    height, width = rgb.shape[:2]
    return cv2.resize(rgb, (width * factor, height * factor), interpolation=cv2.INTER_NEAREST_EXACT)


def _stack(rgb: np.ndarray, strip: np.ndarray) -> np.ndarray:
    width = strip.shape[1]
    if rgb.shape[1] < width:
        pad = np.full((rgb.shape[0], width - rgb.shape[1], 3), 20, dtype=np.uint8)
        rgb = np.concatenate([rgb, pad], axis=1)
    return np.concatenate([rgb, strip], axis=0)


def grey(image: np.ndarray) -> np.ndarray:
    """An 8-bit grey image of a camera frame: as it is if grey, else the mean of its channels."""
    return image if image.ndim == 2 else np.round(image.mean(axis=2)).astype(np.uint8)
