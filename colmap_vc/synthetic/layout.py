"""Scene layouts of the synthetic world: where the cameras and the people are.

Three presets mimic the data the method is for:
- ``dome``: a CMU-Panoptic-like dome, 8-16 cameras (up to 256 when asked) on a 3-5 m
  sphere all around one to three people, elevations 0-60 degrees, so many pairs are
  90-180 degrees apart. The backdrop is the dome's low-texture geodesic panelling, as
  in Panoptic.
- ``dense``: a handheld capture in a textured room, 8-16 cameras (up to 64) 5-20
  degrees apart.
- ``pair``: the paper's two-frame task, two cameras a controlled angle apart.

World frame: metres, +Z up, the floor is z = 0, the people stand around the origin.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..structs import FloatArray


class Preset(enum.StrEnum):
    """Named scene layouts."""

    DOME = "dome"
    DENSE = "dense"
    PAIR = "pair"


class Backdrop(enum.StrEnum):
    """What surrounds the people."""

    DOME = "dome"  # Panoptic-like geodesic dome: low texture, repetitive panels
    ROOM = "room"  # a furnished-looking room: textured floor and walls


@dataclass(frozen=True, kw_only=True, slots=True)
class CameraSpec:
    """One ground-truth camera."""

    name: str
    model: str  # COLMAP camera model name
    width: int
    height: int
    params: FloatArray  # COLMAP parameter vector of ``model``
    cam_from_world: FloatArray  # (3, 4) [R | t]

    @property
    def centre(self) -> FloatArray:
        """(3,) camera centre in world."""
        return -self.cam_from_world[:, :3].T @ self.cam_from_world[:, 3]


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonPlacement:
    """One person: which body, where, facing which way."""

    person_id: int
    phenotype: int
    pose: int
    position_xy: FloatArray  # (2,) metres on the floor
    yaw_rad: float  # rotation about +Z of the body frame (body faces +Y at yaw 0)
    bystander: bool = False  # away from the group, seen by a few cameras only


@dataclass(frozen=True, kw_only=True, slots=True)
class SceneLayout:
    """Cameras, people and backdrop of one scene."""

    preset: Preset
    backdrop: Backdrop
    cameras: tuple[CameraSpec, ...]
    people: tuple[PersonPlacement, ...]


@dataclass(frozen=True, kw_only=True, slots=True)
class LayoutOptions:
    """Options of the layout generator."""

    num_people: int = 1
    """People in the scene (1 to 3)."""
    num_cameras: int | None = None
    """Cameras (8-16 for dome/dense drawn from the seed when None; at most 256 dome, 64
    dense). Pair: always 2."""
    width: int = 640
    """Image width in pixels."""
    height: int = 480
    """Image height in pixels."""
    camera_model: str | None = None
    """COLMAP camera model; None picks the preset's default (with distortion)."""
    pair_angle_deg: float | None = None
    """Pair preset: angle between the two cameras, seen from the people."""
    close_pair: bool = False
    """Place the first two people 0.5-0.8 m apart (centre to centre), so they overlap
    in some views (the default keeps people at least 0.8 m apart)."""
    bystander: bool = False
    """Add a bystander 3-5 m from the group's centre, in the widest gap between camera
    azimuths: only the cameras across the scene see it, small and often cut."""


MAX_CAMERAS = {Preset.DOME: 256, Preset.DENSE: 64}
"""Most cameras of a preset. Dense stops at 64: its cameras follow each other 5-20
degrees apart (12.5 on average), so 64 of them already circle the people twice."""

DEFAULT_CAMERA_MODEL = {
    Preset.DOME: "SIMPLE_RADIAL",
    Preset.DENSE: "OPENCV",
    Preset.PAIR: "PINHOLE",
}


def look_at(
    centre: FloatArray, target: FloatArray, roll_rad: float = 0.0
) -> FloatArray:
    """cam_from_world (3, 4) of a camera at ``centre`` looking at ``target``, Z up."""
    forward = target - centre
    forward = forward / np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0])
    if abs(forward @ up) > 0.999:  # looking straight down: any right vector works
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    R = np.stack([c * right + s * down, -s * right + c * down, forward])
    return np.concatenate([R, (-R @ centre)[:, None]], axis=1)


def _intrinsics(
    model: str, width: int, height: int, rng: np.random.Generator
) -> FloatArray:
    """A plausible parameter vector of ``model`` (about 60 degrees horizontal FOV)."""
    f = width * rng.uniform(0.8, 0.95)
    cx = width / 2 + rng.uniform(-4, 4)
    cy = height / 2 + rng.uniform(-4, 4)
    if model == "PINHOLE":
        return np.array([f, f, cx, cy])
    if model == "SIMPLE_PINHOLE":
        return np.array([f, cx, cy])
    if model == "SIMPLE_RADIAL":
        return np.array([f, cx, cy, rng.uniform(-0.06, -0.02)])
    if model == "RADIAL":
        return np.array([f, cx, cy, rng.uniform(-0.06, -0.02), rng.uniform(0, 0.01)])
    if model == "OPENCV":
        k1, k2 = rng.uniform(-0.08, -0.03), rng.uniform(0.0, 0.02)
        p1, p2 = rng.uniform(-5e-4, 5e-4, size=2)
        return np.array([f, f * rng.uniform(0.995, 1.005), cx, cy, k1, k2, p1, p2])
    raise ValueError(
        f"camera_model={model!r} is not supported by the synthetic world; use one of "
        "PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV"
    )


