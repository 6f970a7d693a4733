#!/bin/bash
# The GPU check: the smoke run and headline benchmarks on a GPU machine, logs and rows into $OUT/gpu.tgz.
# Wheels of the packages the device lacks (jaxopt, OpenEXR, zarr, numcodecs, google-crc32c, imagecodecs, ...)
# go in .whl/ (not tracked). Usage: HEADLINE="shafts_interactive --sections frames;fit_speed" SMOKE_S=100 PER_S=125 \
#   bash benchmarks/gpu_check.sh    (HEADLINE: scripts with their arguments, ';' between; SMOKE_S=0: no smoke run)
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MPLBACKEND=Agg
mkdir -p /tmp/g/rows /tmp/g/logs
export BENCH_RESULTS_DIR=/tmp/g/rows
(nvidia-smi -L; python3 -c "import jax, sys; print(sys.version); print(jax.__version__, jax.devices())"; \
 python3 -c "import sys; sys.path.insert(0, 'benchmarks'); from _results import cpu_description; print(cpu_description())"; nproc) \
 > /tmp/g/logs/device.txt 2>&1
python3 - >> /tmp/g/logs/device.txt 2>&1 <<'PY'
import importlib
mods = "jax equinox jaxtyping optimistix lineax jaxopt numpy OpenEXR skimage matplotlib tqdm imageio imageio_ffmpeg imagecodecs tifffile PIL zarr dask distributed scipy numba mitsuba".split()
missing = []
for m in mods:
    try:
        importlib.import_module(m)
    except Exception as e:
        missing.append(f"{m} ({type(e).__name__}: {e})")
print("missing:", missing or "none")
PY
cat /tmp/g/logs/device.txt
if [ "${SMOKE_S:-300}" != 0 ]; then
  t0=$(date +%s)
  timeout ${SMOKE_S:-300} python3 benchmarks/run_all.py --quick --jobs 4 --results-dir /tmp/g/rows > /tmp/g/logs/smoke.log 2>&1; echo "smoke exit $? in $(( $(date +%s) - t0 )) s" | tee -a /tmp/g/logs/smoke.log
  tail -25 /tmp/g/logs/smoke.log
fi
IFS=';' read -ra runs <<< "$HEADLINE"
for i in "${!runs[@]}"; do
  read -ra cmd <<< "${runs[$i]}"
  t1=$(date +%s); log=/tmp/g/logs/$t1-$i-${cmd[0]}.log
  timeout ${PER_S:-90} python3 benchmarks/${cmd[0]}.py "${cmd[@]:1}" > $log 2>&1; echo "${runs[$i]} exit $? in $(( $(date +%s) - t1 )) s" | tee -a /tmp/g/logs/headline.txt
  tail -12 $log
done
tar czf ${OUT:-.}/gpu.tgz -C /tmp/g .
