"""V4L2 raw pixel formats as a pure codec: buffer bytes <-> 2-D uint16 arrays, vectorized, no I/O.

Byte layouts follow the kernel's V4L2 documentation (pixfmt-yuv-luma, pixfmt-srggb*): unpacked 10..14-bit
samples sit in little-endian 16-bit words with zero high bits; 'P' formats are MIPI CSI-2 packed (high 8 bits
per sample first, the low bits gathered in the trailing byte(s)); Y10B is a big-endian bitstream; Y012 holds
12 bits in the high bits of a little-endian word. `pack` is the inverse, for simulators and mocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mlaqc.errors import InputError

BIG_ENDIAN_FLAG = 1 << 31

# packing -> (pixels per group, bytes per group)
_GROUPS: dict[str, tuple[int, int]] = {
    "u8": (1, 1),
    "u16le": (1, 2),
    "u16be": (1, 2),
    "u16le_msb": (1, 2),
    "mipi10": (4, 5),
    "mipi12": (2, 3),
    "mipi14": (4, 7),
    "y10b": (4, 5),
}


def fourcc(code: str) -> int:
    """The 32-bit V4L2 code of a four-character code: fourcc('Y16 ') == 0x20363159."""
    if len(code) != 4:
        raise ValueError(f"a fourcc has 4 characters, got {code!r}")
    return sum(ord(ch) << (8 * i) for i, ch in enumerate(code))


def fourcc_text(code: int) -> str:
    """Readable form of a V4L2 code for messages: 0x20363159 -> 'Y16', with '-BE' for big-endian codes."""
    text = "".join(chr((code >> (8 * i)) & 0x7F) for i in range(4)).rstrip(" \0")
    return text + ("-BE" if code & BIG_ENDIAN_FLAG else "")


@dataclass(frozen=True)
class PixelFormat:
    """One raw V4L2 format: canonical `name` (used in Frame.pixel_format), `code`, `bits`, `packing`, `cfa`."""

    name: str
    code: int
    bits: int
    packing: str
    cfa: str | None = None
    aliases: tuple[str, ...] = ()

    @property
    def packed(self) -> bool:
        """True for formats that share bytes between pixels."""
        return _GROUPS[self.packing][0] > 1

    def min_bytes_per_line(self, width: int) -> int:
        """Smallest row stride in bytes for `width` pixels (whole packing groups)."""
        per_group, group_bytes = _GROUPS[self.packing]
        return -(-width // per_group) * group_bytes

    def min_image_bytes(self, width: int, height: int, bytes_per_line: int = 0) -> int:
        """Bytes a complete image must hold (the last row needs no padding)."""
        stride = bytes_per_line or self.min_bytes_per_line(width)
        return stride * (height - 1) + self.min_bytes_per_line(width) if height else 0

    def unpack(self, buf: bytes | bytearray | memoryview | np.ndarray, width: int, height: int,
               bytes_per_line: int = 0) -> np.ndarray:
        """Decode one image buffer into a (height, width) uint16 array; ValueError if it is too short."""
        rows = _row_view(self, buf, width, height, bytes_per_line)
        return np.ascontiguousarray(_UNPACK[self.packing](rows, width, self.bits), dtype=np.uint16)

    def pack(self, data: np.ndarray, bytes_per_line: int = 0) -> bytes:
        """Encode a (H, W) array into the bytes a V4L2 driver would deliver (rows padded to `bytes_per_line`)."""
        data = np.asarray(data)
        if data.ndim != 2 or data.size == 0:
            raise ValueError(f"pack needs a non-empty 2-D array, got shape {data.shape}")
        if data.min() < 0 or data.max() >= (1 << self.bits):
            raise ValueError(f"{self.name} holds {self.bits}-bit values, got range {data.min()}..{data.max()}")
        height, width = data.shape
        per_group, _ = _GROUPS[self.packing]
        padded = np.zeros((height, -(-width // per_group) * per_group), dtype=np.uint16)
        padded[:, :width] = data
        rows = _PACK[self.packing](padded, self.bits)
        stride = bytes_per_line or rows.shape[1]
        if stride < rows.shape[1]:
            raise ValueError(f"bytes_per_line {stride} is shorter than a {self.name} row of {rows.shape[1]} bytes")
        out = np.zeros((height, stride), dtype=np.uint8)
        out[:, : rows.shape[1]] = rows
        return out.tobytes()


def _row_view(fmt: PixelFormat, buf, width: int, height: int, bytes_per_line: int) -> np.ndarray:
    """A zero-copy (height, row_bytes) uint8 view of the buffer honouring the row stride."""
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    row_bytes = fmt.min_bytes_per_line(width)
    stride = bytes_per_line or row_bytes
    if stride < row_bytes:
        raise ValueError(f"bytes_per_line {stride} is shorter than a {fmt.name} row of {row_bytes} bytes")
    flat = np.frombuffer(buf, dtype=np.uint8) if not isinstance(buf, np.ndarray) else buf.reshape(-1).view(np.uint8)
    need = fmt.min_image_bytes(width, height, stride)
    if flat.size < need:
        raise ValueError(f"{fmt.name} {width}x{height} needs {need} bytes, buffer holds {flat.size}")
    return np.lib.stride_tricks.as_strided(flat, shape=(height, row_bytes), strides=(stride, 1), writeable=False)


def _groups(rows: np.ndarray, group_bytes: int, dtype: type) -> np.ndarray:
    """Rows of bytes reshaped to (H, groups, group_bytes) in a wider integer type."""
    return rows.reshape(rows.shape[0], -1, group_bytes).astype(dtype)


def _unpack_u8(rows: np.ndarray, width: int, bits: int) -> np.ndarray:
    return rows[:, :width]


def _unpack_u16(order: str, shift: int = 0):
    def unpack(rows: np.ndarray, width: int, bits: int) -> np.ndarray:
        words = np.ascontiguousarray(rows[:, : 2 * width]).view(order + "u2")
        return words >> (16 - bits) if shift else words
    return unpack


def _unpack_mipi10(rows: np.ndarray, width: int, bits: int) -> np.ndarray:
    g = _groups(rows, 5, np.uint16)
    low = (g[..., 4:5] >> np.array([0, 2, 4, 6], np.uint16)) & 0x3
    return ((g[..., :4] << 2) | low).reshape(rows.shape[0], -1)[:, :width]


def _unpack_mipi12(rows: np.ndarray, width: int, bits: int) -> np.ndarray:
    g = _groups(rows, 3, np.uint16)
    low = (g[..., 2:3] >> np.array([0, 4], np.uint16)) & 0xF
    return ((g[..., :2] << 4) | low).reshape(rows.shape[0], -1)[:, :width]


def _unpack_mipi14(rows: np.ndarray, width: int, bits: int) -> np.ndarray:
    g = _groups(rows, 7, np.uint32)
    low_word = g[..., 4] | (g[..., 5] << 8) | (g[..., 6] << 16)
    low = (low_word[..., None] >> np.array([0, 6, 12, 18], np.uint32)) & 0x3F
    return ((g[..., :4] << 6) | low).reshape(rows.shape[0], -1)[:, :width]


def _unpack_y10b(rows: np.ndarray, width: int, bits: int) -> np.ndarray:
    g = _groups(rows, 5, np.uint64)
    word = (g[..., 0] << 32) | (g[..., 1] << 24) | (g[..., 2] << 16) | (g[..., 3] << 8) | g[..., 4]
    pixels = (word[..., None] >> np.array([30, 20, 10, 0], np.uint64)) & 0x3FF
    return pixels.reshape(rows.shape[0], -1)[:, :width]


_UNPACK = {
    "u8": _unpack_u8,
    "u16le": _unpack_u16("<"),
    "u16be": _unpack_u16(">"),
    "u16le_msb": _unpack_u16("<", shift=1),
    "mipi10": _unpack_mipi10,
    "mipi12": _unpack_mipi12,
    "mipi14": _unpack_mipi14,
    "y10b": _unpack_y10b,
}


def _as_bytes(groups: np.ndarray) -> np.ndarray:
    """(H, G, k) byte values -> (H, G*k) uint8 rows."""
    return groups.astype(np.uint8).reshape(groups.shape[0], -1)


def _pack_u8(data: np.ndarray, bits: int) -> np.ndarray:
    return data.astype(np.uint8)


def _pack_u16(order: str, shift: int = 0):
    def pack(data: np.ndarray, bits: int) -> np.ndarray:
        words = (data << (16 - bits)) if shift else data
        return words.astype(order + "u2").view(np.uint8).reshape(data.shape[0], -1)
    return pack


def _pack_mipi(per_group: int, low_bits: int):
    def pack(data: np.ndarray, bits: int) -> np.ndarray:
        p = data.reshape(data.shape[0], -1, per_group).astype(np.uint32)
        low = p & ((1 << low_bits) - 1)
        low_word = np.bitwise_or.reduce(low << (low_bits * np.arange(per_group, dtype=np.uint32)), axis=-1)
        low_bytes = (low_word[..., None] >> (8 * np.arange(per_group * low_bits // 8, dtype=np.uint32))) & 0xFF
        return _as_bytes(np.concatenate([p >> low_bits, low_bytes], axis=-1))
    return pack


def _pack_y10b(data: np.ndarray, bits: int) -> np.ndarray:
    p = data.reshape(data.shape[0], -1, 4).astype(np.uint64)
    word = np.bitwise_or.reduce(p << np.array([30, 20, 10, 0], np.uint64), axis=-1)
    return _as_bytes((word[..., None] >> np.array([32, 24, 16, 8, 0], np.uint64)) & 0xFF)


_PACK = {
    "u8": _pack_u8,
    "u16le": _pack_u16("<"),
    "u16be": _pack_u16(">"),
    "u16le_msb": _pack_u16("<", shift=1),
    "mipi10": _pack_mipi(4, 2),
    "mipi12": _pack_mipi(2, 4),
    "mipi14": _pack_mipi(4, 6),
    "y10b": _pack_y10b,
}


def _mono_formats() -> list[PixelFormat]:
    """Luma-only formats (pixfmt-yuv-luma)."""
    table = [
        ("GREY", "GREY", 8, "u8", ()),
        ("Y10", "Y10 ", 10, "u16le", ()),
        ("Y12", "Y12 ", 12, "u16le", ()),
        ("Y14", "Y14 ", 14, "u16le", ()),
        ("Y16", "Y16 ", 16, "u16le", ()),
        ("Y012", "Y012", 12, "u16le_msb", ()),
        ("Y10P", "Y10P", 10, "mipi10", ()),
        ("Y12P", "Y12P", 12, "mipi12", ()),
        ("Y14P", "Y14P", 14, "mipi14", ()),
        ("Y10B", "Y10B", 10, "y10b", ("Y10BPACK",)),
    ]
    formats = [PixelFormat(name, fourcc(code), bits, packing, None, aliases)
               for name, code, bits, packing, aliases in table]
    formats.append(PixelFormat("Y16_BE", fourcc("Y16 ") | BIG_ENDIAN_FLAG, 16, "u16be", None, ("Y16-BE",)))
    return formats


# (bits, packed) -> fourccs for BGGR, GBRG, GRBG, RGGB (pixfmt-srggb*)
_BAYER_CODES = {
    (8, False): ("BA81", "GBRG", "GRBG", "RGGB"),
    (10, False): ("BG10", "GB10", "BA10", "RG10"),
    (12, False): ("BG12", "GB12", "BA12", "RG12"),
    (14, False): ("BG14", "GB14", "GR14", "RG14"),
    (16, False): ("BYR2", "GB16", "GR16", "RG16"),
    (10, True): ("pBAA", "pGAA", "pgAA", "pRAA"),
    (12, True): ("pBCC", "pGCC", "pgCC", "pRCC"),
    (14, True): ("pBEE", "pGEE", "pgEE", "pREE"),
}
_BAYER_PACKING = {8: "u8", 10: "u16le", 12: "u16le", 14: "u16le", 16: "u16le"}


def _bayer_formats() -> list[PixelFormat]:
    """Raw Bayer formats, unpacked and MIPI-packed."""
    formats = []
    for (bits, packed), codes in _BAYER_CODES.items():
        for cfa, code in zip(("BGGR", "GBRG", "GRBG", "RGGB"), codes):
            packing = f"mipi{bits}" if packed else _BAYER_PACKING[bits]
            alias = f"S{cfa}{bits}" + ("P" if packed else "")
            formats.append(PixelFormat(code, fourcc(code), bits, packing, cfa, (alias,)))
    return formats


FORMATS: tuple[PixelFormat, ...] = tuple(_mono_formats() + _bayer_formats())
_BY_CODE = {f.code: f for f in FORMATS}
_BY_NAME = {f.name: f for f in FORMATS}
_BY_ALIAS = {alias.upper(): f for f in FORMATS for alias in f.aliases}


def format_by_code(code: int) -> PixelFormat | None:
    """The decodable format with this V4L2 code, or None (e.g. MJPG, YUYV)."""
    return _BY_CODE.get(code)


def lookup_format(name: str) -> PixelFormat:
    """Find a format by fourcc name ('Y16', 'RG10', 'pRAA') or kernel name ('SRGGB10P'); InputError if unknown."""
    key = name.strip()
    found = _BY_NAME.get(key) or _BY_ALIAS.get(key.upper()) or _BY_NAME.get(key.upper())
    if found is None:
        known = ", ".join(f.name for f in FORMATS)
        raise InputError(f"unknown or unsupported raw pixel format {name!r}; supported: {known}")
    return found
