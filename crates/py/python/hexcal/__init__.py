"""hexcal from Python: calibrations of structured-light rigs (cameras and projectors).

Units are millimetres and pixels; pixel (0, 0) is the centre of the top-left pixel; poses
are ``T_device_ref`` (``X_device = R @ X_ref + T``). Every refused input raises
:class:`Error` (a ``ValueError``) with the hexcal command line's one-line message.

- :func:`load` reads a ``calibration.json``; ``cal["cam0"]`` is a :class:`Device` that
  projects, unprojects and gives its lens model, pose and covariance.
- :func:`triangulate` intersects pixel pairs of two devices; :func:`verify` is
  ``hexcal verify`` on held-out poses.
- :func:`detect` finds the board's circles and lattice labels in a grey image;
  :func:`decode` turns a camera's phase-shift stack into projector (u, v) maps.
- :func:`calibrate` calibrates from correspondences (the correspondences file's layout).
"""

from ._hexcal import (
    Calibration,
    Device,
    Error,
    calibrate,
    decode,
    detect,
    load,
    triangulate,
    verify,
)

__all__ = [
    "Calibration",
    "Device",
    "Error",
    "calibrate",
    "decode",
    "detect",
    "load",
    "triangulate",
    "verify",
]
