"""Same input, same output: a working copy of a database numbered by image name.

COLMAP numbers images (and cameras, rigs, frames) in the order feature extraction
wrote them, which a threaded extractor does not fix; pycolmap's mappers break ties
by those numbers (initial pair, next image, triangulation order), so the same images
extracted twice can give different models (pose2sim t050: AUC@15 73 in one order, 20
in another). ``map`` therefore maps a copy whose ids follow the image names, and
gives the models back with the user's ids (:func:`relabel`).

The copy holds cameras, rigs, frames, images, keypoints, descriptors, matches and
two-view geometries with inliers, written through pycolmap (which swaps a pair's
matches and inverts its geometry when the new ids reverse it; rejected pairs, with
no inliers, are not copied: mapping ignores them), and colmap-vc's own tables with
the ids mapped and reversed pairs turned the same way. A database with a
multi-camera rig or pose priors is mapped as it is (its ids are kept).
"""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

import pycolmap

from . import database_schema as sch

logger = logging.getLogger(__name__)

__all__ = ["IdMap", "canonical_copy", "relabel"]

IdMap = dict[int, int]  # canonical id -> the user's id


def _trivial_rigs(db: pycolmap.Database) -> bool:
    rigs, frames = db.read_all_rigs(), db.read_all_frames()
    return all(r.num_sensors() == 1 for r in rigs) and all(
        f.num_data_ids() == 1 for f in frames
    )


def canonical_copy(
    src: Path, dst: Path, *, reverse: bool = False
) -> tuple[IdMap, IdMap] | None:
    """Write ``dst``, ``src`` numbered in image-name order (``reverse``: the
    opposite order, which tests use to make a differently numbered database).

    ``src`` must be a working copy: pycolmap migrates what it opens. Returns
    (image ids, camera ids), each canonical -> ``src``'s, or None when ``src`` is
    kept as it is (a rig database, pose priors).
    """
    db = pycolmap.Database.open(str(src))
    try:
        if not _trivial_rigs(db) or db.num_pose_priors() > 0:
            logger.debug("%s: rigs or pose priors, ids kept", src)
            return None
        images = sorted(db.read_all_images(), key=lambda im: im.name, reverse=reverse)
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        new_camera: dict[int, int] = {}
        for image in images:  # cameras in the order of their first image's name
            new_camera.setdefault(image.camera_id, len(new_camera) + 1)
        new_image = {im.image_id: k + 1 for k, im in enumerate(images)}
        out = pycolmap.Database.open(str(dst))
        try:
            for old, new in sorted(new_camera.items(), key=lambda kv: kv[1]):
                camera = cameras[old]
                camera.camera_id = new
                out.write_camera(camera, use_camera_id=True)
                rig = pycolmap.Rig(rig_id=new)
                rig.add_ref_sensor(camera.sensor_id)
                out.write_rig(rig, use_rig_id=True)
            for image in images:  # loop over images: pycolmap writes one at a time
                old_id, new_id = image.image_id, new_image[image.image_id]
                cam = new_camera[image.camera_id]
                out.write_image(
                    pycolmap.Image(name=image.name, camera_id=cam, image_id=new_id),
                    use_image_id=True,
                )
                frame = pycolmap.Frame(frame_id=new_id, rig_id=cam)
                frame.add_data_id(
                    pycolmap.data_t(cameras[image.camera_id].sensor_id, new_id)
                )
                out.write_frame(frame, use_frame_id=True)
                if db.exists_keypoints(old_id):
                    out.write_keypoints(new_id, db.read_keypoints(old_id))
                if db.exists_descriptors(old_id):
                    out.write_descriptors(new_id, db.read_descriptors(old_id))
            pair_ids, matches = db.read_all_matches()
            for pair_id, m in zip(pair_ids, matches, strict=True):  # loop over pairs
                a, b = sch.images_from_pair_id(pair_id)
                out.write_matches(new_image[a], new_image[b], m)
            pair_ids, geometries = db.read_two_view_geometries()
            for pair_id, g in zip(pair_ids, geometries, strict=True):  # over pairs
                a, b = sch.images_from_pair_id(pair_id)
                out.write_two_view_geometry(new_image[a], new_image[b], g)
        finally:
            out.close()
    finally:
        db.close()
    _copy_vc_tables(src, dst, new_image)
    return (
        {new: old for old, new in new_image.items()},
        {new: old for old, new in new_camera.items()},
    )


