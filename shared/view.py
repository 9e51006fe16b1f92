"""A keyframe's RGB-D view as it travels and is stored: colour as JPEG (or any image OpenCV
reads), depth as a 16-bit single-channel PNG. Intrinsics and the camera pose are the frame
structure's own (`fleetmap.frame`): a view is only accepted beside a frame that has both.

Robots encode with `encode_view` (OpenCV only); the services check with `check_view`, which
reads the image headers (Pillow) before decoding anything, so an oversized or lying image
costs no memory.
"""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass

import numpy as np

from fleetmap.camera import no_reading_as_0
from fleetmap.errors import BadInput, PayloadTooLarge

JPEG_QUALITY = 95  # colour: SIFT on q95 JPEG finds the same features as on PNG, 1/5 the size
PARTS = ("rgb", "depth")
MAX_VIEW_PIXELS = 4096 * 4096  # per image
# A JPEG's decoding cost grows with its scans: one for baseline, 10 in libjpeg's standard
# progressive script (6 for grey). A file repeating a scan passes every header check and
# makes the decoder pass over every coefficient once per scan (a scan bomb).
MAX_JPEG_SCANS = 100  # ten times the standard progressive script
JPEG_SCAN_WORK = 10 * MAX_VIEW_PIXELS  # scans x pixels: 10 scans at the pixel limit
# Plausible intrinsics for a view of width w, height h: the focal length between 0.1 w and
# 10 w (a horizontal field of view from 157 to 5.7 degrees), fy/fx within [0.5, 2], the
# principal point in the central half of the image (real cameras: within a few percent of
# the centre; 640x480 intrinsics on a 1280x960 view put it at a quarter).
FOCAL_RANGE = (0.1, 10.0)
MEDIA = {b"\xff\xd8": "image/jpeg", b"\x89P": "image/png"}


def encode_view(rgb: np.ndarray, depth: np.ndarray, quality: int = JPEG_QUALITY) -> dict:
    """{"rgb": JPEG bytes, "depth": 16-bit PNG bytes} of one view (colour in OpenCV's BGR
    order, as `fleetmap.dataset.load_rgb` gives it; depth uint16 in the camera's units)."""
    import cv2

    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise BadInput(f"Depth must be uint16 (H, W), got {depth.dtype} {depth.shape}")
    ok_c, rgb_buf = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    ok_d, depth_buf = cv2.imencode(".png", depth)
    if not (ok_c and ok_d):
        raise BadInput("The view's images do not encode")
    return {"rgb": rgb_buf.tobytes(), "depth": depth_buf.tobytes()}


def media_type(data: bytes) -> str:
    """image/jpeg, image/png, or application/octet-stream for another format."""
    return MEDIA.get(bytes(data[:2]), "application/octet-stream")


