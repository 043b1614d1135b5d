#!/usr/bin/env python3
"""AVIF at a byte budget, for the codec benches: the best quality (imagecodecs' `avif_encode`
level 0-100, its other settings at their defaults; grey as AVIF's 4:0:0 monochrome) whose file is at most MAX_BYTES, decoded
to OUT.png. Prints the file's bytes. Exits 2 where imagecodecs has no AVIF.

    python3 -m venv /tmp/tt && /tmp/tt/bin/pip install imagecodecs pillow
    /tmp/tt/bin/python tools/avif_at.py IN.png MAX_BYTES OUT.png
"""

import sys

import numpy as np
from PIL import Image

try:
    import imagecodecs
except ImportError:
    sys.exit(2)


def main(src, max_bytes, out):
    if not imagecodecs.AVIF.available:
        sys.exit(2)
    data = np.asarray(Image.open(src))
    options = {}
    if data.ndim == 2:
        # A grey image: imagecodecs codes a 2-D array losslessly whatever the level; as three
        # equal channels with 4:0:0 it is AVIF's monochrome, coded lossy (decoded as 2-D).
        data, options = np.stack([data] * 3, -1), {"pixelformat": "400"}
    lo, hi, best = 0, 100, None
    # Bytes grow with the level (not strictly at every step): bisect, then keep the largest
    # file seen under the budget.
    while lo <= hi:
        level = (lo + hi) // 2
        coded = imagecodecs.avif_encode(data, level=level, **options)
        if len(coded) <= max_bytes:
            if best is None or len(coded) > len(best):
                best = coded
            lo = level + 1
        else:
            hi = level - 1
    if best is None:
        sys.exit(1)
    Image.fromarray(imagecodecs.avif_decode(best)).save(out)
    print(len(best))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), sys.argv[3])
