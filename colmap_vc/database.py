"""All access to the COLMAP database: read views, append virtual correspondences, strip.

The database stays in the schema of the COLMAP that made it (3.8 or pycolmap 4.x):
pycolmap's ``Database.open`` creates/migrates tables and switches the journal mode,
so every access goes through :mod:`sqlite3` with named columns, reads run with
``PRAGMA query_only`` and every write is one ``BEGIN IMMEDIATE`` transaction.
The contract (tables, what ``augment`` changes, ``strip``) is in docs/database.md.
"""

from __future__ import annotations

import hashlib
import json
import logging
import sqlite3
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from colmap_vc import __version__
from colmap_vc import database_schema as sch
from colmap_vc import database_write as dbw
from colmap_vc.database_access import (
    BUSY_TIMEOUT_S,
    COMMITTED,
    check_before_write,
    connect,
    require_intact,
    require_writable,
    snapshot,
    transaction,
)
from colmap_vc.database_schema import AssociationMethod, Schema
from colmap_vc.structs import (
    FloatArray,
    IndexArray,
    PairGeometry,
    PairVcMatches,
    VcKeypoints,
)

logger = logging.getLogger(__name__)

__all__ = [
    "BUSY_TIMEOUT_S",
    "COMMITTED",
    "AssociationMethod",
    "DatabaseViews",
    "PersonAssociation",
    "Schema",
    "StripSummary",
    "TwoViewGeometryRow",
    "WriteSummary",
    "check_before_write",
    "drop_classic_matches",
    "read_keypoints",
    "read_matches",
    "read_person_associations",
    "read_run_info",
    "read_two_view_geometries",
    "read_views",
    "read_virtual_correspondences",
    "require_writable",
    "snapshot",
    "strip",
    "table_checksums",
    "write_virtual_correspondences",
]


Pair = tuple[int, int]


@dataclass(frozen=True, kw_only=True, slots=True)
class DatabaseViews:
    """Images and cameras of a database; keypoint counts exclude colmap-vc's VCs."""

    schema: Schema
    image_ids: IndexArray  # (N,) int64, ascending
    image_names: tuple[str, ...]  # (N,)
    camera_ids: IndexArray  # (N,) int64
    cameras: dict[int, pycolmap.Camera]  # camera_id -> model, width, height, params
    num_keypoints: IndexArray  # (N,) int64, classic keypoints (0 without a row)
    num_vc_keypoints: IndexArray  # (N,) int64, VC rows appended by colmap-vc


@dataclass(frozen=True, kw_only=True, slots=True)
class TwoViewGeometryRow:
    """One ``two_view_geometries`` row (image_id1 < image_id2); None for NULL blobs."""

    image_id1: int
    image_id2: int
    inlier_matches: IndexArray  # (M, 2) int64 keypoint indices
    config: int  # pycolmap.TwoViewGeometryConfiguration value
    F: FloatArray | None  # (3, 3)
    E: FloatArray | None  # (3, 3)
    H: FloatArray | None  # (3, 3)
    qvec_wxyz: FloatArray | None  # (4,) rotation of cam2_from_cam1, w first
    tvec: FloatArray | None  # (3,)

    @property
    def cam2_from_cam1(self) -> FloatArray | None:
        """(3, 4) [R | t], or None when the row stores no relative pose."""
        if self.qvec_wxyz is None or self.tvec is None or not self.qvec_wxyz.any():
            return None  # 3.8's matcher stores an all-zero qvec: no pose
        w, x, y, z = self.qvec_wxyz
        rotation = pycolmap.Rotation3d(np.array([x, y, z, w])).matrix()
        return np.column_stack([rotation, self.tvec])


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonAssociation:
    """Person ``person_id1`` of image 1 is person ``person_id2`` of image 2."""

    image_id1: int
    image_id2: int
    person_id1: int
    person_id2: int
    method: AssociationMethod
    score: float


@dataclass(frozen=True, kw_only=True, slots=True)
class WriteSummary:
    """What :func:`write_virtual_correspondences` changed."""

    schema: Schema
    replaced_previous: bool  # an earlier colmap-vc write was stripped first
    num_images: int  # keypoints rows that got VC rows appended
    num_vc_keypoints: int
    num_descriptor_rows: int  # never-matching descriptor rows appended
    num_vcs: int
    num_vc_inliers: int
    pairs_touched: tuple[Pair, ...]
    num_matches_updated: int
    num_matches_inserted: int
    num_geometries_updated: int
    num_geometries_inserted: int


