"""Calibrating a user's own omnidirectional camera from checkerboard photos.

``mowerhw camera calibrate IMAGES... --pattern COLSxROWS --square METRES`` runs
:func:`calibrate`:

1. the board's inner corners in every photo (``cv2.findChessboardCornersSB``, exhaustive and
   accurate: it copes with the strong bending of a mirror or fisheye image); photos of another
   size or without the whole board are reported and left out;
2. the Mei model with radial–tangential distortion and skew (``cv2.omnidir.calibrate``);
3. outlier views — a view whose reprojection error is far above the others' (a corner found
   on the wrong square, a blurred photo) — are dropped and the calibration repeated, each
   drop reported with its error;
4. the usable image region (mirror annulus or fisheye image circle) from the photos
   themselves (:mod:`.region`);
5. a report: overall RMS, per-view error, views used, and how much of the usable region the
   corners covered (the model is only measured where corners were seen).

The result is an :class:`~mowerhw.camera.model.OmniRadtanCamera` that
:func:`~mowerhw.camera.kalibr.save_camchain` writes as a Kalibr camchain.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from mowerhw.camera.model import OmniRadtanCamera
from mowerhw.camera.region import BrightnessStats, Region, find_region

FloatArray = NDArray[np.float64]

#: a view is an outlier when its RMS error exceeds this many times the median view's ...
OUTLIER_FACTOR = 3.0
#: ... and this many pixels
OUTLIER_MIN_PX = 1.0
#: fewest views the calibration needs
MIN_VIEWS = 4
#: cells per side of the grid that measures corner coverage
COVERAGE_GRID = 16


class CalibrationError(ValueError):
    """The photos cannot give a calibration; the message says why and what to do."""


def parse_pattern(text: str) -> tuple[int, int]:
    """``"9x6"`` → (9, 6): inner corners per row and per column."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CalibrationError(
            f"--pattern {text!r}: give the inner corners as COLSxROWS, e.g. 9x6"
        ) from None
    if cols < 3 or rows < 3:
        raise CalibrationError(f"--pattern {text!r}: at least 3x3 inner corners")
    return cols, rows


def board_points(pattern: tuple[int, int], square_m: float) -> FloatArray:
    """The inner corners on the board (metres, z = 0), in OpenCV's detection order."""
    cols, rows = pattern
    pts = np.zeros((cols * rows, 3))
    pts[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return pts


def detect_corners(grey: NDArray[np.uint8], pattern: tuple[int, int]) -> FloatArray | None:
    """The board's inner corners (N, 2) in a grey photo, sub-pixel; None if not all found."""
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    found, corners = cv2.findChessboardCornersSB(grey, pattern, flags=flags)
    if not found:
        return None
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2)


@dataclass
class View:
    """One photo: whether the board was found, used, and its reprojection error."""

    path: str
    corners: FloatArray | None = None
    used: bool = False
    rms_px: float | None = None
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "image": Path(self.path).name,
            "board_found": self.corners is not None,
            "used": self.used,
            "rms_px": None if self.rms_px is None else round(self.rms_px, 4),
            "note": self.note,
        }


@dataclass
class Calibration:
    """The calibrated camera and everything the report says about it."""

    camera: OmniRadtanCamera
    rms_px: float
    views: list[View]
    region: Region
    coverage: dict[str, float]
    image_size: tuple[int, int]
    pattern: tuple[int, int]
    square_m: float
    residuals: list[tuple[FloatArray, FloatArray]] = field(default_factory=list)  # (px, error)

    @property
    def used(self) -> list[View]:
        return [v for v in self.views if v.used]

    def as_dict(self) -> dict[str, Any]:
        return {
            "rms_px": round(self.rms_px, 4),
            "views_used": len(self.used),
            "views_total": len(self.views),
            "image_size": list(self.image_size),
            "pattern": f"{self.pattern[0]}x{self.pattern[1]}",
            "square_m": self.square_m,
            "camera": self.camera.intrinsics(),
            "region": self.region.as_dict(),
            "coverage": self.coverage,
            "views": [v.as_dict() for v in self.views],
        }


