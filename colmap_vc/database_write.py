"""The write transactions behind :mod:`colmap_vc.database` (only it imports this).

Every function here runs inside the caller's ``BEGIN IMMEDIATE`` transaction and
raises to roll it back; none commits.
"""

from __future__ import annotations

import logging
import sqlite3
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from colmap_vc import database_schema as sch
from colmap_vc.database_schema import AssociationMethod, Schema
from colmap_vc.structs import (
    HitKind,
    IndexArray,
    PairGeometry,
    PairVcMatches,
    VcKeypoints,
)

if TYPE_CHECKING:
    from colmap_vc.database import PersonAssociation

logger = logging.getLogger(__name__)
Pair = tuple[int, int]


def check_inputs(
    keypoints: Sequence[VcKeypoints],
    pairs: Sequence[PairVcMatches],
    geometries: Mapping[Pair, PairGeometry],
    classic_inliers: Mapping[Pair, IndexArray],
) -> tuple[dict[int, VcKeypoints], dict[Pair, PairVcMatches]]:
    """Validate what does not need the database; index keypoints and pairs."""
    by_image: dict[int, VcKeypoints] = {}
    for kp in keypoints:
        if kp.image_id in by_image:
            raise ValueError(f"VcKeypoints given twice for image {kp.image_id}")
        by_image[kp.image_id] = kp
    by_pair: dict[Pair, PairVcMatches] = {}
    kinds = np.array([kind.value for kind in HitKind])
    for vc in pairs:
        key = (vc.image_id1, vc.image_id2)
        if key in by_pair:
            raise ValueError(f"PairVcMatches given twice for pair {key}")
        for image_id, idx in ((vc.image_id1, vc.idx1), (vc.image_id2, vc.idx2)):
            if image_id not in by_image:
                raise ValueError(
                    f"pair {key} names image {image_id} without VcKeypoints"
                )
            if len(idx) and (idx.min() < 0 or idx.max() >= len(by_image[image_id])):
                raise ValueError(
                    f"pair {key}: VC keypoint index out of range [0, "
                    f"{len(by_image[image_id])}) of image {image_id}"
                )
        if not np.isin(vc.kind, kinds).all():
            raise ValueError(f"pair {key}: kind values not in {kinds.tolist()}")
        by_pair[key] = vc
    for (image_id1, image_id2), geometry in geometries.items():
        if image_id1 >= image_id2:
            raise ValueError(f"geometry key ({image_id1}, {image_id2}) needs id1 < id2")
        for name, shape in (
            ("F", (3, 3)),
            ("E", (3, 3)),
            ("H", (3, 3)),
            ("cam2_from_cam1", (3, 4)),
        ):
            if np.shape(getattr(geometry, name)) != shape:
                raise ValueError(
                    f"geometry {(image_id1, image_id2)}: {name} not {shape}"
                )
    for key, inliers in classic_inliers.items():
        if key not in geometries:
            raise ValueError(f"classic_inliers given for pair {key} without geometry")
        if inliers.ndim != 2 or inliers.shape[1] != 2:
            raise ValueError(f"classic_inliers[{key}] has shape {inliers.shape}")
    return by_image, by_pair


def backup_pair(conn: sqlite3.Connection, table: str, pair_id: int) -> bool:
    """Save ``table``'s row of ``pair_id`` verbatim (or that there was none)."""
    cols = ", ".join(sch.column_names(conn, table))
    copied = conn.execute(
        f"INSERT INTO {sch.backup_table(table)} ({cols}) "
        f"SELECT {cols} FROM {table} WHERE pair_id = ?",
        (pair_id,),
    ).rowcount
    conn.execute(
        "INSERT INTO colmap_vc_backup_pairs (tbl, pair_id, existed) VALUES (?, ?, ?)",
        (table, pair_id, copied),
    )
    return bool(copied)


def _append_rows(
    conn: sqlite3.Connection,
    table: str,
    image_id: int,
    old: tuple[int, bytes | None],
    new_rows: bytes,
    num_new: int,
) -> None:
    """Back up a keypoints/descriptors row's size and digest, then append rows.

    The old blob stays the prefix of the new one, so the backup needs no copy.
    """
    num_rows, data = old
    conn.execute(
        "INSERT INTO colmap_vc_backup_features (tbl, image_id, num_rows, num_bytes, "
        "data_is_null, sha256) VALUES (?, ?, ?, ?, ?, ?)",
        (table, image_id, num_rows, len(data or b""), data is None, sch.sha256(data)),
    )
    conn.execute(
        f"UPDATE {table} SET rows = ?, data = ? WHERE image_id = ?",
        (num_rows + num_new, (data or b"") + new_rows, image_id),
    )