@dataclass(frozen=True, kw_only=True, slots=True)
class StripSummary:
    """What :func:`strip` restored."""

    had_vcs: bool
    num_keypoints_restored: int
    num_descriptors_restored: int
    num_matches_restored: int  # rows put back verbatim (deleted then re-inserted)
    num_matches_deleted: int  # rows colmap-vc had created
    num_geometries_restored: int
    num_geometries_deleted: int
    num_tables_dropped: int
    num_user_rows_kept: int  # rows changed after augment, kept by --force


# ---------------------------------------------------------------- connections


def _require_keypoints(conn: sqlite3.Connection, path: Path) -> None:
    """Refuse a database that feature extraction never saw (no keypoints rows).
    Empty rows pass: a database made for VCs alone (``synth --no-sift``)."""
    (num_rows,) = conn.execute("SELECT COUNT(*) FROM keypoints").fetchone()
    if num_rows == 0:
        raise ValueError(f"{path} has no keypoints: run feature extraction first")


def _vc_images(conn: sqlite3.Connection) -> dict[int, tuple[int, int]]:
    """image_id -> (num_classic_keypoints, num_vc_keypoints); {} if not augmented."""
    if "colmap_vc_images" not in sch.vc_table_names(conn):
        return {}
    rows = conn.execute(
        "SELECT image_id, num_classic_keypoints, num_vc_keypoints FROM colmap_vc_images"
    )
    return {image_id: (classic, vc) for image_id, classic, vc in rows}


def _pair_rows(
    conn: sqlite3.Connection, table: str, columns: str, include_vc: bool
) -> list[tuple[Any, ...]]:
    """Rows of matches/two_view_geometries, by default as they were before augment."""
    if include_vc or "colmap_vc_state" not in sch.vc_table_names(conn):
        return conn.execute(
            f"SELECT {columns} FROM {table} ORDER BY pair_id"
        ).fetchall()
    backup = sch.backup_table(table)
    return conn.execute(
        f"SELECT {columns} FROM {table} WHERE pair_id NOT IN "
        "(SELECT pair_id FROM colmap_vc_backup_pairs WHERE tbl = ?) "
        f"UNION ALL SELECT {columns} FROM {backup} ORDER BY pair_id",
        (table,),
    ).fetchall()


# ---------------------------------------------------------------- reading


def read_views(db_path: str | PathLike[str]) -> DatabaseViews:
    """Images, cameras and classic keypoint counts of a database."""
    path = Path(db_path)
    with connect(path, write=False) as (conn, schema):
        _require_keypoints(conn, path)
        images = conn.execute(
            "SELECT image_id, name, camera_id FROM images ORDER BY image_id"
        ).fetchall()
        cameras = {
            camera_id: pycolmap.Camera(
                camera_id=camera_id,
                model=pycolmap.CameraModelId(model),
                width=width,
                height=height,
                params=np.frombuffer(params, np.float64).copy(),
                has_prior_focal_length=bool(prior),
            )
            for camera_id, model, width, height, params, prior in conn.execute(
                "SELECT camera_id, model, width, height, params, prior_focal_length "
                "FROM cameras"
            )
        }
        num_rows = dict(conn.execute("SELECT image_id, rows FROM keypoints").fetchall())
        vc_images = _vc_images(conn)
    image_ids = np.array([row[0] for row in images], np.int64)
    num_vc = np.array([vc_images.get(i, (0, 0))[1] for i in image_ids], np.int64)
    num_all = np.array([num_rows.get(i, 0) for i in image_ids], np.int64)
    return DatabaseViews(
        schema=schema,
        image_ids=image_ids,
        image_names=tuple(row[1] for row in images),
        camera_ids=np.array([row[2] for row in images], np.int64),
        cameras=cameras,
        num_keypoints=num_all - num_vc,
        num_vc_keypoints=num_vc,
    )


def read_keypoints(
    db_path: str | PathLike[str], image_id: int, *, include_vc: bool = False
) -> FloatArray:
    """(N, 2) float64 keypoint positions, COLMAP pixel convention (as stored).

    ``include_vc=False`` returns the classic keypoints only (the rows before the VCs).
    """
    path = Path(db_path)
    with connect(path, write=False) as (conn, _):
        row = conn.execute(
            "SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (image_id,)
        ).fetchone()
        num_vc = _vc_images(conn).get(image_id, (0, 0))[1]
    if row is None:
        raise ValueError(
            f"image {image_id} has no keypoints in {path}: run feature extraction first"
        )
    num_rows, num_cols, data = row
    xy = np.frombuffer(data or b"", np.float32).reshape(num_rows, num_cols)[:, :2]
    return xy[: num_rows - (0 if include_vc else num_vc)].astype(np.float64)


