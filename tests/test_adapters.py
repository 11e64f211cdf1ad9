"""Adapters: weak/full-perspective mesh placement, faces files, DensePose IUV."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_vc import adapters, raycast
from colmap_vc.synthetic import bodies as body_lib

# Anny's body frame (+Z up, +Y forward) -> OpenCV axes of a body facing the camera.
TO_OPENCV = np.array([[-1.0, 0, 0], [0, 0, -1], [0, -1, 0]])


@pytest.fixture(scope="module")
def camera() -> pycolmap.Camera:
    return pycolmap.Camera(
        model="OPENCV",
        width=1920,
        height=1080,
        params=[1500.0, 1510.0, 950.0, 545.0, -0.02, 0.01, 0.001, -0.001],
    )


@pytest.fixture(scope="module")
def body() -> np.ndarray:
    """(V, 3) an Anny body, OpenCV axes, origin at the pelvis (a network's frame)."""
    model = body_lib.load_bodies()
    verts = body_lib.pose_body(model, 2, 1) @ TO_OPENCV.T
    return verts - body_lib.joints(model, verts)[0]


def _weak_perspective_fixture(
    body: np.ndarray, camera: pycolmap.Camera, t_true: np.ndarray, fit_to_points: bool
) -> tuple[np.ndarray, np.ndarray, float]:
    """pred_cam, bbox centre (OpenCV pixels) and size of the body placed at t_true."""
    xy = camera.img_from_cam(body + t_true)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    center, size = 0.5 * (lo + hi), 1.2 * float(np.max(hi - lo))
    half = 0.5 * size
    if fit_to_points:
        # What a network approximates: the weak-perspective camera that best
        # reproduces the projection, u = s (X + t) in crop units, by least squares.
        n = len(body)
        a = np.zeros((2 * n, 3))
        a[:n, 0], a[n:, 0] = body[:, 0], body[:, 1]
        a[:n, 1], a[n:, 2] = 1.0, 1.0
        b = np.concatenate(
            [(xy[:, 0] - center[0]) / half, (xy[:, 1] - center[1]) / half]
        )
        s, stx, sty = np.linalg.lstsq(a, b, rcond=None)[0]
        pred_cam = np.array([s, stx / s, sty / s])
    else:
        # Exact at the body origin: its pixel and the scale f / z there.
        focal = float(np.mean(camera.calibration_matrix()[[0, 1], [0, 1]]))
        s = focal / t_true[2] / half
        origin = camera.img_from_cam(t_true[None])[0]
        pred_cam = np.array([s, *((origin - center) / (half * s))])
    return pred_cam, center - 0.5, size  # COLMAP -> OpenCV pixels


def test_weak_perspective_places_the_origin_exactly(body, camera):
    t_true = np.array([0.4, -0.2, 6.0])
    pred_cam, center, size = _weak_perspective_fixture(body, camera, t_true, False)
    verts = adapters.vertices_from_weak_perspective(
        body, pred_cam, center, size, camera
    )
    np.testing.assert_allclose(verts, body + t_true, atol=1e-6)


@pytest.mark.parametrize("t_true", [[0.0, 0.3, 4.0], [-1.5, 0.5, 8.0], [0.8, 0.0, 3.5]])
def test_weak_perspective_fixture_round_trip(body, camera, t_true):
    t_true = np.array(t_true)
    pred_cam, center, size = _weak_perspective_fixture(body, camera, t_true, True)
    verts = adapters.vertices_from_weak_perspective(
        body, pred_cam, center, size, camera
    )
    xy_true = camera.img_from_cam(body + t_true)
    xy = camera.img_from_cam(verts)
    # Weak perspective ignores depth variation across the body: a few pixels and a
    # few percent of depth, no more.
    assert np.median(np.linalg.norm(xy - xy_true, axis=1)) < 0.015 * size
    assert np.abs(verts - (body + t_true)).mean(axis=0)[2] < 0.04 * t_true[2]


def test_opengl_axes_are_flipped(body, camera):
    t_true = np.array([0.4, -0.2, 6.0])
    pred_cam, center, size = _weak_perspective_fixture(body, camera, t_true, False)
    gl = body * [1.0, -1.0, -1.0]
    verts = adapters.vertices_from_weak_perspective(
        gl, pred_cam, center, size, camera, axes=adapters.Axes.OPENGL
    )
    np.testing.assert_allclose(verts, body + t_true, atol=1e-6)


def test_cam_t_with_the_network_pinhole(body, camera):
    t_true = np.array([-0.5, 0.2, 5.0])
    np.testing.assert_allclose(
        adapters.vertices_from_cam_t(body, t_true), body + t_true
    )
    # A network that assumed f = 5000 px and a centred principal point predicts the
    # translation that gives the same pixel and scale at the body origin.
    f_net, pp = 5000.0, np.array([959.5, 539.5])  # OpenCV pixels
    focal = float(np.mean(camera.calibration_matrix()[[0, 1], [0, 1]]))
    z_net = t_true[2] * f_net / focal
    origin = camera.img_from_cam(t_true[None])[0] - 0.5  # COLMAP -> OpenCV
    cam_t = np.array([*((origin - pp) * z_net / f_net), z_net])
    verts = adapters.vertices_from_cam_t(
        body, cam_t, camera, focal_px=f_net, principal_point_xy=pp
    )
    np.testing.assert_allclose(verts, body + t_true, atol=1e-6)


def test_bad_scale_is_an_error(body, camera):
    with pytest.raises(ValueError, match="must be positive"):
        adapters.vertices_from_weak_perspective(
            body, [0.0, 0, 0], [900, 500], 300, camera
        )


def test_load_faces_formats(tmp_path):
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    np.save(tmp_path / "f.npy", faces.astype(np.int32))
    np.savez(tmp_path / "f.npz", faces=faces)
    np.savez(tmp_path / "only.npz", whatever=faces)
    (tmp_path / "f.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 4/1\n"
    )
    for name in ("f.npy", "f.npz", "only.npz", "f.obj"):
        np.testing.assert_array_equal(adapters.load_faces(tmp_path / name), faces)
    with pytest.raises(FileNotFoundError):
        adapters.load_faces(tmp_path / "missing.npy")
    np.save(tmp_path / "bad.npy", np.zeros((3, 4)))
    with pytest.raises(ValueError, match=r"\(F, 3\) integers"):
        adapters.load_faces(tmp_path / "bad.npy")


# --- DensePose --------------------------------------------------------------------


def _cylinder(
    num_a: int = 32, num_h: int = 12, radius: float = 0.3, height: float = 1.0
):
    """A closed cylinder (the template) and its UV-unwrapped copy (DensePose-like).

    Parts: 1 side (chart u = angle, v = height; seam split at angle 0), 2 top cap,
    3 bottom cap (charts: the disc). Template faces list their corners rotated by
    f % 3 so that the UV -> template corner permutation is exercised.
    """
    ang = 2 * np.pi * np.arange(num_a) / num_a
    hs = np.linspace(-height / 2, height / 2, num_h)
    ring = np.stack([radius * np.cos(ang), np.zeros(num_a), radius * np.sin(ang)], 1)
    side = (ring[None] + hs[:, None, None] * [0.0, 1.0, 0.0]).reshape(-1, 3)
    verts = np.concatenate([side, [[0, -height / 2, 0], [0, height / 2, 0]]])
    top_c, bot_c = len(side), len(side) + 1
    # UV mesh: side grid with a duplicated seam column, then each cap's own vertices.
    uu, vv = np.meshgrid(np.arange(num_a + 1) / num_a, np.arange(num_h) / (num_h - 1))
    uv_side = np.stack([uu.ravel(), vv.ravel()], 1)
    to_t_side = (
        np.arange(num_h)[:, None] * num_a + np.arange(num_a + 1) % num_a
    ).ravel()

    def sid(h: np.ndarray, a: np.ndarray) -> np.ndarray:
        return h * (num_a + 1) + a

    h, a = np.meshgrid(np.arange(num_h - 1), np.arange(num_a), indexing="ij")
    h, a = h.ravel(), a.ravel()
    uv_faces = [
        np.stack([sid(h, a), sid(h + 1, a), sid(h + 1, a + 1)], 1),
        np.stack([sid(h, a), sid(h + 1, a + 1), sid(h, a + 1)], 1),
    ]
    parts = [np.ones(2 * len(h), np.int64)]
    uv_all, to_t = [uv_side], [to_t_side]
    for part, row, centre in ((2, 0, top_c), (3, num_h - 1, bot_c)):
        base = sum(len(x) for x in uv_all)
        disc = 0.5 + 0.45 * np.stack([np.cos(ang), np.sin(ang)], 1)
        uv_all += [disc, [[0.5, 0.5]]]
        to_t += [row * num_a + np.arange(num_a), [centre]]
        k = np.arange(num_a)
        uv_faces.append(
            np.stack(
                [np.full(num_a, base + num_a), base + k, base + (k + 1) % num_a], 1
            )
        )
        parts.append(np.full(num_a, part))
    uv_faces_a = np.concatenate(uv_faces)
    uv_a = np.concatenate(uv_all)
    to_t_a = np.concatenate([np.asarray(x) for x in to_t]).astype(np.int64)
    corners = to_t_a[uv_faces_a]
    roll = np.arange(len(corners)) % 3
    template_faces = corners[
        np.arange(len(corners))[:, None], (np.arange(3) + roll[:, None]) % 3
    ]
    return verts, template_faces, uv_faces_a, uv_a, np.concatenate(parts), to_t_a, roll


def test_uv_table_round_trip_through_an_iuv_image(camera, tmp_path):
    verts, faces, uv_faces, uv, part, to_t, roll = _cylinder()
    table = adapters.uv_table_from_uv_mesh(uv_faces, uv, part, to_t, faces)
    np.savez(tmp_path / "uv.npz", **table.arrays())
    table = adapters.load_uv_table(tmp_path / "uv.npz")
    # Render the ground-truth IUV image of the cylinder 3 m in front of the camera.
    c, s = np.cos(np.radians(35.0)), np.sin(np.radians(35.0))
    rot = np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])  # tilted: a cap shows
    verts_cam = verts @ rot.T + [0.2, 0.0, 3.0]
    xy = raycast.pixel_grid(camera.width, camera.height)
    dirs = raycast.rays_cam(camera, xy)
    scene = raycast.build_scene([(verts_cam, faces)])
    _, face, _, bary = raycast.first_hits(scene, np.zeros_like(dirs), dirs)
    hit = face >= 0
    assert set(np.unique(part[face[hit]])) == {1, 2}  # the side and the top cap
    # Template corner k of face f is UV corner (k + roll[f]) % 3 of the same face.
    uv_corner = uv[uv_faces[face[hit]]]  # (H, 3, 2) in UV corner order
    idx = (np.arange(3)[None] + roll[face[hit]][:, None]) % 3
    uv_hit = np.einsum(
        "nk,nkd->nd", bary[hit], np.take_along_axis(uv_corner, idx[..., None], 1)
    )
    shape = (camera.height, camera.width)
    i_img = np.zeros(shape, np.int64)
    u_img, v_img = np.zeros(shape), np.zeros(shape)
    i_img.ravel()[hit], u_img.ravel()[hit], v_img.ravel()[hit] = (
        part[face[hit]],
        *uv_hit.T,
    )
    # Through the 8-bit IUV image that DensePose writes.
    iuv = np.stack([i_img, np.round(u_img * 255), np.round(v_img * 255)], -1).astype(
        np.uint8
    )
    i2, u2, v2 = adapters.split_iuv_image(iuv)
    np.testing.assert_array_equal(i2, i_img)
    # A box crop of the arrays, as DensePose returns per detection.
    rows, cols = np.nonzero(i_img)
    r0, c0 = rows.min(), cols.min()
    crop = np.s_[r0 : rows.max() + 1, c0 : cols.max() + 1]
    sm = adapters.surface_map_from_iuv(
        i_img[crop], u_img[crop], v_img[crop], table, offset_xy=(c0, r0)
    )
    assert len(sm) == hit.sum()  # every foreground pixel found its surface point
    # The recovered surface point is the one the pixel's ray hits (to sample spacing).
    got = raycast.surface_points(verts_cam, faces, sm.face_idx, sm.bary)
    true_pts = np.full((len(xy), 3), np.nan)
    true_pts[hit] = raycast.surface_points(verts_cam, faces, face[hit], bary[hit])
    pix = (np.floor(sm.xy_img[:, 1]) * camera.width + np.floor(sm.xy_img[:, 0])).astype(
        int
    )
    err = np.linalg.norm(got - true_pts[pix], axis=1)
    assert np.median(err) < 0.01 and np.percentile(err, 99) < 0.03
    # 8-bit U, V quantisation adds ~1/255 of a chart: still within ~1 cm.
    sm8 = adapters.surface_map_from_iuv(i2, u2, v2, table)
    got8 = raycast.surface_points(verts_cam, faces, sm8.face_idx, sm8.bary)
    pix8 = (
        np.floor(sm8.xy_img[:, 1]) * camera.width + np.floor(sm8.xy_img[:, 0])
    ).astype(int)
    assert np.median(np.linalg.norm(got8 - true_pts[pix8], axis=1)) < 0.015


