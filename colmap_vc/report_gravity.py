"""The report's "gravity" section: the vertical lines each camera's up rests on.

Every camera that `map` measured (``gravity.json`` beside the model) with the lines
its vanishing point was fitted to and an arrow along its up, so a user sees whether
the lines are the room's verticals (door frames, pillars) or something else.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import pycolmap

from colmap_vc.report_draw import fit_height, polylines
from colmap_vc.report_figures import jpeg_uri
from colmap_vc.report_html import esc
from colmap_vc.structs import FloatArray

LINE_BGR = (60, 200, 60)
ARROW_BGR = (230, 120, 0)
PEOPLE_BGR = (200, 60, 220)


def up_arrow_px(
    camera: pycolmap.Camera, up_cam: FloatArray, length_frac: float = 0.15
) -> tuple[FloatArray, FloatArray]:
    """Start (the image centre) and end of an arrow along ``up`` in the image,
    ``length_frac`` of the image height long, pixels (COLMAP's convention)."""
    centre = np.array([[camera.width / 2.0, camera.height / 2.0]])
    ray = np.c_[np.asarray(camera.cam_from_img(centre)), [[1.0]]][0]
    ahead = np.asarray(camera.img_from_cam((ray + 1e-3 * np.asarray(up_cam))[None]))
    direction = ahead[0] - centre[0]
    direction /= max(float(np.linalg.norm(direction)), 1e-12)
    return centre[0], centre[0] + direction * length_frac * camera.height


def draw_gravity(
    image_bgr: np.ndarray,
    lines_px: FloatArray,
    arrow_px: tuple[FloatArray, FloatArray],
    height: int,
    people_arrow_px: tuple[FloatArray, FloatArray] | None = None,
) -> np.ndarray:
    """The image scaled to ``height`` with the supporting lines, the up arrow
    and, when given, the people's up arrow."""
    import cv2

    canvas, scale = fit_height(image_bgr, height)
    thickness = max(1, height // 240)
    ends = (np.asarray(lines_px, dtype=np.float64).reshape(-1, 2, 2) - 0.5) * scale
    polylines(canvas, ends, np.tile(LINE_BGR, (len(ends), 1)), thickness)
    arrows = [(arrow_px, ARROW_BGR)]
    if people_arrow_px is not None:
        arrows.append((people_arrow_px, PEOPLE_BGR))
    for arrow, colour in arrows:  # the lines' up, then the people's
        start, end = (np.round((p - 0.5) * scale).astype(int) for p in arrow)
        cv2.arrowedLine(
            canvas,
            (int(start[0]), int(start[1])),
            (int(end[0]), int(end[1])),
            colour,
            2 * thickness,
            cv2.LINE_AA,
            tipLength=0.2,
        )
    return canvas


def gravity_section(
    model_path: Path | None,
    cameras: Mapping[str, pycolmap.Camera],
    read_image: Callable[[str], np.ndarray],
    height: int,
) -> str:
    """The HTML section: one panel per camera in ``gravity.json`` beside the model
    (``cameras`` and ``read_image`` by image name); "" without that file (a model
    `map` did not write, or `map --no-gravity`)."""
    parts = [
        '<section id="gravity"><h2>Gravity</h2>',
        '<p class="sub">The vertical lines (green) each camera\'s up was fitted to, '
        "that up (blue arrow) and its people's up (magenta arrow, the hint the "
        "lines were searched near); when the ups were used, the final model's "
        'cameras agree on one up (docs/real-data.md, "Why people alone stop at '
        '2-3 degrees").</p>',
    ]
    found = None if model_path is None else Path(model_path) / "gravity.json"
    if found is None or not found.is_file():
        return ""
    content = json.loads(found.read_text())
    measured = content.get("cameras", {})
    if content.get("rejected"):
        parts.append(
            f'<p class="missing">The ups were not used: {esc(content["rejected"])}.</p>'
        )
    if not measured:
        parts.append(
            '<p class="sub">No camera has 20 agreeing vertical lines (a scene '
            "without door frames, pillars or shelves): the model is as the people "
            "placed it.</p>"
        )
        return "".join([*parts, "</section>"])
    parts.append('<div class="pairs">')
    for name, g in sorted(measured.items()):  # loop over the measured cameras
        if name not in cameras:
            continue
        people = g.get("people_up_cam")
        panel = draw_gravity(
            read_image(name),
            np.asarray(g.get("lines_px", []), dtype=np.float64),
            up_arrow_px(cameras[name], np.asarray(g["up_cam"])),
            height,
            None if people is None else up_arrow_px(cameras[name], np.asarray(people)),
        )
        after = g.get("residual_deg")
        parts.append(
            f'<figure class="gravity"><img alt="vertical lines of {esc(name)}" '
            f'src="{jpeg_uri(panel)}"><figcaption><b>{esc(name)}</b>: '
            f"{g['num_segments']} lines in {g['num_images']} image(s), up +-"
            f"{g['sigma_deg']:.2f} deg"
            + ("" if after is None else f"; the model's up {after:.2f} deg from it")
            + "</figcaption></figure>"
        )
    return "".join([*parts, "</div></section>"])
