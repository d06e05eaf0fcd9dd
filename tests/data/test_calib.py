"""Calibration files in OpenCV, ROS and KITTI formats, and the rectification against the rig's known geometry."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from egorefine.core import DataError, MissingDataError, ValueRangeError
from egorefine.data import StereoCalibration, read_calibration, rectify_maps

from ._files import kitti_numbers, write_filestorage

H, W = 240, 320
K1 = np.array([[300.0, 0.0, 158.0], [0.0, 302.0, 121.0], [0.0, 0.0, 1.0]])
K2 = np.array([[305.0, 0.0, 162.0], [0.0, 304.0, 118.0], [0.0, 0.0, 1.0]])
D1 = np.array([-0.12, 0.03, 0.001, -0.0005, 0.0])
D2 = np.array([-0.10, 0.02, -0.0008, 0.0004, 0.0])
R_TRUE = cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))[0]  # right camera turned by about a degree
T_TRUE = np.array([-0.12, 0.004, -0.002])  # metres: right camera 12 cm to the right


def _rig() -> StereoCalibration:
    return StereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=R_TRUE, T=T_TRUE, image_size=(H, W), source="test rig")


def _check_against_geometry(calib: StereoCalibration) -> None:
    """The rectified cameras are pinholes with K and baseline |T| whose remaps sample the raw cameras right.

    The rectifying rotation is recovered from the left map by aligning rays (Kabsch); a point at a depth giving
    a 10 px disparity is then projected into the raw right camera with the true (R, T, K2, D2) and must land
    where the right map samples, on the same row, 10 px to the left.
    """
    maps, K, baseline = rectify_maps(calib)
    K = K.numpy()
    assert baseline == pytest.approx(np.linalg.norm(T_TRUE), rel=1e-9)
    assert K[0, 0] == K[1, 1] and K[0, 1] == 0 and K[2].tolist() == [0, 0, 1]
    v, u = np.mgrid[20:H - 20:10, 30:W - 20:10]
    u, v = u.reshape(-1), v.reshape(-1)
    raw_left = np.stack([maps[0][0][v, u], maps[0][1][v, u]], -1).astype(np.float64)
    ray_raw = cv2.undistortPoints(raw_left[:, None], K1, D1,
                                  criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))[:, 0]
    ray_raw = np.hstack([ray_raw, np.ones((len(u), 1))])
    ray_rect = np.stack([u, v, np.ones_like(u)], -1).astype(np.float64) @ np.linalg.inv(K).T
    a = ray_raw / np.linalg.norm(ray_raw, axis=1, keepdims=True)
    b = ray_rect / np.linalg.norm(ray_rect, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(a.T @ b)
    cam_R_rect = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    assert np.abs(b @ cam_R_rect.T - a).max() < 1e-5  # the rectified left image is a pinhole camera with K
    d = 10
    Z = K[0, 0] * baseline / d
    X = (ray_rect * Z) @ cam_R_rect.T  # the points in the raw left camera's frame
    raw_right = cv2.projectPoints(X, cv2.Rodrigues(R_TRUE)[0], T_TRUE, K2, D2)[0][:, 0]
    sampled = np.stack([maps[1][0][v, u - d], maps[1][1][v, u - d]], -1)
    np.testing.assert_allclose(sampled, raw_right, atol=0.01)


def test_rectify_maps_matches_rig_geometry() -> None:
    _check_against_geometry(_rig())


@pytest.mark.parametrize("name", ["stereo.yaml", "stereo.json", "stereo.xml"])
def test_opencv_filestorage(tmp_path, name) -> None:
    path = write_filestorage(tmp_path / name, K1=K1, D1=D1, K2=K2, D2=D2, R=R_TRUE, T=T_TRUE.reshape(3, 1),
                     image_size=[W, H])
    c = read_calibration(path)
    assert not c.rectified and c.image_size == (H, W)
    np.testing.assert_allclose(c.K2, K2)
    np.testing.assert_allclose(c.D1, D1)
    np.testing.assert_allclose(c.R, R_TRUE)
    np.testing.assert_allclose(c.T, T_TRUE)
    _check_against_geometry(c)


def test_opencv_sample_names_rotation_vector_and_plain_json(tmp_path) -> None:
    """OpenCV's stereo sample: M1/D1/M2/D2 in intrinsics.yml, R/T in extrinsics.yml; R as a rotation vector."""
    write_filestorage(tmp_path / "intrinsics.yml", M1=K1, D1=D1, M2=K2, D2=D2)
    write_filestorage(tmp_path / "extrinsics.yml", R=cv2.Rodrigues(R_TRUE)[0], T=T_TRUE, imageSize=[W, H])
    for path in (tmp_path / "intrinsics.yml", tmp_path / "extrinsics.yml", tmp_path):
        c = read_calibration(path)
        np.testing.assert_allclose(c.R, R_TRUE, atol=1e-12)
        np.testing.assert_allclose(c.K1, K1)
    plain = {"cameraMatrix1": K1.tolist(), "distCoeffs1": D1.tolist(), "cameraMatrix2": K2.tolist(),
             "distCoeffs2": D2.tolist(), "R": R_TRUE.tolist(), "T": T_TRUE.tolist(), "image_width": W,
             "image_height": H}
    (tmp_path / "plain.json").write_text(json.dumps(plain))
    _check_against_geometry(read_calibration(tmp_path / "plain.json"))


