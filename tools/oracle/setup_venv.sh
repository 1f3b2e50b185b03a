#!/usr/bin/env bash
# Build a virtualenv with the AMULED authors' pinned versions, outside any repository.
#
#   tools/oracle/setup_venv.sh AUTHORS_CHECKOUT VENV [--torch SPEC]
#
# AUTHORS_CHECKOUT: a checkout of temetski/moral_agent (its requirements.txt is read).
# VENV:             where the virtualenv goes (e.g. /work/oracle-venv); created if absent.
# --torch SPEC:     the torch requirement (default: their pin, torch==2.2.2 from PyPI).
#
# Installs the pins of their requirements.txt that finetune_moral.py,
# finetune_moral_human.py, human_policy_milk.py and ppo.py import (numpy 1.26.4,
# scipy 1.14.0, pandas 2.2.2, gymnasium 0.28.1, torch 2.2.2, langchain 0.2.12,
# langchain-openai 0.1.20) and their unpinned ones (tyro, tensorboard), then `regex`
# (imported by llm_moral.py). IPython, matplotlib and stable-baselines3 are left out:
# none of those scripts imports them. Only the package registry is used (pip).
set -euo pipefail
if [[ $# -lt 2 ]]; then sed -n 2,16p "$0"; exit 2; fi
AUTHORS=$(cd "$1" && pwd); VENV=$2; shift 2
TORCH="torch==2.2.2"
while [[ $# -gt 0 ]]; do
  case $1 in
    --torch) TORCH=$2; shift 2;;
    *) echo "unknown option $1" >&2; exit 2;;
  esac
done
REQ="$AUTHORS/requirements.txt"
[[ -f $REQ ]] || { echo "no requirements.txt in $AUTHORS" >&2; exit 1; }
PY=${PYTHON:-python3}
[[ -x $VENV/bin/python ]] || "$PY" -m venv "$VENV"
# their pins, less the packages the scripts run here never import, torch as asked
grep -v -i -E '^(ipython|matplotlib|matplotlib-inline|stable-baselines3|torch)([=<>~ ]|$)' "$REQ" \
  | sed '/^\s*$/d' > "$VENV/oracle-requirements.txt"
echo "$TORCH" >> "$VENV/oracle-requirements.txt"
echo "regex" >> "$VENV/oracle-requirements.txt"
echo "installing into $VENV:"; sed 's/^/  /' "$VENV/oracle-requirements.txt"
"$VENV/bin/python" -m pip install --quiet -r "$VENV/oracle-requirements.txt"
"$VENV/bin/python" - <<'PY'
import importlib.metadata as m
for p in ["numpy", "scipy", "pandas", "gymnasium", "torch", "langchain", "langchain-openai", "tyro", "tensorboard"]:
    print(f"  {p}=={m.version(p)}")
PY
"$VENV/bin/python" -m pip freeze > "$VENV/oracle-freeze.txt"
echo "ok: $VENV (full list in $VENV/oracle-freeze.txt)"