def append_features(conn: sqlite3.Connection, path: Path, vc: VcKeypoints) -> int:
    """Append one image's VC keypoint and descriptor rows.

    Returns the number of descriptor rows appended (0 if left untouched).
    """
    image_id, num_new = vc.image_id, len(vc)
    row = conn.execute(
        "SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (image_id,)
    ).fetchone()
    if row is None:
        raise ValueError(
            f"image {image_id} has no keypoints in {path}: run feature extraction first"
        )
    num_rows, num_cols, data = row
    if not num_new:
        return 0
    new_rows = sch.vc_keypoint_rows(vc.xy_img, num_cols)
    _append_rows(conn, "keypoints", image_id, (num_rows, data), new_rows, num_new)
    has_type = "type" in sch.column_names(conn, "descriptors")  # 4.x only
    desc = conn.execute(
        f"SELECT rows, cols, data, {'type' if has_type else '0'} FROM descriptors "
        "WHERE image_id = ?",
        (image_id,),
    ).fetchone()
    if desc is None:  # nothing a matcher could pair
        return 0
    desc_rows, desc_cols, desc_data, desc_type = desc
    is_sift = desc_type == 0 and desc_cols == sch.SIFT_DIM  # type 0: SIFT in 4.x
    if not is_sift or desc_rows != num_rows or len(desc_data or b"") != desc_rows * 128:
        logger.warning(
            "Image %d: descriptors are not SIFT uint8 rows aligned with the "
            "keypoints; left untouched, so guided and vocab-tree matching will "
            "refuse this database until `colmap-vc strip`",
            image_id,
        )
        return 0
    new_desc = sch.vc_descriptors(image_id, num_new)
    _append_rows(
        conn, "descriptors", image_id, (desc_rows, desc_data), new_desc, num_new
    )
    return num_new


def write_pair(
    conn: sqlite3.Connection,
    schema: Schema,
    pair: Pair,
    vc_matches: IndexArray,
    vc_inliers: IndexArray,
    geometry: PairGeometry | None,
    classic: IndexArray | None,
    num_classic: Mapping[int, int],
) -> IndexArray:
    """Merge one pair's VC (inlier) matches into its rows.

    Returns (4,) counts: matches rows updated, inserted; geometries updated, inserted.
    """
    pair_id = sch.pair_id_from_images(*pair)
    counts = np.zeros(4, np.int64)
    if len(vc_matches):
        existed = backup_pair(conn, "matches", pair_id)
        row = conn.execute(
            "SELECT rows, data FROM matches WHERE pair_id = ?", (pair_id,)
        ).fetchone()
        old = sch.decode_matches(row[1], row[0]) if row else None
        merged = vc_matches if old is None else np.vstack([old, vc_matches])
        values = {
            "pair_id": pair_id,
            "rows": len(merged),
            "cols": 2,
            "data": sch.encode_matches(merged),
        }
        upsert(conn, "matches", values, existed)
        counts[0 if existed else 1] = 1
    if geometry is None:
        return counts
    existed = backup_pair(conn, "two_view_geometries", pair_id)
    if classic is None:
        row = conn.execute(
            "SELECT rows, data FROM two_view_geometries WHERE pair_id = ?", (pair_id,)
        ).fetchone()
        classic = sch.decode_matches(row[1], row[0]) if row else np.zeros((0, 2), int)
    limits = np.array([num_classic.get(pair[0], 0), num_classic.get(pair[1], 0)])
    if len(classic) and ((classic < 0).any() or (classic >= limits).any()):
        raise ValueError(f"classic inliers of pair {pair} exceed the keypoint counts")
    inliers = np.vstack([classic, vc_inliers]).astype(np.int64)
    values = {
        "pair_id": pair_id,
        "rows": len(inliers),
        "cols": 2,
        "data": sch.encode_matches(inliers),
        "config": sch.config_for_schema(int(geometry.config), schema),
        "F": sch.encode_matrix(geometry.F),
        "E": sch.encode_matrix(geometry.E),
        "H": sch.encode_matrix(geometry.H),
        "qvec": sch.encode_matrix(
            sch.rotation_to_qvec_wxyz(geometry.cam2_from_cam1[:, :3])
        ),
        "tvec": sch.encode_matrix(geometry.cam2_from_cam1[:, 3]),
    }
    upsert(conn, "two_view_geometries", values, existed)
    counts[2 if existed else 3] = 1
    return counts


