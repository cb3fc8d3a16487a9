"""Camera-driven flying height and line spacing (seed 000 eqs. 4-6, Alg. 2 lines 5-8).

A target (a printed pattern W x H metres) is detectable while it spans at least ``min_pixels``
pixels; that caps the height (eq. 4). The ground footprint across track grows linearly with
height (eq. 5). Line spacing follows from the footprint and the wanted side overlap.

Units: metres, millimetres for sensor and focal length, degrees for the field of view. The
sensor width, pixel count and field of view are the ones ACROSS the flight direction.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, model_validator


class CameraError(ValueError):
    """The camera/pattern combination cannot produce a usable survey."""


class Camera(BaseModel):
    """A down-looking camera; give the field of view, or sensor width and focal length, or both."""

    model_config = ConfigDict(frozen=True)

    resolution_px: int = Field(gt=0, description="pixels across track")
    fov_deg: float | None = Field(default=None, gt=0.0, lt=180.0)
    sensor_width_mm: float | None = Field(default=None, gt=0.0)
    focal_mm: float | None = Field(default=None, gt=0.0)
    min_pixels: float = Field(default=20.0, gt=0.0, description="pixels the pattern must span")

    @model_validator(mode="after")
    def _consistent(self) -> Camera:
        has_lens = self.sensor_width_mm is not None and self.focal_mm is not None
        if self.fov_deg is None and not has_lens:
            raise ValueError("camera needs fov_deg, or sensor_width_mm and focal_mm")
        if self.fov_deg is not None and has_lens:
            assert self.sensor_width_mm is not None and self.focal_mm is not None
            lens_fov = math.degrees(2 * math.atan(self.sensor_width_mm / (2 * self.focal_mm)))
            if abs(lens_fov - self.fov_deg) > 0.02 * self.fov_deg:
                raise ValueError(
                    f"fov_deg={self.fov_deg} disagrees with sensor/focal ({lens_fov:.2f} deg); "
                    "eqs. 4 and 5 would then describe two different cameras"
                )
        return self

    @property
    def half_fov_tan(self) -> float:
        """tan(FOV/2), from the FOV if given, else from sensor and focal length."""
        if self.fov_deg is not None:
            return math.tan(math.radians(self.fov_deg) / 2)
        assert self.sensor_width_mm is not None and self.focal_mm is not None
        return self.sensor_width_mm / (2 * self.focal_mm)


def h_max(camera: Camera, pattern_w: float, pattern_h: float | None = None) -> float:
    """Eq. 4: highest altitude at which the pattern still spans ``min_pixels`` pixels.

    h_max = w_pattern * C_res / (2 * C_p * tan(C_fov / 2)), w_pattern = min(W, H).
    """
    w = min(pattern_w, pattern_h if pattern_h is not None else pattern_w)
    if w <= 0:
        raise CameraError("pattern size must be positive")
    if camera.min_pixels > camera.resolution_px:
        raise CameraError(
            f"the pattern must span {camera.min_pixels} px but the image is only "
            f"{camera.resolution_px} px wide: "
            "the camera cannot see the pattern at any height"
        )
    return w * camera.resolution_px / (2 * camera.min_pixels * camera.half_fov_tan)


def scene_width(camera: Camera, altitude: float) -> float:
    """Eq. 5: ground width seen across track at ``altitude`` (= w_sensor * h / f = 2 h tan(fov/2))."""
    if altitude <= 0:
        raise CameraError("altitude must be positive")
    return 2 * altitude * camera.half_fov_tan


def paper_height(hmax: float, overlap: float) -> float:
    """Eq. 6 verbatim: h = h_max (1 + v) / 2 with lines spaced scene_width(h_max) / 2.

    Here ``v`` is the overlap band measured against the LINE SPACING (v = 1: every point seen by
    two lines), not the usual side overlap against the footprint; see :func:`paper_side_overlap`.
    """
    if not 0.0 <= overlap <= 1.0:
        raise CameraError("overlap must be within [0, 1]")
    return 0.5 * hmax * (1.0 + overlap)


def paper_side_overlap(overlap: float) -> float:
    """Conventional side overlap (fraction of footprint) produced by eq. 6 with overlap ``v``: v/(1+v)."""
    return overlap / (1.0 + overlap)


class Spacing(BaseModel):
    """Altitude and line spacing of a survey, and how they were obtained."""

    altitude: float = Field(gt=0.0)
    swath: float = Field(gt=0.0, description="footprint width across track at altitude (m)")
    step: float = Field(gt=0.0, description="distance between adjacent lines (m)")
    side_overlap: float = Field(ge=0.0, lt=1.0)
    h_max: float | None = None
    h_min: float | None = None
    source: str = "swath"


def spacing_from_swath(swath: float, altitude: float, side_overlap: float = 0.0) -> Spacing:
    """Plain alternative: the sensor's swath width is known; lines ``(1 - overlap) * swath`` apart."""
    if swath <= 0:
        raise CameraError("swath width must be positive")
    if not 0.0 <= side_overlap < 1.0:
        raise CameraError("side overlap must be within [0, 1)")
    return Spacing(
        altitude=altitude, swath=swath, step=swath * (1.0 - side_overlap), side_overlap=side_overlap
    )


def spacing_from_camera(
    camera: Camera,
    pattern_w: float,
    pattern_h: float | None = None,
    side_overlap: float = 0.0,
    altitude: float | None = None,
    min_altitude: float = 2.0,
) -> Spacing:
    """Altitude and spacing that detect the pattern everywhere with the given side overlap.

    Default altitude is h_max: the widest footprint that still resolves the target, hence the
    fewest lines. A requested altitude above h_max is an error (targets would be missed), as is
    an h_max below ``min_altitude`` (nothing flyable can detect the pattern).
    """
    hm = h_max(camera, pattern_w, pattern_h)
    if hm < min_altitude:
        raise CameraError(
            f"the pattern is only detectable below {hm:.2f} m, under the minimum flying height "
            f"{min_altitude:.2f} m: the camera cannot see it at any usable height"
        )
    alt = hm if altitude is None else altitude
    if alt > hm * (1 + 1e-9):
        raise CameraError(
            f"altitude {alt:.1f} m is above h_max {hm:.1f} m: the pattern would not be detected"
        )
    if alt < min_altitude:
        raise CameraError(f"altitude {alt:.1f} m is below the minimum flying height {min_altitude:.1f} m")
    if not 0.0 <= side_overlap < 1.0:
        raise CameraError("side overlap must be within [0, 1)")
    sw = scene_width(camera, alt)
    return Spacing(
        altitude=alt,
        swath=sw,
        step=sw * (1.0 - side_overlap),
        side_overlap=side_overlap,
        h_max=hm,
        h_min=hm / 2,
        source="camera",
    )


def spacing_paper(
    camera: Camera, pattern_w: float, pattern_h: float | None = None, overlap: float = 0.0
) -> Spacing:
    """Seed 000 Alg. 2 as written: step = scene_width(h_max)/2, height from eq. 6."""
    hm = h_max(camera, pattern_w, pattern_h)
    alt = paper_height(hm, overlap)
    return Spacing(
        altitude=alt,
        swath=scene_width(camera, alt),
        step=scene_width(camera, hm) / 2,
        side_overlap=paper_side_overlap(overlap),
        h_max=hm,
        h_min=hm / 2,
        source="paper-eq6",
    )
