"""RGB-D frame compression: JPEG for colour, lossless 16-bit PNG for depth, in one byte string.

Layout: magic ``CF1``, then big-endian u32 lengths of the JPEG and PNG parts, then both parts.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np

_MAGIC = b"CF1"
_HEADER = struct.Struct(">3sII")


def encode_frame(rgb: np.ndarray, depth_mm: np.ndarray, jpeg_quality: int) -> bytes:
    """Compress an RGB (HxWx3 uint8) and depth (HxW uint16, mm) pair."""
    ok1, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    # PNG level 1: depth compresses little better at higher levels but costs much more CPU.
    ok2, png = cv2.imencode(".png", depth_mm, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not (ok1 and ok2):
        raise RuntimeError("OpenCV failed to encode a frame")
    return _HEADER.pack(_MAGIC, len(jpg), len(png)) + jpg.tobytes() + png.tobytes()


def decode_frame(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``encode_frame``: (rgb uint8 HxWx3, depth uint16 HxW mm)."""
    magic, n_jpg, n_png = _HEADER.unpack_from(data)
    if magic != _MAGIC or _HEADER.size + n_jpg + n_png != len(data):
        raise ValueError("not a compressed RGB-D frame (bad header or truncated)")
    jpg = np.frombuffer(data, np.uint8, n_jpg, _HEADER.size)
    png = np.frombuffer(data, np.uint8, n_png, _HEADER.size + n_jpg)
    bgr = cv2.imdecode(jpg, cv2.IMREAD_COLOR)
    depth = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
    if bgr is None or depth is None:
        raise ValueError("corrupt JPEG or PNG in frame")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth


def split_packets(payload_bytes: int, mtu_bytes: int) -> list[int]:
    """IP packet sizes carrying ``payload_bytes`` of application data (IPv4 + UDP + 12-byte
    application header per packet)."""
    overhead = 20 + 8 + 12
    room = mtu_bytes - overhead
    n = max(1, -(-payload_bytes // room))
    sizes = [room + overhead] * (n - 1)
    sizes.append(payload_bytes - room * (n - 1) + overhead)
    return sizes


def slot_after(t_us: int, slot_us: int) -> int:
    """The first slot boundary strictly after ``t_us``: when a packet handed to the modem at
    ``t_us`` enters the UE buffer."""
    return (t_us // slot_us + 1) * slot_us
