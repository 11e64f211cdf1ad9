"""SQL and blob layouts of the COLMAP database, and colmap-vc's own tables in it.

Only :mod:`colmap_vc.database` imports this module. It holds what depends on the
COLMAP version (3.8 vs 4.x schema), the DDL of the ``colmap_vc_*`` tables and the
numpy <-> blob codecs, so that ``database.py`` is left with the transactions.
"""

from __future__ import annotations

import enum
import hashlib
import sqlite3

import numpy as np
import pycolmap

from colmap_vc.structs import IndexArray

FORMAT_VERSION = 1
MAX_NUM_IMAGES = 2147483647  # COLMAP's kMaxNumImages, base of the pair_id encoding
COLMAP_TABLES = ("cameras", "images", "keypoints", "matches", "two_view_geometries")
PAIR_TABLES = ("matches", "two_view_geometries")
FEATURE_TABLES = ("keypoints", "descriptors")
SIFT_DIM = 128
SIFT_VALUE = 255  # the two non-zero entries of a VC descriptor, see vc_descriptors()
CALIBRATED = 2
CALIBRATED_RIG = 9  # pycolmap 4.x only
MAX_CONFIG_3X = 8  # MULTIPLE, the last configuration COLMAP 3.8 knows


class Schema(enum.StrEnum):
    """Which COLMAP wrote the database (detected from its tables)."""

    COLMAP_3 = "3.x"  # Debian's COLMAP 3.8: no rigs/frames tables
    COLMAP_4 = "4.x"  # pycolmap 4.x: rigs, frames, frame_data, pose_priors


class AssociationMethod(enum.StrEnum):
    """How a person in one image was associated with a person in another."""

    ID = "id"  # the priors share a person identity
    GEOMETRIC = "geometric"  # chosen by the geometric verification score
    JOINT = "joint"  # solved jointly over all views (colmap_vc.association)


# colmap-vc's own tables. COLMAP ignores tables it does not know. The backup tables
# of matches/two_view_geometries get the columns of the COLMAP table at write time
# (untyped, so SQLite stores every value verbatim), see backup_table_ddl().
VC_TABLES_DDL = (
    """CREATE TABLE colmap_vc_state (key TEXT PRIMARY KEY NOT NULL, value TEXT)""",
    """CREATE TABLE colmap_vc_images (
        image_id INTEGER PRIMARY KEY NOT NULL, num_classic_keypoints INTEGER NOT NULL,
        num_vc_keypoints INTEGER NOT NULL)""",
    """CREATE TABLE colmap_vc_keypoints (
        image_id INTEGER NOT NULL, point2D_idx INTEGER NOT NULL, x REAL NOT NULL,
        y REAL NOT NULL, person_id INTEGER NOT NULL, track_id INTEGER NOT NULL,
        PRIMARY KEY (image_id, point2D_idx))""",
    """CREATE TABLE colmap_vc_pairs (
        pair_id INTEGER PRIMARY KEY NOT NULL, image_id1 INTEGER NOT NULL,
        image_id2 INTEGER NOT NULL, num_vcs INTEGER NOT NULL,
        num_vc_inliers INTEGER NOT NULL, has_geometry INTEGER NOT NULL)""",
    """CREATE TABLE colmap_vc_matches (
        pair_id INTEGER NOT NULL, vc_idx INTEGER NOT NULL, image_id1 INTEGER NOT NULL,
        image_id2 INTEGER NOT NULL, point2D_idx1 INTEGER NOT NULL,
        point2D_idx2 INTEGER NOT NULL, person_id INTEGER NOT NULL,
        kind INTEGER NOT NULL, track_id INTEGER NOT NULL, x1 REAL NOT NULL,
        y1 REAL NOT NULL, z1 REAL NOT NULL, x2 REAL NOT NULL, y2 REAL NOT NULL,
        z2 REAL NOT NULL, a REAL NOT NULL, b REAL NOT NULL,
        is_inlier INTEGER NOT NULL, PRIMARY KEY (pair_id, vc_idx))""",
    """CREATE TABLE colmap_vc_person_pairs (
        image_id1 INTEGER NOT NULL, image_id2 INTEGER NOT NULL,
        person_id1 INTEGER NOT NULL, person_id2 INTEGER NOT NULL,
        method TEXT NOT NULL, score REAL NOT NULL)""",
    """CREATE TABLE colmap_vc_backup_features (
        tbl TEXT NOT NULL, image_id INTEGER NOT NULL, num_rows INTEGER NOT NULL,
        num_bytes INTEGER NOT NULL, data_is_null INTEGER NOT NULL,
        sha256 TEXT NOT NULL, PRIMARY KEY (tbl, image_id))""",
    """CREATE TABLE colmap_vc_backup_pairs (
        tbl TEXT NOT NULL, pair_id INTEGER NOT NULL, existed INTEGER NOT NULL,
        written_sha256 TEXT, PRIMARY KEY (tbl, pair_id))""",
)
VC_MATCH_COLUMNS = (
    "pair_id, vc_idx, image_id1, image_id2, point2D_idx1, point2D_idx2, person_id, "
    "kind, track_id, x1, y1, z1, x2, y2, z2, a, b, is_inlier"
)