def test_iuv_background_and_unknown_parts_are_dropped():
    table = adapters.UvSurfaceTable(
        part=np.array([1, 1]),
        u=np.array([0.1, 0.9]),
        v=np.array([0.1, 0.9]),
        face=np.array([0, 1]),
        bary=np.full((2, 3), 1 / 3),
    )
    i_img = np.array([[0, 1, 5], [1, 1, 0]])
    u_img = np.array([[0.0, 0.12, 0.5], [0.88, 0.5, 0.0]])
    v_img = np.array([[0.0, 0.1, 0.5], [0.9, 0.5, 0.0]])
    sm = adapters.surface_map_from_iuv(i_img, u_img, v_img, table, offset_xy=(10, 20))
    np.testing.assert_array_equal(sm.face_idx, [0, 1])  # (0.5, 0.5) is too far
    np.testing.assert_allclose(sm.xy_img, [[11.5, 20.5], [10.5, 21.5]])


def test_load_uv_table_errors(tmp_path):
    np.savez(tmp_path / "t.npz", part=np.array([1]), u=np.array([0.1]))
    with pytest.raises(ValueError, match="missing array"):
        adapters.load_uv_table(tmp_path / "t.npz")
    np.savez(
        tmp_path / "p.npz",
        part=np.array([25]),
        u=np.array([0.1]),
        v=np.array([0.1]),
        face=np.array([0]),
        bary=np.full((1, 3), 1 / 3),
    )
    with pytest.raises(ValueError, match="part must lie"):
        adapters.load_uv_table(tmp_path / "p.npz")
