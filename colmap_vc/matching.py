"""Virtual correspondences between images, from per-image human priors.

The idea (DESIGN.md section 1): a point s of the body surface has, in every image, one
pixel whose ray passes through s, whether s is visible there or hidden behind the
front of the body. We find that pixel for a fixed set of template surface samples,
in every image, so one sample is one multi-view track:

1. Project s through the image's own predicted mesh: the mesh's 3D shape says which
   pixel's ray passes through s (all hits of the ray, not only the first).
2. Use the 2D evidence (dense surface map, 2D keypoints): first re-pose each mesh
   rigidly so its surface points project onto the map pixels that see them (PnP);
   then correct each sample's pixel through the body surface: the map pixels whose
   surface points are next to the first point the sample's ray meets on the body
   (the sample itself when visible, the front of the body when hidden) say where
   that point really is; their offset to its mesh projection is added. A point
   behind the body thus lands behind the pixel the map puts its front on, whatever
   the predicted depth, articulation or shape.
3. Consistency filters (as in the paper): map pixels whose mesh hit disagrees with the
   map by more than a tolerance in cm, or that fall outside the silhouette, are not
   used; samples without consistent support, or outside the silhouette, are dropped.
4. 2D keypoints (joint centres, inside the body) are observations too: the rays of one
   joint in two images meet at an invisible point.

Two images then share a virtual correspondence (VC) for every track both observe and
at least one sees directly: co-visible when both see it, virtual when one does.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from dataclasses import dataclass

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from . import raycast
from .structs import (
    BoolArray,
    FloatArray,
    HitKind,
    ImagePrior,
    IndexArray,
    PersonPrior,
)

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, slots=True)
class MatchingOptions:
    """Options of VC matching."""

    num_samples: int = 1000
    """Template surface samples per body topology (one track each). The verified
    pairs' rotation error does not fall with more of them: on the accuracy domes
    with realistic priors it stays at a median 75-81 deg (one person) and 18-22
    deg (three) from 250 to 2000 samples (bench/vc_samples.py), because the
    predicted mesh's own error, shared by all its samples, dominates. Ray casting,
    verification and the mapper's points grow linearly with them. 1000 (was
    2000): on the multi-view rows of docs/results.md, pose2sim and the 128- and
    256-image domes AUC@15 moved by -3.4 (dense, now 23/23 registered instead of
    22/23) to +1.6 points, the two-image pair rows (4 pairs per bin) both ways;
    half the cost (docs/scaling.md)."""
    consistency_tolerance_cm: float = 5.0
    """A map pixel is consistent when its map point and its mesh hit are this close."""
    visibility_tolerance_cm: float = 1.0
    """A sample is visible when the first hit of its ray is this close to it."""
    refit_pose: bool = True
    """Re-fit each mesh's rigid pose to the 2D evidence (dense-map pixels and 2D
    keypoints against their mesh points) by PnP (pycolmap LO-RANSAC + refinement)."""
    refit_max_error_px: float = 6.0
    """RANSAC threshold of that PnP, pixels."""
    refit_max_points: int = 1000
    """Map pixels used by the PnP at most (an even subsample)."""
    snap_tolerance_cm: float = 6.0
    """A sample's front surface point is found in the dense map when a consistent
    map pixel's surface point lies within this distance on the body."""
    snap_neighbours: int = 16
    """Map pixels (nearest on the body, within the tolerance) averaged for the 2D
    correction of one sample."""
    max_correction_px: float = 25.0
    """Samples whose 2D correction is larger are dropped (mesh and map disagree)."""
    use_dense_map: bool = True
    """Use the dense surface maps when the priors have them."""
    use_keypoints: bool = True
    """Use 2D keypoints (joint centres) as VCs."""
    use_surface_samples: bool = True
    """Use the body-surface samples (off: keypoints only, the keypoint baseline)."""
    people_occlude: bool = True
    """People hide each other (off when the people of one image come from different
    instants of a static camera, see docs/real-data.md)."""
    use_mask: bool = True
    """Drop samples outside the person's silhouette when the priors have one."""


