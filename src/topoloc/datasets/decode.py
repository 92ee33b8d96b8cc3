"""One way from stored pixels to the pixels every method sees, whatever the source.

A frame reaches topoloc as an image file (a folder, a traverse, ``localize``), a ROS message
(``sensor_msgs/CompressedImage`` or a raw ``sensor_msgs/Image``), a video frame or an array
held in memory.  All of them go through the same two steps, so that the same frame gives the
same pixels, bit for bit, from every source:

1. decode to the colour it is stored in: :func:`decode_bytes` for encoded files and messages
   (8 bits, BGR for colour, grey for grey files, EXIF orientation applied); raw messages and
   video frames are already pixels (:func:`to_bgr` brings a raw encoding's channel order to BGR);
2. convert once: :func:`to_gray` (OpenCV's ``BGR2GRAY``, the Rec. 601 weights) for the grey
   images features are extracted from, or :func:`to_bgr` where colour is wanted.

Decoding a JPEG straight to grey (``cv2.IMREAD_GRAYSCALE``) is *not* that path: libjpeg then
takes the luma channel as stored and skips the colour conversion, which differs from
``BGR2GRAY`` of the decoded colour in 0.7% of the pixels of every gardens_point day image, by up
to 16 grey levels (``python -m benchmarks.bench_decode``, ``docs/results/decode.md``), so a folder
of JPEGs and a raw ``bgr8`` bag of the same frames gave different features.  Anything that changes the pixels
this module gives must raise :data:`DECODE_VERSION`, which is part of every feature cache key.
"""

from __future__ import annotations

import io
import re
import warnings
from pathlib import Path

import cv2
import numpy as np

from topoloc.errors import input_error

DECODE_VERSION = 2
"""Version of the decode-and-convert path (1: files decoded straight to grey by libjpeg; 2: decoded
in their stored colour, then one ``BGR2GRAY``); part of every feature cache key, so that features
cached under another version are never reused."""

# Colour as stored, 8 bits, EXIF orientation applied (unlike IMREAD_UNCHANGED, which skips it):
# grey files stay one channel, colour files (alpha dropped) come as BGR.
_DECODE_FLAGS = cv2.IMREAD_ANYCOLOR

#: Most pixels (width x height) an image may have.  The size is read from the file's header and a
#: larger image is refused before it is decoded: a few megabytes of PNG can announce 32000 x 32000
#: pixels, 1 GB grey and 3 GB BGR once decoded.  2**28 (268 million) is above the largest camera
#: sensors (200 megapixels, 805 MB BGR at most).
MAX_IMAGE_PIXELS = 1 << 28


def image_header_size(data: bytes | np.ndarray) -> tuple[int, int] | None:
    """Width and height an encoded image announces in its header, without decoding it.

    Parameters
    ----------
    data : bytes or ndarray of uint8
        The encoded file (PNG, JPEG, TIFF, WebP, BMP, PPM/PGM...).

    Returns
    -------
    (width, height) or None
        None when Pillow does not know the format (OpenCV then decides).
    """
    from PIL import Image

    buf = data if isinstance(data, bytes) else np.ascontiguousarray(data).data
    try:
        with warnings.catch_warnings():
            # Pillow warns of (and past twice its own limit, refuses) large images: the size is what we need.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(buf)) as im:
                width, height = im.size
    except Image.DecompressionBombError as exc:
        # Pillow refuses to report sizes past twice its own limit, which is above ours.
        match = re.search(r"\((\d+) pixels\)", str(exc))
        pixels = int(match.group(1)) if match else MAX_IMAGE_PIXELS + 1
        return pixels, 1
    except Exception:  # any format Pillow cannot parse is left to OpenCV
        return None
    return int(width), int(height)


def check_image_size(data: bytes | np.ndarray, where: str | Path, *, context: str = "") -> None:
    """Refuse an encoded image whose header announces more than :data:`MAX_IMAGE_PIXELS` pixels.

    Parameters
    ----------
    data : bytes or ndarray of uint8
        The encoded image.
    where : str or Path
        The file the message names.
    context : str
        Said before the problem (``"topic /cam, message 3: "``).

    Raises
    ------
    TopolocError
        One line naming ``where`` (the file, or the message of a recording).
    """
    size = image_header_size(data)
    if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
        shown = f"{size[0]}x{size[1]} pixels" if size[1] > 1 else f"{size[0]} pixels"
        raise input_error(f"{context}image is too large to decode ({shown}, more than {MAX_IMAGE_PIXELS} pixels)",
                          where)