def read_matches(
    db_path: str | PathLike[str],
    pairs: Iterable[Pair] | None = None,
    *,
    include_vc: bool = False,
) -> dict[Pair, IndexArray]:
    """Matches as (M, 2) int64 keypoint indices per pair.

    Without ``pairs``: every row, keyed (image_id1, image_id2) with id1 < id2. With
    ``pairs``: those keys as given; columns are swapped for id1 > id2 (COLMAP's
    convention) and a pair without a row maps to an empty (0, 2) array.
    ``include_vc=False`` reads the rows as they were before colmap-vc wrote.
    """
    with connect(db_path, write=False) as (conn, _):
        rows = _pair_rows(conn, "matches", "pair_id, rows, data", include_vc)
    stored = {
        sch.images_from_pair_id(pair_id): sch.decode_matches(data, num_rows)
        for pair_id, num_rows, data in rows
    }
    if pairs is None:
        return stored
    result: dict[Pair, IndexArray] = {}
    for image_id1, image_id2 in pairs:
        key = (min(image_id1, image_id2), max(image_id1, image_id2))
        matches = stored.get(key, np.zeros((0, 2), np.int64))
        result[(image_id1, image_id2)] = (
            matches[:, ::-1].copy() if image_id1 > image_id2 else matches
        )
    return result


def read_two_view_geometries(
    db_path: str | PathLike[str], *, include_vc: bool = False
) -> dict[Pair, TwoViewGeometryRow]:
    """Every ``two_view_geometries`` row, keyed (image_id1, image_id2), id1 < id2.

    ``include_vc=False`` reads the rows as they were before colmap-vc wrote.
    """
    columns = "pair_id, rows, data, config, F, E, H, qvec, tvec"
    with connect(db_path, write=False) as (conn, _):
        rows = _pair_rows(conn, "two_view_geometries", columns, include_vc)
    result: dict[Pair, TwoViewGeometryRow] = {}
    for pair_id, num_rows, data, config, f, e, h, qvec, tvec in rows:
        image_id1, image_id2 = sch.images_from_pair_id(pair_id)
        result[(image_id1, image_id2)] = TwoViewGeometryRow(
            image_id1=image_id1,
            image_id2=image_id2,
            inlier_matches=sch.decode_matches(data, num_rows),
            config=int(config),
            F=sch.decode_matrix(f, (3, 3)),
            E=sch.decode_matrix(e, (3, 3)),
            H=sch.decode_matrix(h, (3, 3)),
            qvec_wxyz=sch.decode_matrix(qvec, (4,)),
            tvec=sch.decode_matrix(tvec, (3,)),
        )
    return result


def read_virtual_correspondences(
    db_path: str | PathLike[str],
) -> tuple[list[VcKeypoints], list[PairVcMatches]]:
    """The VCs colmap-vc wrote, as written (indices relative to each VC block).

    Returns empty lists for a database colmap-vc has not augmented.
    """
    with connect(db_path, write=False) as (conn, _):
        vc_images = _vc_images(conn)
        if not vc_images:
            return [], []
        kp = sch.fetch_records(
            conn,
            "SELECT image_id, x, y, person_id, track_id FROM colmap_vc_keypoints "
            "ORDER BY image_id, point2D_idx",
            "image:i8 x:f8 y:f8 person:i8 track:i8",
        )
        pair_rows = conn.execute(
            "SELECT image_id1, image_id2, num_vcs FROM colmap_vc_pairs ORDER BY pair_id"
        ).fetchall()
        vc = sch.fetch_records(
            conn,
            "SELECT point2D_idx1, point2D_idx2, person_id, kind, x1, y1, z1, x2, y2, "
            "z2, a, b, is_inlier FROM colmap_vc_matches ORDER BY pair_id, vc_idx",
            "idx1:i8 idx2:i8 person:i8 kind:i8 x1:f8 y1:f8 z1:f8 x2:f8 y2:f8 z2:f8 "
            "a:f8 b:f8 inlier:?",
        )
    image_ids = sorted(vc_images)
    kp_blocks = np.split(kp, np.cumsum([vc_images[i][1] for i in image_ids])[:-1])
    keypoints = [
        VcKeypoints(
            image_id=image_id,
            xy_img=np.column_stack([block["x"], block["y"]]),
            person_id=block["person"].copy(),
            track_id=block["track"].copy(),
        )
        for image_id, block in zip(image_ids, kp_blocks, strict=True)
    ]
    vc_blocks = np.split(vc, np.cumsum([row[2] for row in pair_rows])[:-1])
    pairs = [
        PairVcMatches(
            image_id1=image_id1,
            image_id2=image_id2,
            idx1=block["idx1"] - vc_images[image_id1][0],
            idx2=block["idx2"] - vc_images[image_id2][0],
            person_id=block["person"].copy(),
            kind=block["kind"].copy(),
            points1_cam=np.column_stack([block["x1"], block["y1"], block["z1"]]),
            points2_cam=np.column_stack([block["x2"], block["y2"], block["z2"]]),
            a=block["a"].copy(),
            b=block["b"].copy(),
            is_inlier=block["inlier"].copy(),
        )
        for (image_id1, image_id2, _), block in zip(pair_rows, vc_blocks, strict=True)
    ]
    return keypoints, pairs


