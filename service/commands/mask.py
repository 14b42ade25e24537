"""``proceduralize mask fit`` / ``mask render``: a PPTBF for any binary mask an artist has, outside a job.

``mask fit MASK.png [--valid VALID.png] [--cell-length PX] --out FIT.json`` fits a PPTBF
(workers.masks.fit_pptbf_mask: lattice-first with the VGG-19 loss when the mask has a layout, else query and
optimise) and writes FIT.json (the fit, the mask's size, the lattice found) and FIT.png beside it: target | a fresh
realisation at the mask's size. ``--cell-length`` is the cells' length for a mask of rows alone.
``mask render FIT.json --size WxH [--seed N] [--scale S] --out MASK.png`` renders the fitted mask at any size:
scale 1 keeps the pattern size the mask had, --seed picks a realisation (none: the fit's own).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from service.commands.common import common_parser, parse_size, positive_float
from workers.errors import InputError

FORMAT = "proceduralize-mask/1"
#: the smallest side of a mask the fit reads (its lattice analysis needs 16 px)
MIN_MASK_SIDE = 16


def _read_mask(path: Path, field: str) -> np.ndarray:
    """A bool HxW mask from an image file (first channel > 0.5); InputError naming the file and the field."""
    from workers.maps import read_image

    img = read_image(path)
    if img.ndim == 3:
        img = img[..., 0]
    if min(img.shape) < MIN_MASK_SIDE:
        raise InputError(f"{path}: {field} is {img.shape[1]}x{img.shape[0]} pixels; a mask needs at least "
                         f"{MIN_MASK_SIDE}x{MIN_MASK_SIDE}")
    m = img > 0.5
    if m.all() or not m.any():
        raise InputError(f"{path}: {field} is uniform ({'all' if m.all() else 'no'} pixels above 0.5): nothing to fit")
    return m


def fit_document(fit, source: Path, size: tuple[int, int]) -> dict:
    """The JSON document of a standalone mask fit."""
    return {"format": FORMAT, "source": str(source), "source_size": [int(size[0]), int(size[1])],
            "fit": fit.to_dict()}


def load_fit(path: Path):
    """(MaskFit, source width) from a FIT.json; InputError naming the file and the field otherwise."""
    from pptbf_db import pptbf as pp
    from workers.masks import MaskFit

    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the mask fit ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"{path}: 'format' must be {FORMAT!r} (a file written by 'proceduralize mask fit')")
    try:
        fit = MaskFit.from_dict(doc["fit"])
        width = int(doc["source_size"][0])
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise InputError(f"{path}: field 'fit' or 'source_size' is malformed ({exc})") from None
    if fit.params.size != 29 or width < 1:
        raise InputError(f"{path}: field 'fit.params' must hold 29 numbers and 'source_size' a positive width")
    try:
        pp.decode(fit.params)
    except ValueError as exc:
        raise InputError(f"{path}: field 'fit.params': {exc}") from None
    return fit, width


def render_fit(fit, source_width: int, width: int, height: int, *, scale: float = 1.0,
               seed: int | None = None) -> np.ndarray:
    """The fitted mask (bool HxW) at any size; scale 1 = the source mask's pattern size; seed None = the fit's
    own realisation, else one drawn from the seed."""
    shift = None if seed is None else tuple(float(v) for v in np.random.default_rng(seed).uniform(8.0, 16.0, 2))
    return fit.render(width, height, pixel_scale=scale * source_width / float(fit.fit_size[0]), shift=shift)


def register(sub) -> None:
    p = sub.add_parser("mask", parents=[common_parser()], help="fit a PPTBF to any binary mask, or render a fit",
                       description="Fit a procedural PPTBF mask to a binary image (bricks, tiles, stains...) and "
                                   "render it at any size, scale and seed.")
    msub = p.add_subparsers(dest="mask_command", metavar="ACTION")
    msub.required = True
    f = msub.add_parser("fit", parents=[common_parser()], help="fit a PPTBF to a binary mask image",
                        description="Fit a PPTBF to MASK (white = the layer, first channel > 0.5). A mask with a "
                                    "lattice (bricks, tiles, plates) is fitted lattice-first with the VGG-19 Gram "
                                    "loss at up to 256 px; others by database query and optimisation. Writes "
                                    "FIT.json and FIT.png (target | a fresh realisation).")
    f.add_argument("mask", type=Path, metavar="MASK.png")
    f.add_argument("--valid", type=Path, default=None, metavar="VALID.png",
                   help="pixels where the mask is known (white); the loss ignores the rest")
    f.add_argument("--out", type=Path, required=True, metavar="FIT.json")
    f.add_argument("--db", type=Path, default=None, metavar="DIR", help="PPTBF database (default: the bundled one)")
    f.add_argument("--budget", type=positive_float, default=None, metavar="S",
                   help="time limit in seconds, a safety net (default 300): --evals decides how far the fit "
                   "searches, so the same mask gives the same fit on any machine")
    f.add_argument("--evals", type=int, default=None, metavar="N", help="loss evaluations at most")
    f.add_argument("--seed", type=int, default=0, help="optimiser seed (default 0)")
    f.add_argument("--cell-length", type=positive_float, default=None, metavar="PX",
                   help="the cells' length along the rows (px at the mask's size) for a mask of rows alone, whose "
                        "lines show where the rows are but not where a cell ends (slate edges); ignored otherwise")
    f.set_defaults(handler=handle_fit)
    r = msub.add_parser("render", parents=[common_parser()], help="render a mask fit at any size",
                        description="Render FIT.json at WxH; scale 1 keeps the pattern size of the fitted mask.")
    r.add_argument("fit", type=Path, metavar="FIT.json")
    r.add_argument("--size", type=parse_size, required=True, metavar="WxH")
    r.add_argument("--seed", type=int, default=None, help="realisation (default: the fit's own)")
    r.add_argument("--scale", type=positive_float, default=1.0, help="pattern scale (2 = twice as big)")
    r.add_argument("--out", type=Path, required=True, metavar="MASK.png")
    r.set_defaults(handler=handle_render)


def handle_fit(args) -> int:
    from pptbf_db.index import PPTBFIndex, default_database_path
    from workers.maps import write_image
    from workers.masks import MaskFitConfig, fit_pptbf_mask

    mask = _read_mask(args.mask, "mask")
    valid = None if args.valid is None else _read_mask(args.valid, "valid")
    if valid is not None and valid.shape != mask.shape:
        raise InputError(f"{args.valid}: valid is {valid.shape[1]}x{valid.shape[0]}, the mask "
                         f"{mask.shape[1]}x{mask.shape[0]}")
    index = PPTBFIndex.load(args.db or default_database_path())
    cfg = MaskFitConfig(seed=args.seed)
    if args.budget is not None:
        cfg.time_budget_s = args.budget
    if args.evals is not None:
        cfg.max_evals = args.evals
    t0 = time.perf_counter()
    fit = fit_pptbf_mask(mask, index, valid=valid, config=cfg, cell_length=args.cell_length)
    h, w = mask.shape
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(fit_document(fit, args.mask, (w, h)), indent=1), encoding="utf-8")
    fresh = render_fit(fit, w, w, h, seed=args.seed + 1)
    panel = np.concatenate([mask, np.ones((h, max(2, w // 64)), bool), fresh], axis=1).astype(np.float32)
    png = write_image(args.out.with_suffix(".png"), panel, bits=8)
    lat = fit.meta.get("lattice") or {}
    print(f"fitted {args.mask} ({w}x{h}) in {time.perf_counter() - t0:.1f} s: "
          f"{fit.meta.get('method', 'query')} fit, loss {fit.loss_final:.4f}"
          + (f", lattice period {lat['period']:.1f} px" if lat.get("period") else "")
          + f" -> {args.out}, {png}")
    return 0


def handle_render(args) -> int:
    from workers.maps import write_image

    fit, width = load_fit(args.fit)
    w, h = args.size
    m = render_fit(fit, width, w, h, scale=args.scale, seed=args.seed)
    out = write_image(args.out, m.astype(np.float32), bits=8)
    print(f"rendered {args.fit} at {w}x{h} (scale {args.scale}, seed {args.seed}) -> {out}")
    return 0
