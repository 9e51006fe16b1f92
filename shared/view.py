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

from fleetmap.errors import BadInput, PayloadTooLarge

JPEG_QUALITY = 95  # colour: SIFT on q95 JPEG finds the same features as on PNG, 1/5 the size
PARTS = ("rgb", "depth")
MAX_VIEW_PIXELS = 4096 * 4096  # per image
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
                return im.size
    except Image.DecompressionBombError as exc:
        raise PayloadTooLarge(f"{name}: {exc}") from exc
    except (OSError, ValueError, SyntaxError) as exc:
        raise BadInput(f"{name}: not an image OpenCV or Pillow can read ({exc})") from exc


def decode_image(data: bytes, name: str, depth: bool) -> np.ndarray:
    """Colour (H, W, 3) uint8 BGR, or depth (H, W) uint16; BadInput naming the part."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED if depth else 1)
    if img is None:
        raise BadInput(f"{name}: image does not decode")
    if depth and (img.dtype != np.uint16 or img.ndim != 2):
        raise BadInput(f"{name}: depth must be 16-bit single channel, got {img.dtype} {img.shape}")
    return img


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
    decode_image(parts["rgb"], "rgb", False)
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