def upsert(
    conn: sqlite3.Connection, table: str, values: dict[str, Any], existed: bool
) -> None:
    """UPDATE the named columns of an existing row (others, e.g. 4.x's camera1,
    stay as they are) or INSERT a new row with them."""
    if existed:
        assignments = ", ".join(f"{name} = :{name}" for name in values)
        conn.execute(
            f"UPDATE {table} SET {assignments} WHERE pair_id = :pair_id", values
        )
    else:
        names = ", ".join(values)
        placeholders = ", ".join(f":{name}" for name in values)
        conn.execute(f"INSERT INTO {table} ({names}) VALUES ({placeholders})", values)


def records(*columns: np.ndarray) -> list[tuple[Any, ...]]:
    """Rows for ``executemany``, assembled column-wise by numpy (no Python loop)."""
    if not len(columns[0]):
        return []
    rows: list[tuple[Any, ...]] = np.rec.fromarrays(list(columns)).tolist()
    return rows


def write_metadata(
    conn: sqlite3.Connection,
    by_image: Mapping[int, VcKeypoints],
    by_pair: Mapping[Pair, PairVcMatches],
    geometries: Mapping[Pair, PairGeometry],
    num_classic: Mapping[int, int],
    persons: Sequence[PersonAssociation],
) -> None:
    """Fill colmap_vc_images/_keypoints/_pairs/_matches/_person_pairs."""
    image_ids = sorted(by_image)
    conn.executemany(
        "INSERT INTO colmap_vc_images (image_id, num_classic_keypoints, "
        "num_vc_keypoints) VALUES (?, ?, ?)",
        [(i, num_classic[i], len(by_image[i])) for i in image_ids],
    )
    for image_id in image_ids:
        kp = by_image[image_id]
        conn.executemany(
            "INSERT INTO colmap_vc_keypoints (image_id, point2D_idx, x, y, person_id, "
            "track_id) VALUES (?, ?, ?, ?, ?, ?)",
            records(
                np.full(len(kp), image_id),
                num_classic[image_id] + np.arange(len(kp)),
                kp.xy_img[:, 0],
                kp.xy_img[:, 1],
                kp.person_id,
                kp.track_id,
            ),
        )
    for (image_id1, image_id2), vc in sorted(by_pair.items()):
        pair_id = sch.pair_id_from_images(image_id1, image_id2)
        conn.execute(
            "INSERT INTO colmap_vc_pairs (pair_id, image_id1, image_id2, num_vcs, "
            "num_vc_inliers, has_geometry) VALUES (?, ?, ?, ?, ?, ?)",
            (
                pair_id,
                image_id1,
                image_id2,
                len(vc),
                int(vc.is_inlier.sum()),
                (image_id1, image_id2) in geometries,
            ),
        )
        num = len(vc)
        conn.executemany(
            f"INSERT INTO colmap_vc_matches ({sch.VC_MATCH_COLUMNS}) "
            f"VALUES ({', '.join('?' * 18)})",
            records(
                np.full(num, pair_id),
                np.arange(num),
                np.full(num, image_id1),
                np.full(num, image_id2),
                vc.idx1 + num_classic[image_id1],
                vc.idx2 + num_classic[image_id2],
                vc.person_id,
                vc.kind,
                by_image[image_id1].track_id[vc.idx1],
                *vc.points1_cam.T,
                *vc.points2_cam.T,
                vc.a,
                vc.b,
                vc.is_inlier,
            ),
        )
    conn.executemany(
        "INSERT INTO colmap_vc_person_pairs (image_id1, image_id2, person_id1, "
        "person_id2, method, score) VALUES (?, ?, ?, ?, ?, ?)",
        [
            (
                p.image_id1,
                p.image_id2,
                p.person_id1,
                p.person_id2,
                str(AssociationMethod(p.method)),
                float(p.score),
            )
            for p in persons
        ],
    )


