"""Arrays inside a material file's node params: a small JSON object (zlib-compressed base64 of a fixed dtype),
never a pickle, with the declared size checked before anything is inflated."""
from __future__ import annotations

import base64
import zlib
from typing import Any

import numpy as np

from .errors import GraphError

#: the most bytes one encoded array of a material file may inflate to (real ones are a few KB)
MAX_ARRAY_BYTES = 16 * 2**20


def encode_array(a: np.ndarray, dtype: str = "float16") -> dict:
    """Encode an array as a small JSON object (zlib-compressed base64 of a fixed dtype)."""
    arr = np.ascontiguousarray(np.asarray(a), dtype=np.dtype(dtype))
    return {
        "__array__": True,
        "dtype": str(arr.dtype),
        "shape": list(arr.shape),
        "data": base64.b64encode(zlib.compress(arr.tobytes(), 6)).decode("ascii"),
    }


def decode_array(obj: Any) -> np.ndarray:
    """Decode an object written by :func:`encode_array` (plain lists are accepted too) to float32/int. The
    declared size is checked against MAX_ARRAY_BYTES before anything is inflated, and inflation stops there."""
    if isinstance(obj, dict) and obj.get("__array__"):
        try:
            dtype = np.dtype(obj["dtype"])
            shape = [int(n) for n in obj["shape"]]
            if dtype.kind not in "fiub" or any(n < 0 for n in shape) or len(shape) > 8:
                raise ValueError(f"dtype {dtype} / shape {shape} not allowed")
            nbytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
            if nbytes > MAX_ARRAY_BYTES:
                raise ValueError(f"declares {nbytes / 2**20:.0f} MiB, more than the {MAX_ARRAY_BYTES >> 20} MiB "
                                 "an array of a material file may hold")
            z = zlib.decompressobj()
            raw = z.decompress(base64.b64decode(obj["data"]), nbytes + 1)
            if len(raw) != nbytes or z.unconsumed_tail:
                raise ValueError(f"data does not match its declared shape {shape} ({dtype})")
            arr = np.frombuffer(raw, dtype=dtype).reshape(shape)
        except Exception as exc:  # noqa: BLE001 - any corruption is a GraphError
            raise GraphError(f"corrupt array in material file: {exc}") from None
        return arr.astype(np.float32) if arr.dtype.kind == "f" else arr.copy()
    return np.asarray(obj, dtype=np.float32)
