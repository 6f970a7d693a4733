"""A huge broken manifest fails fast with bounded memory: 10^5 light entries whose images
are missing stop after the first 200 problems, one line each, exit code 2, and the process's peak
memory stays near that of an empty run (the manifest's own objects, no per-image ones)."""

import json
import subprocess
import sys

N_LIGHTS = 10**5
# peak resident memory of the child (Python, JAX, the parsed manifest of ~9 MB): before the streaming
# validation the same run took 1.65 GB; this bound leaves room for JAX's own ~0.3 GB
PEAK_RSS_MB = 800
# the command line in a child that reports its own peak: VmHWM of its address space (getrusage's
# ru_maxrss would carry the forking test worker's peak across exec; RUSAGE_CHILDREN would be the
# largest of every earlier child of this test process)
CHILD = """
import sys
from jaxrender.app.cli.programs import fitting_main
try:
    code = fitting_main(["ingest", sys.argv[1], "--store", sys.argv[2]])
finally:
    print(next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:")))  # kB
sys.exit(code)
"""


def test_a_huge_manifest_with_missing_images_stops_at_200_problems(tmp_path):
    manifest = {"format": "jaxrender-capture", "version": 1, "size": [32, 32], "response": "linear",
                "exposures_s": [0.01, 0.1], "view": {"theta_deg": 0, "phi_deg": 0},
                "white": {"reflectance": 0.9, "images": ["w0.png", "w1.png"]},
                "lights": [{"theta_deg": 30, "phi_deg": i * 1e-3, "images": [f"l{i}_0.png", f"l{i}_1.png"]}
                           for i in range(N_LIGHTS)]}
    (tmp_path / "capture.json").write_text(json.dumps(manifest))
    proc = subprocess.run([sys.executable, "-c", CHILD, str(tmp_path), str(tmp_path / "store")],
                          capture_output=True, text=True, timeout=600)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert len(lines) == 201 and lines[-1].endswith("... stopped after 200 problems"), lines[-3:]
    assert "w0.png: missing image" in lines[0] and "Traceback" not in proc.stderr
    assert not (tmp_path / "store").exists()
    peak_mb = float(proc.stdout.strip().splitlines()[-1]) / 1024
    assert peak_mb < PEAK_RSS_MB, peak_mb
