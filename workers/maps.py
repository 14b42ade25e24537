"""Material maps: load, validate and save via OpenImageIO; colour spaces; channel picks."""
from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Union

import numpy as np

from pptbf_db.files import atomic_path

from .errors import InputError

logger = logging.getLogger(__name__)

MAP_NAMES = ("albedo", "normal", "roughness", "height", "metallic")


@dataclass
class Material:
    """One SVBRDF material in memory: float32 HxWxC maps plus their metadata.

    albedo: HxWx3 in [0,1], *linear* (converted from sRGB on load when declared sRGB);
    normal: HxWx3 xyz in [-1,1], OpenGL convention (+y up) after load; roughness, height,
    metallic: HxWx1 in [0,1]. ``height_scale`` is the factor that maps height units to the
    gradient units of the normal map (see workers.height); ``normal_tilt`` is the normal map's mean slope
    (dh/dx, dh/drow), which a tileable height cannot hold: ``height_to_normal(height, height_scale,
    tilt=normal_tilt)`` reproduces the normals.
    """

    albedo: np.ndarray
    normal: np.ndarray | None = None
    roughness: np.ndarray | None = None
    height: np.ndarray | None = None
    metallic: np.ndarray | None = None
    name: str = "material"
    sources: dict[str, str] = field(default_factory=dict)
    height_scale: float = 1.0
    meta: dict = field(default_factory=dict)
    normal_tilt: tuple[float, float] = (0.0, 0.0)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return int(self.albedo.shape[1]), int(self.albedo.shape[0])

    def maps(self) -> dict[str, np.ndarray]:
        """The maps that are present, by name."""
        return {k: getattr(self, k) for k in MAP_NAMES if getattr(self, k) is not None}

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """(maps as float32 arrays, JSON-able metadata): the material stored without files (see from_arrays)."""
        arrays = {k: v.astype(np.float32) for k, v in self.maps().items()}
        meta = {"name": self.name, "size": list(self.size), "height_scale": self.height_scale,
                "normal_tilt": list(self.normal_tilt), "sources": self.sources, "meta": self.meta,
                "maps": sorted(arrays)}
        return arrays, meta

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], meta: dict) -> "Material":
        """The material :meth:`to_arrays` stored."""
        return cls(albedo=arrays["albedo"], normal=arrays.get("normal"), roughness=arrays.get("roughness"),
                   height=arrays.get("height"), metallic=arrays.get("metallic"), name=meta["name"],
                   sources=meta.get("sources", {}), height_scale=float(meta.get("height_scale", 1.0)),
                   meta=meta.get("meta", {}), normal_tilt=tuple(meta.get("normal_tilt", (0.0, 0.0))))


# ----------------------------------------------------------------------------- reading

DEFAULT_MAX_PIXELS = 64 * 1024 * 1024
#: the smallest side the stages work at (filters, spectra and matting need a few pixels)
MIN_WORKING_SIDE = 8
_CHANNEL_LETTERS = {"R": 0, "G": 1, "B": 2, "A": 3}
_BITS = {"uint8": 8, "int8": 8, "uint16": 16, "int16": 16, "half": 16, "uint32": 32, "int32": 32,
         "float": 32, "double": 64}

Channel = Union[str, int]
ImageLike = Union[str, Path, np.ndarray]


def _open_input(path: Path, max_pixels: int):
    """Open ``path`` with OpenImageIO (alpha kept unassociated) after header checks; InputError on failure."""
    import OpenImageIO as oiio

    if not path.exists():
        raise InputError(f"{path}: file not found (check the path)")
    if not path.is_file():
        raise InputError(f"{path}: not a regular file")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        msg = " ".join(oiio.geterror().split()) or "unknown format"
        raise InputError(f"{path}: cannot read as an image ({msg}); is it a PNG/JPEG/TIFF/EXR?")
    spec = inp.spec()
    npx = int(spec.width) * int(spec.height)
    if spec.width < 1 or spec.height < 1 or spec.nchannels < 1:
        inp.close()
        raise InputError(f"{path}: empty image ({spec.width}x{spec.height}, {spec.nchannels} channels)")
    if npx > max_pixels:
        inp.close()
        raise InputError(f"{path}: {spec.width}x{spec.height} = {npx} pixels exceeds the limit of {max_pixels} "
                         f"({max_pixels / 2**20:.0f} Mpx; raise max_pixels if the image is genuine)")
    return inp


