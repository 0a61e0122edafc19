#!/usr/bin/env bash
# One time-limited call of the per-library table on a GPU host (docs/other-libraries.md, "Split over 10-minute calls"): each
# row trains on its own GPU until what it keeps (below) plus the packing before the call's end (recipes/
# library_table.py --no_eval --minutes), then the call packs into $OUT what must come back, most important first: the
# table, the logs, the resume states this call wrote, its snapshots (~4.5 MB each), then the rest of the runs without the libraries' own
# checkpoints, which nothing reads (benchmarks/device_out.py). Gait-test the snapshots afterwards where they land
# (python recipes/library_table.py --eval_only --device cpu ..., with the same --json).
#
#   S=$(date +%s) END=580 bash benchmarks/table_call.sh torchrl@0 skrl@1        # from the repository root
#   S=$(date +%s) END=580 bash benchmarks/table_call.sh rsl_rl:torque@0 sb3:default:256@1
#
# A row is LIBRARY[:PRESET[:ENVS]][+new]@GPU (PRESET and ENVS default to $PRESET and $NUM_ENVS; +new starts that row
# anew, replacing the json's row of the same library, preset and env count; one row per GPU, each row once); its log is
# $LOGS/LIBRARY_PRESET_ENVS.log. The resume states this call wrote are packed before its snapshots: a row can go on
# in a later session only from them (benchmarks/table_carry.py). Files older than S are not this call's, so put
# carried runs in place (cp -a) before S.
#
# S: the call's start (epoch seconds); END: seconds it may run. Each row keeps 75 s (TorchRL: ppo_walk's clock starts
# after its ~40 s set-up), 160 s (SB3: at 256 envs one PPO update, ~70 s on an H100, runs past the time cap before
# the clock can stop it) or 65 s (rsl_rl, skrl) for its start-up and end. Optional: NEW=1 starts all the rows
# anew (--new); PRESET (default); RUNS (runs/library_table: the rows' run folders); TABLE ($RUNS/h100.json: the json
# must stay on the host between calls, so it lives under the ignored runs/), seeded from SEED
# (docs/adapters_table_h100.json) when missing; NUM_ENVS (4096); LOGS (/tmp/table_logs); PACK (30 s kept for
# packing); DRY_RUN=1 prints the commands (with the GPU each row gets) instead of running them.
set -uo pipefail
: "${S:?S=<call start, epoch seconds>}" "${END:?END=<seconds this call may run>}"
RUNS=${RUNS:-runs/library_table} SEED=${SEED:-docs/adapters_table_h100.json} PRESET=${PRESET:-default}
TABLE=${TABLE:-$RUNS/h100.json}
NUM_ENVS=${NUM_ENVS:-4096} LOGS=${LOGS:-/tmp/table_logs} PACK=${PACK:-30} OUT=${OUT:-/tmp/out}
usage="a row is LIBRARY[:PRESET[:ENVS]][+new]@GPU (ENVS and GPU numbers, one row per GPU)"
[ $# -ge 1 ] || { echo "usage: S=... END=... bash benchmarks/table_call.sh ROW...; $usage" >&2; exit 2; }
gpus=" " keys=" "
for row in "$@"; do  # all rows checked before any starts
  [[ $row =~ ^[a-z_0-9]+(:[a-z_0-9]+(:[0-9]+)?)?(\+new)?@[0-9]+$ ]] || { echo "table_call.sh: $usage, got '$row'" >&2; exit 2; }
  [[ $gpus == *" ${row#*@} "* ]] && { echo "table_call.sh: two rows on GPU ${row#*@}: their rates would share it ($usage)" >&2; exit 2; }
  gpus+="${row#*@} "
  spec=${row%@*} && spec=${spec%+new} && IFS=: read -r lib preset envs <<< "$spec"
  key="$lib:${preset:-${PRESET:-default}}:${envs:-${NUM_ENVS:-4096}}"
  [[ $keys == *" $key "* ]] && { echo "table_call.sh: row $key given twice: two calls would train one run folder at once ($usage)" >&2; exit 2; }
  keys+="$key "
done
run() { if [ -n "${DRY_RUN:-}" ]; then echo "+ CUDA_VISIBLE_DEVICES=${CUDA_VISIBLE_DEVICES:-} $*"; else "$@"; fi; }
left() { echo $(( END - $(date +%s) + S )); }
say() { echo "[$(( $(date +%s) - S )) s] $*" | tee -a "$LOGS/driver.log"; }
mkdir -p "$LOGS" "$RUNS" "$(dirname "$TABLE")"
[ -f "$TABLE" ] || { [ -f "$SEED" ] && cp "$SEED" "$TABLE"; }
marker=$(mktemp) && touch -d "@$S" "$marker"   # snapshots newer than the call's start are this call's

train_row() {  # library preset envs gpu: train until keep + PACK seconds before the end (ppo_walk's clock starts after its set-up)
  local lib=$1 preset=$2 envs=$3 gpu=$4 new=$5 keep=65 l m name
  [ "$lib" = torchrl ] && keep=75
  [ "$lib" = sb3 ] && keep=160  # SB3's clock stops it at the next env step, after an update that can take ~70 s
  name="gpu$gpu $lib $preset $envs"
  l=$(left) m=$(python3 -c "print(round(($l - $keep - $PACK) / 60, 2))")
  if ! python3 -c "import sys; sys.exit(0 if $m >= 0.5 else 1)"; then say "$name: no time left"; return; fi
  say "$name: --minutes $m (timeout $((l - PACK)) s)"
  CUDA_VISIBLE_DEVICES=$gpu run timeout $((l - PACK)) python3 recipes/library_table.py --json "$TABLE" \
    --md "${TABLE%.json}.md" --runs "$RUNS" --checkpoint_minutes 2 --no_eval --minutes "$m" --libraries "$lib" \
    --num_envs "$envs" --preset "$preset" ${new:+--new} >> "$LOGS/${lib}_${preset}_$envs.log" 2>&1
  say "$name: rc $?"
}

for row in "$@"; do
  spec=${row%@*} new=
  [ "${NEW:-0}" = 1 ] && new=1
  [[ $spec == *+new ]] && spec=${spec%+new} new=1
  IFS=: read -r lib preset envs <<< "$spec"
  train_row "$lib" "${preset:-$PRESET}" "${envs:-$NUM_ENVS}" "${row#*@}" "$new" &
done
wait
say "packing"
run python3 benchmarks/device_out.py "$OUT" "$TABLE" "${TABLE%.json}.md" "$LOGS" \
  $(find "$RUNS" \( -name 'resume.json' -o -name 'result.json' -o -path '*/resume/state_call*.pt' -o -path '*/checkpoints/latest.pt' \) -newer "$marker" | sort) \
  $(find "$RUNS" -name 'wall_*.pt' -newer "$marker" | sort) \
  "$RUNS" \
  --skip '*/skrl/*/checkpoints/*' --skip '*/checkpoints/iter_*.pt' --skip "*/$(basename "$TABLE").lock"
rm -f "$marker"
say "done"