def record_written_rows(conn: sqlite3.Connection) -> None:
    """Store the digest of every pair row just written, for strip's check."""
    rows = conn.execute("SELECT tbl, pair_id FROM colmap_vc_backup_pairs").fetchall()
    conn.executemany(
        "UPDATE colmap_vc_backup_pairs SET written_sha256 = ? "
        "WHERE tbl = ? AND pair_id = ?",
        [(sch.pair_row_digest(conn, t, p), t, p) for t, p in rows],
    )


def _pair_names(conn: sqlite3.Connection, pair_ids: Sequence[int]) -> str:
    names = dict(conn.execute("SELECT image_id, name FROM images"))
    shown = [
        "-".join(str(names.get(i, i)) for i in sch.images_from_pair_id(p))
        for p in sorted(pair_ids)[:4]
    ]
    more = f" and {len(pair_ids) - 4} more" if len(pair_ids) > 4 else ""
    return ", ".join(shown) + more


def changes_since_write(conn: sqlite3.Connection) -> dict[tuple[str, str], list[int]]:
    """Rows of COLMAP tables someone changed after colmap-vc wrote them.

    Keys are (table, "changed" | "deleted"); values are pair ids (matches,
    two_view_geometries) or image ids (keypoints, descriptors). Databases augmented
    before colmap-vc recorded row digests report no pair changes.
    """
    changes: dict[tuple[str, str], list[int]] = {}
    backups = conn.execute(
        "SELECT tbl, image_id, num_bytes, data_is_null, sha256 "
        "FROM colmap_vc_backup_features ORDER BY tbl, image_id"
    ).fetchall()
    for table, image_id, num_bytes, is_null, digest in backups:
        row = conn.execute(
            f"SELECT data FROM {table} WHERE image_id = ?", (image_id,)
        ).fetchone()
        if row is None:
            changes.setdefault((table, "deleted"), []).append(image_id)
        elif sch.sha256(None if is_null else (row[0] or b"")[:num_bytes]) != digest:
            changes.setdefault((table, "changed"), []).append(image_id)
    if "written_sha256" in sch.column_names(conn, "colmap_vc_backup_pairs"):
        written = conn.execute(
            "SELECT tbl, pair_id, written_sha256 FROM colmap_vc_backup_pairs "
            "ORDER BY tbl, pair_id"
        ).fetchall()
        for table, pair_id, digest in written:
            now = sch.pair_row_digest(conn, table, pair_id)
            if now != digest:
                kind = "deleted" if now is None else "changed"
                changes.setdefault((table, kind), []).append(pair_id)
    return changes


def describe_changes(
    conn: sqlite3.Connection, changes: Mapping[tuple[str, str], list[int]]
) -> str:
    """One sentence per changed table, naming the first images or pairs."""
    parts = []
    for (table, kind), ids in sorted(changes.items()):
        if table in sch.PAIR_TABLES:
            parts.append(
                f"{table} rows of {len(ids)} pair(s) {kind} ({_pair_names(conn, ids)})"
            )
        else:
            names = dict(conn.execute("SELECT image_id, name FROM images"))
            shown = ", ".join(str(names.get(i, i)) for i in ids[:4])
            parts.append(f"{table} of {len(ids)} image(s) {kind} ({shown})")
    return "; ".join(parts)


def _drop_vc_matches(conn: sqlite3.Connection, table: str, pair_id: int) -> None:
    """Keep a user's row, without the matches that index VC keypoints."""
    num_classic = dict(
        conn.execute("SELECT image_id, num_classic_keypoints FROM colmap_vc_images")
    )
    image_id1, image_id2 = sch.images_from_pair_id(pair_id)
    rows, data = conn.execute(
        f"SELECT rows, data FROM {table} WHERE pair_id = ?", (pair_id,)
    ).fetchone()
    matches = sch.decode_matches(data, rows)
    limits = np.array(
        [num_classic.get(image_id1, 2**62), num_classic.get(image_id2, 2**62)]
    )
    kept = matches[(matches < limits).all(axis=1)]
    conn.execute(
        f"UPDATE {table} SET rows = ?, cols = 2, data = ? WHERE pair_id = ?",
        (len(kept), sch.encode_matches(kept), pair_id),
    )


