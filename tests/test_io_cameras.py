"""Camera files: eifslam YAML, OpenCV/ORB-SLAM YAML, EuRoC sensor.yaml, KITTI, Strecha."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.geometry.camera import PinholeCamera
from eifslam.errors import CalibrationError
from eifslam.io.cameras import (
    load_camera,
    parse_camera_yaml,
    parse_kitti_calib,
    parse_strecha_camera,
    read_euroc_sensor,
    write_camera_yaml,
)

EIFSLAM_YAML = """# comment
model: pinhole
width: 640
height: 480
fx: 525.0
fy: 526.0
cx: 319.5
cy: 239.5
distortion: [0.1, -0.2, 0.001, 0.002, 0.0]
"""

ORB_YAML = """%YAML:1.0
---
Camera.type: "PinHole"
Camera.fx: 517.306408
Camera.fy: 516.469215
Camera.cx: 318.643040
Camera.cy: 255.313989
Camera.k1: 0.262383
Camera.k2: -0.953104
Camera.p1: -0.005358
Camera.p2: 0.002628
Camera.k3: 1.163314
Camera.width: 640
Camera.height: 480
Camera.fps: 30.0
LEFT.K: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
"""

EUROC_YAML = """%YAML:1.0
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""

KITTI_LABELLED = "\n".join(
    f"P{k}: 7.188560e+02 0.000000e+00 6.071928e+02 {-386.1448 * (k % 2):.6e} "
    "0.000000e+00 7.188560e+02 1.852157e+02 0.000000e+00 "
    "0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00"
    for k in range(4)
) + "\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n"

STRECHA = """2759.48 0 1520.69
0 2764.16 1006.81
0 0 1
0 0 0
0.450927 -0.0945642 -0.887537
-0.892535 -0.0401974 -0.449183
0.00679989 0.994707 -0.102528
-7.28137 -7.57667 0.204446
3072 2048
"""


def test_eifslam_yaml(tmp_path):
    f = tmp_path / "camera.yaml"
    f.write_text(EIFSLAM_YAML)
    cam = load_camera(f)
    assert cam == PinholeCamera(525.0, 526.0, 319.5, 239.5, 640, 480, (0.1, -0.2, 0.001, 0.002, 0.0))


def test_write_read_round_trip(tmp_path):
    cam = PinholeCamera(700.5, 701.25, 600.1, 180.2, 1226, 370, (0.01, 0.0, 0.0, 0.0, 0.0))
    write_camera_yaml(tmp_path / "c.yaml", cam)
    assert load_camera(tmp_path / "c.yaml") == cam


def test_orbslam_yaml_with_directive_and_matrix(tmp_path):
    f = tmp_path / "TUM1.yaml"
    f.write_text(ORB_YAML)
    cam = load_camera(f)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (517.306408, 516.469215, 318.643040, 255.313989)
    assert (cam.width, cam.height) == (640, 480)
    assert cam.distortion == (0.262383, -0.953104, -0.005358, 0.002628, 1.163314)


def test_orbslam2_without_size_needs_image_size(tmp_path):
    f = tmp_path / "TUM1.yaml"
    f.write_text("\n".join(ln for ln in ORB_YAML.splitlines() if "width" not in ln and "height" not in ln))
    with pytest.raises(CalibrationError, match="TUM1.yaml"):
        load_camera(f)
    assert load_camera(f, image_size=(640, 480)).width == 640
    assert load_camera(f, image_size=lambda: (320, 240)).height == 240


def test_euroc_sensor(tmp_path):
    f = tmp_path / "sensor.yaml"
    f.write_text(EUROC_YAML)
    cam, T_BS = read_euroc_sensor(f)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (
        458.654, 457.296, 367.215, 248.375, 752, 480,
    )
    assert cam.distortion[0] == -0.28340811
    assert T_BS.shape == (4, 4) and T_BS[0, 3] == -0.0216401454975
    assert load_camera(f) == cam


