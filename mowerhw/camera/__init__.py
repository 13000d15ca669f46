"""Cameras (docs/design.md §6): the model, its calibration files, checks and calibration.

* :mod:`.model` — :class:`CameraModel` and the Mei omnidirectional model with radtan
  distortion (:class:`OmniRadtanCamera`), its valid domain for any ξ;
* :mod:`.kalibr` — Kalibr camchain files, read and written;
* :mod:`.check` — numerical checks of a model and its agreement with ``cv2.omnidir``;
* :mod:`.calibrate` — calibration from checkerboard photos (``mowerhw camera calibrate``);
* :mod:`.region` — the usable image region (mirror annulus, image circle) from photos.
"""

from mowerhw.camera.kalibr import camera_names, load_camchain, save_camchain
from mowerhw.camera.model import (
    Annulus,
    CameraCalibrationError,
    CameraModel,
    OmniRadtanCamera,
    paper_table1_camera,
)

__all__ = [
    "Annulus",
    "CameraCalibrationError",
    "CameraModel",
    "OmniRadtanCamera",
    "camera_names",
    "load_camchain",
    "paper_table1_camera",
    "save_camchain",
]
