"""Aerial maps on disk: nav2 ``map_server``'s YAML + image convention (BEVO+).

A map is a YAML file next to (or naming) an image::

    image: orthophoto.png        # relative to the YAML file, or absolute
    resolution: 0.25             # metres per pixel
    origin: [-120.0, -80.0, 0.0] # map-frame pose (x, y, yaw) of the image's lower-left corner
    negate: 0                    # optional: 1 inverts the intensities
    mode: raw                    # for nav2 map_server (RViz display); ignored here

The image may be grey (8 or 16 bit), RGB or RGBA (any format OpenCV reads: PNG, JPEG, TIFF; a
GeoTIFF's geo-referencing is not read: give ``origin`` and ``resolution`` from its metadata). An
alpha channel is the validity mask (0 = no data), which is how :func:`save_map` stores a mosaic.
Files are written atomically (:func:`bevo_ros.io.files.atomic_write_bytes`).
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

from bevo_ros.config import ConfigError, read_yaml
from bevo_ros.io.files import atomic_write_bytes, atomic_write_text
from bevo_ros.core.aerial_map import AerialMap

__all__ = ["load_map", "save_map"]


def load_map(path: str | os.PathLike) -> AerialMap:
    """Read a map YAML and its image. Raises :class:`~bevo_ros.config.ConfigError` naming the
    file and the problem (missing keys, unreadable image, bad resolution/origin)."""
    path = Path(path)
    doc = read_yaml(path, "map file")
    if not isinstance(doc, dict):
        raise ConfigError(f"map file {path}: expected a mapping with image, resolution, origin")
    missing = [k for k in ("image", "resolution", "origin") if k not in doc]
    if missing:
        raise ConfigError(f"map file {path}: missing {', '.join(missing)}")
    try:
        if isinstance(doc["resolution"], bool) or not isinstance(doc["origin"], (list, tuple)) or any(
                isinstance(v, bool) for v in doc["origin"]):
            raise TypeError
        resolution = float(doc["resolution"])
        origin = [float(v) for v in doc["origin"]]
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"map file {path}: resolution must be a number and origin [x, y, yaw]") from None
    if not (math.isfinite(resolution) and resolution > 0):
        raise ConfigError(f"map file {path}: resolution must be > 0, got {doc['resolution']!r}")
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise ConfigError(f"map file {path}: origin must be three finite numbers [x, y, yaw], got {doc['origin']!r}")
    image_path = Path(str(doc["image"]))
    if not image_path.is_absolute():
        image_path = path.parent / image_path
    raw = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ConfigError(f"map file {path}: cannot read the image {image_path}")
    if raw.dtype in (np.uint8, np.uint16):
        img = raw.astype(np.float32) / (65535.0 if raw.dtype == np.uint16 else 255.0)
    else:  # a float (or other) image must hold [0, 1] already: a float TIFF of 0..255 loaded unscaled before
        img = raw.astype(np.float32)
        if not (np.isfinite(img).all() and img.min() >= 0.0 and img.max() <= 1.0):
            raise ConfigError(f"map file {path}: the {raw.dtype} image {image_path} holds values outside [0, 1] "
                              f"({float(np.nanmin(img)):g} .. {float(np.nanmax(img)):g}): write it as an 8- or "
                              "16-bit PNG")
    valid = None
    if img.ndim == 2:
        chans = img[None]
    elif img.shape[2] in (2, 4):  # grey + alpha, BGR + alpha
        valid = (img[..., -1] > 0.5).astype(np.float32)[None]
        chans = img[..., 0][None] if img.shape[2] == 2 else img[..., 2::-1].transpose(2, 0, 1)
    else:
        chans = img[..., 2::-1].transpose(2, 0, 1)  # BGR -> RGB
    negate = doc.get("negate", 0)
    if negate not in (0, 1, None) or isinstance(negate, float) and negate not in (0.0, 1.0):  # map_server's 0 / 1
        raise ConfigError(f"map file {path}: negate must be 0 or 1, got {negate!r}")
    if negate:
        chans = 1.0 - chans
    if chans.shape[0] == 3 and np.allclose(chans[0], chans[1]) and np.allclose(chans[1], chans[2]):
        chans = chans[:1]
    return AerialMap(torch.from_numpy(np.ascontiguousarray(chans)),
                     resolution, tuple(origin), None if valid is None else torch.from_numpy(valid))


def save_map(aerial: AerialMap, path: str | os.PathLike, image_name: str | None = None) -> Path:
    """Write ``aerial`` as ``path`` (YAML) + a PNG beside it (8-bit; an alpha channel holds the
    ``valid`` mask when there is one). Both atomically. Returns the YAML path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image_name = image_name or path.with_suffix(".png").name
    if (path.parent / image_name).resolve() == path.resolve():  # `--out map.png`: the YAML overwrote the image
        raise ValueError(f"{path}: the map's YAML would overwrite its own image {image_name}: give the YAML a name "
                         f"ending in .yaml (the image is written beside it as .png)")
    img = aerial.image.detach().cpu().float().clamp(0.0, 1.0).numpy()
    chans = img[:3] if img.shape[0] >= 3 else img[:1]
    bgr = chans[::-1].transpose(1, 2, 0) if chans.shape[0] == 3 else chans[0]
    out = np.round(bgr * 255.0).astype(np.uint8)
    if aerial.valid is not None:
        alpha = (aerial.valid.detach().cpu().numpy()[0] > 0.5).astype(np.uint8) * 255
        out = np.dstack([out] * 3 + [alpha]) if out.ndim == 2 else np.dstack([out, alpha])
    ok, png = cv2.imencode(".png", out)
    if not ok:
        raise ValueError(f"could not encode the map image for {path}")
    atomic_write_bytes(path.parent / image_name, png.tobytes())
    doc = {"image": image_name, "resolution": float(aerial.resolution),
           "origin": [float(v) for v in aerial.origin], "negate": 0, "mode": "raw",
           "occupied_thresh": 0.65, "free_thresh": 0.25}
    atomic_write_text(path, yaml.safe_dump(doc, sort_keys=False))
    return path
