"""Ray-cast rendering of synthetic scenes (Embree through colmap_vc.raycast).

One primary ray per pixel through the real camera model (distortion included), smooth
Lambert shading from interpolated vertex normals, a shadow ray per floor pixel, a
little blur and sensor noise. Besides the image, every pixel records what it sees
(mesh, face, barycentric), which gives the ground-truth surface maps exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap
import trimesh

from .. import raycast
from ..structs import FloatArray, IndexArray
from . import texture
from .layout import Backdrop, CameraSpec, SceneLayout

if TYPE_CHECKING:
    from .bodies import BodyModel

FLOOR, WALLS, FIRST_PERSON = 0, 1, 2  # mesh indices in the render scene
LIGHT_DIR = np.array([0.35, -0.45, 1.0]) / np.linalg.norm([0.35, -0.45, 1.0])


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonMesh:
    """A person posed and placed in the world."""

    person_id: int
    vertices_world: FloatArray  # (V, 3)
    faces: IndexArray  # (F, 3)
    rest_vertices: FloatArray  # (V, 3) body-frame rest pose (texture coordinates)
    body_from_world: FloatArray  # (3, 4) the placement, inverted
    outfit: texture.Outfit


@dataclass(frozen=True, kw_only=True, slots=True)
class World:
    """Everything a camera can see."""

    backdrop: Backdrop
    people: tuple[PersonMesh, ...]
    scene: raycast.MeshScene
    normals: tuple[FloatArray, ...]  # per mesh (V_i, 3) unit vertex normals
    seed: texture.TextureSeed
    part_names: tuple[str, ...]
    face_part: IndexArray  # (F,) body-part label of each face of the template


@dataclass(frozen=True, kw_only=True, slots=True)
class RenderedView:
    """One rendered image and what each pixel sees."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    geom_idx: IndexArray  # (H, W) mesh index, -1 = nothing
    face_idx: IndexArray  # (H, W)
    bary: FloatArray  # (H, W, 3)


def _vertex_normals(vertices: FloatArray, faces: IndexArray) -> FloatArray:
    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals)


def _room() -> list[tuple[FloatArray, IndexArray]]:
    """Floor and a closed box of walls and ceiling (14 x 14 x 6 m), as two meshes."""
    h, s = 6.0, 7.0
    floor_v = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], dtype=float)
    floor_f = np.array([[0, 1, 2], [0, 2, 3]])
    box = trimesh.creation.box(extents=[2 * s, 2 * s, h])
    box.apply_translation([0, 0, h / 2])
    # Drop the box's bottom (it would hide the floor); flip faces to point inward.
    walls_f = np.asarray(box.faces)[box.face_normals[:, 2] > -0.5][:, ::-1]
    return [(floor_v, floor_f), (np.asarray(box.vertices), walls_f)]


def _dome() -> list[tuple[FloatArray, IndexArray]]:
    """Floor disc and a geodesic hemisphere of radius 9 m (Panoptic-like)."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=9.0)
    keep = sphere.triangles_center[:, 2] > -0.5
    dome = trimesh.Trimesh(sphere.vertices, sphere.faces[keep][:, ::-1], process=False)
    s = 9.5
    floor_v = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], dtype=float)
    floor_f = np.array([[0, 1, 2], [0, 2, 3]])
    return [(floor_v, floor_f), (np.asarray(dome.vertices), np.asarray(dome.faces))]


def place_person(position_xy: FloatArray, yaw_rad: float) -> FloatArray:
    """(3, 4) world_from_body: rotate by yaw about +Z, then move to the position."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.concatenate([R, np.r_[position_xy, 0.0][:, None]], axis=1)


def build_world(
    layout: SceneLayout,
    bodies: BodyModel,
    posed_body_vertices: list[FloatArray],
    rng: np.random.Generator,
    dress_alike: bool = False,
) -> World:
    """Assemble the render scene: backdrop, then the people in layout order.

    ``dress_alike``: the second person wears the first one's clothes (same shirt
    colours and pattern, trousers, shoes; own skin and hair).
    """
    backdrop = _room() if layout.backdrop is Backdrop.ROOM else _dome()
    people: list[PersonMesh] = []
    for person, verts in zip(layout.people, posed_body_vertices, strict=True):
        world_from_body = place_person(person.position_xy, person.yaw_rad)
        v_world = verts @ world_from_body[:, :3].T + world_from_body[:, 3]
        R = world_from_body[:, :3]
        body_from_world = np.concatenate(
            [R.T, (-R.T @ world_from_body[:, 3])[:, None]], axis=1
        )
        people.append(
            PersonMesh(
                person_id=person.person_id,
                vertices_world=v_world,
                faces=bodies.faces,
                rest_vertices=bodies.rest_vertices[person.phenotype],
                body_from_world=body_from_world,
                outfit=texture.Outfit.from_rng(rng),
            )
        )
    if dress_alike:
        if len(people) < 2:
            raise ValueError("dress_alike needs at least two people")
        first, second = people[0].outfit, people[1].outfit
        people[1] = replace(
            people[1],
            outfit=replace(first, skin=second.skin, hair=second.hair),
        )
    meshes = backdrop + [(p.vertices_world, p.faces) for p in people]
    scene = raycast.build_scene(meshes)
    return World(
        backdrop=layout.backdrop,
        people=tuple(people),
        scene=scene,
        normals=tuple(_vertex_normals(v, f) for v, f in meshes),
        seed=texture.TextureSeed.from_rng(rng),
        part_names=bodies.part_names,
        face_part=bodies.face_part,
    )