def test_opencv_rectified_projections(tmp_path) -> None:
    """A file with P1/P2 and no distortion describes rectified images: no remap, K and baseline from P."""
    f = 400.0
    P1 = np.array([[f, 0, 160, 0], [0, f, 120, 0], [0, 0, 1, 0]])
    P2 = P1.copy()
    P2[0, 3] = -f * 0.25
    c = read_calibration(write_filestorage(tmp_path / "calib.yaml", K1=K1, K2=K1, D1=np.zeros(5), D2=np.zeros(5),
                                   R=np.eye(3), T=[-0.25, 0, 0], P1=P1, P2=P2))
    assert c.rectified
    maps, K, baseline = rectify_maps(c)
    assert maps is None and baseline == pytest.approx(0.25) and K.numpy().tolist() == P1[:, :3].tolist()
    c = read_calibration(write_filestorage(tmp_path / "p_only.yaml", P1=P1, P2=P2))
    assert c.rectified and c.K1 is None


def _ros_file(path: Path, name: str, K, D, R, P) -> Path:
    def mat(key, M, rows, cols):
        return (f"{key}:\n  rows: {rows}\n  cols: {cols}\n  data: [{', '.join(repr(float(x)) for x in np.ravel(M))}]\n")

    path.write_text(f"image_width: {W}\nimage_height: {H}\ncamera_name: {name}\n" + mat("camera_matrix", K, 3, 3)
                    + "distortion_model: plumb_bob\n" + mat("distortion_coefficients", D, 1, 5)
                    + mat("rectification_matrix", R, 3, 3) + mat("projection_matrix", P, 3, 4))
    return path


def test_ros_camera_info_pair(tmp_path) -> None:
    """ROS's stereo calibrator writes the rectification of each camera; the rig's R, T come back from them."""
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K1, D1, K2, D2, (W, H), R_TRUE, T_TRUE[:, None],
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    assert P2[0, 3] < 0  # -fx * B, as ROS writes it
    left = _ros_file(tmp_path / "left.yaml", "stereo/left", K1, D1, R1, P1)
    _ros_file(tmp_path / "right.yaml", "stereo/right", K2, D2, R2, P2)
    for path in (left, tmp_path):
        c = read_calibration(path)
        assert not c.rectified and c.image_size == (H, W)
        np.testing.assert_allclose(c.R, R_TRUE, atol=1e-9)
        np.testing.assert_allclose(c.T, T_TRUE, atol=1e-9)
        _check_against_geometry(c)
    # cam0.yaml / cam1.yaml pairs are found too; a rectified pair (no distortion, no rotation) needs no remap.
    f, B = 250.0, 0.3
    P = np.array([[f, 0, 160, 0], [0, f, 120, 0], [0, 0, 1, 0]])
    _ros_file(tmp_path / "cam0.yaml", "cam0", P[:, :3], np.zeros(5), np.eye(3), P)
    P_right = P.copy()
    P_right[0, 3] = -f * B
    _ros_file(tmp_path / "cam1.yaml", "cam1", P[:, :3], np.zeros(5), np.eye(3), P_right)
    c = read_calibration(tmp_path / "cam0.yaml")
    maps, K, baseline = rectify_maps(c)
    assert c.rectified and maps is None and baseline == pytest.approx(B) and float(K[0, 0]) == f


