"""Figures as PNG bytes (uint8 arrays), so nodes can store them under "figures/"."""
from __future__ import annotations

import io

import numpy as np


def png(image: np.ndarray) -> np.ndarray:
    """Encode a uint8 grayscale (H,W) or RGB (H,W,3) image as PNG bytes."""
    import cv2
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., ::-1]  # OpenCV writes BGR
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.ravel()


def figure_png(fig, dpi: int = 100) -> np.ndarray:
    """Encode a matplotlib Figure as PNG bytes.  Figures are made with
    ``matplotlib.figure.Figure`` (no pyplot), so no global backend or state is touched; the
    PNG carries no software tag, so its bytes do not change with the matplotlib version."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    return np.frombuffer(buf.getvalue(), np.uint8).copy()


def contact_sheet(images, cols: int, border: int = 2, fill: int = 90) -> np.ndarray:
    """Tile equally sized images row by row with a grey border; grayscale (H,W) images give a
    grayscale sheet, and when any image is RGB (H,W,3) the sheet is RGB."""
    images = [np.asarray(i, np.uint8) for i in images]
    if any(i.ndim == 3 for i in images):
        images = [np.repeat(i[..., None], 3, 2) if i.ndim == 2 else i for i in images]
    h, w = images[0].shape[:2]
    rows = -(-len(images) // cols)
    sheet = np.full((rows * (h + border) + border, cols * (w + border) + border, *images[0].shape[2:]),
                    fill, np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, cols)
        y, x = border + r * (h + border), border + c * (w + border)
        sheet[y:y + h, x:x + w] = img
    return sheet