@dataclass(frozen=True, kw_only=True, slots=True)
class TemplateSamples:
    """Fixed surface samples of a body topology: (face, barycentric) pairs."""

    key: str  # template name, or a hash of the faces
    face_idx: IndexArray  # (S,) int64
    bary: FloatArray  # (S, 3) float64


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonObservations:
    """The tracks one person's prior gives in one image.

    ``point_cam`` is where the track's rays meet according to this image's mesh
    (the sample or the joint), ``first_hit_cam`` is the first hit of the ray on this
    person's mesh (X1/X2 of the GBA); NaN when the ray misses the mesh.
    """

    person_index: int  # index in ImagePrior.persons
    person_id: int  # the prior's id, or -1
    template: str
    track_id: IndexArray  # (T,) int64: sample index, or num_samples + joint index
    xy_img: FloatArray  # (T, 2)
    is_visible: BoolArray  # (T,) seen directly (keypoints: False)
    is_keypoint: BoolArray  # (T,)
    point_cam: FloatArray  # (T, 3)
    first_hit_cam: FloatArray  # (T, 3)

    def __len__(self) -> int:
        return int(self.track_id.shape[0])


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonMatches:
    """VCs between one person in image 1 and one person in image 2."""

    idx1: IndexArray  # (M,) rows of the person's observations in image 1
    idx2: IndexArray  # (M,)
    kind: IndexArray  # (M,) HitKind
    track_id: IndexArray  # (M,)

    def __len__(self) -> int:
        return int(self.idx1.shape[0])


def template_key(person: PersonPrior) -> str:
    """The topology a person's mesh uses: its template name or a hash of its faces."""
    if person.template:
        return person.template
    # tobytes(): the bytes of the buffer (C order), which mypy accepts on Python 3.11,
    # where numpy's stubs give ndarray no __buffer__.
    digest = hashlib.sha1(
        np.ascontiguousarray(person.faces, dtype=np.int64).tobytes()
    ).hexdigest()
    return f"faces:{digest[:12]}"


def sample_template(
    vertices: FloatArray, faces: IndexArray, key: str, num_samples: int = 2000
) -> TemplateSamples:
    """Evenly spread surface samples of a topology, from one reference mesh.

    Area-weighted random points (seeded), thinned by farthest-point sampling; the
    samples are (face, barycentric), so they name the same body points on every mesh
    of the topology.
    """
    rng = np.random.default_rng(0)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(
        np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1
    )
    num_candidates = 10 * num_samples
    face = rng.choice(len(faces), size=num_candidates, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(num_candidates)), rng.random(num_candidates)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
    points = np.einsum("nk,nkd->nd", bary, tri[face])
    chosen = np.zeros(num_samples, dtype=np.int64)
    dist = np.full(num_candidates, np.inf)
    for i in range(
        1, num_samples
    ):  # loop over samples (2000), vectorized over candidates
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[i - 1]], axis=1))
        chosen[i] = int(np.argmax(dist))
    return TemplateSamples(
        key=key, face_idx=face[chosen].astype(np.int64), bary=bary[chosen]
    )


def _in_image(xy: FloatArray, camera: pycolmap.Camera) -> BoolArray:
    return (
        np.isfinite(xy).all(axis=1)
        & (xy[:, 0] >= 0)
        & (xy[:, 1] >= 0)
        & (xy[:, 0] < camera.width)
        & (xy[:, 1] < camera.height)
    )


def refit_mesh_pose(
    person: PersonPrior, camera: pycolmap.Camera, options: MatchingOptions
) -> tuple[FloatArray, int]:
    """Vertices (V, 3) moved rigidly so the mesh projects onto the 2D evidence.

    Mesh-recovery networks get the 3D orientation wrong by about 10 degrees while the
    dense map and 2D keypoints say precisely where body points are in the image. Each
    map pixel (and keypoint) gives a 2D-3D correspondence with its point on the mesh;
    their robust PnP re-poses the mesh. Returns the vertices and the number of PnP
    inliers (0: the mesh was kept as predicted).
    """
    verts, faces = person.vertices_cam, person.faces
    xy_parts, xyz_parts = [], []
    if (
        options.use_dense_map
        and person.surface_map is not None
        and len(person.surface_map)
    ):
        sm = person.surface_map
        step = max(1, len(sm) // options.refit_max_points)
        xy_parts.append(sm.xy_img[::step])
        xyz_parts.append(
            raycast.surface_points(verts, faces, sm.face_idx[::step], sm.bary[::step])
        )
    if (
        options.use_keypoints
        and person.keypoints_xy is not None
        and person.keypoints_cam is not None
    ):
        valid = (
            np.ones(len(person.keypoints_xy), dtype=bool)
            if person.keypoints_valid is None
            else person.keypoints_valid
        )
        xy_parts.append(person.keypoints_xy[valid])
        xyz_parts.append(person.keypoints_cam[valid])
    if not xy_parts or sum(len(x) for x in xy_parts) < 12:
        return verts, 0
    xy = np.concatenate(xy_parts)
    xyz = np.concatenate(xyz_parts)
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = options.refit_max_error_px
    estimation.ransac.random_seed = 0
    result = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, camera, estimation)
    if result is None:
        return verts, 0
    T = result["cam_from_world"].matrix()  # "world" = the predicted camera frame
    num_inliers = int(np.sum(result["inlier_mask"]))
    if num_inliers < 0.3 * len(xy):
        return verts, 0
    return verts @ T[:, :3].T + T[:, 3], num_inliers