def decode_bytes(data: bytes | np.ndarray, where: str | Path, *, gray: bool = True, context: str = "") -> np.ndarray:
    """Pixels of an encoded image (a file's bytes, a ``CompressedImage`` message's data).

    The size announced in the header is checked first (:func:`check_image_size`), then the
    image is decoded in its stored colour and converted once (:func:`to_gray` or :func:`to_bgr`).

    Parameters
    ----------
    data : bytes or ndarray of uint8
        The encoded image (JPEG, PNG, anything ``cv2.imdecode`` reads).
    where : str or Path
        The file a message names.
    gray : bool
        Grey (H, W) or BGR (H, W, 3).
    context : str
        Said before the problem (``"topic /cam, message 3: "``).

    Returns
    -------
    ndarray of uint8, shape (H, W) if ``gray`` else (H, W, 3)

    Raises
    ------
    TopolocError
        For empty data, an image too large to decode, or data OpenCV cannot decode.
    """
    buf = np.frombuffer(data, np.uint8) if isinstance(data, bytes) else np.asarray(data, np.uint8).reshape(-1)
    if buf.size == 0:
        raise input_error(f"{context}image is empty", where)
    check_image_size(buf, where, context=context)
    try:
        img = cv2.imdecode(buf, _DECODE_FLAGS)
    except cv2.error:
        # OpenCV refuses some headers itself (a size past its own limit) with an exception.
        img = None
    if img is None or img.size == 0:
        raise input_error(f"{context}image is corrupt or not a supported format", where)
    return to_gray(img) if gray else to_bgr(img)


def has_image_reader(path: str | Path) -> bool:
    """Whether OpenCV has a decoder for the file's header (``cv2.haveImageReader``), whatever its name.

    OpenCV takes the name as UTF-8: a name that is not (bytes of another
    encoding, as Python's surrogate escapes carry them) crashed the process
    (issue #41), so such a file's first bytes are looked at through a
    temporary copy under a plain name.
    """
    name = str(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        import tempfile

        try:
            with open(path, "rb") as fh:
                head = fh.read(1 << 16)
        except OSError:
            return False
        suffix = Path(name).suffix
        with tempfile.NamedTemporaryFile(prefix="topoloc-header-", suffix=suffix if suffix.isascii() else "") as tmp:
            tmp.write(head)
            tmp.flush()
            return bool(cv2.haveImageReader(tmp.name))
    return bool(cv2.haveImageReader(name))


def read_image(path: str | Path, *, gray: bool = True) -> np.ndarray:
    """Read an image file: its bytes through :func:`decode_bytes`.

    Returns
    -------
    ndarray of uint8, shape (H, W) if ``gray`` else (H, W, 3) BGR

    Raises
    ------
    TopolocError
        If the file is missing, empty, too large or cannot be decoded.
    """
    path = Path(path)
    try:
        buf = np.fromfile(path, dtype=np.uint8)
    except OSError:
        raise input_error("cannot open image", path) from None
    if buf.size == 0:
        raise input_error("image file is empty", path)
    return decode_bytes(buf, path, gray=gray)


def to_gray(image: np.ndarray) -> np.ndarray:
    """The one conversion to grey: ``BGR2GRAY`` of a BGR image, ``BGRA2GRAY`` of BGRA; grey as it is.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA

    Returns
    -------
    ndarray of uint8, shape (H, W), C-contiguous

    Raises
    ------
    ValueError
        For another dtype or shape.
    """
    if image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return np.ascontiguousarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise ValueError(f"expected a gray (H, W) or BGR (H, W, 3) image, got shape {image.shape}")


def to_bgr(image: np.ndarray, code: int | None = None) -> np.ndarray:
    """BGR pixels: ``code`` (a ``cv2.COLOR_*2BGR`` conversion of a raw encoding) applied, grey replicated.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4)
        BGR, BGRA or grey; or pixels in the channel order ``code`` converts from.
    code : int, optional
        The conversion to BGR of a raw message's encoding (``cv2.COLOR_RGB2BGR``, a Bayer or
        YUV code...); None when the pixels are already BGR, BGRA or grey.

    Returns
    -------
    ndarray of uint8, shape (H, W, 3), C-contiguous
    """
    if code is not None:
        return np.ascontiguousarray(cv2.cvtColor(image, code))
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(image)


__all__ = ["DECODE_VERSION", "MAX_IMAGE_PIXELS", "check_image_size", "decode_bytes", "has_image_reader",
           "image_header_size", "read_image", "to_bgr", "to_gray"]
