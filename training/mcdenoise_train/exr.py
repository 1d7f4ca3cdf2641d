"""OpenEXR I/O, the one module that reads and writes EXR files (training, evaluation, data generation).

Frames are in the layout of docs/frame-layout.md: single-part scanline files, channel
names exactly as the engine reads them, as dicts of 2-D arrays keyed by full channel name
(`diffuse.R`, `depth.Z`, `covariance`, ...). Every writer is atomic (`files.atomic_path`):
a temporary name in the same directory, then a rename, so an interrupted run never leaves
a truncated file under the final name.

- `write_exr` / `read_exr`: plain frames, float32 (or all half) with ZIP compression; the
  reader takes any single-part file and gives float32 arrays. `exr_pixel_types` tells the
  stored sample type per channel.
- `write_frame` / `read_frame` / `is_complete`: the data generator's frames, with
  metadata and the storage precision below.
- `read_parts`: every part of a multi-part file (Blender's multi-layer EXRs).

Data sets are written in half float (`precision="half"`) with PXR24 compression: every
image channel as half (compressed losslessly), every `*Variance` channel as float32 rounded to half's
10-bit mantissa (relative precision 5e-4, far below the estimator's own scatter, which is
at least 12 % at 128 spp), because variances span more decades than half holds (a pixel
on the edge of a directly seen sun has a variance above half's maximum of 65504, a dim
diffuse wall one far below its smallest normal value, 6e-5, and the engine divides diffuse
variance by the squared albedo). An image channel whose values exceed the half range is
kept in float32 as well. A 256x256 frame takes about 1-2 MB. Test fixtures stay float32 with
ZIP (`precision="float"`, lossless). Metadata (scene, seed, spp, covariance scale, ...) goes into
string/float header attributes prefixed `mcdenoise.`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import OpenEXR

from .files import atomic_path

#: Every channel of a frame with covariance, in the layout's naming.
CHANNELS_NOCOV = (
    "R", "G", "B", "colorVariance.Z",
    "diffuse.R", "diffuse.G", "diffuse.B", "diffuseVariance.Z",
    "specular.R", "specular.G", "specular.B", "specularVariance.Z",
    "albedo.R", "albedo.G", "albedo.B", "albedoVariance.Z",
    "normal.R", "normal.G", "normal.B", "normalVariance.Z",
    "depth.Z", "depthVariance.Z",
)
CHANNELS = CHANNELS_NOCOV + ("covariance", "covarianceVariance.Z")


def _attr(v):
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v)).lower()
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    if isinstance(v, str):
        return v
    return json.dumps(v)


HALF_MAX = 65504.0


def round_mantissa(v, bits: int = 10):
    """float32 rounded to nearest with `bits` mantissa bits (half's precision, float32's
    range); the zeroed low bits compress."""
    u = np.ascontiguousarray(v, np.float32).view(np.uint32).astype(np.uint64)
    drop = 23 - bits
    u = ((u + (1 << (drop - 1))) >> drop) << drop
    r = np.minimum(u, 0xFFFFFFFF).astype(np.uint32).view(np.float32)
    return np.where(np.isfinite(r), r, v).astype(np.float32)  # never round up into infinity


def _pixels(name: str, v, precision: str):
    v = np.ascontiguousarray(v, np.float32)
    if precision == "half":
        if "Variance" in name:
            return round_mantissa(v) if np.isfinite(v).all() else v
        if float(np.max(np.abs(v), initial=0.0)) < HALF_MAX:
            return v.astype(np.float16)
    return v


def write_frame(path, channels: dict, meta: dict | None = None, compression=None,
                precision: str = "float") -> None:
    """Write `channels` (name -> (H, W) array) atomically as a single-part EXR, float32
    (`precision="float"`) or half float for image channels (`"half"`, see above)."""
    if precision not in ("float", "half"):
        raise ValueError(f"precision must be 'float' or 'half', not {precision!r}")
    if compression is None:
        compression = OpenEXR.PXR24_COMPRESSION if precision == "half" else OpenEXR.ZIP_COMPRESSION
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": compression, "type": OpenEXR.scanlineimage}
    for k, v in (meta or {}).items():
        header[f"mcdenoise.{k}"] = _attr(v)
    _write(path, header, {k: _pixels(k, v, precision) for k, v in channels.items()})


def _write(path, header: dict, data: dict) -> None:
    with atomic_path(path) as tmp, OpenEXR.File(header, data) as f:
        f.write(tmp)


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray], half: bool = False) -> None:
    """Write `channels` (name -> [H, W] array) atomically as a single-part, ZIP-compressed
    EXR, every channel float32 or (`half`) half."""
    shapes = {np.shape(a) for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"channels must be 2-D arrays of one shape, got {sorted(shapes)}")
    dtype = np.float16 if half else np.float32
    # OpenEXR.File replaces the dict's values by Channel objects: give it a copy.
    data = {name: np.ascontiguousarray(a, dtype=dtype) for name, a in channels.items()}
    _write(path, {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, data)


def read_frame(path) -> tuple[dict, dict]:
    """(channels, metadata) of an EXR: float32 (H, W) arrays by full channel name, and the
    `mcdenoise.*` header attributes without the prefix."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = {k: np.asarray(c.pixels, np.float32) for k, c in f.channels().items()}
        meta = {k[len("mcdenoise."):]: v for k, v in f.header().items() if k.startswith("mcdenoise.")}
    return ch, meta


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All channels of a single-part EXR as float32 [H, W] arrays keyed by full name."""
    return read_frame(path)[0]


def exr_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an EXR's data window, from its header alone."""
    with OpenEXR.File(str(path), header_only=True) as f:
        lo, hi = f.header()["dataWindow"]
    return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)


def exr_pixel_types(path: str | os.PathLike) -> dict[str, str]:
    """Stored sample type per channel ('HALF', 'FLOAT' or 'UINT')."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        return {name: ch.type().name for name, ch in f.channels().items()}


def read_parts(path: str | os.PathLike) -> list[dict[str, np.ndarray]]:
    """The channels of every part of a (multi-part) EXR, float32 arrays by channel name."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        return [{name: np.asarray(ch.pixels, np.float32) for name, ch in part.channels.items()}
                for part in f.parts]


def is_complete(path, expect_channels=CHANNELS) -> bool:
    """Whether `path` is a readable frame with all `expect_channels` (used to resume)."""
    if not os.path.isfile(path):
        return False
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            names = set(f.channels().keys())
        return set(expect_channels) <= names
    except Exception:
        return False
