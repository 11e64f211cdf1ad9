"""The HTML report: self-contained, complete, right colours, renders in Chromium."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_vc import database
from colmap_vc.augment import AugmentOptions
from colmap_vc.augment import run as augment
from colmap_vc.evaluation import evaluate_reconstruction
from colmap_vc.report import ReportInputs, build_report
from colmap_vc.report_draw import (
    PANEL_GAP_PX,
    draw_pair,
    epipolar_errors_px,
    error_colors_bgr,
    fundamental_errors_px,
)
from colmap_vc.structs import PairVcMatches, VcKeypoints

CHROMIUM = shutil.which("chromium")
DATA_URI = re.compile(r'src="data:image/(png|jpeg);base64,([A-Za-z0-9+/=]+)"')
RED = (0, 0, 255)
GREEN = (0, 255, 0)


@dataclass(frozen=True)
class Run:
    scene: Path
    database_path: Path  # augmented
    model_path: Path
    gt_model_path: Path


@pytest.fixture(scope="module")
def run(dome_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Run:
    """The shared dome scene, augmented with its noisy priors and mapped."""
    tmp = tmp_path_factory.mktemp("report")
    db = tmp / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    augment(db, dome_scene / "priors", AugmentOptions(show_progress=False))
    pycolmap.set_random_seed(0)
    options = pycolmap.IncrementalPipelineOptions(
        num_threads=2, ba_refine_focal_length=False, ba_refine_extra_params=False
    )
    models = pycolmap.incremental_mapping(
        db, dome_scene / "images", tmp / "sparse", options
    )
    assert models, "the mapper made no model"
    return Run(
        scene=dome_scene,
        database_path=db,
        model_path=tmp / "sparse" / "0",
        gt_model_path=dome_scene / "gt" / "sparse",
    )


@pytest.fixture(scope="module")
def full_report(run: Run, tmp_path_factory: pytest.TempPathFactory) -> Path:
    gt = pycolmap.Reconstruction(run.gt_model_path)
    metrics = {
        "classic COLMAP": evaluate_reconstruction(None, gt).to_dict(),
        "colmap-vc": evaluate_reconstruction(
            pycolmap.Reconstruction(run.model_path), gt
        ),
    }
    inputs = ReportInputs(
        database_path=run.database_path,
        image_dir=run.scene / "images",
        model_path=run.model_path,
        gt_model_path=run.gt_model_path,
        timings_s={"augment": 4.2, "mapping": 1.3},
        metrics=metrics,
        max_pairs=8,
    )
    return build_report(inputs, tmp_path_factory.mktemp("html") / "report.html")


def _images(page: str) -> dict[str, np.ndarray]:
    """Every inlined image, decoded, keyed by the alt text of its <img> (or index)."""
    out = {}
    for i, match in enumerate(DATA_URI.finditer(page)):
        tag_start = page.rfind("<img", 0, match.start())
        alt = re.search(r'alt="([^"]*)"', page[tag_start : match.start()])
        data = np.frombuffer(base64.b64decode(match.group(2)), np.uint8)
        out[alt.group(1) if alt else str(i)] = cv2.imdecode(data, cv2.IMREAD_COLOR)
    return out


def _looks(bgr: np.ndarray, color: tuple[int, int, int], tol: int = 80) -> bool:
    return bool(np.all(np.abs(bgr.astype(int) - color) < tol))


# ---------------------------------------------------------------- numerics


def test_error_colors_run_green_to_red() -> None:
    colors = error_colors_bgr(np.array([0.0, 4.0, 8.0, 100.0, np.nan]), 8.0)
    assert colors.tolist() == [
        [0, 255, 0],
        [0, 255, 255],
        [0, 0, 255],
        [0, 0, 255],
        [170, 170, 170],
    ]


def test_fundamental_errors_on_rectified_pair() -> None:
    # Pure x translation, identity intrinsics: epipolar lines are the rows y = y1.
    F = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    errors = fundamental_errors_px(
        np.array([[10.0, 20], [0, 0]]), np.array([[30.0, 25], [7, 0]]), F
    )
    np.testing.assert_allclose(errors, [5.0, 0.0], atol=1e-12)


def _look_at(gt: pycolmap.Reconstruction) -> np.ndarray:
    """The 3D point closest to every camera's principal ray (where people stand)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for image in gt.images.values():
        d = image.viewing_direction()
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ image.projection_center()
    return np.linalg.solve(A, b)