def read_person_associations(db_path: str | PathLike[str]) -> list[PersonAssociation]:
    """The person associations colmap-vc wrote ([] if none)."""
    with connect(db_path, write=False) as (conn, _):
        if "colmap_vc_person_pairs" not in sch.vc_table_names(conn):
            return []
        rows = conn.execute(
            "SELECT image_id1, image_id2, person_id1, person_id2, method, score "
            "FROM colmap_vc_person_pairs ORDER BY rowid"
        ).fetchall()
    return [
        PersonAssociation(
            image_id1=i1,
            image_id2=i2,
            person_id1=p1,
            person_id2=p2,
            method=AssociationMethod(method),
            score=score,
        )
        for i1, i2, p1, p2, method, score in rows
    ]


def table_checksums(db_path: str | PathLike[str]) -> dict[str, str]:
    """sha256 of every table's rows in rowid order: equal dicts = equal contents."""
    with connect(db_path, write=False) as (conn, _):
        checksums = {}
        for table in sch.table_names(conn):
            digest = hashlib.sha256()
            for row in conn.execute(f"SELECT * FROM {table} ORDER BY rowid"):
                digest.update(repr(row).encode())
            checksums[table] = digest.hexdigest()
    return checksums


# ---------------------------------------------------------------- writing


def write_virtual_correspondences(
    db_path: str | PathLike[str],
    keypoints: Sequence[VcKeypoints],
    pairs: Sequence[PairVcMatches],
    geometries: Mapping[Pair, PairGeometry],
    *,
    classic_inliers: Mapping[Pair, IndexArray] | None = None,
    persons: Sequence[PersonAssociation] | None = None,
    run_info: Mapping[str, Any] | None = None,
) -> WriteSummary:
    """Append VCs to a COLMAP database in one transaction, replacing earlier ones.

    Args:
        db_path: the user's database (COLMAP 3.8 or pycolmap 4.x schema, kept as is).
        keypoints: VC keypoints per image, appended after the image's keypoints.
        pairs: VCs per pair; ``idx1``/``idx2`` index the rows of ``keypoints``.
        geometries: verified geometry per pair (id1 < id2). Its pair's
            ``two_view_geometries`` row becomes classic inliers + VC inliers.
            Pairs in ``pairs`` without a geometry get their matches only.
        classic_inliers: (K, 2) classic inlier matches per pair, replacing the
            stored inliers of pairs in ``geometries`` (default: keep them).
        persons: person associations, stored for the record.
        run_info: JSON-serializable description of the run (options, inputs).
    """
    path = Path(db_path)
    classic_inliers = classic_inliers or {}
    by_image, by_pair = dbw.check_inputs(keypoints, pairs, geometries, classic_inliers)
    needed = set(by_image) | {i for pair in geometries for i in pair}
    counts = np.zeros(4, np.int64)
    num_desc = 0
    with connect(path, write=True) as (conn, schema), transaction(conn, path):
        require_intact(conn, path)
        _require_keypoints(conn, path)
        missing = needed - {
            row[0] for row in conn.execute("SELECT image_id FROM images")
        }
        if missing:
            raise ValueError(f"images {sorted(missing)} are not in {path}")
        try:
            replaced = dbw.strip_rows(conn)["had_vcs"]
        except ValueError as error:
            raise ValueError(
                f"{path}: cannot replace the earlier VCs: {error}"
            ) from error
        for ddl in sch.VC_TABLES_DDL:
            conn.execute(ddl)
        for table in sch.PAIR_TABLES:
            conn.execute(sch.backup_table_ddl(conn, table))
        num_classic = dict(conn.execute("SELECT image_id, rows FROM keypoints"))
        for image_id in sorted(by_image):
            num_desc += dbw.append_features(conn, path, by_image[image_id])
        empty = np.zeros((0, 2), np.int64)
        for pair in sorted(set(by_pair) | set(geometries)):
            vc = by_pair.get(pair)
            vc_matches = (
                empty
                if vc is None
                else np.column_stack(
                    [vc.idx1 + num_classic[pair[0]], vc.idx2 + num_classic[pair[1]]]
                )
            )
            vc_inliers = empty if vc is None else vc_matches[vc.is_inlier]
            counts += dbw.write_pair(
                conn,
                schema,
                pair,
                vc_matches,
                vc_inliers,
                geometries.get(pair),
                classic_inliers.get(pair),
                num_classic,
            )
        dbw.record_written_rows(conn)
        dbw.write_metadata(
            conn, by_image, by_pair, geometries, num_classic, persons or ()
        )
        state = {
            "format_version": str(sch.FORMAT_VERSION),
            "colmap_vc_version": __version__,
            "schema": str(schema),
            "run_info": json.dumps(dict(run_info or {}), sort_keys=True, default=str),
        }
        conn.executemany(
            "INSERT INTO colmap_vc_state (key, value) VALUES (?, ?)", state.items()
        )
    summary = WriteSummary(
        schema=schema,
        replaced_previous=replaced,
        num_images=sum(len(kp) > 0 for kp in by_image.values()),
        num_vc_keypoints=sum(len(kp) for kp in by_image.values()),
        num_descriptor_rows=num_desc,
        num_vcs=sum(len(vc) for vc in by_pair.values()),
        num_vc_inliers=sum(int(vc.is_inlier.sum()) for vc in by_pair.values()),
        pairs_touched=tuple(sorted(set(by_pair) | set(geometries))),
        num_matches_updated=int(counts[0]),
        num_matches_inserted=int(counts[1]),
        num_geometries_updated=int(counts[2]),
        num_geometries_inserted=int(counts[3]),
    )
    logger.info(
        "Wrote %d VC keypoints in %d images and %d VCs (%d inliers) in %d pairs to %s "
        "(COLMAP %s schema; matches rows %d updated/%d new, two-view geometries "
        "%d updated/%d new%s)",
        summary.num_vc_keypoints,
        summary.num_images,
        summary.num_vcs,
        summary.num_vc_inliers,
        len(summary.pairs_touched),
        path,
        schema,
        *counts.tolist(),
        ", replacing earlier VCs" if replaced else "",
    )
    return summary