def calibrate(
    images: Sequence[str | Path],
    pattern: tuple[int, int],
    square_m: float,
    progress: Callable[[str], None] | None = None,
) -> Calibration:
    """Calibrate from checkerboard photos (see the module doc)."""
    if not square_m > 0:
        raise CalibrationError(f"--square {square_m}: the square size must be positive (metres)")
    tell = progress or (lambda _msg: None)
    views: list[View] = []
    stats = BrightnessStats()
    size: tuple[int, int] | None = None
    for path in images:
        view = View(str(path))
        views.append(view)
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if grey is None:
            view.note = "not an image OpenCV can read"
            tell(f"{Path(path).name}: unreadable")
            continue
        h, w = grey.shape
        if size is None:
            size = (w, h)
        elif (w, h) != size:
            view.note = f"{w}x{h} px, unlike the first photo's {size[0]}x{size[1]}"
            tell(f"{Path(path).name}: other size, left out")
            continue
        stats.add(grey)
        view.corners = detect_corners(grey, pattern)
        if view.corners is None:
            view.note = f"no complete {pattern[0]}x{pattern[1]} board found"
        tell(f"{Path(path).name}: {'board found' if view.corners is not None else 'no board'}")
    found = [v for v in views if v.corners is not None]
    if size is None:
        names = ", ".join(Path(v.path).name for v in views[:3]) + (", …" if len(views) > 3 else "")
        raise CalibrationError(
            f"none of the {len(views)} images could be read ({names}): not images OpenCV can "
            "read (JPEG, PNG, TIFF, …) or not readable files"
        )
    if len(found) < MIN_VIEWS:
        raise CalibrationError(
            f"the board was found in {len(found)} of {len(views)} photos; at least {MIN_VIEWS} "
            f"are needed (check --pattern {pattern[0]}x{pattern[1]}: inner corners, not squares)"
        )
    obj = board_points(pattern, square_m)
    active = list(found)
    while True:
        tell(f"calibrating on {len(active)} views")
        cam, rms, errors_by_view, dropped_by_cv = _omnidir(active, obj, size)
        for v in active:
            v.used = v not in dropped_by_cv
            err = errors_by_view.get(id(v))
            v.rms_px = None if err is None else float(np.sqrt(np.mean(np.sum(err * err, 1))))
        for v in dropped_by_cv:
            v.note = "left out by cv2.omnidir.calibrate (its initialisation failed on it)"
        used = [v for v in active if v.used]
        errors = np.array([v.rms_px for v in used], dtype=np.float64)
        limit = max(OUTLIER_FACTOR * float(np.median(errors)), OUTLIER_MIN_PX)
        worst = max(used, key=lambda v: v.rms_px or 0.0)
        if (worst.rms_px or 0.0) <= limit or len(used) <= MIN_VIEWS:
            break
        worst.used = False
        worst.note = f"outlier: {worst.rms_px:.2f} px > {limit:.2f} px (3x the median view)"
        tell(f"{Path(worst.path).name}: {worst.note}; calibrating again")
        active = [v for v in used if v is not worst]
    used = [v for v in views if v.used]
    radii = np.concatenate(
        [np.hypot(v.corners[:, 0] - cam.cu, v.corners[:, 1] - cam.cv) for v in used]  # type: ignore[index]
    )
    tell("finding the usable image region")
    region = find_region(stats, (cam.cu, cam.cv), radii)
    cam = replace(cam, mask=region.annulus)
    residuals = [(v.corners, errors_by_view[id(v)]) for v in used]
    return Calibration(
        camera=cam,
        rms_px=rms,
        views=views,
        region=region,
        coverage=_coverage(cam, used),
        image_size=size,
        pattern=pattern,
        square_m=square_m,
        residuals=residuals,
    )