def _ddl_name(ddl: str) -> str:
    return ddl.split()[2]


def missing_vc_tables(conn: sqlite3.Connection) -> list[str]:
    """colmap-vc tables an augmented database must hold to be restored, but lacks."""
    present = set(table_names(conn))
    needed = [_ddl_name(ddl) for ddl in VC_TABLES_DDL]
    needed += [backup_table(table) for table in PAIR_TABLES]
    return [name for name in needed if name not in present]


def backup_table(table: str) -> str:
    """Name of the table holding verbatim copies of ``table``'s original rows."""
    return f"colmap_vc_backup_{table}"


def table_names(conn: sqlite3.Connection) -> list[str]:
    """Names of all tables, sorted."""
    rows = conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
    return sorted(row[0] for row in rows)


def vc_table_names(conn: sqlite3.Connection) -> list[str]:
    """Names of colmap-vc's own tables present in the database."""
    return [name for name in table_names(conn) if name.startswith("colmap_vc_")]


def column_names(conn: sqlite3.Connection, table: str) -> list[str]:
    """Column names of ``table`` in declaration order."""
    return [row[1] for row in conn.execute(f"PRAGMA table_info({table})")]


def detect_schema(tables: list[str]) -> Schema:
    """4.x databases have ``rigs`` and ``frames``; 3.x databases have neither."""
    return Schema.COLMAP_4 if {"rigs", "frames"} <= set(tables) else Schema.COLMAP_3


def backup_table_ddl(conn: sqlite3.Connection, table: str) -> str:
    """DDL of a backup table with ``table``'s columns, untyped (no conversions)."""
    return (
        f"CREATE TABLE {backup_table(table)} ({', '.join(column_names(conn, table))})"
    )


def config_for_schema(config: int, schema: Schema) -> int:
    """The two-view configuration to store: 3.8 knows no CALIBRATED_RIG (9)."""
    if schema is Schema.COLMAP_3 and config == CALIBRATED_RIG:
        return CALIBRATED  # a metric relative pose is a calibrated one for 3.8
    if config < 0 or (schema is Schema.COLMAP_3 and config > MAX_CONFIG_3X):
        raise ValueError(f"two-view configuration {config} unknown to COLMAP {schema}")
    return config


def pair_id_from_images(image_id1: int, image_id2: int) -> int:
    """COLMAP's pair_id (database.h): the smaller image id comes first."""
    lo, hi = min(image_id1, image_id2), max(image_id1, image_id2)
    return lo * MAX_NUM_IMAGES + hi


def images_from_pair_id(pair_id: int) -> tuple[int, int]:
    """Inverse of :func:`pair_id_from_images`: ``(image_id1, image_id2)``, id1 < id2."""
    return pair_id // MAX_NUM_IMAGES, pair_id % MAX_NUM_IMAGES


def fetch_records(conn: sqlite3.Connection, sql: str, fields: str) -> np.ndarray:
    """Rows of a query as a numpy record array; ``fields`` is "name:dtype ...".

    numpy converts the row tuples in C, so callers stay free of per-row loops.
    """
    dtype = [tuple(field.split(":")) for field in fields.split()]
    return np.array(conn.execute(sql).fetchall(), dtype=dtype)


