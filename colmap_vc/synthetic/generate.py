"""`colmap-vc synth`: write a synthetic scene as a COLMAP project.

Layout of OUT_DIR::

    images/cam00.jpg ...        rendered images (cam00_t00.jpg ... with instants)
    gt/sparse/                  ground-truth COLMAP model (.bin and .txt)
    gt/surface/cam00.npz ...    ground-truth surface maps (pixel -> person, face, bary)
    gt/priors/                  ground-truth priors (every visible person, true ids)
    gt/persons.json             true id of each person of priors/ (gt.py has the format)
    gt/persons_<level>.json     the same for priors_<level>/
    priors/                     predicted priors at the requested noise level:
                                anonymous (unless with_ids), detection failures
    priors_<level>/             more levels when asked (--extra-noise)
    database.db                 SIFT features + exhaustive matches (pycolmap), or
                                cameras and images only (sift=False)
    scene.json                  what was generated, from which seed and options

With ``num_instants`` > 1 the cameras stay where they are and the people are drawn
anew at each instant (``static cameras``): every file above holds one image per
camera and instant, and instant k's people have the ids k * P ... k * P + P - 1 (P
people per instant). Instant 0 is the scene of one instant; the others draw from
their own random streams.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from .. import __version__, outputs
from ..priors import write_priors
from ..structs import FloatArray, ImagePrior, ScenePriors
from . import bodies as body_lib
from .colmap_db import build_bare_database, build_sift_database, spec_camera
from .detection import DETECTION_LEVELS
from .gt import FALSE_ID_BASE, GtPersons, gt_persons_path, write_gt_persons
from .layout import (
    LayoutOptions,
    Preset,
    SceneLayout,
    draw_people,
    instant_image_name,
    make_layout,
)
from .noise import NOISE_LEVELS, NOISE_REVISION, NoiseLevel, predict_person
from .render import World, build_world, render_view
from .views import Detections, detect, person_views, size_errors_of, write_surface_map

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class SynthOptions:
    """Options of `colmap-vc synth`."""

    seed: int = 0
    """Seed of everything random: same seed, same files."""
    num_people: int = 1
    """People in the scene (1 to 3)."""
    noise: NoiseLevel = NoiseLevel.REALISTIC
    """Noise level of the predicted priors (clean, realistic, hard, fitted)."""
    num_cameras: int | None = None
    """Cameras (dome/dense: 8-16, drawn from the seed when unset; at most 256 dome,
    64 dense)."""
    num_instants: int = 1
    """Instants seen by the same static cameras: the people are drawn anew at each
    (images cam00_t00.jpg, cam00_t01.jpg, ...)."""
    width: int = 640
    """Image width."""
    height: int = 480
    """Image height."""
    camera_model: str | None = None
    """COLMAP camera model (default: SIMPLE_RADIAL dome, OPENCV dense, PINHOLE pair)."""
    pair_angle_deg: float | None = None
    """Pair preset: angle between the two views, degrees (random when unset)."""
    extra_noise: tuple[NoiseLevel, ...] = ()
    """Also write priors at these levels to priors_<level>/ (same scene, independent
    random stream, so the default outputs do not change)."""
    max_num_features: int = 2048
    """SIFT features per image (a cap keeps extraction and matching fast)."""
    make_database: bool = True
    """Write database.db."""
    sift: bool = True
    """SIFT extraction and exhaustive matching into database.db; without, it holds
    the cameras and images only (empty keypoints), for VCs alone: exhaustive
    matching grows with the square of the images."""
    overwrite: bool = False
    """Replace an existing OUT_DIR."""
    num_threads: int = -1
    """Threads for COLMAP (-1: all cores)."""
    with_ids: bool = False
    """Give the predicted priors each person's true id (the association solved);
    by default they are anonymous, as a detector's output is."""
    close_pair: bool = False
    """The first two people stand 0.5-0.8 m apart and overlap in some views."""
    bystander: bool = False
    """Add a bystander 3-5 m from the group, seen by a few cameras only."""
    dress_alike: bool = False
    """The second person wears the first one's clothes (own skin and hair)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class SynthSummary:
    """What `synth` wrote."""

    out_dir: Path
    preset: Preset
    num_images: int
    num_people: int
    person_pixels: dict[str, int]
    timings_s: dict[str, float] = field(default_factory=dict)


def gt_reconstruction(layout: SceneLayout) -> pycolmap.Reconstruction:
    """Ground-truth model: camera i and image i (1-based, name order), no points."""
    rec = pycolmap.Reconstruction()
    for i, spec in enumerate(sorted(layout.cameras, key=lambda c: c.name), start=1):
        rec.add_camera_with_trivial_rig(spec_camera(spec, i))
        image = pycolmap.Image(name=spec.name, camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(
            image,
            pycolmap.Rigid3d(
                pycolmap.Rotation3d(spec.cam_from_world[:, :3]),
                spec.cam_from_world[:, 3],
            ),
        )
    return rec


def build_database(out_dir: Path, layout: SceneLayout, options: SynthOptions) -> Path:
    """database.db of the images of ``layout``: SIFT extraction with the known
    intrinsics and exhaustive matching, or (``sift`` off) cameras and images only."""
    db_path = out_dir / "database.db"
    if not options.sift:
        return build_bare_database(db_path, layout.cameras)
    return build_sift_database(
        db_path,
        out_dir / "images",
        layout.cameras,
        max_num_features=options.max_num_features,
        num_threads=options.num_threads,
    )


def _check_instants(options: SynthOptions) -> None:
    people = options.num_people + int(options.bystander)
    if options.num_instants < 1:
        raise ValueError(f"num_instants={options.num_instants} must be at least 1")
    if people * options.num_instants > FALSE_ID_BASE:
        raise ValueError(
            f"num_instants={options.num_instants} x {people} people per instant "
            f"needs person ids past {FALSE_ID_BASE}, the first id of false detections"
        )


def _instants(
    layout: SceneLayout,
    rng: np.random.Generator,
    bodies: body_lib.BodyModel,
    layout_options: LayoutOptions,
    options: SynthOptions,
) -> list[tuple[SceneLayout, np.random.Generator]]:
    """The scene at each instant, with the random stream of its images: the static
    cameras named for the instant's images and the instant's people. Instant 0 is
    ``layout`` with ``rng``; instant k draws from its own stream (seed, 2000 + k), so
    more instants change nothing of instant 0."""
    out = []
    for k in range(options.num_instants):
        cameras = tuple(
            replace(c, name=instant_image_name(c.name, k, options.num_instants))
            for c in layout.cameras
        )
        if k == 0:
            out.append((replace(layout, cameras=cameras), rng))
            continue
        rng_k = np.random.default_rng([options.seed, 2000 + k])
        people = draw_people(
            layout.cameras,
            rng_k,
            num_phenotypes=bodies.rest_vertices.shape[0],
            num_poses=bodies.pose_rotvec.shape[0],
            options=layout_options,
            first_person_id=k * len(layout.people),
        )
        out.append((replace(layout, cameras=cameras, people=people), rng_k))
    return out


def _instant_world(
    layout: SceneLayout,
    bodies: body_lib.BodyModel,
    rng: np.random.Generator,
    backdrop: World,
    options: SynthOptions,
) -> tuple[list[FloatArray], World]:
    """Posed bodies and render world of a later instant: its people before the
    backdrop of instant 0 (same texture)."""
    posed = [body_lib.pose_body(bodies, p.phenotype, p.pose) for p in layout.people]
    world = build_world(layout, bodies, posed, rng, dress_alike=options.dress_alike)
    return posed, replace(world, seed=backdrop.seed)


def generate(
    preset: Preset | str, out_dir: Path, options: SynthOptions | None = None
) -> SynthSummary:
    """Generate one synthetic scene into ``out_dir`` (see the module docstring)."""
    options = options or SynthOptions()
    preset = Preset(preset)
    out_dir = Path(out_dir)
    _check_instants(options)
    outputs.prepare_output_dir(out_dir, "synth", overwrite=options.overwrite)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    rng = np.random.default_rng(options.seed)
    bodies = body_lib.load_bodies()
    layout_options = LayoutOptions(
        num_people=options.num_people,
        num_cameras=options.num_cameras,
        width=options.width,
        height=options.height,
        camera_model=options.camera_model,
        pair_angle_deg=options.pair_angle_deg,
        close_pair=options.close_pair,
        bystander=options.bystander,
    )
    layout = make_layout(
        preset,
        rng,
        num_phenotypes=bodies.rest_vertices.shape[0],
        num_poses=bodies.pose_rotvec.shape[0],
        options=layout_options,
    )
    posed = [body_lib.pose_body(bodies, p.phenotype, p.pose) for p in layout.people]
    world = build_world(layout, bodies, posed, rng, dress_alike=options.dress_alike)
    instants = _instants(layout, rng, bodies, layout_options, options)
    # Every image (camera x instant) and every person of every instant.
    scene = replace(
        layout,
        cameras=tuple(c for inst, _ in instants for c in inst.cameras),
        people=tuple(p for inst, _ in instants for p in inst.people),
    )
    for sub in ("images", "gt/surface", "gt/sparse"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
    timings["setup"] = time.perf_counter() - t0

    gt_priors: dict[str, ImagePrior] = {}
    visible: dict[str, list[int]] = {}
    main_level = NoiseLevel(options.noise)
    extra = [NoiseLevel(level) for level in options.extra_noise]
    size_errors = {
        level: size_errors_of(level, options.seed, scene.people)
        for level in [main_level, *extra]
    }
    pred = Detections(size_errors=size_errors[main_level])
    extra_pred = {level: Detections(size_errors=size_errors[level]) for level in extra}
    extra_rng = {
        level: np.random.default_rng(
            [options.seed, 1000 + list(NoiseLevel).index(level)]
        )
        for level in extra
    }
    person_pixels: dict[str, int] = {}
    t_render = t_priors = 0.0
    for k, (instant, rng_k) in enumerate(instants):
        if k:
            t1 = time.perf_counter()
            posed, world = _instant_world(instant, bodies, rng_k, world, options)
            timings["setup"] += time.perf_counter() - t1
        for spec in instant.cameras:
            t1 = time.perf_counter()
            view = render_view(world, spec, rng_k)
            # OpenCV writes BGR; the renderer produces RGB.
            cv2.imwrite(
                str(out_dir / "images" / spec.name),
                view.image[:, :, ::-1],
                [cv2.IMWRITE_JPEG_QUALITY, 95],
            )
            t2 = time.perf_counter()
            camera = spec_camera(spec, 1)
            views = person_views(view, instant, posed, spec, world)
            stem = Path(spec.name).stem
            person_pixels[spec.name] = write_surface_map(
                out_dir / "gt/surface" / f"{stem}.npz", views, bodies
            )
            # Detector order is not identity order: shuffle the people per image.
            order = rng_k.permutation(len(views))
            clean = [
                predict_person(bodies, views[i], camera, NoiseLevel.CLEAN, rng_k)
                for i in order
            ]
            gt_priors[spec.name] = ImagePrior(
                image_name=spec.name,
                persons=tuple(p for p in clean if p is not None),
            )
            visible[spec.name] = sorted(v.person_id for v in views)
            detect(
                pred,
                bodies,
                views,
                view,
                instant,
                spec.name,
                camera,
                main_level,
                rng_k,
                options.with_ids,
            )
            for level in extra:
                detect(
                    extra_pred[level],
                    bodies,
                    views,
                    view,
                    instant,
                    spec.name,
                    camera,
                    level,
                    extra_rng[level],
                    options.with_ids,
                )
            t_render += t2 - t1
            t_priors += time.perf_counter() - t2
    timings["render"] = t_render
    timings["priors"] = t_priors

    t1 = time.perf_counter()
    sizes = {c.name: (c.width, c.height) for c in scene.cameras}
    templates = {"anny": bodies.faces}
    write_priors(
        ScenePriors(images=gt_priors),
        out_dir / "gt/priors",
        templates=templates,
        image_sizes=sizes,
    )
    roles = {
        p.person_id: "bystander" if p.bystander else "person" for p in scene.people
    }
    for folder, det in [("priors", pred)] + [
        (f"priors_{level.value}", d) for level, d in extra_pred.items()
    ]:
        write_priors(
            ScenePriors(images=det.priors),
            out_dir / folder,
            templates=templates,
            image_sizes=sizes,
        )
        write_gt_persons(
            gt_persons_path(out_dir, folder),
            GtPersons(
                priors=folder,
                people=roles,
                images=det.true_ids,
                visible=visible,
                dropped=det.dropped,
            ),
        )
    rec = gt_reconstruction(scene)
    rec.write_binary(str(out_dir / "gt/sparse"))
    rec.write_text(str(out_dir / "gt/sparse"))
    timings["write"] = time.perf_counter() - t1

    if options.make_database:
        t1 = time.perf_counter()
        build_database(out_dir, scene, options)
        timings["database"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t0

    (out_dir / "scene.json").write_text(
        json.dumps(_scene_spec(preset, scene, bodies, options, size_errors), indent=1)
    )
    summary = SynthSummary(
        out_dir=out_dir,
        preset=preset,
        num_images=len(scene.cameras),
        num_people=len(scene.people),
        person_pixels=person_pixels,
        timings_s=timings,
    )
    logger.info(
        "synth %s: %d images, %d people, %.1f s "
        "(render %.1f s, priors %.1f s, database %.1f s; per image: render %.3f s, "
        "priors %.3f s)",
        preset.value,
        summary.num_images,
        summary.num_people,
        timings["total"],
        timings["render"],
        timings["priors"],
        timings.get("database", 0.0),
        timings["render"] / summary.num_images,
        timings["priors"] / summary.num_images,
    )
    return summary


def _scene_spec(
    preset: Preset,
    scene: SceneLayout,
    bodies: body_lib.BodyModel,
    options: SynthOptions,
    size_errors: dict[NoiseLevel, dict[int, float]],
) -> dict:
    """scene.json: what was generated (every image and person), from which options;
    the noise model of every level whose priors were made (``noise_models``), the
    revision of the code that drew them (``noise_revision``) and each person's size
    error at each (``size_error``)."""
    num_people = len(scene.people) // options.num_instants
    people = []
    for p in scene.people:
        person = {
            "person_id": p.person_id,
            "phenotype": bodies.phenotype_names[p.phenotype],
            "pose": bodies.pose_names[p.pose],
            "position_xy": p.position_xy.tolist(),
            "yaw_deg": float(np.degrees(p.yaw_rad)),
            "bystander": p.bystander,
            "size_error": {
                level.value: errors[p.person_id]
                for level, errors in size_errors.items()
            },
        }
        if options.num_instants > 1:
            person["instant"] = p.person_id // num_people
        people.append(person)
    return {
        "colmap_vc_version": __version__,
        "preset": preset.value,
        "options": {
            k: (v.value if hasattr(v, "value") else v)
            for k, v in asdict(options).items()
        },
        "noise_model": asdict(NOISE_LEVELS[NoiseLevel(options.noise)]),
        "noise_models": {
            level.value: asdict(NOISE_LEVELS[level]) for level in size_errors
        },
        "noise_revision": NOISE_REVISION,
        "detection_model": asdict(DETECTION_LEVELS[NoiseLevel(options.noise)]),
        "backdrop": scene.backdrop.value,
        "people": people,
        "cameras": [
            {
                "name": c.name,
                "model": c.model,
                "params": c.params.tolist(),
                "cam_from_world": c.cam_from_world.tolist(),
            }
            for c in scene.cameras
        ],
    }