def _place_people(
    num_people: int,
    num_phenotypes: int,
    num_poses: int,
    rng: np.random.Generator,
    close_pair: bool = False,
) -> tuple[PersonPlacement, ...]:
    """Up to three people near the origin, at least 0.8 m apart, random bodies.

    ``close_pair``: the second person stands 0.5-0.8 m from the first.
    """
    if not 1 <= num_people <= 3:
        raise ValueError(f"num_people={num_people} must be between 1 and 3")
    if close_pair and num_people < 2:
        raise ValueError("close_pair needs num_people >= 2")
    positions: list[FloatArray] = []
    while len(positions) < num_people:
        if num_people == 1:
            p = rng.uniform(-0.2, 0.2, size=2)
        elif close_pair and len(positions) == 1:
            angle = rng.uniform(0, 2 * math.pi)
            p = positions[0] + rng.uniform(0.5, 0.8) * np.array(
                [math.cos(angle), math.sin(angle)]
            )
            positions.append(p)
            continue
        else:
            angle = rng.uniform(0, 2 * math.pi)
            p = rng.uniform(0.5, 1.0) * np.array([math.cos(angle), math.sin(angle)])
        if all(np.linalg.norm(p - q) > 0.8 for q in positions):
            positions.append(p)
    phenotypes = rng.permutation(num_phenotypes)[:num_people]
    return tuple(
        PersonPlacement(
            person_id=i,
            phenotype=int(phenotypes[i]),
            pose=int(rng.integers(num_poses)),
            position_xy=positions[i],
            yaw_rad=float(rng.uniform(-math.pi, math.pi)),
        )
        for i in range(num_people)
    )


def make_layout(
    preset: Preset,
    rng: np.random.Generator,
    *,
    num_phenotypes: int,
    num_poses: int,
    options: LayoutOptions | None = None,
) -> SceneLayout:
    """Draw cameras and people of one scene of ``preset``."""
    options = options or LayoutOptions()
    preset = Preset(preset)
    model = options.camera_model or DEFAULT_CAMERA_MODEL[preset]
    people = _place_people(
        options.num_people, num_phenotypes, num_poses, rng, options.close_pair
    )
    centroid = np.mean([p.position_xy for p in people], axis=0)
    if preset is Preset.PAIR:
        num_cameras = 2
    else:
        num_cameras = options.num_cameras or int(rng.integers(8, 17))
        most = MAX_CAMERAS[preset]
        if not 2 <= num_cameras <= most:
            why = (
                ": its cameras stand 5-20 degrees apart in a row, 64 of them already "
                "circle the people twice (use the dome preset for more)"
                if preset is Preset.DENSE
                else ""
            )
            raise ValueError(
                f"num_cameras={num_cameras} must be between 2 and {most} for the "
                f"{preset.value} preset{why}"
            )

    if preset is Preset.DOME:
        # All around: even azimuths with jitter, so neighbours are 360/N apart.
        base = rng.uniform(0, 2 * math.pi)
        step = 2 * math.pi / num_cameras
        azimuth = base + step * np.arange(num_cameras, dtype=np.float64)
        azimuth += rng.uniform(-0.3, 0.3, num_cameras) * step
        elevation = np.deg2rad(rng.uniform(0, 60, num_cameras))
        radius = rng.uniform(3.0, 5.0, num_cameras)
        backdrop = Backdrop.DOME
    elif preset is Preset.DENSE:
        base = rng.uniform(0, 2 * math.pi)
        steps = np.deg2rad(rng.uniform(5, 20, num_cameras - 1))
        azimuth = base + np.r_[0.0, np.cumsum(steps)]
        elevation = np.deg2rad(
            np.clip(15 + np.cumsum(rng.normal(0, 3, num_cameras)), 5, 35)
        )
        radius = np.clip(3.5 + np.cumsum(rng.normal(0, 0.1, num_cameras)), 3.0, 4.5)
        backdrop = Backdrop.ROOM
    else:
        angle = (
            rng.uniform(0, 180)
            if options.pair_angle_deg is None
            else float(options.pair_angle_deg)
        )
        if not 0 <= angle <= 180:
            raise ValueError(f"pair_angle_deg={angle} must be within [0, 180]")
        # Opposite views need low elevations: the angle is at most 180 - (e1 + e2).
        top = min(25.0, (180.0 - angle) / 2)
        # ... and at least |e1 - e2|, so the second elevation stays within `angle`.
        e1, e2 = rng.uniform(min(5.0, top), top, 2)
        elevation = np.deg2rad([e1, np.clip(e2, e1 - angle, e1 + angle)])
        # Azimuth difference that makes the 3D angle between the two viewing
        # directions exactly `angle` (given both elevations), where reachable.
        c1, c2 = np.cos(elevation)
        s1, s2 = np.sin(elevation)
        cos_dazi = (math.cos(math.radians(angle)) - s1 * s2) / (c1 * c2)
        base = rng.uniform(0, 2 * math.pi)
        azimuth = np.array(
            [base, base + math.acos(float(np.clip(cos_dazi, -1.0, 1.0)))]
        )
        # At 0 degrees the cameras still differ in distance, so there is a baseline.
        radius = np.array([rng.uniform(3.0, 3.5), rng.uniform(4.0, 4.5)])
        backdrop = Backdrop.ROOM

    digits = index_digits(num_cameras)
    cameras = []
    shared_target = np.r_[centroid, 1.0]
    for i in range(num_cameras):
        target = np.r_[centroid + rng.normal(0, 0.1, 2), rng.uniform(0.8, 1.2)]
        if preset is Preset.PAIR:
            target = shared_target  # the angle is measured at this point
        centre = target + radius[i] * np.array(
            [
                math.cos(elevation[i]) * math.cos(azimuth[i]),
                math.cos(elevation[i]) * math.sin(azimuth[i]),
                math.sin(elevation[i]),
            ]
        )
        cameras.append(
            CameraSpec(
                name=f"cam{i:0{digits}d}.jpg",
                model=model,
                width=options.width,
                height=options.height,
                params=_intrinsics(model, options.width, options.height, rng),
                cam_from_world=look_at(centre, target, math.radians(rng.normal(0, 2))),
            )
        )
    if options.bystander:
        bystander = _place_bystander(
            len(people), centroid, azimuth, num_phenotypes, num_poses, rng
        )
        people = (*people, bystander)
    return SceneLayout(
        preset=preset, backdrop=backdrop, cameras=tuple(cameras), people=people
    )


