#!/usr/bin/env bash
# Run the AMULED authors' own fine-tune scripts on their published base and cache.
#
#   tools/oracle/run_oracle.sh AUTHORS_CHECKOUT VENV OUT [options]
#
#   --task findmilk|driving   (default findmilk)
#   --scripts LIST            comma list of amuled,human (default amuled)
#                             amuled = algorithms/finetune_moral.py (gpt-4o-mini cache)
#                             human  = algorithms/finetune_moral_human.py (their synthetic
#                                      human, its demonstrator made by human_policy_<task>.py)
#   --seeds "42 43 44 45 46"  training seeds (default: those five)
#   --on-miss zero|error      a state missing from the cache: reward 0 (kl_sensitivity.py's
#                             rule, default) or stop the run (finetune_moral.py with no LLM)
#   --extra "ARGS"            more options for their script (tyro), e.g. "--total-timesteps 1280"
#
# One seed at a time, under nice -n 19, one torch thread. Each run works in its own folder
# OUT/<task>-<script>/seed<S>/ (their scripts write relative to the working directory):
# a copy of their cache goes to models/<Env>_<S>/ (their script reads and rewrites it
# there), the base is passed with --load-model, and their checkpoints land in
# models/<Env>_<S>/moral_llm_gpt-4o-mini/ppo_<N>.cleanrl_model (amuled) or
# models/<Env>_<S>/RLHF/ppo_<N>.cleanrl_model (human). stdout.log, misses and timing
# are kept beside them. A seed whose last checkpoint exists is skipped.
# Their files are never edited; the LLM client is stubbed (stub/sitecustomize.py).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
if [[ $# -lt 3 ]]; then sed -n 2,25p "$0"; exit 2; fi
AUTHORS=$(cd "$1" && pwd); VENV=$(cd "$2" && pwd); mkdir -p "$3"; OUT=$(cd "$3" && pwd); shift 3
TASK=findmilk; SCRIPTS=amuled; SEEDS="42 43 44 45 46"; ON_MISS=zero; EXTRA=""
while [[ $# -gt 0 ]]; do
  case $1 in
    --task) TASK=$2; shift 2;;
    --scripts) SCRIPTS=$2; shift 2;;
    --seeds) SEEDS=$2; shift 2;;
    --on-miss) ON_MISS=$2; shift 2;;
    --extra) EXTRA=$2; shift 2;;
    *) echo "unknown option $1" >&2; exit 2;;
  esac
done
case $TASK in
  findmilk) ENV_ID=environments.milk:FindMilk-v4; ENV=FindMilk-v4; TAG=milk
            CACHE=$AUTHORS/models/FindMilk-v4_42/gpt-4o-mini_llm_cache.pickle;;
  driving)  ENV_ID=environments.drive:Driving; ENV=Driving; TAG=drive
            CACHE=$AUTHORS/models/Driving_42/gpt-4o-mini_llm_cache.pickle
            [[ -f $CACHE ]] || CACHE=$AUTHORS/PickleCacheAndBaseModels/Drive/gpt-4o-mini_llm_cache.pickle;;
  *) echo "--task findmilk|driving" >&2; exit 2;;
esac
BASE=$AUTHORS/models/${ENV}_42/base.cleanrl_model
for f in "$BASE" "$CACHE" "$AUTHORS/algorithms/finetune_moral.py"; do
  [[ -f $f ]] || { echo "missing $f" >&2; exit 1; }
done
PY=$VENV/bin/python
export ORACLE_STUB=1 ORACLE_ON_MISS=$ON_MISS PYTHONPATH=$HERE/stub OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
export PYTHONDONTWRITEBYTECODE=1   # nothing written into their checkout
{ echo "authors checkout: $AUTHORS"
  git -C "$AUTHORS" rev-parse HEAD 2>/dev/null || echo "(not a git work tree)"
  sha256sum "$BASE" "$CACHE" "$AUTHORS/algorithms/finetune_moral.py" "$AUTHORS/algorithms/finetune_moral_human.py" "$AUTHORS/algorithms/ppo.py"
  "$PY" -c 'import torch, numpy, scipy, gymnasium; print("torch", torch.__version__, "numpy", numpy.__version__, "scipy", scipy.__version__, "gymnasium", gymnasium.__version__)'
} > "$OUT/oracle-provenance-$TASK.txt"
cat "$OUT/oracle-provenance-$TASK.txt"

demonstrator() {  # their synthetic human's counts, made once per OUT by their own script
  local d=$OUT/$TASK-human/demonstrator
  if [[ ! -f $d/runs/human_policy/hpolicy_$TAG.pkl ]]; then
    mkdir -p "$d/runs/human_policy"
    echo "demonstrator: human_policy_$TAG.py in $d"
    ( cd "$d" && nice -n 19 "$PY" "$AUTHORS/algorithms/human_policy_$TAG.py" > stdout.log 2>&1 )
  fi
  echo "$d/runs/human_policy/hpolicy_$TAG.pkl"
}

for SCRIPT in ${SCRIPTS//,/ }; do
  case $SCRIPT in
    amuled) FILE=finetune_moral.py; SUB=moral_llm_gpt-4o-mini;;
    human)  FILE=finetune_moral_human.py; SUB=RLHF; HPOL=$(demonstrator | tail -1);;
    *) echo "--scripts amuled,human" >&2; exit 2;;
  esac
  for S in $SEEDS; do
    W=$OUT/$TASK-$SCRIPT/seed$S
    CK=$W/models/${ENV}_$S/$SUB
    if [[ -f $W/oracle-done ]]; then echo "$TASK $SCRIPT seed $S: done before, skipped"; continue; fi
    rm -rf "$W"; mkdir -p "$W/models/${ENV}_$S"
    if [[ $SCRIPT == amuled ]]; then cp "$CACHE" "$W/models/${ENV}_$S/gpt-4o-mini_llm_cache.pickle"
    else mkdir -p "$W/runs/human_policy"; cp "$HPOL" "$W/runs/human_policy/"; fi
    echo "$TASK $SCRIPT seed $S -> $CK"
    T0=$(date +%s.%N)
    # shellcheck disable=SC2086
    ( cd "$W" && nice -n 19 "$PY" "$AUTHORS/algorithms/$FILE" --env-id "$ENV_ID" --seed "$S" \
        --load-model "$BASE" $EXTRA > stdout.log 2>&1 ) || { echo "FAILED: see $W/stdout.log" >&2; tail -5 "$W/stdout.log" >&2; exit 1; }
    T1=$(date +%s.%N)
    LAST=$(ls "$CK" | sed -n 's/^ppo_\([0-9]*\)\.cleanrl_model$/\1/p' | sort -n | tail -1)
    MISSES=$( [[ -f $W/oracle_misses.jsonl ]] && wc -l < "$W/oracle_misses.jsonl" || echo 0)
    python3 - "$W" "$T0" "$T1" "$LAST" "$MISSES" <<'PY'
import json, sys
w, t0, t1, last, misses = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
json.dump({"seconds": round(t1 - t0, 1), "iterations": last, "s_per_iteration": round((t1 - t0) / last, 3),
           "llm_cache_misses": misses}, open(f"{w}/oracle-done", "w"))
print(f"  {last} iterations in {t1 - t0:.0f} s ({(t1 - t0) / last:.3f} s/iteration), cache misses {misses}")
PY
  done
done