def _vcs_with_known_errors(
    gt: pycolmap.Reconstruction, name1: str, name2: str
) -> tuple[np.ndarray, np.ndarray]:
    """(2, 2) VCs per image: row 0 exact, row 1 40 px off its epipolar line."""
    im1, im2 = gt.find_image_with_name(name1), gt.find_image_with_name(name2)
    center = _look_at(gt)
    points = np.array([center, center + np.array([0.2, -0.3, 0.1])])
    xy1 = np.array([im1.project_point(p) for p in points])
    xy2 = np.array([im2.project_point(p) for p in points])
    # The epipolar line of xy1[1] in image 2, from two depths along its ray.
    c1 = im1.projection_center()
    a, b = (im2.project_point(c1 + s * (points[1] - c1)) for s in (0.8, 1.25))
    normal = np.array([a[1] - b[1], b[0] - a[0]]) / np.linalg.norm(b - a)
    xy2[1] += 40.0 * normal
    return xy1, xy2


def test_epipolar_errors_are_zero_on_gt_and_large_off_the_line(
    dome_scene: Path,
) -> None:
    gt = pycolmap.Reconstruction(dome_scene / "gt" / "sparse")
    xy1, xy2 = _vcs_with_known_errors(gt, "cam00.jpg", "cam01.jpg")
    im1, im2 = (
        gt.find_image_with_name("cam00.jpg"),
        gt.find_image_with_name("cam01.jpg"),
    )
    R1, R2 = im1.cam_from_world().matrix(), im2.cam_from_world().matrix()
    rot = R2[:, :3] @ R1[:, :3].T
    cam2_from_cam1 = np.column_stack([rot, R2[:, 3] - rot @ R1[:, 3]])
    errors = epipolar_errors_px(
        xy1, xy2, gt.cameras[im1.camera_id], gt.cameras[im2.camera_id], cam2_from_cam1
    )
    assert errors[0] < 1e-6
    assert 20.0 < errors[1] < 60.0


def test_draw_pair_colors_vcs_by_error() -> None:
    image = np.full((100, 150, 3), 128, np.uint8)
    xy = np.array([[30.5, 40.5], [90.5, 60.5]])  # COLMAP: centre of pixel (30, 40)
    panel = draw_pair(
        image,
        image,
        vc_xy1=xy,
        vc_xy2=xy,
        vc_errors_px=np.array([0.0, 50.0]),
        classic_xy1=np.array([[10.5, 10.5]]),
        classic_xy2=np.array([[20.5, 80.5]]),
        height=100,
        max_error_px=8.0,
        max_vc_lines=0,
    )
    assert panel.shape == (100, 300 + PANEL_GAP_PX, 3)
    for dx in (0, 150 + PANEL_GAP_PX):
        assert tuple(panel[40, 30 + dx]) == GREEN
        assert tuple(panel[60, 90 + dx]) == RED
    assert _looks(panel[10, 10], (255, 140, 0), tol=2)  # classic match: azure


# ---------------------------------------------------------------- the report


def test_report_is_self_contained_and_complete(full_report: Path) -> None:
    page = full_report.read_text(encoding="utf-8")
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:)?//""", page)
    assert "http://" not in page and "https://" not in page and "<script" not in page
    for text in (
        'id="summary"',
        'id="poses"',
        'id="errors"',
        'id="pairs"',
        "Pose accuracy",
        "classic COLMAP",
        "colmap-vc",
        "AUC@15°",
        "AUC@45°",
        "Per-stage timings",
        "augment",
        "mapping",
        "registered images",
        "VCs by kind",
        # pycolmap's own mapper wrote the model: no metres, said so
        "arbitrary (no metric_scale.json beside the model)",
        "camera distances / ground truth&#x27;s",
        "epipolar error vs GT relative pose",
    ):
        assert text in page, text
    assert 'class="missing"' not in page
    assert page.count('<figure class="pair"') == 8