def image_size(data: bytes, name: str) -> tuple[int, int]:
    """(width, height) from an encoded image's header alone, nothing decoded (Pillow reads
    the header lazily): the pixel limit is checked before any memory is spent."""
    from PIL import Image

    if not data:
        raise BadInput(f"{name}: empty file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as im:
                size = im.size
    except Image.DecompressionBombError as exc:
        raise PayloadTooLarge(f"{name}: {exc}") from exc
    except (OSError, ValueError, SyntaxError) as exc:  # Pillow's message names the buffer
        why = str(exc).split(" <_io.BytesIO")[0]  # object at 0x..: an address, not a reason
        raise BadInput(f"{name}: not an image OpenCV or Pillow can read ({why})") from exc
    if media_type(data) == "image/jpeg":
        check_jpeg_scans(data, name, size[0] * size[1])
    return size


def jpeg_scans(data: bytes) -> int:
    """The start-of-scan markers (FF DA) in a JPEG's bytes, nothing decoded. Entropy-coded
    data stuffs every FF byte with 00 (restart markers are FF D0-D7), so FF DA appears only
    as a marker, or by chance inside a metadata segment (counted too: a bound, not a parse)."""
    return bytes(data).count(b"\xff\xda")


def check_jpeg_scans(data: bytes, name: str, pixels: int) -> None:
    """PayloadTooLarge for a JPEG with more scans than any encoder writes (MAX_JPEG_SCANS)
    or whose scans x pixels exceed the decoding budget (JPEG_SCAN_WORK)."""
    n = jpeg_scans(data)
    limit = min(MAX_JPEG_SCANS, max(1, JPEG_SCAN_WORK // max(pixels, 1)))
    if n > limit:
        raise PayloadTooLarge(
            f"{name}: a JPEG of {n} scans; at most {limit} are decoded at this size "
            f"(baseline has 1, a standard progressive JPEG 10)"
        )


def check_intrinsics(intrinsics, width: int, height: int, name: str) -> None:
    """BadInput unless the intrinsics are plausible for a view of width x height pixels
    (FOCAL_RANGE, fy/fx, principal point in the central half)."""
    k, lo, hi = intrinsics, FOCAL_RANGE[0] * width, FOCAL_RANGE[1] * width
    why = None
    if not (lo <= k.fx <= hi):
        why = f"fx {k.fx:g} outside [{lo:g}, {hi:g}] ({FOCAL_RANGE} x the width)"
    elif not (0.5 <= k.fy / k.fx <= 2.0):
        why = f"fy / fx = {k.fy / k.fx:g}, expected within [0.5, 2]"
    elif abs(k.cx - width / 2) > width / 4 or abs(k.cy - height / 2) > height / 4:
        why = f"principal point ({k.cx:g}, {k.cy:g}) outside the image's central half"
    if why:
        raise BadInput(f"{name}: intrinsics implausible for a {width}x{height} view: {why}")


def decode_image(data: bytes, name: str, depth: bool) -> np.ndarray:
    """Colour (H, W, 3) uint8 BGR, or depth (H, W) uint16; BadInput naming the part."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED if depth else 1)
    if img is None:
        raise BadInput(f"{name}: image does not decode")
    if depth and (img.dtype != np.uint16 or img.ndim != 2):
        raise BadInput(f"{name}: depth must be 16-bit single channel, got {img.dtype} {img.shape}")
    return no_reading_as_0(img) if depth else img


def _check_colour(data: bytes) -> None:
    """The colour part decodes to 8-bit grey or colour: a 16-bit image there (a depth image
    in the wrong part) was squeezed to 8 bits and stored as the view's colour."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise BadInput("rgb: image does not decode")
    if img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise BadInput(f"rgb: colour must be 8-bit, got {img.dtype} {img.shape} (a depth image?)")


def check_view(frame, parts: dict[str, bytes], max_pixels: int) -> tuple[bytes, bytes]:
    """The (colour, depth) bytes of a view posted with `frame`, checked: both parts present,
    the frame carries a pose and intrinsics, both images of the frame's size and within
    `max_pixels`, decodable, the depth 16-bit with some reading."""
    missing = [p for p in PARTS if not parts.get(p)]
    if missing:
        raise BadInput(f"A view needs both parts 'rgb' and 'depth'; missing {missing}")
    if frame.T_map_cam is None or frame.intrinsics is None:
        raise BadInput("A view needs its frame to carry the camera pose and intrinsics")
    for p in PARTS:
        w, h = image_size(parts[p], p)
        if w * h > max_pixels:
            raise PayloadTooLarge(f"{p}: {w}x{h} exceeds the pixel limit of {max_pixels}")
        if (w, h) != (frame.width, frame.height):
            raise BadInput(f"{p}: {w}x{h}, but the frame is {frame.width}x{frame.height}")
    check_intrinsics(frame.intrinsics, frame.width, frame.height, "view")
    _check_colour(parts["rgb"])
    if not decode_image(parts["depth"], "depth", True).any():
        raise BadInput("depth: the image has no valid reading")
    return bytes(parts["rgb"]), bytes(parts["depth"])


@dataclass
class StoredView:
    """A stored view as the aligner client sends it: the images as posted (`encoded`), the
    frame's pose and intrinsics; nothing decoded."""

    encoded: dict[str, bytes]
    intrinsics: object
    T_map_cam: np.ndarray
    stamp: float

    def decoded(self):
        """The view as the aligner's `RGBDView` (images decoded)."""
        from fleetmap.correspondences import RGBDView

        return RGBDView(
            decode_image(self.encoded["rgb"], "rgb", False),
            decode_image(self.encoded["depth"], "depth", True),
            self.intrinsics,
            self.T_map_cam,
            self.stamp,
        )


def stored_view(frame, rgb: bytes, depth: bytes) -> StoredView:
    return StoredView({"rgb": rgb, "depth": depth}, frame.intrinsics, frame.T_map_cam, frame.stamp)
