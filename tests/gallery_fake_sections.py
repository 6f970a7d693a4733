"""Stand-in gallery sections for tests/test_gallery.py, importable by the processes that render
sections side by side: what a section does is chosen by its folder's name. "together_*": waits
until its partner has started too (proof that they run at once), with a progress bar of 3 steps;
"broken": fails after its first entry; "dies": its process ends after its first entry, without a
result."""

import os
import time
from pathlib import Path

import numpy as np

from jaxrender import io
from jaxrender.app.gallery.progress import progress_bar

PARTNER_WAIT_S = 60.0


def gallery_section(out_dir: Path, *, quick: bool = False):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    name = out_dir.name
    io.write_png(out_dir / "img.png", np.full((4, 4, 3), 0.5))
    if name.startswith("together_"):
        (out_dir.parent / f"{name}.started").touch()
        partners = [p for p in ("together_a", "together_b") if p != name]
        deadline = time.monotonic() + PARTNER_WAIT_S
        while not all((out_dir.parent / f"{p}.started").exists() for p in partners):
            if time.monotonic() > deadline:
                raise RuntimeError(f"{name}: its partner never started")
            time.sleep(0.05)
        with progress_bar(3, "steps", "step") as bar:
            for _ in range(3):
                bar.update(1)
    params = {"pid": os.getpid(), "cores": sorted(os.sched_getaffinity(0))}
    yield {"title": name, "images": ["img.png"], "caption": "a grey square", "params": params}
    if name == "broken":
        raise RuntimeError("boom")
    if name == "dies":
        os._exit(3)