def require_strippable(
    conn: sqlite3.Connection, *, force: bool = False
) -> Mapping[tuple[str, str], list[int]]:
    """The user's changes since augment; ValueError when strip cannot restore.

    Raises when colmap-vc's tables are incomplete, or (unless ``force``) when a row
    colmap-vc wrote was changed or deleted since. Only reads.
    """
    missing = sch.missing_vc_tables(conn)
    if missing:
        raise ValueError(
            "strip refused, nothing changed: colmap-vc's table(s) "
            f"{', '.join(missing)} are missing, so the rows from before augment "
            "cannot be restored exactly; restore the database from a backup, or "
            "re-create it with COLMAP (feature extraction and matching)"
        )
    changes = changes_since_write(conn)
    if changes and not force:
        raise ValueError(
            "strip refused, nothing changed: "
            + describe_changes(conn, changes)
            + " after colmap-vc augment. Restoring would overwrite them with the "
            "rows from before augment. `colmap-vc strip --force` keeps your rows "
            "instead (it only removes colmap-vc's VC matches from them; rows you "
            "deleted stay deleted, keypoints you re-extracted stay as they are)"
        )
    return changes


def strip_rows(conn: sqlite3.Connection, *, force: bool = False) -> dict[str, Any]:
    """Restore every row colmap-vc changed and drop its tables.

    Refuses (ValueError, nothing changed) when a row colmap-vc wrote was changed or
    deleted since; with ``force`` such rows stay as the user left them, minus the
    matches that index VC keypoints, and only untouched rows are restored.
    Returns the fields of :class:`colmap_vc.database.StripSummary`.
    """
    vc_tables = sch.vc_table_names(conn)
    restored = {"keypoints": 0, "descriptors": 0}
    moved = {table: (0, 0) for table in sch.PAIR_TABLES}
    num_kept = 0
    if "colmap_vc_state" in vc_tables:
        changes = require_strippable(conn, force=force)
        for (table, _kind), ids in changes.items():
            num_kept += len(ids)
            if table in sch.PAIR_TABLES:
                for pair_id in ids:
                    if _kind == "changed":
                        _drop_vc_matches(conn, table, pair_id)
                    conn.execute(
                        "DELETE FROM colmap_vc_backup_pairs WHERE tbl = ? AND "
                        "pair_id = ?",
                        (table, pair_id),
                    )
                    conn.execute(
                        f"DELETE FROM {sch.backup_table(table)} WHERE pair_id = ?",
                        (pair_id,),
                    )
            else:
                conn.executemany(
                    "DELETE FROM colmap_vc_backup_features WHERE tbl = ? AND "
                    "image_id = ?",
                    [(table, i) for i in ids],
                )
        backups = conn.execute(
            "SELECT tbl, image_id, num_rows, num_bytes, data_is_null "
            "FROM colmap_vc_backup_features ORDER BY tbl, image_id"
        ).fetchall()
        for table, image_id, num_rows, num_bytes, is_null in backups:
            data = conn.execute(
                f"SELECT data FROM {table} WHERE image_id = ?", (image_id,)
            ).fetchone()[0]
            original = None if is_null else (data or b"")[:num_bytes]
            conn.execute(
                f"UPDATE {table} SET rows = ?, data = ? WHERE image_id = ?",
                (num_rows, original, image_id),
            )
            restored[table] += 1
        for table in sch.PAIR_TABLES:
            backup = sch.backup_table(table)
            cols = ", ".join(sch.column_names(conn, backup))
            deleted = conn.execute(
                f"DELETE FROM {table} WHERE pair_id IN "
                "(SELECT pair_id FROM colmap_vc_backup_pairs WHERE tbl = ?)",
                (table,),
            ).rowcount
            reinserted = conn.execute(
                f"INSERT INTO {table} ({cols}) SELECT {cols} FROM {backup}"
            ).rowcount
            moved[table] = (reinserted, deleted - reinserted)
    for table in vc_tables:
        conn.execute(f"DROP TABLE {table}")
    return {
        "had_vcs": "colmap_vc_state" in vc_tables,
        "num_keypoints_restored": restored["keypoints"],
        "num_descriptors_restored": restored["descriptors"],
        "num_matches_restored": moved["matches"][0],
        "num_matches_deleted": moved["matches"][1],
        "num_geometries_restored": moved["two_view_geometries"][0],
        "num_geometries_deleted": moved["two_view_geometries"][1],
        "num_tables_dropped": len(vc_tables),
        "num_user_rows_kept": num_kept,
    }
