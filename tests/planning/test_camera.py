import math

import pytest

from gcs.planning.camera import (
    Camera,
    CameraError,
    h_max,
    paper_height,
    paper_side_overlap,
    scene_width,
    spacing_from_camera,
    spacing_from_swath,
    spacing_paper,
)

# seed 001 §6.1: 640 px, fov 60 deg, 0.5 m tag, ~20 px minimal detection size
ASAF = Camera(resolution_px=640, fov_deg=60.0, min_pixels=20)


def test_eq4_h_max():
    expected = 0.5 * 640 / (2 * 20 * math.tan(math.radians(30)))
    assert h_max(ASAF, 0.5) == pytest.approx(expected)
    assert h_max(ASAF, 0.5) == pytest.approx(13.856, abs=1e-3)
    assert h_max(ASAF, 0.8, 0.5) == h_max(ASAF, 0.5)  # min(W, H)


def test_eq5_scene_width():
    # seed 001 §6: "at a height of 20 m the camera can view 24 m by 18 m" -> w_sensor/f = 1.2
    cam = Camera(resolution_px=4000, sensor_width_mm=6.0, focal_mm=5.0)
    assert scene_width(cam, 20.0) == pytest.approx(24.0)
    assert scene_width(ASAF, 20.0) == pytest.approx(40 * math.tan(math.radians(30)))


def test_eq6_and_its_overlap_meaning():
    hm = 20.0
    assert paper_height(hm, 0.0) == pytest.approx(10.0)  # h_min: zero overlap
    assert paper_height(hm, 1.0) == pytest.approx(20.0)  # "100 %" at h_max
    # spacing is w(h_max)/2 = w(h)/ (1 + v): conventional side overlap v / (1 + v), 50 % at "100 %"
    sp = spacing_paper(ASAF, 0.5, overlap=1.0)
    assert 1 - sp.step / sp.swath == pytest.approx(paper_side_overlap(1.0)) == pytest.approx(0.5)


def test_spacing_from_camera():
    sp = spacing_from_camera(ASAF, 0.5, side_overlap=0.2)
    assert sp.altitude == pytest.approx(h_max(ASAF, 0.5))
    assert sp.step == pytest.approx(0.8 * scene_width(ASAF, sp.altitude))
    lower = spacing_from_camera(ASAF, 0.5, altitude=10.0)
    assert lower.swath == pytest.approx(scene_width(ASAF, 10.0))


def test_camera_errors():
    with pytest.raises(CameraError, match="any height"):
        h_max(Camera(resolution_px=10, fov_deg=60, min_pixels=20), 0.5)
    with pytest.raises(CameraError, match="any usable height"):
        spacing_from_camera(Camera(resolution_px=100, fov_deg=90, min_pixels=40), 0.05)
    with pytest.raises(CameraError, match="above h_max"):
        spacing_from_camera(ASAF, 0.5, altitude=30.0)
    with pytest.raises(ValueError, match="disagrees"):
        Camera(resolution_px=640, fov_deg=60.0, sensor_width_mm=6.0, focal_mm=5.0)
    with pytest.raises(ValueError):
        Camera(resolution_px=640)


def test_swath_alternative():
    sp = spacing_from_swath(30.0, 40.0, 0.25)
    assert sp.step == pytest.approx(22.5) and sp.altitude == 40.0
    with pytest.raises(CameraError):
        spacing_from_swath(30.0, 40.0, 1.0)
