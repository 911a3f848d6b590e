#!/usr/bin/env bash
# The GPU check, run on a lent CUDA machine from the repository root: the CUDA parity tests,
# python -m rtsplat.bench.gpu, and short trainings of the demo scenes on the GPU, with logs in $OUT.
#
# Prepared on the CPU machine first (the GPU image has torch, triton, numba, scipy and OpenCV, but neither
# jsonschema nor pycolmap nor Mitsuba):
#   .whl/        wheels of jsonschema, jsonschema-specifications, referencing, rpds-py for its Python 3.12
#   .gpu/prep/{dome,cabin}   `rtsplat synth --views 80 --layers-every 8`, `rtsplat masks`, `rtsplat sfm
#                --config-json '{"use_dataset_model": true}'` and `rtsplat prepare --config-json '{"downsample": 2}'`
#   .gpu/near.yaml  a pipeline config with the methods rtsplat_near (near_reflection on), rtsplat_nonear
#                (off) and 2dgs at demo/config.yaml's budget
# SKIP_CHECKS=1 runs the trainings only.
set -u
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/gpu-check}; mkdir -p "$OUT"
# the wheels go to /tmp/site once (a caller that installed them already, for jobs of its own beside this script,
# is not disturbed)
[ -d /tmp/site/jsonschema ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/env.txt"
python3 -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__)" | tee -a "$OUT/env.txt"
RT=(python3 -c 'import sys; from rtsplat.cli import main; sys.exit(main())')
if [ -z "${SKIP_CHECKS:-}" ]; then
  s=$(date +%s)
  timeout 170 python3 -m pytest -q -p no:cacheprovider tests/test_raster_triton.py tests/test_train_device.py 2>&1 \
    | tee "$OUT/tests.txt" | tail -15
  echo "== parity tests $(( $(date +%s) - s )) s"
  timeout 120 python3 -m rtsplat.bench.gpu --no-gsplat 2>&1 | tee "$OUT/bench.txt"
fi
train() {  # scene config method
  local s; s=$(date +%s)
  timeout 150 "${RT[@]}" train --data ".gpu/prep/$1" --out "/tmp/runs/$1_$3" --config "$2" --method "$3" \
    --device cuda --quiet > "$OUT/train_$1_$3.log" 2>&1
  echo "== train $1 $3 rc=$? $(( $(date +%s) - s )) s"; grep -E "^near reflection|^done" "$OUT/train_$1_$3.log"
}
train dome demo/config.yaml rtsplat
train cabin .gpu/near.yaml rtsplat_near
train cabin .gpu/near.yaml rtsplat_nonear
train cabin .gpu/near.yaml 2dgs
timeout 60 "${RT[@]}" render --data .gpu/prep/dome --run /tmp/runs/dome_rtsplat --out /tmp/render_dome --device cuda \
  --quiet 2>&1 | tee "$OUT/render.log"
