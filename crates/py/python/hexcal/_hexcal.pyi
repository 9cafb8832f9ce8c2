"""Type stubs of the extension module hexcal._hexcal (re-exported by ``hexcal``).

Units: millimetres and pixels; pixel (0, 0) is the centre of the top-left pixel; poses are
``T_device_ref`` (``X_device = R @ X_ref + T``).
"""

import os
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple, Union, overload

import numpy as np
import numpy.typing as npt

_Path = Union[str, "os.PathLike[str]"]
_Floats = npt.ArrayLike
_Json = Union[Dict[str, Any], _Path]

class Error(ValueError):
    """A refused input or a failed step, with the hexcal command line's one-line message."""

class Device:
    """One calibrated camera or projector (a projector is an inverse camera: its image is
    the projected raster)."""

    @property
    def name(self) -> str: ...
    @property
    def kind(self) -> Literal["camera", "projector"]: ...
    @property
    def width(self) -> int:
        """Image (raster) width (px)."""
    @property
    def height(self) -> int:
        """Image (raster) height (px)."""
    @property
    def intrinsics(self) -> Dict[str, float]:
        """{"fx", "fy", "cx", "cy"} (px)."""
    @property
    def distortion(self) -> Dict[str, float]:
        """OpenCV coefficients {"k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"}."""
    @property
    def camera_matrix(self) -> npt.NDArray[np.float64]:
        """OpenCV's K (3 × 3)."""
    @property
    def dist_coeffs(self) -> npt.NDArray[np.float64]:
        """OpenCV's distortion vector: 5 values, or 8 with the rational k4–k6."""
    @property
    def pose(self) -> npt.NDArray[np.float64]:
        """T_device_ref (4 × 4, mm)."""
    @property
    def rvec(self) -> npt.NDArray[np.float64]:
        """Rotation of the pose as a Rodrigues vector (rad)."""
    @property
    def tvec(self) -> npt.NDArray[np.float64]:
        """Translation of the pose (mm)."""
    @property
    def lens_params(self) -> List[str]:
        """Names of the estimated lens parameters, the rows of ``lens_covariance``."""
    @property
    def lens_std(self) -> npt.NDArray[np.float64]:
        """Standard deviations of the estimated lens parameters."""
    @property
    def lens_covariance(self) -> Optional[npt.NDArray[np.float64]]:
        """Covariance of the estimated lens parameters, None in files of older builds."""
    @property
    def pose_std(self) -> npt.NDArray[np.float64]:
        """σ of a left pose increment (ω rad, τ mm); zero for the reference device."""
    @property
    def lens_model(self) -> List[Dict[str, Any]]:
        """Per distortion term: "term", "estimated", "estimate", "std", "reason"."""
    def project(
        self, points: _Floats, frame: Literal["reference", "device"] = "reference"
    ) -> npt.NDArray[np.float64]:
        """Pixels (N × 2) of points (N × 3, mm) in the reference (or the device's) frame;
        NaN behind the device. Equal to ``cv2.projectPoints`` with the OpenCV export."""
    def unproject(self, pixels: _Floats) -> npt.NDArray[np.float64]:
        """Unit rays (N × 3) through pixels (N × 2) in the device's frame; NaN where the lens
        model cannot be inverted."""
    def rays(
        self, pixels: _Floats
    ) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(origins N × 3, unit directions N × 3) of the rays through pixels, reference frame."""
    def projection_uncertainty(self, pixels: _Floats) -> npt.NDArray[np.float64]:
        """Projection uncertainty (px, 1σ worst direction) at pixels (N × 2) from the lens
        covariance; raises Error for a file without covariance."""
    def opencv_yaml(self) -> str:
        """The OpenCV FileStorage YAML of ``calibration/opencv/NAME.yml``."""

class Calibration:
    """Every calibrated device's model and pose in the reference device's frame."""

    def __getitem__(self, name: str) -> Device:
        """The device called ``name``; KeyError if there is none."""
    def __contains__(self, name: object) -> bool: ...
    def __len__(self) -> int: ...
    @property
    def devices(self) -> List[Device]: ...
    @property
    def names(self) -> List[str]: ...
    @property
    def reference(self) -> str: ...
    @property
    def board(self) -> str: ...
    @property
    def sigma(self) -> float:
        """Posterior σ per residual coordinate (px)."""
    @property
    def front_back(self) -> Optional[npt.NDArray[np.float64]]:
        """T_board_back (4 × 4, mm); None for a single-sided board (no back)."""
    @property
    def excluded(self) -> List[Tuple[str, str]]:
        """Devices a calibration left out: (name, reason); empty for a loaded file."""
    def to_json(self) -> str:
        """``calibration.json`` text."""
    def save(self, path: _Path) -> None:
        """Writes ``calibration.json`` text to ``path`` atomically."""

def load(path: _Path) -> Calibration:
    """Reads a ``calibration.json``, checked as the command line checks it."""

@overload
def triangulate(
    calibration: Calibration,
    first: str,
    second: str,
    pixels_first: _Floats,
    pixels_second: _Floats,
    pixel_sigma: None = None,
) -> npt.NDArray[np.float64]: ...
@overload
def triangulate(
    calibration: Calibration,
    first: str,
    second: str,
    pixels_first: _Floats,
    pixels_second: _Floats,
    pixel_sigma: float,
) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Points (N × 3, mm, reference frame): midpoints of the two devices' rays through each
    pixel pair, as ``hexcal verify``; with ``pixel_sigma`` also their covariance
    (N × 3 × 3, mm²) from the lens covariances, pose σ and pixel noise."""

def verify(calibration: Calibration, held_out: _Json) -> List[Dict[str, Any]]:
    """``hexcal verify`` on a correspondences file or dict of held-out poses: per pair and
    pose "first", "second", "pose", "points", "length_rms", "length_max", "flatness_rms"."""

def detect(image: npt.ArrayLike, board: str = "hex600") -> Dict[str, npt.NDArray[Any]]:
    """Circles and labelled lattice points of a grey image: "circles" (N × 4: x, y, radius,
    score), "points" (M × 2), "hex" (M × 2 q, r), "circle" (M), "side" (M: 0 front, 1 back,
    −1 unknown), "anchored" (M bool)."""

def decode(
    frames: Union[npt.ArrayLike, Sequence[npt.ArrayLike]],
    sequence: _Json,
    full_scale: Optional[float] = None,
    camera: str = "camera",
) -> Dict[str, Any]:
    """One camera's phase-shift stack (K × H × W) decoded: "projectors" (per projector "u",
    "v", "valid", "modulation", "reliability", "sigma_u", "sigma_v"), "ambient",
    "saturated"."""

def calibrate(
    correspondences: _Json,
    reference: Optional[str] = None,
    fix_k3: bool = False,
    refine_flatness: bool = False,
) -> Calibration:
    """Calibrates every device from correspondences, as ``hexcal calibrate FILE``."""