def _omnidir(
    views: list[View], obj: FloatArray, size: tuple[int, int]
) -> tuple[OmniRadtanCamera, float, dict[int, FloatArray], list[View]]:
    """One ``cv2.omnidir.calibrate`` run: camera, RMS, per-view reprojection errors (N, 2),
    views it left out."""
    object_points = [obj.reshape(1, -1, 3).astype(np.float64) for _ in views]
    image_points = [v.corners.reshape(1, -1, 2).astype(np.float64) for v in views]  # type: ignore[union-attr]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 300, 1e-10)
    try:
        rms, k, xi, d, rvecs, tvecs, idx = cv2.omnidir.calibrate(
            object_points, image_points, size, None, None, None, 0, criteria
        )
    except cv2.error as exc:
        raise CalibrationError(f"cv2.omnidir.calibrate failed: {exc}") from None
    kept = [int(i) for i in np.asarray(idx).ravel()] if idx is not None else list(range(len(views)))
    camera = OmniRadtanCamera(
        xi=float(np.asarray(xi).ravel()[0]),
        fu=float(k[0, 0]),
        fv=float(k[1, 1]),
        cu=float(k[0, 2]),
        cv=float(k[1, 2]),
        k1=float(np.asarray(d).ravel()[0]),
        k2=float(np.asarray(d).ravel()[1]),
        p1=float(np.asarray(d).ravel()[2]),
        p2=float(np.asarray(d).ravel()[3]),
        width=size[0],
        height=size[1],
        skew=float(k[0, 1] / k[0, 0]),
    )
    per_view: dict[int, FloatArray] = {}
    for j, i in enumerate(kept):
        proj, _ = cv2.omnidir.projectPoints(
            object_points[i], rvecs[j], tvecs[j], camera.K, camera.xi, camera.D
        )
        per_view[id(views[i])] = proj.reshape(-1, 2) - image_points[i].reshape(-1, 2)
    dropped = [v for i, v in enumerate(views) if i not in kept]
    return camera, float(rms), per_view, dropped


def _coverage(cam: OmniRadtanCamera, views: list[View]) -> dict[str, float]:
    """How much of the usable region the corners cover: the share of the grid cells (of the
    image, :data:`COVERAGE_GRID` per side) in the region holding a corner, and the range of
    angles from the camera axis seen by corners against the region's."""
    corners = np.concatenate([v.corners for v in views if v.corners is not None])
    w, h = cam.width, cam.height
    gv, gu = np.mgrid[0:COVERAGE_GRID, 0:COVERAGE_GRID]
    centres = np.stack(
        [(gu.ravel() + 0.5) * w / COVERAGE_GRID, (gv.ravel() + 0.5) * h / COVERAGE_GRID], axis=1
    )
    in_region = cam.valid(centres)
    cu = np.clip((corners[:, 0] * COVERAGE_GRID / w).astype(int), 0, COVERAGE_GRID - 1)
    cv_ = np.clip((corners[:, 1] * COVERAGE_GRID / h).astype(int), 0, COVERAGE_GRID - 1)
    hit = np.zeros(COVERAGE_GRID * COVERAGE_GRID, bool)
    hit[cv_ * COVERAGE_GRID + cu] = True
    polar = np.degrees(np.arccos(np.clip(cam.lift(corners)[:, 2], -1, 1)))
    from mowerhw.camera.check import sample_valid_pixels

    region_polar = np.degrees(
        np.arccos(np.clip(cam.lift(sample_valid_pixels(cam, 20000, seed=3))[:, 2], -1, 1))
    )
    return {
        "grid_cells_covered": round(float((hit & in_region).sum() / max(in_region.sum(), 1)), 3),
        "corners": int(corners.shape[0]),
        "corner_polar_deg": [round(float(np.nanmin(polar)), 1), round(float(np.nanmax(polar)), 1)],
        "region_polar_deg": [
            round(float(region_polar.min()), 1),
            round(float(region_polar.max()), 1),
        ],
    }


def plot_residuals(calib: Calibration, mean_image: FloatArray | None, out: Path) -> Path:
    """A PNG of the reprojection errors over the image (arrows ×50), with the region."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w, h = calib.image_size
    fig, ax = plt.subplots(figsize=(10, 10 * h / w))
    if mean_image is not None:
        ax.imshow(mean_image, cmap="gray", vmin=0, vmax=255, alpha=0.6)
    cmap = plt.get_cmap("tab20")
    scale = 50.0
    for k, (px, err) in enumerate(calib.residuals):
        ax.quiver(
            px[:, 0],
            px[:, 1],
            err[:, 0] * scale,
            err[:, 1] * scale,
            angles="xy",
            scale_units="xy",
            scale=1.0,
            color=cmap(k % 20),
            width=0.002,
        )
    ann = calib.camera.mask
    if ann is not None:
        for r in (ann.inner_radius_px, ann.outer_radius_px):
            if r > 0:
                ax.add_patch(plt.Circle(ann.center_px, r, fill=False, color="lime", lw=1))
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_title(
        f"reprojection errors ×{scale:.0f}: RMS {calib.rms_px:.3f} px over "
        f"{len(calib.used)} views; green: usable region"
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