def test_report_images_decode(full_report: Path) -> None:
    images = _images(full_report.read_text(encoding="utf-8"))
    pairs = [k for k in images if k.startswith("pair ")]
    assert len(pairs) == 8
    assert {
        "camera poses",
        "pose error curve",
        "oblique 3D view",
        "top 3D view",
    } <= set(images)
    for name, image in images.items():
        assert image is not None, name
        assert min(image.shape[:2]) >= 200, (name, image.shape)
        assert image.std() > 10, name  # not a blank canvas
    panel = images[pairs[0]]
    vc_colored = (panel[..., 0] < 60) & (
        np.abs(panel[..., 1:].astype(int) - 128) > 100
    ).any(-1)
    assert vc_colored.sum() > 500  # green..red VC dots are drawn


def test_report_draws_a_large_error_vc_red(dome_scene: Path, tmp_path: Path) -> None:
    db = tmp_path / "database.db"
    shutil.copyfile(dome_scene / "database.db", db)
    views = database.read_views(db)
    ids = dict(zip(views.image_names, views.image_ids.tolist(), strict=True))
    gt_path = dome_scene / "gt" / "sparse"
    xy1, xy2 = _vcs_with_known_errors(
        pycolmap.Reconstruction(gt_path), "cam00.jpg", "cam01.jpg"
    )
    i1, i2 = ids["cam00.jpg"], ids["cam01.jpg"]
    zeros, two = np.zeros(2), np.arange(2)
    database.write_virtual_correspondences(
        db,
        [
            VcKeypoints(
                image_id=i, xy_img=xy, person_id=np.zeros(2, np.int64), track_id=two
            )
            for i, xy in ((i1, xy1), (i2, xy2))
        ],
        [
            PairVcMatches(
                image_id1=i1,
                image_id2=i2,
                idx1=two,
                idx2=two,
                person_id=np.zeros(2, np.int64),
                kind=np.ones(2, np.int64),
                points1_cam=np.zeros((2, 3)),
                points2_cam=np.zeros((2, 3)),
                a=zeros,
                b=zeros,
                is_inlier=np.ones(2, bool),
            )
        ],
        {},
    )
    height = views.cameras[int(views.camera_ids[0])].height
    out = build_report(
        ReportInputs(
            database_path=db,
            image_dir=dome_scene / "images",
            gt_model_path=gt_path,
            max_vc_lines=0,
            panel_height_px=height,
        ),
        tmp_path / "r.html",
    )
    page = out.read_text(encoding="utf-8")
    panel = _images(page)[f"pair {i1}-{i2}"]
    width1 = views.cameras[int(views.camera_ids[0])].width
    # Scale 1: OpenCV pixel = COLMAP pixel - 0.5; image 2 starts after the gap.
    (g1, r1), (g2, r2) = np.floor(xy1).astype(int), np.floor(xy2).astype(int)
    offset = np.array([width1 + PANEL_GAP_PX, 0])
    g2, r2 = g2 + offset, r2 + offset
    for (x, y), color in ((g1, GREEN), (g2, GREEN), (r1, RED), (r2, RED)):
        assert _looks(panel[y, x], color), (x, y, panel[y, x], color)
    assert "epipolar error vs GT relative pose" in page
    assert "No reconstructed model given" in page


def test_report_without_vcs_shows_classic_matches(
    dome_scene: Path, tmp_path: Path
) -> None:
    db = tmp_path / "plain.db"
    shutil.copyfile(dome_scene / "database.db", db)
    out = build_report(
        ReportInputs(database_path=db, image_dir=dome_scene / "images"),
        tmp_path / "plain.html",
    )
    page = out.read_text(encoding="utf-8")
    assert "has no virtual correspondences" in page
    assert "No reconstructed model given" in page
    assert "no pose-error curve" in page
    figures = page.count('<figure class="pair"')
    num_verified = sum(
        len(r.inlier_matches) > 0
        for r in database.read_two_view_geometries(db).values()
    )
    assert figures == min(num_verified, 12) > 0
    assert all(img is not None for img in _images(page).values())


