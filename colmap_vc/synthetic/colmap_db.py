"""database.db of a synthetic scene: SIFT and exhaustive matches, or cameras only.

Both put the images in name order with one camera per image (the true intrinsics).
The database is new, so pycolmap writes it in its own schema; colmap_vc.database is
the door to databases the user made.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap

from .layout import CameraSpec

NUM_KEYPOINT_COLS = 6  # COLMAP 4.x keypoint rows: x, y and the affine shape a11..a22


def spec_camera(spec: CameraSpec, camera_id: int) -> pycolmap.Camera:
    """pycolmap camera of ``spec`` (its true intrinsics)."""
    return pycolmap.Camera(
        camera_id=camera_id,
        model=spec.model,
        width=spec.width,
        height=spec.height,
        params=spec.params,
    )


def build_sift_database(
    db_path: Path,
    image_dir: Path,
    cameras: Sequence[CameraSpec],
    *,
    max_num_features: int,
    num_threads: int,
) -> Path:
    """SIFT extraction with the known intrinsics, then exhaustive matching."""
    extraction = pycolmap.FeatureExtractionOptions(num_threads=num_threads)
    extraction.sift.max_num_features = max_num_features
    for spec in sorted(cameras, key=lambda c: c.name):
        reader = pycolmap.ImageReaderOptions(
            camera_model=spec.model,
            camera_params=",".join(f"{p:.17g}" for p in spec.params),
        )
        pycolmap.extract_features(
            db_path,
            image_dir,
            image_names=[spec.name],
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
    matching = pycolmap.FeatureMatchingOptions(num_threads=num_threads)
    pycolmap.match_exhaustive(
        db_path, matching_options=matching, device=pycolmap.Device.cpu
    )
    return db_path


def build_bare_database(db_path: Path, cameras: Sequence[CameraSpec]) -> Path:
    """Cameras and images as SIFT extraction would write them (a camera, trivial rig
    and frame per image), each image with an empty keypoints row and no descriptors
    or matches: ``colmap-vc augment`` appends its VCs to the empty rows."""
    with pycolmap.Database.open(db_path) as db, pycolmap.DatabaseTransaction(db):
        for spec in sorted(cameras, key=lambda c: c.name):
            camera = spec_camera(spec, 0)
            camera.has_prior_focal_length = True  # known, as the SIFT database says
            camera.camera_id = db.write_camera(camera)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(camera.sensor_id)
            rig_id = db.write_rig(rig)
            image = pycolmap.Image(name=spec.name, camera_id=camera.camera_id)
            image.image_id = db.write_image(image)
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(image.data_id)
            db.write_frame(frame)
            db.write_keypoints(
                image.image_id, np.zeros((0, NUM_KEYPOINT_COLS), np.float32)
            )
    return db_path
