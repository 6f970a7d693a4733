"""Copy one picture per showcase from a gallery run into the reference site's front page.

    jaxrender gallery --out gallery
    python examples/gallery_images.py gallery      # writes docs/images/{stage,desert,fitting,noh}.jpg

Each is the gallery's own PNG, scaled to `WIDTH` pixels across and stored as JPEG (quality 85), so
the repository stays small; docs/index.md shows them with the command that made them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from skimage.transform import resize

DOCS_IMAGES = Path(__file__).resolve().parents[1] / "docs" / "images"
WIDTH = 640
PICTURES = {  # docs name -> the gallery file it shows
    "stage.jpg": "stage/stage.png",
    "desert.jpg": "desert/fig18_dust.png",
    "fitting.jpg": "fit/fitting_fit.png",
    "noh.jpg": "noh/noh/frame_030.png",
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("gallery", type=Path, help="the folder `jaxrender gallery --out` wrote")
    args = parser.parse_args()
    missing = [str(args.gallery / src) for src in PICTURES.values() if not (args.gallery / src).is_file()]
    if missing:
        print(f"{missing[0]}: not found (run `jaxrender gallery --out {args.gallery}` first)", file=sys.stderr)
        return 2
    DOCS_IMAGES.mkdir(exist_ok=True)
    for name, src in PICTURES.items():
        image = iio.imread(args.gallery / src)[..., :3]
        height = round(image.shape[0] * WIDTH / image.shape[1])
        small = resize(image, (height, WIDTH), anti_aliasing=True, preserve_range=True)
        iio.imwrite(DOCS_IMAGES / name, np.clip(small + 0.5, 0, 255).astype(np.uint8), quality=85)
        print(f"{DOCS_IMAGES / name}: from {src}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