def _shade(
    world: World,
    points: FloatArray,
    dirs: FloatArray,
    geom: IndexArray,
    face: IndexArray,
    bary: FloatArray,
) -> FloatArray:
    """RGB in [0, 1] (N, 3) of hit points, Lambert + ambient + floor shadows."""
    n = len(points)
    albedo = np.zeros((n, 3))
    normal = np.zeros((n, 3))
    for g in np.unique(geom):  # loop over meshes, vectorized over their pixels
        sel = geom == g
        f = world.scene.faces[g][face[sel]]
        nrm = np.einsum("nk,nkd->nd", bary[sel], world.normals[g][f])
        normal[sel] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
        if g in (FLOOR, WALLS):
            if world.backdrop is Backdrop.ROOM:
                albedo[sel] = texture.room_surface(world.seed, points[sel], normal[sel])
            elif g == FLOOR:
                albedo[sel] = texture.dome_floor(world.seed, points[sel])
            else:
                albedo[sel] = texture.dome_surface(
                    world.seed, points[sel], bary[sel], face[sel]
                )
        else:
            person = world.people[g - FIRST_PERSON]
            rest = raycast.surface_points(
                person.rest_vertices, person.faces, face[sel], bary[sel]
            )
            albedo[sel] = texture.clothing(
                world.seed,
                person.outfit,
                rest,
                world.part_names,
                world.face_part[face[sel]],
            )
    # Two-sided lighting: flip normals that face away from the viewer.
    facing = np.einsum("nd,nd->n", normal, dirs) > 0
    normal[facing] *= -1
    lambert = np.clip(normal @ LIGHT_DIR, 0.0, 1.0)
    # Shadows of the people on the floor: one shadow ray per floor pixel.
    on_floor = np.flatnonzero(geom == FLOOR)
    if len(on_floor) and world.people:
        o = points[on_floor] + 1e-4 * LIGHT_DIR
        g2, _, _, _ = raycast.first_hits(
            world.scene, o, np.broadcast_to(LIGHT_DIR, o.shape).copy()
        )
        lambert[on_floor[g2 >= FIRST_PERSON]] *= 0.25
    light = 0.45 + 0.65 * lambert
    return np.clip(albedo * light[:, None], 0.0, 1.0)


def render_view(
    world: World, camera: CameraSpec, rng: np.random.Generator, noise_sigma: float = 1.5
) -> RenderedView:
    """Render one camera's image and its per-pixel surface record."""
    cam = pycolmap.Camera(
        model=camera.model,
        width=camera.width,
        height=camera.height,
        params=camera.params,
    )
    xy = raycast.pixel_grid(camera.width, camera.height)
    origins, dirs = raycast.rays_world(cam, camera.cam_from_world, xy)
    geom, face, depth, bary = raycast.first_hits(world.scene, origins, dirs)
    hit = geom >= 0
    rgb = np.full((len(xy), 3), 0.6)  # nothing: neutral grey (never seen in practice)
    points = origins[hit] + depth[hit, None] * dirs[hit]
    rgb[hit] = _shade(world, points, dirs[hit], geom[hit], face[hit], bary[hit])
    shape = (camera.height, camera.width)
    image = rgb.reshape(*shape, 3)
    # Optics and sensor: a slight blur (anti-aliasing) and Gaussian read noise.
    image = cv2.GaussianBlur(image, (0, 0), 0.6)
    image = image * 255.0 + rng.normal(0.0, noise_sigma, image.shape)
    return RenderedView(
        image=np.clip(image, 0, 255).astype(np.uint8),
        geom_idx=geom.reshape(shape),
        face_idx=face.reshape(shape),
        bary=raycast.inside_face(bary, hit).reshape(*shape, 3),
    )
