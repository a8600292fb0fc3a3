#!/usr/bin/env bash
# On a lent GPU machine (the device tool's): the parts scripts/device_bundle.py made arrive in .gpu/, one or two a
# call, and are kept in /root/stage; `stage` keeps this call's, `run` unpacks them all at their absolute paths,
# adds the system libraries that machine lacks, then runs the GPU oracle tests and bench/render/gpu_cost.py into
# $OUT, and prints the busy fractions: the GPU's (nvidia-smi) beside the render process's (its time in render
# tasks), with one render process on the GPU (--render-workers 1) as well as the default.
# `dry` runs the same benchmark's CPU path and busy printout with this checkout's .venv (no GPU, no staging):
# what the lent machine will print, checked here.
# Usage: bash scripts/device_run.sh stage | probe | dry | run [gpu_cost.py flags...]
set -uo pipefail
what=${1:-run}
shift || true
stage=/root/stage
out=${OUT:-/tmp/od-out}
if [ "$what" = dry ]; then
  mkdir -p "$out"
  PYTHONPATH=$PWD .venv/bin/python bench/render/gpu_cost.py --rooms icl_livingroom --points 1 --points-many 1 \
    --device cpu --cores 1,2 --render-workers 1 --out "$out/gpu.json" "$@" > "$out/gpu_cost.log" 2>&1 \
    || { tail -20 "$out/gpu_cost.log"; exit 1; }
  PYTHONPATH=$PWD .venv/bin/python bench/render/gpu_cost.py --busy "$out/gpu.json"
  exit $?
fi
mkdir -p "$stage" "$out"
cp .gpu/part_* "$stage"/ 2>/dev/null
ls -la "$stage"
[ "$what" = stage ] && exit 0

py=/root/.pyenv/versions/3.11.7/bin/python3.11
if [ "$what" = probe ]; then
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nproc; python3 --version
  ls /usr/local/nvidia/lib64 2>/dev/null | grep -iE "optix|libcuda" ; which xz zstd taskset; uname -r
  taskset -c 0 python3 -c "import os; print('pinned to', os.sched_getaffinity(0))"
  ldconfig -p | grep -cE "libX11.so.6|libGL.so.1|libxkbcommon.so.0|libSM.so.6|libsqlite3.so.0"
  exit 0
fi

if [ ! -x "$py" ]; then
  t0=$(date +%s)
  if command -v xz >/dev/null; then cat "$stage"/part_* | xz -d -T0 | tar -x -C /
  else cat "$stage"/part_* | python3 -c "import sys, tarfile; tarfile.open(fileobj=sys.stdin.buffer, mode='r|xz').extractall('/')"
  fi
  echo "unpacked in $(( $(date +%s) - t0 )) s"
fi
mkdir -p /root/od-fallback
for lib in /root/od-syslibs/*; do
  ldconfig -p | grep -q "[[:space:]]$(basename "$lib") " || cp "$lib" /root/od-fallback/
done
echo "system libraries added: $(ls /root/od-fallback | tr '\n' ' ')"
export LD_LIBRARY_PATH=/root/od-fallback:/usr/local/nvidia/lib64:${LD_LIBRARY_PATH:-}
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
"$py" -c "
from services.worker.blender.threads import import_bpy; import_bpy(None); import bpy
prefs = bpy.context.preferences.addons['cycles'].preferences
for kind in ('OPTIX', 'CUDA'):
    prefs.compute_device_type = kind; prefs.refresh_devices()
    print(kind, [d.name for d in prefs.devices if d.type == kind])
" 2>&1 | tail -3
[ -e ../shared/scenes ] || { mkdir -p ../shared && ln -s /root/od-scenes ../shared/scenes; }  # where the tests look
test_device=${TEST_DEVICE:-optix}
OMNIDATA_TEST_RENDER_DEVICE=$test_device PYTEST_DISABLE_PLUGIN_AUTOLOAD=1 timeout "${TEST_TIMEOUT:-150}" "$py" -m pytest -q \
  -p no:cacheprovider -p pytest_timeout tests/worker/blender/test_render.py 2>&1 | tee "$out/oracle_tests.txt" | tail -15
tests_rc=${PIPESTATUS[0]}
# One lease, one try: when the oracle tests failed on OptiX, the benchmark's GPU runs take CUDA instead of auto.
device=auto
[ "$tests_rc" = 0 ] || { [ "$test_device" = optix ] && device=cuda; }
echo "benchmark on --device $device"
flags=("$@")
[[ " $* " == *" --render-workers"* ]] || flags+=(--render-workers 1)  # one render process on the GPU
timeout "${BENCH_TIMEOUT:-330}" "$py" bench/render/gpu_cost.py --scenes /root/od-scenes --out "$out/gpu.json" \
  --device "$device" "${flags[@]}" 2>&1 | tee "$out/gpu_cost.log" | tail -40
"$py" bench/render/gpu_cost.py --busy "$out/gpu.json"
