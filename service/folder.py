"""The layout of one material's folder inside a job's output: every file a stage writes or reads is named here.

::

    <material>/
      load/maps.npz, load/material.json, load/maps/*.png     working-size maps (load)
      decompose/masks.npz, decompose/tree.json,               decomposition tree and its masks (decompose)
      decompose/masks/<node>.png
      noise/<leaf>__<map>.json                                one noise model per leaf x map (noise)
      masks/<node>.json                                       one PPTBF mask fit per fitted node (masks)
      recompose/material.json, recompose/report.json          optimised graph and its report (recompose)
      material.json, maps/<render>/{albedo,...}.png,          published graph and regenerated maps (output)
      maps/<render>/preview.png, maps/<render>/material.mtlx
      evaluation.json                                         scorecard (proceduralize evaluate)
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


def safe_name(text: str) -> str:
    """A file-name-safe version of an item id."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)


@dataclass(frozen=True)
class MaterialFolder:
    """Paths of one material's artefacts (nothing is read or created here)."""

    path: Path

    @classmethod
    def of(cls, where: MaterialFolder | str | Path) -> MaterialFolder:
        """``where`` as a MaterialFolder (a folder path is wrapped)."""
        return where if isinstance(where, MaterialFolder) else cls(Path(where))

    # -- load: the maps at working size

    @property
    def load_dir(self) -> Path:
        return self.path / "load"

    @property
    def working_maps(self) -> Path:
        """The working-size maps (npz, float32 arrays)."""
        return self.load_dir / "maps.npz"

    @property
    def working_meta(self) -> Path:
        """Name, size, height scale, normal tilt and sources of the working maps (JSON)."""
        return self.load_dir / "material.json"

    @property
    def working_pngs(self) -> Path:
        """Folder of the working maps as images, for people."""
        return self.load_dir / "maps"

    # -- decompose: the tree of masks

    @property
    def decompose_dir(self) -> Path:
        return self.path / "decompose"

    @property
    def tree_masks(self) -> Path:
        """Masks, alphas and large node metadata of the decomposition tree (npz)."""
        return self.decompose_dir / "masks.npz"

    @property
    def tree(self) -> Path:
        """The decomposition tree (JSON: nodes, methods, shares; arrays point into :attr:`tree_masks`)."""
        return self.decompose_dir / "tree.json"

    def mask_png(self, node: str) -> Path:
        """A tree node's mask as an image."""
        return self.decompose_dir / "masks" / f"{safe_name(node)}.png"

    # -- noise: one model per (leaf, map)

    @property
    def noise_dir(self) -> Path:
        return self.path / "noise"

    def noise_model(self, leaf: str, map_name: str) -> Path:
        return self.noise_dir / f"{safe_name(leaf)}__{map_name}.json"

    def noise_models(self) -> list[Path]:
        """Every noise model written, sorted by file name."""
        return sorted(self.noise_dir.glob("*.json")) if self.noise_dir.is_dir() else []

    # -- masks: one PPTBF fit per fitted node

    @property
    def fits_dir(self) -> Path:
        return self.path / "masks"

    def mask_fit(self, node: str) -> Path:
        return self.fits_dir / f"{safe_name(node)}.json"

    def mask_fits(self) -> list[Path]:
        """Every mask fit written, sorted by file name."""
        return sorted(self.fits_dir.glob("*.json")) if self.fits_dir.is_dir() else []

    # -- recompose: the optimised graph

    @property
    def recomposed(self) -> Path:
        """The graph the recomposition wrote (material.json format)."""
        return self.path / "recompose" / "material.json"

    @property
    def recompose_report(self) -> Path:
        """Loss before/after, iterations, device and seconds of the recomposition (JSON)."""
        return self.path / "recompose" / "report.json"

    # -- output: the published graph and the regenerated maps

    @property
    def published(self) -> Path:
        """The published graph, next to the map folders."""
        return self.path / "material.json"

    @property
    def renders_dir(self) -> Path:
        return self.path / "maps"

    def render_dir(self, tag: str) -> Path:
        """Folder of one render's maps (``WxH_seedS[_scaleX]``; map files named by workers.maps.output_file)."""
        return self.renders_dir / tag

    def preview(self, tag: str) -> Path:
        """One render's preview image (top light | side light)."""
        return self.render_dir(tag) / "preview.png"

    def materialx(self, tag: str) -> Path:
        """One render's MaterialX document over its maps."""
        return self.render_dir(tag) / "material.mtlx"

    def orm(self, tag: str) -> Path:
        """One render's glTF occlusion-roughness-metallic texture (materials with a metallic map)."""
        return self.render_dir(tag) / "orm.png"

    def previews(self) -> list[Path]:
        """Every render's preview image, sorted."""
        return sorted(self.renders_dir.glob("*/preview.png")) if self.renders_dir.is_dir() else []

    # -- proceduralize evaluate

    @property
    def evaluation(self) -> Path:
        """The material's scorecard (JSON)."""
        return self.path / "evaluation.json"