def refit_image_prior(
    prior: ImagePrior, camera: pycolmap.Camera, options: MatchingOptions
) -> ImagePrior:
    """The image's priors with every mesh re-posed by :func:`refit_mesh_pose`."""
    if not options.refit_pose:
        return prior
    persons = tuple(
        dataclasses.replace(p, vertices_cam=refit_mesh_pose(p, camera, options)[0])
        for p in prior.persons
    )
    return dataclasses.replace(prior, persons=persons)


def observe_person(
    prior: ImagePrior,
    person_index: int,
    camera: pycolmap.Camera,
    samples: TemplateSamples,
    options: MatchingOptions | None = None,
    others: raycast.MeshScene | None = None,
) -> PersonObservations:
    """Tracks of one person in one image (see the module docstring).

    The meshes are used as given: call :func:`refit_image_prior` first to re-pose
    them to the 2D evidence.

    Args:
        prior: the image's priors.
        person_index: which person of ``prior.persons``.
        camera: the image's camera (COLMAP model, distortion included).
        samples: the template surface samples of the person's topology.
        options: matching options.
        others: all people's meshes of the image (mesh k = person k), to tell samples
            hidden by another person; None when the person is alone.
    """
    options = options or MatchingOptions()
    person = prior.persons[person_index]
    verts, faces = person.vertices_cam, person.faces
    own = raycast.build_scene([(verts, faces)])
    tol_vis = options.visibility_tolerance_cm / 100.0
    tol_con = options.consistency_tolerance_cm / 100.0

    # 1. Samples through the mesh: pixel, visibility, first hit on the own mesh.
    points = raycast.surface_points(verts, faces, samples.face_idx, samples.bary)
    xy = np.full((len(points), 2), np.nan)
    front = points[:, 2] > 1e-6
    xy[front] = camera.img_from_cam(points[front], check_cheirality=False)
    keep = _in_image(xy, camera)
    xy_k = xy[keep]
    dirs = raycast.rays_cam(camera, xy_k)
    origins = np.zeros_like(dirs)
    _, face1, depth1, bary1 = raycast.first_hits(own, origins, dirs)
    first_hit = np.full((len(xy_k), 3), np.nan)
    hit = face1 >= 0
    first_hit[hit] = raycast.surface_points(verts, faces, face1[hit], bary1[hit])
    dist_to_point = np.linalg.norm(points[keep], axis=1)
    visible = hit & (np.abs(depth1 - dist_to_point) < tol_vis)
    if others is not None:
        geom_o, _, depth_o, _ = raycast.first_hits(others, origins, dirs)
        hidden_by_other = (
            (geom_o >= 0)
            & (geom_o != person_index)
            & (depth_o < dist_to_point - tol_vis)
        )
        visible &= ~hidden_by_other

    # 2.-3. Dense-map correction through the body surface, with consistency filters.
    # The sample's ray meets the body first at `first_hit` (the sample itself when
    # visible, the front of the body when hidden). Map pixels whose surface point
    # is next to that front point on the body say where it really is in the image:
    # their offset to the mesh projection corrects the sample's pixel.
    if not options.use_surface_samples:
        keep[:] = False
        xy_k, visible, first_hit = xy_k[:0], visible[:0], first_hit[:0]
    idx = np.flatnonzero(keep)
    if (
        options.use_dense_map
        and person.surface_map is not None
        and len(person.surface_map)
        and len(idx)
    ):
        sm = person.surface_map
        map_points = raycast.surface_points(verts, faces, sm.face_idx, sm.bary)
        map_xy = np.full((len(sm), 2), np.nan)
        ok = map_points[:, 2] > 1e-6
        map_xy[ok] = camera.img_from_cam(map_points[ok], check_cheirality=False)
        d = raycast.rays_cam(camera, sm.xy_img)
        _, f_m, _, b_m = raycast.first_hits(own, np.zeros_like(d), d)
        mesh_hit = np.full((len(sm), 3), np.nan)
        on_mesh = f_m >= 0
        mesh_hit[on_mesh] = raycast.surface_points(
            verts, faces, f_m[on_mesh], b_m[on_mesh]
        )
        # Consistency: the map's surface point and the mesh's hit at the pixel agree
        # (front/back and left/right flips fail this), inside the silhouette.
        consistent = (
            ok & on_mesh & (np.linalg.norm(mesh_hit - map_points, axis=1) < tol_con)
        )
        if options.use_mask and person.mask is not None:
            px = np.floor(sm.xy_img).astype(np.int64)
            consistent &= person.mask[px[:, 1], px[:, 0]]
        good = np.zeros(len(xy_k), dtype=bool)
        correction = np.zeros_like(xy_k)
        if consistent.any() and hit.any():
            tree = cKDTree(map_points[consistent])
            offsets = (sm.xy_img - map_xy)[consistent]
            k = min(options.snap_neighbours, int(consistent.sum()))
            dist, nn = tree.query(
                np.nan_to_num(first_hit, nan=1e9),
                k=k,
                distance_upper_bound=options.snap_tolerance_cm / 100.0,
            )
            dist, nn = dist.reshape(len(xy_k), k), nn.reshape(len(xy_k), k)
            found = np.isfinite(dist)
            num = found.sum(axis=1)
            safe_nn = np.where(found, nn, 0)
            correction = (offsets[safe_nn] * found[..., None]).sum(axis=1) / np.maximum(
                num, 1
            )[:, None]
            good = (num > 0) & (
                np.linalg.norm(correction, axis=1) <= options.max_correction_px
            )
        xy_k = xy_k + correction
        sel = good & _in_image(xy_k, camera)
        idx, xy_k, visible, first_hit = (
            idx[sel],
            xy_k[sel],
            visible[sel],
            first_hit[sel],
        )
    if options.use_mask and person.mask is not None and len(xy_k):
        px = np.floor(xy_k).astype(np.int64)
        sel = person.mask[px[:, 1], px[:, 0]]
        idx, xy_k, visible, first_hit = (
            idx[sel],
            xy_k[sel],
            visible[sel],
            first_hit[sel],
        )

    track = idx
    point_cam = points[idx]
    is_kp = np.zeros(len(idx), dtype=bool)
    # 4. Keypoints: joint centres, whose rays meet inside the body.
    if (
        options.use_keypoints
        and person.keypoints_xy is not None
        and person.keypoints_cam is not None
    ):
        valid = (
            np.ones(len(person.keypoints_xy), dtype=bool)
            if person.keypoints_valid is None
            else person.keypoints_valid.copy()
        )
        valid &= _in_image(person.keypoints_xy, camera)
        j = np.flatnonzero(valid)
        kd = raycast.rays_cam(camera, person.keypoints_xy[j])
        _, fk, _, bk = raycast.first_hits(own, np.zeros_like(kd), kd)
        kp_hit = np.full((len(j), 3), np.nan)
        kp_hit[fk >= 0] = raycast.surface_points(verts, faces, fk[fk >= 0], bk[fk >= 0])
        track = np.r_[track, len(samples.face_idx) + j]
        xy_k = np.r_[xy_k, person.keypoints_xy[j]]
        visible = np.r_[visible, np.zeros(len(j), dtype=bool)]
        is_kp = np.r_[is_kp, np.ones(len(j), dtype=bool)]
        point_cam = np.r_[point_cam, person.keypoints_cam[j]]
        first_hit = np.r_[first_hit, kp_hit]
    return PersonObservations(
        person_index=person_index,
        person_id=-1 if person.person_id is None else int(person.person_id),
        template=samples.key,
        track_id=track.astype(np.int64),
        xy_img=xy_k,
        is_visible=visible,
        is_keypoint=is_kp,
        point_cam=point_cam,
        first_hit_cam=first_hit,
    )


def match_persons(obs1: PersonObservations, obs2: PersonObservations) -> PersonMatches:
    """VCs between two observations of (what is taken to be) the same person.

    A track both observe is a VC when at least one image sees it directly, or when it
    is a keypoint: co-visible if both see it, virtual if one does.
    """
    if obs1.template != obs2.template:
        empty = np.zeros(0, dtype=np.int64)
        return PersonMatches(idx1=empty, idx2=empty, kind=empty, track_id=empty)
    tracks, i1, i2 = np.intersect1d(obs1.track_id, obs2.track_id, return_indices=True)
    v1, v2 = obs1.is_visible[i1], obs2.is_visible[i2]
    kp = obs1.is_keypoint[i1] & obs2.is_keypoint[i2]
    keep = kp | v1 | v2
    kind = np.where(
        kp, HitKind.KEYPOINT, np.where(v1 & v2, HitKind.COVISIBLE, HitKind.VIRTUAL)
    )
    return PersonMatches(
        idx1=i1[keep].astype(np.int64),
        idx2=i2[keep].astype(np.int64),
        kind=kind[keep].astype(np.int64),
        track_id=tracks[keep].astype(np.int64),
    )