def _kitti_line(key: str, M) -> str:
    return f"{key}: {kitti_numbers(M)}\n"


def test_kitti_real_frame_calib(kitti_root) -> None:
    path = kitti_root / "calib" / "000001.txt"
    maps, K, baseline = rectify_maps(read_calibration(path, camera="colour"))
    assert maps is None and float(K[0, 0]) == pytest.approx(721.5377) and float(K[1, 2]) == pytest.approx(172.854)
    assert baseline == pytest.approx(0.53273, abs=1e-5)
    _, K0, baseline0 = rectify_maps(read_calibration(path))  # grey pair P0/P1: 387.5744 / 721.5377
    assert baseline0 == pytest.approx(387.5744 / 721.5377, rel=1e-9)


def test_kitti_cam_to_cam(tmp_path) -> None:
    """Raw KITTI: the rectified P_rect_xx pair, the size from S_rect_xx, the raw cameras' relative pose."""
    R_02 = cv2.Rodrigues(np.array([0.002, 0.01, -0.003]))[0]
    T_02, T_03 = np.array([0.06, -0.001, 0.002]), np.array([-0.47, 0.002, 0.004])
    R_03 = cv2.Rodrigues(np.array([-0.001, 0.02, 0.004]))[0]
    P = {c: np.array([[720.0, 0, 600, 720.0 * tx], [0, 720.0, 180, 0], [0, 0, 1, 0]])
         for c, tx in ((0, 0.0), (1, -0.54), (2, 0.06), (3, -0.47))}
    text = "calib_time: 09-Jan-2012 13:57:47\ncorner_dist: 9.950000e-02\n"
    for c in range(4):
        Rc, Tc = {2: (R_02, T_02), 3: (R_03, T_03)}.get(c, (np.eye(3), np.zeros(3)))
        text += (_kitti_line(f"S_{c:02d}", [1392, 512]) + _kitti_line(f"K_{c:02d}", K1) + _kitti_line(f"D_{c:02d}", D1)
                 + _kitti_line(f"R_{c:02d}", Rc) + _kitti_line(f"T_{c:02d}", Tc)
                 + _kitti_line(f"S_rect_{c:02d}", [1242, 375]) + _kitti_line(f"R_rect_{c:02d}", np.eye(3))
                 + _kitti_line(f"P_rect_{c:02d}", P[c]))
    (tmp_path / "calib_cam_to_cam.txt").write_text(text)
    c = read_calibration(tmp_path / "calib_cam_to_cam.txt", camera="colour")
    assert c.rectified and c.image_size == (375, 1242)
    np.testing.assert_allclose(c.P2, P[3])
    # Camera 3 relative to camera 2: X3 = R X2 + T, with X_c = R_0c X_0 + T_0c.
    X0 = np.array([1.0, -2.0, 9.0])
    np.testing.assert_allclose(c.R @ (R_02 @ X0 + T_02) + c.T, R_03 @ X0 + T_03, atol=1e-12)
    assert rectify_maps(c)[2] == pytest.approx(0.53)
    assert rectify_maps(read_calibration(tmp_path))[2] == pytest.approx(0.54)  # the folder, grey pair


# ---------------------------------------------------------------- bad input


