#!/usr/bin/env bash
# Run the AMULED authors' base training (algorithms/ppo.py, CleanRL) with their settings.
#
#   tools/oracle/run_base.sh AUTHORS_CHECKOUT VENV OUT [options]
#
#   --task findmilk|driving   (default findmilk)
#   --seeds "42 43 44 45 46"  training seeds (default: those five)
#   --extra "ARGS"            more options for ppo.py (tyro), e.g. "--total-timesteps 8192"
#                             for a shortened run (the rate is what it measures)
#
# Their settings: ppo.py's defaults (Args, ppo.py:18-85: 500,000 steps, 128 steps per copy,
# lr 2.5e-4 annealed, 4 epochs x 4 mini-batches, ...) with --num-envs 8: the README's
# pretraining command for FindMilk ("python algorithms/ppo.py --seed 42 --env-id
# environments.milk:FindMilk-v4 --num-envs 8") and the hyperparameters their published
# Driving base recorded (models/Driving_42/events.out.tfevents.1725371465: num_envs 8,
# 488 iterations). No LLM is involved, so the stub of run_oracle.sh is not used.
#
# One seed at a time, under nice -n 19, one torch thread, on the CPU (--no-cuda). Each seed
# works in OUT/<task>-base/seed<S>/ (ppo.py writes relative to the working directory):
# models/<Env>_<S>/base.cleanrl_model (the base) and the TensorBoard events beside it,
# stdout.log (their prints: SPS per iteration, every training episode's return) and
# oracle-done (JSON: wall time, iterations, environment steps, steps per second). A seed
# whose folder holds oracle-done is skipped. Their files are never edited.
set -euo pipefail
if [[ $# -lt 3 ]]; then sed -n 2,24p "$0"; exit 2; fi
AUTHORS=$(cd "$1" && pwd); VENV=$(cd "$2" && pwd); mkdir -p "$3"; OUT=$(cd "$3" && pwd); shift 3
TASK=findmilk; SEEDS="42 43 44 45 46"; EXTRA=""
while [[ $# -gt 0 ]]; do
  case $1 in
    --task) TASK=$2; shift 2;;
    --seeds) SEEDS=$2; shift 2;;
    --extra) EXTRA=$2; shift 2;;
    *) echo "unknown option $1" >&2; exit 2;;
  esac
done
case $TASK in
  findmilk) ENV_ID=environments.milk:FindMilk-v4; ENV=FindMilk-v4;;
  driving)  ENV_ID=environments.drive:Driving; ENV=Driving;;
  *) echo "--task findmilk|driving" >&2; exit 2;;
esac
[[ -f $AUTHORS/algorithms/ppo.py ]] || { echo "missing $AUTHORS/algorithms/ppo.py" >&2; exit 1; }
PY=$VENV/bin/python
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 CUDA_VISIBLE_DEVICES=""
export PYTHONDONTWRITEBYTECODE=1   # nothing written into their checkout
{ echo "authors checkout: $AUTHORS"
  cat "$AUTHORS/.oracle-commit" 2>/dev/null || git -C "$AUTHORS" rev-parse HEAD 2>/dev/null || echo "(commit unknown)"
  sha256sum "$AUTHORS/algorithms/ppo.py" "$AUTHORS/environments/milk.py" "$AUTHORS/environments/drive.py"
  "$PY" -c 'import torch, numpy, gymnasium, tyro; print("torch", torch.__version__, "numpy", numpy.__version__, "gymnasium", gymnasium.__version__, "tyro", tyro.__version__)'
} > "$OUT/oracle-provenance-base-$TASK.txt"
cat "$OUT/oracle-provenance-base-$TASK.txt"

for S in $SEEDS; do
  W=$OUT/$TASK-base/seed$S
  if [[ -f $W/oracle-done ]]; then echo "$TASK base seed $S: done before, skipped"; continue; fi
  rm -rf "$W"; mkdir -p "$W/models/${ENV}_$S"
  echo "$TASK base seed $S -> $W/models/${ENV}_$S/base.cleanrl_model"
  T0=$(date +%s.%N)
  # shellcheck disable=SC2086
  ( cd "$W" && nice -n 19 "$PY" "$AUTHORS/algorithms/ppo.py" --env-id "$ENV_ID" --seed "$S" \
      --num-envs 8 --no-cuda $EXTRA > stdout.log 2>&1 ) \
    || { echo "FAILED: see $W/stdout.log" >&2; tail -5 "$W/stdout.log" >&2; exit 1; }
  T1=$(date +%s.%N)
  python3 - "$W" "$T0" "$T1" <<'PY'
import json, sys
w, t0, t1 = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
log = open(f"{w}/stdout.log").read().splitlines()
iterations = sum(1 for line in log if line.startswith("SPS:"))
sps = [int(line.split()[1]) for line in log if line.startswith("SPS:")]
steps = iterations * 8 * 128  # --num-envs 8 x num_steps 128 (ppo.py:50)
done = {"seconds": round(t1 - t0, 1), "iterations": iterations, "env_steps": steps,
        "steps_per_second": round(steps / (t1 - t0), 1), "last_sps_printed": sps[-1] if sps else None}
json.dump(done, open(f"{w}/oracle-done", "w"))
print(f"  {done}")
PY
done
