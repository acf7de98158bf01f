"""OpenEXR in and out with a JSON metadata header (the ``openexr`` package).

Writes are atomic: the image goes to a temporary file beside the target and is
renamed into place only when complete, so a failure leaves no partial file.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .atomic import OutputError, atomic_path

METADATA_KEY = "skyfit"
"""EXR header attribute holding skyfit's metadata as a JSON string."""


class ExrError(ValueError):
    """An EXR file that cannot be read or lacks what skyfit needs."""


def write_exr(path: str | Path, channels: dict[str, np.ndarray], metadata: dict | None = None) -> Path:
    """Write float32 channels (each (H, W)) and a JSON metadata header atomically."""
    import OpenEXR

    path = Path(path)
    if not channels:
        raise ExrError("no channels to write")
    shapes = {np.shape(v) for v in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ExrError(f"all EXR channels must share one 2-D shape, got {shapes}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if metadata is not None:
        try:
            header[METADATA_KEY] = json.dumps(metadata, sort_keys=True)
        except (TypeError, ValueError) as e:
            raise ExrError(f"EXR metadata for {path} is not JSON-serialisable: {e}") from None
    # float16 arrays stay HALF channels (LUTs in half precision); everything else is written as float32.
    data = {k: np.ascontiguousarray(v, dtype=np.float16 if np.asarray(v).dtype == np.float16 else np.float32)
            for k, v in channels.items()}
    try:
        with atomic_path(path, ".tmp.exr") as tmp:
            OpenEXR.File(header, data).write(str(tmp))
    except OutputError:  # already one line naming the file
        raise
    except OSError as e:
        raise ExrError(f"cannot write EXR {path}: {e.strerror or e}") from None
    except Exception as e:  # the binding raises plain exceptions (RuntimeError, ValueError)
        raise ExrError(f"cannot write EXR {path}: {e}") from None
    return path


def read_exr(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """Read all channels (float32 arrays) and skyfit's metadata (empty dict if absent)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise ExrError(f"file not found: {path}")
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as e:  # unreadable (permissions, I/O): name the file
        raise ExrError(f"cannot read {path}: {e.strerror or e}") from None
    if magic != b"\x76\x2f\x31\x01":
        raise ExrError(f"not an OpenEXR file: {path}")
    try:
        try:
            exr = OpenEXR.File(str(path), separate_channels=True)
        except TypeError:  # a binding without separate_channels: split its groups below
            exr = OpenEXR.File(str(path))
        chans = {}
        for name, c in exr.channels().items():
            px = np.asarray(c.pixels, dtype=np.float32)  # half and uint channels too
            if px.ndim == 3:  # the binding groups R, G, B (and A) of a layer into one channel
                prefix = "" if name in ("RGB", "RGBA") else f"{name}."
                for k in range(px.shape[-1]):
                    chans[prefix + "RGBA"[k]] = px[..., k]
            else:
                chans[name] = px
        raw = exr.header().get(METADATA_KEY)
    except Exception as e:  # the binding raises plain exceptions for corrupt files
        raise ExrError(f"cannot read EXR {path}: {e}") from None
    try:
        meta = json.loads(raw) if raw else {}
    except (TypeError, json.JSONDecodeError):
        raise ExrError(f"EXR {path}: metadata header {METADATA_KEY!r} is not valid JSON") from None
    if not isinstance(meta, dict):
        raise ExrError(f"EXR {path}: metadata header {METADATA_KEY!r} must hold a JSON object")
    return chans, meta
