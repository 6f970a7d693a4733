"""README's "API in ten lines" block runs as printed (it is what users copy first)."""

import math
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_api_example_runs_and_its_gradient_points_back_to_the_target():
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## API in ten lines\n\n```python\n(.*?)```", text, re.S)
    assert block, "README.md lost its '## API in ten lines' python block"
    out = subprocess.run([sys.executable, "-c", block.group(1)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    shape, loss, grad = out.stdout.strip().splitlines()[-1].rsplit(" ", 2)
    assert shape == "(64, 96, 3)"
    # the target is the ray march of the same scene (rho = 1): the plane method's loss there is
    # its small discretization error, and at rho = 1.2 the gradient points back down towards 1
    assert 0 <= float(loss) < 1e-6 and math.isfinite(float(grad)) and float(grad) > 0