def _copy_vc_tables(src: Path, dst: Path, new_image: dict[int, int]) -> None:
    """colmap-vc's tables (not the backups: nothing is stripped from a copy)."""
    conn = sqlite3.connect(dst)
    try:
        conn.execute("ATTACH DATABASE ? AS src", (f"{src}",))
        tables = "SELECT name FROM src.sqlite_master WHERE type = 'table'"
        present = {r[0] for r in conn.execute(tables)}
        if "colmap_vc_state" not in present:
            conn.execute("DETACH DATABASE src")
            return
        conn.execute("CREATE TEMP TABLE idmap (old INTEGER PRIMARY KEY, new INTEGER)")
        conn.executemany("INSERT INTO idmap VALUES (?, ?)", sorted(new_image.items()))
        for ddl in sch.VC_TABLES_DDL:
            if "colmap_vc_backup" not in ddl:
                conn.execute(ddl)
        big = 2147483647
        pair = f"MIN(m1.new, m2.new) * {big} + MAX(m1.new, m2.new)"  # new pair id
        swap = "(m1.new > m2.new)"  # the new ids reverse the pair

        def first(x: str, y: str) -> str:
            return f"CASE WHEN {swap} THEN {y} ELSE {x} END"

        join = (
            "JOIN idmap m1 ON m1.old = t.image_id1 JOIN idmap m2 ON m2.old = "
            "t.image_id2"
        )
        # A reversed VC: X1 and X2 exchange, and X2 = X1 + a (X1 - o1) + b (o2 - o1)
        # becomes X1 = X2 + a' (X2 - o2) + b' (o1 - o2) with a' = -a / (1 + a),
        # b' = (a + b) / (1 + a); its person is the one of image 2's keypoint.
        conn.executescript(
            f"""
            INSERT INTO colmap_vc_state SELECT * FROM src.colmap_vc_state
                ORDER BY key;
            INSERT INTO colmap_vc_images SELECT m.new, t.num_classic_keypoints,
                t.num_vc_keypoints FROM src.colmap_vc_images t
                JOIN idmap m ON m.old = t.image_id ORDER BY m.new;
            INSERT INTO colmap_vc_keypoints SELECT m.new, t.point2D_idx, t.x, t.y,
                t.person_id, t.track_id FROM src.colmap_vc_keypoints t
                JOIN idmap m ON m.old = t.image_id ORDER BY m.new, t.point2D_idx;
            INSERT INTO colmap_vc_pairs SELECT {pair}, MIN(m1.new, m2.new),
                MAX(m1.new, m2.new), t.num_vcs, t.num_vc_inliers, t.has_geometry
                FROM src.colmap_vc_pairs t {join} ORDER BY 1;
            INSERT INTO colmap_vc_matches SELECT {pair}, t.vc_idx,
                MIN(m1.new, m2.new), MAX(m1.new, m2.new),
                {first("t.point2D_idx1", "t.point2D_idx2")},
                {first("t.point2D_idx2", "t.point2D_idx1")},
                {first("t.person_id", "COALESCE(k2.person_id, t.person_id)")},
                t.kind, t.track_id,
                {first("t.x1", "t.x2")}, {first("t.y1", "t.y2")},
                {first("t.z1", "t.z2")}, {first("t.x2", "t.x1")},
                {first("t.y2", "t.y1")}, {first("t.z2", "t.z1")},
                {first("t.a", "-t.a / (1.0 + t.a)")},
                {first("t.b", "(t.a + t.b) / (1.0 + t.a)")}, t.is_inlier
                FROM src.colmap_vc_matches t {join}
                LEFT JOIN src.colmap_vc_keypoints k2 ON k2.image_id = t.image_id2
                    AND k2.point2D_idx = t.point2D_idx2
                ORDER BY 1, t.vc_idx;
            INSERT INTO colmap_vc_person_pairs SELECT MIN(m1.new, m2.new),
                MAX(m1.new, m2.new), {first("t.person_id1", "t.person_id2")},
                {first("t.person_id2", "t.person_id1")}, t.method, t.score
                FROM src.colmap_vc_person_pairs t {join} ORDER BY 1, 2, 3, 4;
            """
        )
        conn.commit()
        conn.execute("DETACH DATABASE src")
    finally:
        conn.close()


def relabel(
    rec: pycolmap.Reconstruction, images: IdMap, cameras: IdMap
) -> pycolmap.Reconstruction:
    """``rec`` (canonical ids) with the user's image and camera ids."""
    out = pycolmap.Reconstruction()
    for camera_id, camera in sorted(rec.cameras.items()):
        out.add_camera_with_trivial_rig(
            pycolmap.Camera(
                camera_id=cameras[camera_id],
                model=camera.model,
                width=camera.width,
                height=camera.height,
                params=camera.params,
            )
        )
    for image_id, image in sorted(rec.images.items()):  # loop over images
        new = pycolmap.Image(
            name=image.name,
            camera_id=cameras[image.camera_id],
            image_id=images[image_id],
            points2D=pycolmap.Point2DList(
                [pycolmap.Point2D(p.xy) for p in image.points2D]
            ),
        )
        if image.has_pose:
            out.add_image_with_trivial_frame(new, image.cam_from_world())
        else:  # its frame has no pose: not registered
            out.add_image_with_trivial_frame(new)
    for point in rec.points3D.values():  # loop over points: pycolmap adds one
        track = pycolmap.Track()
        for e in point.track.elements:
            track.add_element(images[e.image_id], e.point2D_idx)
        out.add_point3D(point.xyz, track, point.color)
    out.update_point_3d_errors()
    return out