def test_report_without_model_uses_two_view_geometry(run: Run, tmp_path: Path) -> None:
    out = build_report(
        ReportInputs(
            database_path=run.database_path, image_dir=run.scene / "images", max_pairs=3
        ),
        tmp_path / "vc_only.html",
    )
    page = out.read_text(encoding="utf-8")
    assert "No reconstructed model given" in page
    assert "epipolar error vs two-view pose" in page
    assert page.count('<figure class="pair"') == 3
    assert 'id="pairs"' in page and "has no virtual correspondences" not in page


def test_report_rejects_a_missing_model(run: Run, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="model_path"):
        build_report(
            ReportInputs(
                database_path=run.database_path,
                image_dir=run.scene / "images",
                model_path=tmp_path / "nope",
            ),
            tmp_path / "x.html",
        )


# ---------------------------------------------------------------- Chromium


def _screenshot(html_path: Path, png_path: Path, tmp: Path) -> np.ndarray:
    assert CHROMIUM
    args = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--hide-scrollbars",
        f"--user-data-dir={tmp / 'chromium-profile'}",
        "--window-size=1400,3000",
        f"--screenshot={png_path}",
        html_path.resolve().as_uri(),
    ]
    env = {**os.environ, "HOME": str(tmp)}  # keep Chromium's dot-files in tmp
    subprocess.run(args, check=True, capture_output=True, timeout=120, env=env)
    image = cv2.imread(str(png_path), cv2.IMREAD_COLOR)
    assert image is not None and image.shape == (3000, 1400, 3), png_path
    return image


def _num_colorful(image: np.ndarray) -> int:
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    return int(((hsv[..., 1] > 80) & (hsv[..., 2] > 60)).sum())


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium: run `make chromium`")
def test_chromium_renders_the_images_and_plots(
    full_report: Path, tmp_path: Path
) -> None:
    shot = _screenshot(full_report, tmp_path / "report.png", tmp_path)
    # The same page with every inlined image removed: text, tables and CSS only.
    stripped = tmp_path / "stripped.html"
    stripped.write_text(
        DATA_URI.sub('src=""', full_report.read_text(encoding="utf-8")),
        encoding="utf-8",
    )
    blank = _screenshot(stripped, tmp_path / "stripped.png", tmp_path)
    assert _num_colorful(shot) > 100_000
    assert _num_colorful(shot) > 10 * max(_num_colorful(blank), 1)
    non_white = (shot < 235).any(-1)
    assert non_white.mean() > 3 * (blank < 235).any(-1).mean()
    # The pose plots sit in the first screen: blue/orange camera markers drawn there.
    top = cv2.cvtColor(shot[:1500], cv2.COLOR_BGR2HSV)
    orange = (np.abs(top[..., 0].astype(int) - 14) < 5) & (top[..., 1] > 150)
    assert orange.sum() > 200


def test_report_survives_pycolmap_imported_first(run: Run, tmp_path: Path) -> None:
    # `import pycolmap` before anything loads libz makes every later deflate (PNG,
    # zlib) abort the process; the report must not deflate. Fresh process: the
    # import order of this test session does not matter.
    out = tmp_path / "order.html"
    code = (
        "import sys, pycolmap\n"
        "from pathlib import Path\n"
        "from colmap_vc.report import ReportInputs, build_report\n"
        "a = [Path(x) for x in sys.argv[1:]]\n"
        "build_report(ReportInputs(database_path=a[0], image_dir=a[1], model_path=a[2],"
        " gt_model_path=a[3], max_pairs=2), a[4])\n"
    )
    args = [run.database_path, run.scene / "images", run.model_path, run.gt_model_path]
    subprocess.run(
        [sys.executable, "-c", code, *map(str, args), str(out)],
        check=True,
        capture_output=True,
        timeout=120,
    )
    page = out.read_text(encoding="utf-8")
    assert "this model (vs GT)" in page  # no metrics given: the model is evaluated
    # pairs + poses, 3 views, curve + the people in each of the 6 images
    assert len(_images(page)) == 2 + 5 + 6


