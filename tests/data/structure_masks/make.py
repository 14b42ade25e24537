"""Rebuild the binary structure masks of tests/data/structure_masks from ../shared/materials (CC0, Poly Haven).

Each mask is 512x512, white = the thin network (mortar, slate edges, panel seams) or the stains (rust):

* castle_brick_mortar.png: castle_brick_broken_06, height integrated from the OpenGL normal map at 512 px
  (workers.height.normal_to_height), high-passed (minus a Gaussian blur, sigma 3 px), white = the lowest 30 %
  (the mortar grooves), 3x3 median filtered.
* roof_slate_edges.png: roof_slates_02, the normal map's tilt (1 - n_z), white = the most tilted 25 % (the
  slates' lower edges and the joints between them), 3x3 median filtered.
* roof_slate_edges_fine.png: the same tilt, white = the most tilted 15 %, 3x3 median filtered: what the automatic
  decomposition's structural split gives roof_slates_02 at working size 512 (relief tilt at share 0.15; IoU 0.94
  with that mask). Its lattice shows at 512 px (21.5 px, significance 2.7) and not at 256 px (2.1).
* metal_plate_seams.png: metal_plate_02, same high-passed height (sigma 12 px), white = the lowest 8 % (the
  recessed seams between panels; the tread pattern sits above them).
* metal_plate_courses.png: metal_plate_02, the first layer of the pipeline's automatic decomposition at working
  size 512 (``workers.decompose.decompose``, two layers, seed 0; the seams, widened by the matting to 12-20 px):
  plates 86 px wide in courses 125 px apart, each course offset by about half a plate, the offset drifting by a
  few pixels, which the lattice analysis once read as a cell of two courses.
* rusty_metal_rust.png: rusty_metal_05, albedo luminance blurred (sigma 2 px), white = the darkest 40 %: a
  noise-like mask without a lattice (the control).

Run: python tests/data/structure_masks/make.py [MATERIALS_DIR]
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]
sys.path.insert(0, str(REPO))

from workers.height import normal_to_height  # noqa: E402
from workers.maps import read_image, resize_image, write_image  # noqa: E402

SIZE = 512


def _map(folder: Path, suffix: str) -> np.ndarray:
    path = next(folder.glob(f"*_{suffix}_1k.jpg"))
    img = read_image(path)
    return resize_image(img, SIZE, SIZE)


def _highpass_height(folder: Path, sigma: float) -> np.ndarray:
    n = _map(folder, "nor_gl")[..., :3] * 2.0 - 1.0
    h, _ = normal_to_height(n, "opengl")
    return h - ndimage.gaussian_filter(h, sigma, mode="wrap")


def _decomposition_layer(folder: Path) -> np.ndarray:
    """The first layer's mask of the automatic two-layer decomposition at working size SIZE (as a job makes it)."""
    from workers.decompose import decompose
    from workers.maps import load_material

    files = {k: next(folder.glob(f"*_{k}_1k.jpg")) for k in ("diff", "nor_gl", "rough")}
    mat = load_material(files["diff"], files["nor_gl"], files["rough"], roughness_channel=0, working_size=SIZE)
    return np.asarray(decompose(mat, {"layers": 2}, seed=0).children[0].mask, bool)


def build(materials: Path) -> dict[str, np.ndarray]:
    """The masks (bool 512x512) by file name."""
    out = {}
    for name, mat, sigma, share in (("castle_brick_mortar", "castle_brick_broken_06", 3.0, 0.30),
                                    ("metal_plate_seams", "metal_plate_02", 12.0, 0.08)):
        h = _highpass_height(materials / mat, sigma)
        out[name] = h < np.quantile(h, share)
    out["castle_brick_mortar"] = ndimage.median_filter(out["castle_brick_mortar"], 3, mode="wrap")
    n = _map(materials / "roof_slates_02", "nor_gl")[..., :3] * 2.0 - 1.0
    tilt = 1.0 - n[..., 2] / np.maximum(np.linalg.norm(n, axis=-1), 1e-6)
    out["roof_slate_edges"] = ndimage.median_filter(tilt > np.quantile(tilt, 0.75), 3, mode="wrap")
    out["roof_slate_edges_fine"] = ndimage.median_filter(tilt > np.quantile(tilt, 0.85), 3, mode="wrap")
    out["metal_plate_courses"] = _decomposition_layer(materials / "metal_plate_02")
    alb = _map(materials / "rusty_metal_05", "diff")[..., :3]
    lum = ndimage.gaussian_filter(alb @ np.array([0.2126, 0.7152, 0.0722]), 2.0, mode="wrap")
    out["rusty_metal_rust"] = lum < np.quantile(lum, 0.40)
    return out


if __name__ == "__main__":
    src = Path(sys.argv[1]) if len(sys.argv) > 1 else REPO.parent / "shared" / "materials"
    for name, m in build(src).items():
        write_image(HERE / f"{name}.png", m.astype(np.float32))
        print(name, m.shape, f"white {m.mean():.3f}")