def strip(db_path: str | PathLike[str], *, force: bool = False) -> StripSummary:
    """Remove colmap-vc's VCs: every COLMAP table as before the first augment.

    Raises ValueError (the database unchanged) when rows colmap-vc wrote were
    changed after augment (e.g. the user re-matched); ``force`` keeps those rows
    as the user left them, minus the matches that index VC keypoints.
    """
    path = Path(db_path)
    with connect(path, write=True) as (conn, _), transaction(conn, path):
        require_intact(conn, path)
        try:
            summary = StripSummary(**dbw.strip_rows(conn, force=force))
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from error
    logger.info(
        "Stripped %s: %d keypoints and %d descriptors rows restored, matches "
        "%d restored/%d removed, two-view geometries %d restored/%d removed",
        path,
        summary.num_keypoints_restored,
        summary.num_descriptors_restored,
        summary.num_matches_restored,
        summary.num_matches_deleted,
        summary.num_geometries_restored,
        summary.num_geometries_deleted,
    )
    return summary


def drop_classic_matches(db_path: str | PathLike[str]) -> int:
    """Delete every match and two-view geometry row (for a VC-only ablation copy).

    Refuses a database that already holds VCs (strip it first). Returns the number
    of pairs removed.
    """
    path = Path(db_path)
    with connect(path, write=True) as (conn, _), transaction(conn, path):
        if sch.vc_table_names(conn):
            raise ValueError(
                f"{path} holds colmap-vc VCs: strip it before dropping matches"
            )
        num = conn.execute("SELECT COUNT(*) FROM matches").fetchone()[0]
        conn.execute("DELETE FROM matches")
        conn.execute("DELETE FROM two_view_geometries")
    logger.info("dropped the classic matches of %d pairs from %s", num, path)
    return int(num)


def read_run_info(db_path: str | PathLike[str]) -> dict[str, Any]:
    """The run description `augment` recorded ({} for a database never augmented)."""
    path = Path(db_path)
    with connect(path, write=False) as (conn, _):
        if "colmap_vc_state" not in sch.vc_table_names(conn):
            return {}
        row = conn.execute(
            "SELECT value FROM colmap_vc_state WHERE key = 'run_info'"
        ).fetchone()
    return json.loads(row[0]) if row and row[0] else {}