def test_people_section_colours_each_identity_alike_in_every_view(
    full_report: Path,
) -> None:
    """One panel per image; a person's dots share one colour in every view."""
    from colmap_vc.report_people import PALETTE

    page = full_report.read_text(encoding="utf-8")
    assert 'id="people"' in page
    people = {k: v for k, v in _images(page).items() if k.startswith("people in ")}
    assert len(people) == 6
    captions = re.findall(
        r'<figure class="person".*?<figcaption>(.*?)</figcaption>', page
    )
    identities = {int(i) for c in captions for i in re.findall(r"identity (\d+)", c)}
    assert identities == {0, 1}  # the dome's two people, linked in every view
    for panel in people.values():
        for i in identities:  # both identity colours are drawn in each view
            near = np.abs(panel.astype(int) - PALETTE[i].astype(int)).max(-1) < 40
            assert near.sum() > 30


def test_gravity_section_draws_the_lines_of_each_measured_camera(
    run: Run, tmp_path: Path
) -> None:
    """A model with gravity.json beside it: one panel per measured camera, its
    lines drawn in green and its people's up in magenta; when the people undid
    the step, the section says why; a model without the file has no gravity
    section."""
    from colmap_vc.report_gravity import LINE_BGR, PEOPLE_BGR

    model = tmp_path / "model"
    shutil.copytree(run.model_path, model)
    rec = pycolmap.Reconstruction(model)
    image = next(iter(sorted(rec.images.values(), key=lambda im: im.name)))
    up = image.cam_from_world().rotation.matrix() @ np.array([0.0, 0.0, 1.0])
    lines = [[40.0 + 30 * k, 20.0, 40.0 + 30 * k, 300.0] for k in range(5)]
    (model / "gravity.json").write_text(
        json.dumps(
            {
                "used": False,
                "pixel_noise_px": 10.0,
                "cameras": {
                    image.name: {
                        "up_cam": up.tolist(),
                        "sigma_deg": 0.3,
                        "num_segments": 5,
                        "num_images": 1,
                        "residual_deg": 0.1,
                        "lines_px": lines,
                        "people_up_cam": up.tolist(),
                    }
                },
                "rejected": "their people's ups say the turn is wrong (test)",
            }
        )
    )
    common = {"database_path": run.database_path, "image_dir": run.scene / "images"}
    page = build_report(
        ReportInputs(**common, model_path=model), tmp_path / "with.html"
    ).read_text(encoding="utf-8")
    assert 'id="gravity"' in page and 'href="#gravity"' in page
    panels = {k: v for k, v in _images(page).items() if k.startswith("vertical lines")}
    assert list(panels) == [f"vertical lines of {image.name}"]
    green = np.abs(panels[f"vertical lines of {image.name}"].astype(int) - LINE_BGR)
    assert (green.max(-1) < 40).sum() > 50  # the five lines
    magenta = np.abs(panels[f"vertical lines of {image.name}"].astype(int) - PEOPLE_BGR)
    assert (magenta.max(-1) < 40).sum() > 20  # the people's up
    assert "The ups were not used: their people&#x27;s ups say the turn" in page
    assert "5 lines in 1 image(s), up +-0.30 deg" in page
    without = build_report(
        ReportInputs(**common, model_path=run.model_path), tmp_path / "without.html"
    ).read_text(encoding="utf-8")
    assert 'id="gravity"' not in without and 'href="#gravity"' not in without


def test_people_caption_says_why_a_person_was_left_out() -> None:
    """A person the visibility check left out carries its reason under the image;
    one the association found no partner for is just left out."""
    from colmap_vc.report import _who

    unseen = {"cam02.jpg #1": "not found in 2 of the 2 other images it is in view of"}
    who = _who("cam02.jpg", {1: -1, 0: 0, 2: -1}, unseen)
    assert who == (
        "person 0 = identity 0, person 1 left out: not found in 2 of the 2 other "
        "images it is in view of, person 2 left out"
    )
    assert _who("cam03.jpg", {1: -1}, unseen) == "person 1 left out"
