#!/usr/bin/env bash
# GPU figures for experiments/benchmark.py, plus the core physics tests run on the GPU.
#
#   OUT=experiments/results/gpu bash experiments/gpu_benchmark.sh "NVIDIA H100"
#
# Parts (PARTS, default all), each under its own time limit so that one failure
# leaves the rest:
#   standard  the standard benchmark (2D 10,000 discs, 3D 20,000 spheres; float32)
#   large     3D at 1,000,000 spheres (the GPU size; float32)
#   det       3D at 1,000,000 spheres with XLA_FLAGS=--xla_gpu_deterministic_ops=true
#   tests     the core engine / contact / neighbour / bond / restart tests (float64)
#             on the GPU, then the bit-for-bit tests again with deterministic ops
#   bonded    the bonded benchmark (benchmark.py --bonded) at 1,000,000 spheres,
#             float32 then float64 (the specimen built on the machine)
#   ucs       the reduced UCS study (tests/test_ucs_reduced.py, its slow float32 vs
#             float64 comparison included), figures printed
# Set PY to choose the interpreter (default python3) and QUICK=1 for a smoke run.
set -u
OUT=${OUT:-experiments/results/gpu}
LABEL=${1:-GPU}
PY=${PY:-python3}
PARTS=${PARTS:-standard large det tests}
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
mkdir -p "$OUT"
if [ "${QUICK:-0}" = 1 ]; then std="--quick"; big="--n 5000 --quick"; t=60; bn=5000;
else std="--repeats 5"; big="--n 1000000 --repeats 5"; t=240; bn=1000000; fi
DET=--xla_gpu_deterministic_ops=true

{ nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv 2>&1
  $PY -c "import jax, jaxlib; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, jax.devices())" 2>&1
}

for part in $PARTS; do case $part in
  standard) timeout $t $PY experiments/benchmark.py $std --device-label "$LABEL" \
                --out "$OUT/standard" 2>&1 | tee "$OUT/standard.log" | tail -30 ;;
  large)    timeout $t $PY experiments/benchmark.py --dim 3 $big --device-label "$LABEL" \
                --out "$OUT/large" 2>&1 | tee "$OUT/large.log" | tail -30 ;;
  det)      XLA_FLAGS="${XLA_FLAGS:-} $DET" timeout $t $PY experiments/benchmark.py --dim 3 $big \
                --no-profile --chunks 3 --device-label "$LABEL, deterministic ops" \
                --out "${TMPDIR:-/tmp}/jdem-det" 2>&1 | tee "$OUT/det.log" | tail -8 ;;
  tests)    { timeout $t $PY -m pytest -q -p no:cacheprovider -o addopts="" -m "not slow" -rfE \
                --tb=line tests/test_engine.py tests/test_contact_laws.py tests/test_neighbors.py \
                tests/test_io.py tests/test_single_bond.py tests/test_bond_unit.py
              echo "---- bit-for-bit tests with XLA_FLAGS=$DET"
              XLA_FLAGS="${XLA_FLAGS:-} $DET" timeout 120 $PY -m pytest -q -p no:cacheprovider \
                -o addopts="" -rfE --tb=line tests/test_engine.py \
                -k "restart or too_small or vmap_over_friction"; } 2>&1 | tee "$OUT/tests.log" | tail -30 ;;
  bonded)   timeout ${BONDED_LIMIT:-330} $PY experiments/benchmark.py --bonded --bonded-n $bn \
                --chunks 5 --records 4 --no-profile --out "$OUT/bonded" 2>&1 \
                | tee "$OUT/bonded.log" | tail -30 ;;
  ucs)      timeout ${UCS_LIMIT:-240} $PY -m pytest -q -s -p no:cacheprovider -o addopts="" -rfE \
                --tb=short --durations=5 tests/test_ucs_reduced.py 2>&1 \
                | tee "$OUT/ucs.log" | tail -40 ;;
esac; done
