"""Images and video for the demo and the examples: colour maps, side-by-side panels, JPEG/PNG
encoding (Debian's python3-pil) and a dependency-free MJPEG AVI writer."""
import io
import os
import struct

import numpy as np
from PIL import Image, ImageDraw, ImageFont

# Anchor colours of a perceptually ordered map (dark blue -> cyan -> yellow -> dark red), so a
# range image reads near = warm, far = cold without a plotting library.
_ANCHORS = np.array([[48, 18, 59], [40, 120, 240], [30, 210, 190], [130, 250, 80], [245, 200, 40],
                     [240, 90, 20], [122, 4, 3]], dtype=np.float64)


def colourise(values, lo, hi, invalid=None):
    """float HxW -> uint8 HxWx3; values outside [lo, hi] clamp; `invalid` (bool HxW) is black."""
    t = np.clip((np.asarray(values, dtype=np.float64) - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    x = t * (len(_ANCHORS) - 1)
    i = np.minimum(x.astype(np.int64), len(_ANCHORS) - 2)
    f = (x - i)[..., None]
    rgb = (_ANCHORS[i] * (1 - f) + _ANCHORS[i + 1] * f).round().astype(np.uint8)
    if invalid is not None:
        rgb[invalid] = 0
    return rgb


def range_image_rgb(range_m, max_range_m=50.0):
    """A LiDAR range image (beams x columns, 0 = no return) as colour, near warm, far cold."""
    r = np.asarray(range_m, dtype=np.float64)
    return colourise(max_range_m - np.minimum(r, max_range_m), 0.0, max_range_m, invalid=r <= 0)


def resize(rgb, width, height, nearest=False):
    img = Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8))
    return np.asarray(img.resize((width, height), Image.NEAREST if nearest else Image.BILINEAR))


def load_rgb(path):
    with Image.open(path) as img:
        return np.asarray(img.convert("RGB"))


def side_by_side(rendered, logged, range_m=None, gap=4):
    """[rendered | logged] on top, the LiDAR range image stretched across the width below."""
    h, w = rendered.shape[:2]
    logged = resize(logged, w, h) if logged.shape[:2] != (h, w) else logged
    top = np.concatenate([rendered, np.zeros((h, gap, 3), np.uint8), logged], axis=1)
    if range_m is None:
        return top
    lidar = resize(range_image_rgb(range_m), top.shape[1], max(48, 2 * np.asarray(range_m).shape[0]), nearest=True)
    return np.concatenate([top, np.zeros((gap, top.shape[1], 3), np.uint8), lidar], axis=0)


def caption(rgb, text, height=16):
    """A black strip with one line of text above the image (PIL's built-in bitmap font)."""
    bar = Image.new("RGB", (rgb.shape[1], height), (0, 0, 0))
    ImageDraw.Draw(bar).text((4, 2), text, fill=(235, 235, 235), font=ImageFont.load_default())
    return np.concatenate([np.asarray(bar), rgb], axis=0)


def encode(rgb, fmt="JPEG", quality=85):
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8)).save(buf, format=fmt, quality=quality)
    return buf.getvalue()


def write_mjpeg_avi(path, jpegs, width, height, fps):
    """A minimal AVI (RIFF) with one MJPG video stream: no codec library needed, plays anywhere.
    Written to a temporary name and renamed, so a reader never sees half a file."""
    def chunk(fourcc, data):
        pad = b"\0" if len(data) % 2 else b""
        return fourcc + struct.pack("<I", len(data)) + data + pad

    def lst(kind, payload):
        return b"LIST" + struct.pack("<I", len(payload) + 4) + kind + payload

    n = len(jpegs)
    max_size = max((len(j) for j in jpegs), default=0)
    avih = struct.pack("<IIIIIIIIII4I", int(1e6 / fps), max_size * fps, 0, 0x10, n, 0, 1, max_size,
                       width, height, 0, 0, 0, 0)
    strh = struct.pack("<4s4sIHHIIIIIIIIhhhh", b"vids", b"MJPG", 0, 0, 0, 0, 1, fps, 0, n, max_size,
                       0xFFFFFFFF, 0, 0, 0, width, height)
    strf = struct.pack("<IiiHH4sIiiII", 40, width, height, 1, 24, b"MJPG", width * height * 3, 0, 0, 0, 0)
    hdrl = lst(b"hdrl", chunk(b"avih", avih) + lst(b"strl", chunk(b"strh", strh) + chunk(b"strf", strf)))
    movi_payload = b""
    index = b""
    offset = 4
    for j in jpegs:
        c = chunk(b"00dc", j)
        index += b"00dc" + struct.pack("<III", 0x10, offset, len(j))
        movi_payload += c
        offset += len(c)
    movi = lst(b"movi", movi_payload)
    body = b"AVI " + hdrl + movi + chunk(b"idx1", index)
    with open(path + ".tmp", "wb") as f:
        f.write(b"RIFF" + struct.pack("<I", len(body)) + body)
    os.replace(path + ".tmp", path)
