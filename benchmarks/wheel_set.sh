#!/usr/bin/env bash
# A pinned set of wheels (benchmarks/<set>_pins.txt) for the GPU machine, which cannot download. From the repository
# root (docs/benchmarks.md "Peer: mjlab" and docs/other-libraries.md "Per-library table" have the GPU calls):
#   bash benchmarks/wheel_set.sh <set> stage     here: the wheels (Python 3.12), one tar split into .<set>wheels/1, 2,
#                                                ..., each small enough to travel beside the working tree
#   bash benchmarks/wheel_set.sh <set> install   there, in the call carrying the last folder (earlier calls copy theirs
#                                                to /tmp/<set>_wheels), after our own two staging calls
# Sets: mjlab (mjlab's own pins, mujoco 3.11 where we use 4.0: installed apart, into /tmp/mjlab_site, with our warp
# linked in) and adapters (the RL libraries of tocabi_torchrl.adapters and what they import beyond our staged set,
# into /tmp/adapters_site, last on PYTHONPATH after /tmp/site and the repository, so that its general packages do not
# shadow what other runs on that machine import).
set -euo pipefail
set_name=${1:-} action=${2:-}
case "$set_name" in
mjlab) site=/tmp/mjlab_site path=/tmp/mjlab_site
       check="import mujoco_warp, rsl_rl, torch, warp, importlib.metadata as m
print('mjlab site:', *(f'{d} {m.version(d)}' for d in ('mjlab', 'mujoco-warp', 'rsl-rl-lib')), 'warp', warp.__version__,
      'cuda', torch.cuda.is_available())" ;;
adapters) site=/tmp/adapters_site path=/tmp/site:$PWD:/tmp/adapters_site
          check="import rsl_rl, skrl, stable_baselines3, tocabi_torchrl.adapters, importlib.metadata as m
print('adapters:', *(f'{d} {m.version(d)}' for d in ('rsl-rl-lib', 'skrl', 'stable-baselines3')))" ;;
*) echo "usage: bash benchmarks/wheel_set.sh mjlab|adapters stage|install" >&2; exit 2 ;;
esac
pins=benchmarks/${set_name}_pins.txt folder=.${set_name}wheels parts=/tmp/${set_name}_wheels
case "$action" in
stage)
  # A call carries 64 MiB in all, the working tree (as tar packs it) included.
  tree=$(git ls-files -co --exclude-standard -z | tar cf - --null -T - 2>/dev/null | wc -c)
  limit=${LIMIT_MIB:-$((63 - (tree + 1048575) / 1048576))}
  tmp=$(mktemp -d) && rm -rf "$folder" && mkdir "$folder"
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$tmp" -r "$pins" 2> >(grep -v "^WARNING" >&2)
  tar cf - -C "$tmp" . | split -b "${limit}m" - "$folder/part."
  n=$(ls "$folder" | wc -l) i=0
  for p in "$folder"/part.*; do
    i=$((i + 1)) && mkdir "$folder/$i" && mv "$p" "$folder/$i/wheels.tar.$i-of-$n"
  done
  rm -rf "$tmp" && du -sh "$folder"/*
  echo "$(grep -c . "$pins") wheels in $n folder(s) of at most $limit MiB; the last call installs" ;;
install)
  mkdir -p "$parts" && cp "$folder"/*/wheels.tar.* "$parts/"
  n=$(ls "$parts" | head -1 | sed 's/.*-of-//')
  for i in $(seq "$n"); do
    [ -f "$parts/wheels.tar.$i-of-$n" ] || { echo "wheel_set.sh: part $i of $n missing: carry $folder/$i" \
      "in a call just before this one (cp to $parts)" >&2; exit 3; }
  done
  [ -d /tmp/site/warp ] || { echo "wheel_set.sh: no /tmp/site/warp: make our two staging calls first" >&2; exit 3; }
  tmp=$(mktemp -d) && mkdir -p "$site"
  # mujoco-warp 3.11 asks for warp-lang>=1.14: mjlab's set runs on our staged warp 1.19.0.
  [ "$set_name" = mjlab ] && ln -sfn /tmp/site/warp "$site/warp"
  for i in $(seq "$n"); do cat "$parts/wheels.tar.$i-of-$n"; done | tar xf - -C "$tmp"
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target "$site" "$tmp"/*.whl 2>&1 \
    | grep -vi warning || true
  rm -rf "$tmp"
  PYTHONPATH=$path python3 -c "$check" ;;
*) echo "usage: bash benchmarks/wheel_set.sh mjlab|adapters stage|install" >&2; exit 2 ;;
esac