def index_digits(count: int) -> int:
    """Digits of the indices 0..count-1 in file names, so that names sort in index
    order: 2 up to 100 (``cam00``-``cam99`` as always), 3 up to 1000."""
    return max(2, len(str(count - 1)))


def instant_image_name(camera_name: str, instant: int, num_instants: int) -> str:
    """Image of one camera at one instant: ``cam00.jpg`` -> ``cam00_t01.jpg`` (the
    regular expression ``(cam\\d+)_`` finds the camera); one instant keeps the name."""
    if num_instants == 1:
        return camera_name
    stem, dot, ext = camera_name.rpartition(".")
    return f"{stem}_t{instant:0{index_digits(num_instants)}d}{dot}{ext}"


def draw_people(
    cameras: Sequence[CameraSpec],
    rng: np.random.Generator,
    *,
    num_phenotypes: int,
    num_poses: int,
    options: LayoutOptions,
    first_person_id: int,
) -> tuple[PersonPlacement, ...]:
    """The people of another instant before the same static cameras: new positions,
    bodies, poses and facing drawn from ``rng`` as :func:`make_layout` draws them
    (bystander included), with ids from ``first_person_id`` on."""
    people = _place_people(
        options.num_people, num_phenotypes, num_poses, rng, options.close_pair
    )
    if options.bystander:
        centroid = np.mean([p.position_xy for p in people], axis=0)
        centres = np.array([c.centre for c in cameras])
        azimuth = np.arctan2(centres[:, 1] - centroid[1], centres[:, 0] - centroid[0])
        bystander = _place_bystander(
            len(people), centroid, azimuth, num_phenotypes, num_poses, rng
        )
        people = (*people, bystander)
    return tuple(replace(p, person_id=first_person_id + p.person_id) for p in people)


def _place_bystander(
    person_id: int,
    centroid: FloatArray,
    camera_azimuth: FloatArray,
    num_phenotypes: int,
    num_poses: int,
    rng: np.random.Generator,
) -> PersonPlacement:
    """A person 3-5 m from the group, in the widest gap between camera azimuths (so no
    camera stands next to it), facing a random way."""
    azi = np.sort(np.mod(camera_azimuth, 2 * math.pi))
    gaps = np.diff(np.r_[azi, azi[0] + 2 * math.pi])
    k = int(np.argmax(gaps))
    angle = azi[k] + gaps[k] * rng.uniform(0.4, 0.6)
    radius = rng.uniform(3.0, 5.0)
    return PersonPlacement(
        person_id=person_id,
        phenotype=int(rng.integers(num_phenotypes)),
        pose=int(rng.integers(num_poses)),
        position_xy=centroid + radius * np.array([math.cos(angle), math.sin(angle)]),
        yaw_rad=float(rng.uniform(-math.pi, math.pi)),
        bystander=True,
    )


def pair_angle_deg(cam1: CameraSpec, cam2: CameraSpec, point: FloatArray) -> float:
    """Angle at ``point`` (3,) between the two camera centres, in degrees."""
    d1, d2 = cam1.centre - point, cam2.centre - point
    c = d1 @ d2 / (np.linalg.norm(d1) * np.linalg.norm(d2))
    return math.degrees(math.acos(np.clip(c, -1.0, 1.0)))