def test_kitti_calib_labelled_and_unlabelled(tmp_path):
    f = tmp_path / "calib.txt"
    f.write_text(KITTI_LABELLED)
    cam = load_camera(f, image_size=(1241, 376))
    assert (cam.fx, cam.cx, cam.cy, cam.width, cam.height) == (718.856, 607.1928, 185.2157, 1241, 376)
    cam1, P1 = parse_kitti_calib(KITTI_LABELLED, row="P1", image_size=(1241, 376))
    assert P1[0, 3] == pytest.approx(-386.1448)
    unlabelled = "\n".join(ln.split(":", 1)[1] for ln in KITTI_LABELLED.splitlines()[:2])
    f.write_text(unlabelled)
    assert load_camera(f, image_size=(1241, 376)) == cam
    with pytest.raises(CalibrationError, match="image size"):
        load_camera(f)
    with pytest.raises(CalibrationError, match="P2"):
        load_camera(f, image_size=(1241, 376), kitti_row="P2")


def test_strecha_camera(tmp_path):
    f = tmp_path / "0000.jpg.camera"
    f.write_text(STRECHA)
    sc = parse_strecha_camera(STRECHA)
    assert sc.camera.fx == 2759.48 and sc.camera.width == 3072
    np.testing.assert_allclose(sc.C, [-7.28137, -7.57667, 0.204446])
    assert load_camera(f) == sc.camera


@pytest.mark.parametrize(
    "text, key",
    [
        (EIFSLAM_YAML.replace("fx: 525.0", "fx: -525.0"), "'fx'"),
        (EIFSLAM_YAML.replace("fx: 525.0\n", ""), "'fx'"),
        (EIFSLAM_YAML.replace("cy: 239.5", "cy: abc"), "'cy'"),
        (EIFSLAM_YAML.replace("width: 640", "width: 640.5"), "'width'"),
        (EIFSLAM_YAML.replace("model: pinhole", "model: fisheye"), "'model'"),
        (EIFSLAM_YAML + "fps: 30\n", "'fps'"),
        (EIFSLAM_YAML.replace("[0.1, -0.2, 0.001, 0.002, 0.0]", "[0.1, -0.2]"), "'distortion'"),
        (EIFSLAM_YAML.replace("fy: 526.0", "fy: .nan"), "'fy'"),
        (ORB_YAML.replace("Camera.fy: 516.469215", "Camera.fy: 0"), "Camera.fy"),
        (ORB_YAML.replace("Camera.cx: 318.643040\n", ""), "Camera.cx"),
        (EUROC_YAML.replace("resolution: [752, 480]\n", ""), "'resolution'"),
        ("fx: [1, 2\n", "not valid YAML"),
        ("- 1\n- 2\n", "mapping"),
        ("foo: 1\n", "unknown camera"),
    ],
)
def test_bad_yaml_names_file_and_key(tmp_path, text, key):
    f = tmp_path / "broken.yaml"
    f.write_text(text)
    with pytest.raises(CalibrationError) as exc:
        load_camera(f)
    msg = str(exc.value)
    assert "broken.yaml" in msg and key in msg and "\n" not in msg


def test_bad_strecha_and_missing(tmp_path):
    with pytest.raises(CalibrationError, match="9 rows"):
        parse_strecha_camera(STRECHA + "1 2 3\n", "x.camera")
    with pytest.raises(CalibrationError, match="rotation"):
        parse_strecha_camera(STRECHA.replace("0.450927", "5.0"), "x.camera")
    with pytest.raises(CalibrationError, match="nope.yaml"):
        load_camera(tmp_path / "nope.yaml")
    with pytest.raises(CalibrationError, match="T_BS"):
        f = tmp_path / "sensor.yaml"
        f.write_text(EUROC_YAML.replace("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 0.0]"))
        read_euroc_sensor(f)


def test_parse_camera_yaml_from_string():
    assert parse_camera_yaml(EIFSLAM_YAML).fx == 525.0