def image_header(path: str | Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> tuple[int, int, int]:
    """(width, height, channels) from an image file's header, without decoding its pixels."""
    inp = _open_input(Path(path), max_pixels)
    spec = inp.spec()
    inp.close()
    return int(spec.width), int(spec.height), int(spec.nchannels)


def working_size_for(working_size: int | tuple[int, int] | None, w: int, h: int) -> tuple[int, int]:
    """The (w, h) a material of w x h pixels is processed at (see load_material's ``working_size``)."""
    return _target_size(working_size, w, h)


def _channel_index(pick: Channel, names: tuple[str, ...], path: Path) -> int:
    """Resolve a channel pick (letter, channel name or index) against an image's channel names."""
    n = len(names)
    if isinstance(pick, (int, np.integer)):
        idx = int(pick)
    else:
        key = str(pick)
        upper = [c.upper() for c in names]
        if key.upper() in upper:
            idx = upper.index(key.upper())
        elif key.upper() in _CHANNEL_LETTERS and n >= 3:
            idx = _CHANNEL_LETTERS[key.upper()]
        else:
            raise InputError(f"{path}: has no channel {key!r} (channels: {', '.join(names)}); "
                             "a grey image has one channel only")
    if not 0 <= idx < n:
        raise InputError(f"{path}: channel index {idx} out of range (image has {n} channels: {', '.join(names)})")
    return idx


def read_image(path: str | Path, channels: Channel | list[Channel] | None = None,
               max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read PNG/JPEG/TIFF/EXR as float32 HxWxC (integers scaled to [0,1]); ``channels`` picks by name or index."""
    import OpenImageIO as oiio

    p = Path(path)
    inp = _open_input(p, max_pixels)
    try:
        spec = inp.spec()
        names = tuple(spec.channelnames) or tuple(str(i) for i in range(spec.nchannels))
        picks = None if channels is None else [channels] if not isinstance(channels, (list, tuple)) else list(channels)
        idx = None if picks is None else [_channel_index(c, names, p) for c in picks]
        data = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        err = inp.geterror() if inp.has_error else ""
    finally:
        inp.close()
    if data is None or err or not isinstance(data, np.ndarray):
        msg = " ".join((err or oiio.geterror()).split()) or "no pixels"
        raise InputError(f"{p}: unreadable or truncated image data ({msg})")
    arr = np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    if idx is not None:
        arr = arr[..., idx]
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise InputError(f"{p}: {bad} pixel values are NaN or infinite; fix or re-export the image")
    return np.ascontiguousarray(arr)


def inspect_image(path: str | Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> dict:
    """Header and per-channel statistics of an image file (for ``proceduralize inspect``)."""
    p = Path(path)
    inp = _open_input(p, max_pixels)
    spec = inp.spec()
    fmt = inp.format_name()
    dtype = str(spec.format)
    inp.close()
    arr = read_image(p, max_pixels=max_pixels)
    names = list(spec.channelnames) or [str(i) for i in range(spec.nchannels)]
    return {
        "path": str(p),
        "format": fmt,
        "width": int(spec.width),
        "height": int(spec.height),
        "channels": names,
        "dtype": dtype,
        "bit_depth": _BITS.get(dtype, 8 * int(spec.format.size())),
        "file_bytes": p.stat().st_size,
        "stats": {c: {"min": float(arr[..., i].min()), "mean": float(arr[..., i].mean()),
                      "max": float(arr[..., i].max())} for i, c in enumerate(names)},
    }


# ----------------------------------------------------------------------------- writing

_FILE_STEM = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")


def output_file(folder: str | Path, stem: str, suffix: str) -> Path:
    """``folder / (stem + suffix)`` for a name that comes from a file or a user (a map name, an export prefix):
    letters, digits, '_', '.', '-', no '..', no separators, so the file always lands directly in ``folder``."""
    if not isinstance(stem, str) or not _FILE_STEM.match(stem) or ".." in stem:
        raise InputError(f"file name {stem!r}: must be 1-128 letters, digits, '_', '.', '-' (no path "
                         f"separators, no '..'); it names a file inside {folder}")
    return Path(folder) / f"{stem}{suffix}"


def write_image(path: str | Path, array: np.ndarray, bits: int | str = 8) -> Path:
    """Write HxW or HxWxC (C<=4) values in [0,1]: PNG 8/16, JPEG 8, TIFF 8/16/half/float, EXR half/float."""
    import OpenImageIO as oiio

    p = Path(path)
    a = np.asarray(array, dtype=np.float32)
    a = a[..., None] if a.ndim == 2 else a
    if a.ndim != 3 or not 1 <= a.shape[2] <= 4:
        raise InputError(f"{p}: cannot write an array of shape {a.shape} (need HxW or HxWxC with C<=4)")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{p}: refusing to write NaN/inf values")
    ext = p.suffix.lower()
    allowed = {".png": (8, 16), ".jpg": (8,), ".jpeg": (8,), ".tif": (8, 16, "half", "float"),
               ".tiff": (8, 16, "half", "float"), ".exr": ("half", "float")}
    bits = {32: "float"}.get(bits, bits) if not isinstance(bits, str) else bits
    if ext not in allowed:
        raise InputError(f"{p}: unsupported output extension {ext!r} (use .png, .jpg, .tif or .exr)")
    if bits not in allowed[ext]:
        raise InputError(f"{p}: {ext} cannot hold bits={bits!r}; allowed: {allowed[ext]}")
    if ext in (".jpg", ".jpeg") and a.shape[2] not in (1, 3):
        raise InputError(f"{p}: JPEG holds 1 or 3 channels, got {a.shape[2]}")
    if bits == 8:
        pix, fmt = np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8), oiio.UINT8
    elif bits == 16:
        pix, fmt = np.round(np.clip(a, 0.0, 1.0) * 65535.0).astype(np.uint16), oiio.UINT16
    elif bits == "half":
        pix, fmt = a.astype(np.float16), oiio.HALF
    else:
        pix, fmt = a, oiio.FLOAT
    h, w, c = pix.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    if c == 4:
        spec.attribute("oiio:UnassociatedAlpha", 1)
    if ext in (".jpg", ".jpeg"):
        spec.attribute("Compression", "jpeg:95")
    with atomic_path(p) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise InputError(f"{p}: cannot open for writing ({oiio.geterror().strip()})")
        ok = out.write_image(np.ascontiguousarray(pix))
        err = out.geterror() if not ok else ""
        out.close()
        if not ok:
            raise InputError(f"{p}: write failed ({err.strip()})")
    return p


# ----------------------------------------------------------------------------- colour and size


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0,1] -> linear (IEC 61966-2-1 piecewise curve)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values in [0,1] -> sRGB encoding (inverse of :func:`srgb_to_linear`)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1.0 / 2.4) - 0.055).astype(np.float32)


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize HxW or HxWxC: block mean for integer downsampling, antialiased (wrap) resize otherwise."""
    a = np.asarray(img, dtype=np.float32)
    h0, w0 = a.shape[:2]
    if (w0, h0) == (width, height):
        return a.copy()
    if width < 1 or height < 1:
        raise ValueError(f"bad target size {width}x{height}")
    fy, fx = h0 / height, w0 / width
    if fy >= 1 and fx >= 1 and h0 % height == 0 and w0 % width == 0:
        fy, fx = h0 // height, w0 // width
        return a.reshape(height, fy, width, fx, *a.shape[2:]).mean(axis=(1, 3)).astype(np.float32)
    from skimage.transform import resize

    out = resize(a, (height, width) + a.shape[2:], order=1, mode="wrap", anti_aliasing=fy > 1 or fx > 1,
                 preserve_range=True)
    return out.astype(np.float32)


# ----------------------------------------------------------------------------- materials

_NAME_SUFFIXES = re.compile(r"(_(diff|diffuse|albedo|basecolor|base_color|color|col))?(_\d+k)?$", re.I)


def _read(src: ImageLike, label: str, max_pixels: int, channels: Channel | None = None) -> tuple[np.ndarray, str]:
    """Read one map from a path or take an in-memory array; returns (HxWxC float32, source label)."""
    if isinstance(src, np.ndarray):
        a = np.asarray(src, dtype=np.float32)
        a = a[..., None] if a.ndim == 2 else a
        if a.ndim != 3:
            raise InputError(f"{label} array: expected HxW or HxWxC, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"{label} array: contains NaN or infinite values")
        if channels is not None:
            a = a[..., [_channel_index(channels, tuple("RGBA"[: a.shape[2]]) if a.shape[2] > 1 else ("Y",),
                                       Path(f"<{label} array>"))]]
        return a, f"<{label} array>"
    a = read_image(src, channels=channels, max_pixels=max_pixels)
    return (a[..., None] if a.ndim == 2 else a), str(src)


def _grey(a: np.ndarray, label: str, src: str) -> np.ndarray:
    """Reduce a map to one channel (mean of RGB, alpha ignored); warn if the channels disagree (packed map?)."""
    if a.shape[2] == 1:
        return a
    rgb = a[..., :3] if a.shape[2] >= 3 else a[..., :1]
    spread = float(np.mean(np.ptp(rgb, axis=2))) if rgb.shape[2] > 1 else 0.0
    if spread > 0.05:
        logger.warning("%s (%s): channels differ (mean spread %.3f); using their mean. Name a channel "
                       "(e.g. roughness_channel='G' for an ARM map) if this is a packed map.", label, src, spread)
    return rgb.mean(axis=2, keepdims=True).astype(np.float32)


def decode_normal(a: np.ndarray, src: str, convention: str = "opengl") -> np.ndarray:
    """Encoded normal texture (or signed float data) -> unit xyz in [-1,1], then ``convention`` -> OpenGL.

    ``convention`` is "opengl", "directx" or another key of workers.height.ORIENTATIONS ("rot90", "swap_xy").
    Raises InputError for a map with < 3 channels or vectors that are not plausibly unit and outward.
    """
    from .height import ORIENTATIONS, apply_orientation

    if a.ndim != 3 or a.shape[2] < 3:
        raise InputError(f"{src}: a normal map needs 3 channels (x, y, z), got {a.shape[2] if a.ndim == 3 else 1}")
    if convention not in ORIENTATIONS:
        raise InputError(f"{src}: normal_convention must be one of {sorted(ORIENTATIONS)} or 'auto', "
                         f"got {convention!r}")
    v = a[..., :3].astype(np.float32)
    n = v if float(v.min()) < -0.01 else v * 2.0 - 1.0
    mean_len = float(np.linalg.norm(n, axis=2).mean())
    mean_z = float(np.mean(n[..., 2]))
    if not 0.75 <= mean_len <= 1.25 or mean_z <= 0.3:
        raise InputError(f"{src}: does not look like a tangent-space normal map (mean |n| = {mean_len:.2f}, "
                         f"mean z = {mean_z:.2f}; expected about 1 and > 0.3). "
                         "Is it a height or grey map given as the normal?")
    return normalize_vectors(apply_orientation(n, convention))


def _orient_normal(n: np.ndarray, convention: str, src: str) -> tuple[np.ndarray, str, dict[str, float]]:
    """Pick the orientation ("auto") or check the declared one against the most integrable; warn if off."""
    from .height import apply_orientation, detect_orientation

    h, w = n.shape[:2]
    k = max(1, max(h, w) // 256)  # the decision is clear at 256 px and 4 solves at full size cost ~0.5 s per Mpx
    small = normalize_vectors(resize_image(n, max(8, w // k), max(8, h // k))) if k > 1 else n
    best, res = detect_orientation(small)
    if convention == "auto":
        if best != "opengl":
            logger.info("%s: normal orientation detected as %s (residuals %s)", src, best, res)
        return apply_orientation(n, best), best, res
    if best != "opengl" and res["opengl"] > 1.3 * res[best]:
        logger.warning("%s: the normals are far more consistent as %r than as the declared %r "
                       "(non-integrable share %.2f vs %.2f); pass normal_convention='auto' to correct them",
                       src, best, convention, res[best], res["opengl"])
    return n, convention, res


def normalize_vectors(n: np.ndarray) -> np.ndarray:
    """Unit-normalise HxWx3 vectors; degenerate ones become (0, 0, 1)."""
    length = np.linalg.norm(n, axis=2, keepdims=True)
    out = np.where(length > 1e-6, n / np.maximum(length, 1e-6), np.array([0.0, 0.0, 1.0], np.float32))
    return out.astype(np.float32)


def _target_size(working_size: int | tuple[int, int] | None, w: int, h: int) -> tuple[int, int]:
    """(w, h) to process at: an int sets the longer side (aspect kept); a pair is used as is."""
    if working_size is None:
        if min(w, h) < MIN_WORKING_SIDE:
            raise InputError(f"the maps are {w}x{h} pixels; the pipeline needs at least {MIN_WORKING_SIDE} on each "
                             "side: set working_size to process them at a larger size")
        return w, h
    if isinstance(working_size, (int, np.integer)):
        n = int(working_size)
        if n < MIN_WORKING_SIDE:
            raise InputError(f"working_size must be >= {MIN_WORKING_SIDE}, got {n}")
        # the longer side is n, the aspect ratio kept (the shorter side at least MIN_WORKING_SIDE)
        short = lambda a, b: max(MIN_WORKING_SIDE, round(a * n / b))  # noqa: E731
        return (n, short(h, w)) if w >= h else (short(w, h), n)
    tw, th = (int(v) for v in working_size)
    if tw < 8 or th < 8:
        raise InputError(f"working_size must be >= 8x8, got {tw}x{th}")
    return tw, th


def _material_name(albedo: ImageLike, name: str | None) -> str:
    """The given name, else the albedo file stem without map/resolution suffixes."""
    if name:
        return name
    if isinstance(albedo, np.ndarray):
        return "material"
    return _NAME_SUFFIXES.sub("", Path(albedo).stem) or Path(albedo).stem


def load_material(
    albedo: ImageLike,
    normal: ImageLike | None = None,
    roughness: ImageLike | None = None,
    height: ImageLike | None = None,
    metallic: ImageLike | None = None,
    *,
    roughness_channel: Channel | None = None,
    metallic_channel: Channel | None = None,
    albedo_colorspace: str = "srgb",
    normal_convention: str = "opengl",
    working_size: int | tuple[int, int] | None = None,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    name: str | None = None,
    height_scale: float | None = None,
) -> Material:
    """Read, validate and normalise a material's maps (paths or arrays) into a :class:`Material`.

    Albedo becomes linear, normals unit OpenGL vectors, roughness/height/metallic one channel; all maps
    must share one size, optionally resized to ``working_size``. Without a height map, the height is
    integrated from the normals (workers.height) and its gradient scale stored in ``height_scale``; with both,
    the scale is fitted so Sobel(height)*scale matches the normals. ``height_scale`` overrides that.
    """
    from .height import fit_height_scale, height_to_normal, normal_tilt, normal_to_height

    if albedo_colorspace not in ("srgb", "linear"):
        raise InputError(f"albedo_colorspace must be 'srgb' or 'linear', got {albedo_colorspace!r}")
    raw: dict[str, tuple[np.ndarray, str]] = {"albedo": _read(albedo, "albedo", max_pixels)}
    for key, src, ch in (("normal", normal, None), ("roughness", roughness, roughness_channel),
                         ("height", height, None), ("metallic", metallic, metallic_channel)):
        if src is not None:
            raw[key] = _read(src, key, max_pixels, ch)
    a0, s0 = raw["albedo"]
    for key, (a, s) in raw.items():
        if a.shape[:2] != a0.shape[:2]:
            raise InputError(f"{s}: {key} map is {a.shape[1]}x{a.shape[0]} but the albedo {s0} is "
                             f"{a0.shape[1]}x{a0.shape[0]}; all maps must have the same size")
    h0, w0 = a0.shape[:2]
    try:
        tw, th = _target_size(working_size, w0, h0)
    except InputError as exc:
        raise InputError(f"{s0}: {exc}") from None

    def fit(a: np.ndarray) -> np.ndarray:
        return resize_image(a, tw, th) if (tw, th) != (w0, h0) else a

    if a0.shape[2] == 2 or a0.shape[2] > 4:
        raise InputError(f"{s0}: albedo needs 1 (grey), 3 (RGB) or 4 (RGBA) channels, got {a0.shape[2]}")
    alb = np.repeat(a0, 3, axis=2) if a0.shape[2] == 1 else a0[..., :3]
    alb = srgb_to_linear(alb) if albedo_colorspace == "srgb" else np.clip(alb, 0.0, 1.0)
    mat = Material(albedo=np.ascontiguousarray(fit(alb)), name=_material_name(albedo, name),
                   sources={k: s for k, (_, s) in raw.items()})
    if "normal" in raw:
        n = decode_normal(*raw["normal"], convention="opengl" if normal_convention == "auto" else normal_convention)
        mat.normal, orientation, residuals = _orient_normal(normalize_vectors(fit(n)), normal_convention,
                                                            raw["normal"][1])
        mat.normal_tilt = normal_tilt(mat.normal)
        mat.meta["normal_orientation"] = orientation
        mat.meta["normal_residuals"] = residuals
    for key in ("roughness", "metallic"):
        if key in raw:
            setattr(mat, key, np.clip(fit(_grey(*raw[key], key)), 0.0, 1.0))
    if "height" in raw:
        hgt = fit(_grey(*raw["height"], "height"))
        lo, hi = float(hgt.min()), float(hgt.max())
        mat.height = ((hgt - lo) / (hi - lo) if hi > lo else np.zeros_like(hgt)).astype(np.float32)
        if height_scale is not None:
            mat.height_scale = float(height_scale)
        elif mat.normal is not None:
            mat.height_scale = fit_height_scale(mat.height[..., 0], mat.normal)
        mat.meta["height_source"] = "file"
    elif mat.normal is not None:
        hgt, scale = normal_to_height(mat.normal)
        mat.height = hgt[..., None]
        mat.height_scale = float(height_scale) if height_scale is not None else scale
        mat.meta["height_source"] = "normal"
    if mat.normal is None and mat.height is not None:
        mat.normal = height_to_normal(mat.height[..., 0], strength=mat.height_scale)
        mat.normal_tilt = (0.0, 0.0)
        mat.meta["normal_source"] = "height"
    mat.meta.update({"original_size": [w0, h0], "working_size": [tw, th], "albedo_colorspace": albedo_colorspace,
                     "normal_convention": normal_convention,
                     "roughness_channel": roughness_channel, "metallic_channel": metallic_channel})
    logger.info("loaded %s: %dx%d -> %dx%d, maps %s, height scale %.3g", mat.name, w0, h0, tw, th,
                sorted(mat.maps()), mat.height_scale)
    return mat


def encode_map(name: str, arr: np.ndarray) -> np.ndarray:
    """A map as an image file holds it: albedo in sRGB, normal xyz mapped from [-1, 1] to [0, 1], others as they
    are (the writer clips to its range)."""
    if name == "albedo":
        return linear_to_srgb(arr)
    if name == "normal":
        return np.clip(arr * 0.5 + 0.5, 0.0, 1.0)
    return arr


def write_maps(maps: dict[str, np.ndarray], folder: str | Path, bits: int = 8) -> dict[str, Path]:
    """Write evaluated maps as PNG, one file per map named after it: albedo sRGB and normal encoded 0..1 at
    ``bits``, every other map 16-bit grey (clipped to [0, 1], with a warning when it reached outside)."""
    files: dict[str, Path] = {}
    for name, arr in maps.items():
        data, b = encode_map(name, arr), bits
        if name not in ("albedo", "normal"):
            lo, hi = float(arr.min()), float(arr.max())
            if lo < 0.0 or hi > 1.0:
                logger.warning("map %s spans [%.3g, %.3g]: clipped to [0, 1] in the PNG", name, lo, hi)
            data, b = np.clip(arr, 0.0, 1.0), 16
        if data.ndim == 3 and data.shape[2] == 2:
            data = np.concatenate([data, np.zeros_like(data[..., :1])], axis=2)
        files[name] = write_image(output_file(Path(folder), name, ".png"), data[..., :4] if data.ndim == 3 else data,
                                  bits=b)
    return files


def save_material(material: Material, folder: str | Path, bits: int | str = 8) -> dict[str, Path]:
    """Write a material's maps (albedo sRGB, normal encoded 0..1, grey maps; height >= 16-bit) plus maps.json."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    ext = ".exr" if bits in ("half", "float") else ".png"
    hbits = bits if ext == ".exr" else 16
    written: dict[str, Path] = {}
    for key, arr in material.maps().items():
        written[key] = write_image(output_file(out, key, ext), encode_map(key, arr),
                                   bits=hbits if key == "height" else bits)
    info = {"name": material.name, "height_scale": material.height_scale, "size": list(material.size),
            "albedo_colorspace": "srgb", "normal_convention": "opengl", "sources": material.sources,
            "files": {k: p.name for k, p in written.items()}}
    (out / "maps.json").write_text(json.dumps(info, indent=1, default=str), encoding="utf-8")
    written["info"] = out / "maps.json"
    return written
