"""``proceduralize inspect MAP...``: what is read from map files."""
from __future__ import annotations

import json
import sys

from service.commands.common import common_parser
from workers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("inspect", parents=[common_parser()], help="show what is read from map files",
                       description="Read each image as the pipeline would and print its size, format, bit "
                                   "depth, channels and per-channel min/mean/max (values scaled to [0,1]).")
    p.add_argument("maps", nargs="+", metavar="MAP", help="image files (PNG, JPEG, TIFF, EXR)")
    p.add_argument("--json", action="store_true", help="print one JSON object per file instead of text")
    p.set_defaults(handler=handle)


def handle(args) -> int:
    from workers.maps import inspect_image

    bad = 0
    for path in args.maps:
        try:
            info = inspect_image(path)
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            bad += 1
            continue
        if args.json:
            print(json.dumps(info))
            continue
        print(f"{info['path']}: {info['format']} {info['width']}x{info['height']}, "
              f"{len(info['channels'])} channel(s) ({','.join(info['channels'])}), "
              f"{info['dtype']} ({info['bit_depth']}-bit), {info['file_bytes'] / 1024:.0f} KiB")
        for ch, st in info["stats"].items():
            print(f"  {ch:>3}  min {st['min']:.4f}  mean {st['mean']:.4f}  max {st['max']:.4f}")
    return 2 if bad else 0