def test_unparsable_files(tmp_path) -> None:
    (tmp_path / "bad.yaml").write_text("K1: [1, 2\n  : :: }")
    with pytest.raises(DataError, match="bad.yaml does not parse as an OpenCV YAML/XML file"):
        read_calibration(tmp_path / "bad.yaml")
    (tmp_path / "bad.json").write_text('{"K1": [1, 2')
    with pytest.raises(DataError, match="bad.json does not parse as JSON"):
        read_calibration(tmp_path / "bad.json")
    (tmp_path / "list.json").write_text("[1, 2, 3]")
    with pytest.raises(DataError, match="expected a map of named fields at the top level, found list"):
        read_calibration(tmp_path / "list.json")
    (tmp_path / "calib.txt").write_bytes(bytes(range(256)))
    with pytest.raises(DataError, match="calib.txt is not a text file"):
        read_calibration(tmp_path / "calib.txt")
    (tmp_path / "calib.txt").write_text("just some words\nno numbers here\n")
    with pytest.raises(DataError, match="holds no 'key: numbers' lines"):
        read_calibration(tmp_path / "calib.txt")


def test_missing_fields(tmp_path) -> None:
    path = write_filestorage(tmp_path / "c.yaml", K1=K1, D1=D1, D2=D2, R=R_TRUE, T=T_TRUE)
    with pytest.raises(DataError, match=r"c.yaml lacks K2 or M2 or cameraMatrix2 \(found D1, D2, K1, R, T\)"):
        read_calibration(path)
    path = write_filestorage(tmp_path / "c.yaml", K1=K1, K2=K2, R=R_TRUE, T=[1.0, 2.0])
    with pytest.raises(DataError, match="T in .*c.yaml: expected 3 numbers, found 2"):
        read_calibration(path)
    (tmp_path / "calib.txt").write_text(_kitti_line("P0", np.eye(3, 4)) + _kitti_line("P1", np.eye(3, 4)))
    with pytest.raises(DataError, match=r"calib.txt lacks P2 \(found P0, P1\)"):
        read_calibration(tmp_path / "calib.txt", camera="colour")
    _ros_file(tmp_path / "left.yaml", "left", K1, D1, np.eye(3), np.eye(3, 4))
    with pytest.raises(MissingDataError, match="expected the right camera's beside it \\(tried right.yaml\\)"):
        read_calibration(tmp_path / "left.yaml")
    (tmp_path / "right.yaml").write_text((tmp_path / "left.yaml").read_text().replace("projection_matrix", "P"))
    with pytest.raises(DataError, match="right.yaml lacks projection_matrix"):
        read_calibration(tmp_path / "left.yaml")
    (tmp_path / "right.yaml").write_text((tmp_path / "left.yaml").read_text().replace("plumb_bob", "equidistant"))
    with pytest.raises(DataError, match="distortion_model 'equidistant' is not supported"):
        read_calibration(tmp_path / "left.yaml")
    (tmp_path / "empty").mkdir()
    with pytest.raises(MissingDataError, match="calib: no calibration file in .*empty"):
        read_calibration(tmp_path / "empty")
    with pytest.raises(ValueRangeError, match="camera: expected one of"):
        read_calibration(tmp_path / "left.yaml", camera="ir")


def test_bad_geometry() -> None:
    swapped = StereoCalibration(K1=K1, K2=K2, R=np.eye(3), T=[0.12, 0, 0], image_size=(H, W), source="swapped.yaml")
    with pytest.raises(DataError, match="swapped.yaml: the right camera is not right of the left .*swapped"):
        rectify_maps(swapped)
    vertical = StereoCalibration(K1=K1, K2=K2, R=np.eye(3), T=[0, -0.12, 0], image_size=(H, W), source="v.yaml")
    with pytest.raises(DataError, match="v.yaml: the cameras are stacked vertically"):
        rectify_maps(vertical)
    with pytest.raises(DataError, match="gives no image size"):
        rectify_maps(StereoCalibration(K1=K1, K2=K2, R=np.eye(3), T=[-0.1, 0, 0], source="s.yaml"))
    P1, P2 = np.eye(3, 4), np.eye(3, 4) * 2
    with pytest.raises(DataError, match="rectified projections P1 and P2 have different intrinsics"):
        rectify_maps(StereoCalibration(P1=P1, P2=P2, rectified=True))
    with pytest.raises(DataError, match="lacks P2 \\(needed for rectified images\\)"):
        StereoCalibration(P1=P1, rectified=True)
    with pytest.raises(DataError, match="lacks R \\(needed for raw \\(unrectified\\) images\\)"):
        StereoCalibration(K1=K1, K2=K2, T=[-0.1, 0, 0])