def decode_matches(data: bytes | None, num_rows: int) -> IndexArray:
    """A matches blob (uint32, (M, 2) row-major) as (M, 2) int64."""
    if not num_rows:
        return np.zeros((0, 2), np.int64)
    return np.frombuffer(data or b"", np.uint32).reshape(num_rows, 2).astype(np.int64)


def encode_matches(matches: IndexArray) -> bytes:
    """(M, 2) indices as COLMAP's uint32 matches blob."""
    return np.ascontiguousarray(matches, np.uint32).tobytes()


def decode_matrix(data: bytes | None, shape: tuple[int, ...]) -> np.ndarray | None:
    """A float64 row-major blob (F, E, H, qvec, tvec), or None if NULL/empty."""
    if not data:
        return None
    return np.frombuffer(data, np.float64).reshape(shape).copy()


def encode_matrix(matrix: np.ndarray) -> bytes:
    """float64 row-major blob, as COLMAP stores F/E/H (transposed Eigen) and vectors."""
    return np.ascontiguousarray(matrix, np.float64).tobytes()


def vc_keypoint_rows(xy_img: np.ndarray, num_cols: int) -> bytes:
    """float32 keypoint rows for VC pixels, in the image's existing column layout.

    COLMAP's FeatureKeypoint: 2 cols (x, y); 4 cols (x, y, scale, orientation);
    6 cols (x, y, a11, a12, a21, a22) with the affine shape [[a11, a12], [a21, a22]].
    A VC is an isotropic keypoint of unit scale and zero orientation.
    """
    rows = np.zeros((xy_img.shape[0], num_cols), np.float32)
    rows[:, :2] = xy_img
    if num_cols == 4:
        rows[:, 2] = 1.0
    elif num_cols == 6:
        rows[:, 2] = rows[:, 5] = 1.0
    elif num_cols != 2:
        raise ValueError(f"keypoints with {num_cols} columns are not a COLMAP layout")
    return rows.tobytes()


def vc_descriptors(image_id: int, num_rows: int) -> bytes:
    """uint8 SIFT rows for VC keypoints that no SIFT matcher can pair with anything.

    Each image gets one code d: 255 at two dimensions (a, b), zero elsewhere,
    distinct for the first 8128 image ids. With COLMAP's default max_distance of
    0.7 rad (L2: 0.49 * 512**2) and descriptors r scaled to norm 512:
    - dot-product matching (3.8, 4.x brute force): r . d = 255 (r_a + r_b) <= 255**2
      * 2, so the angle is >= 1.05 rad for every uint8 r, and 1.32 rad between codes;
    - L2 matching (4.x index and guided): |r - d|**2 >= |r|**2 - 2 * 255**2, above the
      threshold for every r of norm > 508.43 (no entry clipped at 255), and
      2 * 255**2 > 0.49 * 512**2 between codes. All-zero rows would not do: two
      zero rows are at L2 distance 0, and 4.x guided matching then pairs VCs.
    """
    dim_a, dim_b = np.triu_indices(SIFT_DIM, 1)
    code = (image_id - 1) % dim_a.size
    row = np.zeros(SIFT_DIM, np.uint8)
    row[[dim_a[code], dim_b[code]]] = SIFT_VALUE
    return np.tile(row, (num_rows, 1)).tobytes()


def sha256(data: bytes | None) -> str:
    """Hex digest of a blob (NULL hashes like an empty blob)."""
    return hashlib.sha256(data or b"").hexdigest()


def pair_row_digest(conn: sqlite3.Connection, table: str, pair_id: int) -> str | None:
    """Digest of a matches/two_view_geometries row (None: no row), to tell later
    whether someone changed the row colmap-vc wrote."""
    row = conn.execute(
        f"SELECT rows, cols, data FROM {table} WHERE pair_id = ?", (pair_id,)
    ).fetchone()
    if row is None:
        return None
    return hashlib.sha256(f"{row[0]}:{row[1]}:".encode() + (row[2] or b"")).hexdigest()


def rotation_to_qvec_wxyz(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> unit quaternion (w, x, y, z), the order 3.8 and 4.x store."""
    x, y, z, w = pycolmap.Rotation3d(np.asarray(rotation, np.float64)).quat
    return np.array([w, x, y, z])
