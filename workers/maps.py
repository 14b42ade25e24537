"""Material maps: load, validate and save via OpenImageIO; colour spaces; channel picks."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MAP_NAMES = ("albedo", "normal", "roughness", "height", "metallic")


@dataclass
class Material:
    """One SVBRDF material in memory: float32 HxWxC maps plus their metadata.

    albedo: HxWx3 in [0,1], *linear* (converted from sRGB on load when declared sRGB);
    normal: HxWx3 xyz in [-1,1], OpenGL convention (+y up) after load; roughness, height,
    metallic: HxWx1 in [0,1]. ``height_scale`` is the factor that maps height units to the
    gradient units of the normal map (see workers.height).
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

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return int(self.albedo.shape[1]), int(self.albedo.shape[0])

    def maps(self) -> dict[str, np.ndarray]:
        """The maps that are present, by name."""
        return {k: getattr(self, k) for k in MAP_NAMES if getattr(self, k) is not None}
