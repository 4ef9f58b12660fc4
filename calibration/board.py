"""The printable fiducial board: the calibration's ArUco marker at its true size, its quiet zone, a label.

`board_image` draws the board at `dpi` dots per inch: the marker's cells (flightstack.vision.fiducial.
marker_cells) over side_m, the white quiet zone around it, a thin grey cutting line just outside the quiet
zone, and below it a label (dictionary, id, sizes, which corner is which feature point) with a 100 mm
scale bar to check that the printer did not scale the page. `write_board` saves it as PNG (with its DPI in
the file) or PDF (a page of exactly the board's size), by the file name.

Units: lengths in metres, 1 inch = 0.0254 m; image pixels at `dpi`.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from flightstack.vision.camera_file import Fiducial
from flightstack.vision.fiducial import marker_cells

INCH_M = 0.0254
LABEL_M = 0.03
"""Height of the label strip below the board (m)."""
SCALE_BAR_M = 0.1
"""Length of the label's scale bar (m): measure it on the print."""
CUT_GREY = 170
"""Grey level of the cutting line around the quiet zone."""
BOARD_SUFFIXES = (".png", ".pdf")


def _px(length_m: float, dpi: float) -> int:
    return round(length_m / INCH_M * dpi)


def board_image(fid: Fiducial, dpi: float = 300.0, label: str = "") -> np.ndarray:
    """The board as an (H, W) uint8 grey image at `dpi`: the marker (side_m), its quiet zone, a 1-pixel
    cutting line outside it, and a label strip (LABEL_M) with `label`'s text and a SCALE_BAR_M bar.

    The marker occupies pixels [q, q + S) on both axes, S = side_m at dpi and q the quiet zone (+ 2 pixels
    for the cutting line); pixel (i, j) takes the cell that its centre falls in.
    """
    if not dpi > 0:
        raise ValueError(f"dpi must be > 0, got {dpi}")
    cells = marker_cells(fid)
    n = cells.shape[0]
    side = _px(fid.side_m, dpi)
    if side < n:
        raise ValueError(f"{dpi:g} dpi draws the {n}-cell marker on {side} pixels: raise the dpi")
    quiet = _px(fid.quiet_zone_m, dpi)
    edge = 2  # the cutting line and one white pixel inside it
    board = side + 2 * (quiet + edge)
    strip = _px(LABEL_M, dpi)
    img = np.full((board + strip, board), 255, dtype=np.uint8)
    centres = (np.arange(side) + 0.5) / side * n
    idx = np.minimum(centres.astype(int), n - 1)
    img[quiet + edge : quiet + edge + side, quiet + edge : quiet + edge + side] = cells[np.ix_(idx, idx)]
    cv2.rectangle(img, (0, 0), (board - 1, board - 1), CUT_GREY, 1)
    # the label strip: a scale bar and its length on the first row, the label's lines below it
    bar, x0, row = _px(SCALE_BAR_M, dpi), edge, strip // 4
    thick = max(1, _px(0.0004, dpi))
    lines = [t for t in label.split("\n") if t]
    font = cv2.FONT_HERSHEY_SIMPLEX
    widest = max([cv2.getTextSize(t, font, 1.0, 1)[0][0] for t in lines] or [1])
    scale = min(0.6 * row / 22.0, 0.95 * (board - 2 * x0) / widest)
    y = board + row // 2
    if x0 + bar < board:
        cv2.line(img, (x0, y), (x0 + bar, y), 0, thick)
        for x in (x0, x0 + bar):
            cv2.line(img, (x, y - row // 4), (x, y + row // 4), 0, thick)
        mm = f"{SCALE_BAR_M * 1e3:.0f} mm"
        cv2.putText(img, mm, (x0 + bar + row // 2, y + row // 4), font, scale, 0, thick, cv2.LINE_AA)
    for k, text in enumerate(lines, start=1):
        cv2.putText(img, text, (x0, board + k * row + 3 * row // 4), font, scale, 0, thick, cv2.LINE_AA)
    return img


def board_label(fid: Fiducial) -> str:
    """The label printed under the board: what it is and how it goes on the robot."""
    order = ", ".join(f"p{j}=c{c}" for j, c in enumerate(fid.corners))
    return (
        f"ArUco {fid.dictionary} id {fid.id}: black square {fid.side_m * 1e3:g} mm, quiet zone "
        f"{fid.quiet_zone_m * 1e3:g} mm\n"
        f"print at 100 %, matte; face up on the plate; feature points at corners {order}"
    )


def write_board(fid: Fiducial, path: str | Path, dpi: float = 300.0) -> tuple[int, int]:
    """Write the board (`board_image` with `board_label`) to a .png (its DPI stored) or a .pdf (one page of
    the board's physical size); returns its size in pixels (width, height)."""
    path = Path(path)
    if path.suffix.lower() not in BOARD_SUFFIXES:
        raise ValueError(f"{path}: the board is written as .png or .pdf")
    img = board_image(fid, dpi, board_label(fid))
    h, w = img.shape
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    if path.suffix.lower() == ".png":
        plt.imsave(path, img, cmap="gray", vmin=0, vmax=255, dpi=dpi)
    else:
        fig = plt.figure(figsize=(w / dpi, h / dpi), dpi=dpi)
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.imshow(img, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_axis_off()
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
    return w, h
