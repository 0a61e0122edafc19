#!/usr/bin/env bash
# mjlab's pinned set (benchmarks/mjlab_pins.txt) for benchmarks/mjlab_peer.py, kept apart from ours: mjlab pins
# mujoco 3.11, we use 4.0. From the repository root (docs/benchmarks.md, "Peer: mjlab", has the GPU calls):
#   bash benchmarks/mjlab_env.sh stage     here: the wheels for the GPU machine (Python 3.12), one tar split into
#                                          .mjlabwheels/1, 2, ..., each small enough to travel beside the working tree
#   bash benchmarks/mjlab_env.sh install   there, in the call carrying the last folder (earlier calls copy theirs to
#                                          /tmp/mjlab_wheels): installs into /tmp/mjlab_site, with our warp linked in
set -euo pipefail
parts=/tmp/mjlab_wheels site=/tmp/mjlab_site
case "${1:-}" in
stage)
  # A call carries 64 MiB in all, the working tree (as tar packs it) included.
  tree=$(git ls-files -co --exclude-standard -z | tar cf - --null -T - 2>/dev/null | wc -c)
  limit=${LIMIT_MIB:-$((63 - (tree + 1048575) / 1048576))}
  tmp=$(mktemp -d) && rm -rf .mjlabwheels && mkdir .mjlabwheels
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$tmp" -r benchmarks/mjlab_pins.txt 2> >(grep -v "^WARNING" >&2)
  tar cf - -C "$tmp" . | split -b "${limit}m" - .mjlabwheels/part.
  n=$(ls .mjlabwheels | wc -l) i=0
  for p in .mjlabwheels/part.*; do
    i=$((i + 1)) && mkdir .mjlabwheels/$i && mv "$p" ".mjlabwheels/$i/wheels.tar.$i-of-$n"
  done
  rm -rf "$tmp" && du -sh .mjlabwheels/*
  echo "$(wc -l < benchmarks/mjlab_pins.txt) wheels in $n folder(s) of at most $limit MiB; the last call installs" ;;
install)
  mkdir -p "$parts" && cp .mjlabwheels/*/wheels.tar.* "$parts/"
  n=$(ls "$parts" | head -1 | sed 's/.*-of-//')
  for i in $(seq "$n"); do
    [ -f "$parts/wheels.tar.$i-of-$n" ] || { echo "mjlab_env.sh: part $i of $n missing: carry .mjlabwheels/$i" \
      "in a call just before this one (cp to $parts)" >&2; exit 3; }
  done
  [ -d /tmp/site/warp ] || { echo "mjlab_env.sh: no /tmp/site/warp: make our two staging calls first" >&2; exit 3; }
  # mujoco-warp 3.11 asks for warp-lang>=1.14: it runs on our staged warp 1.19.0.
  tmp=$(mktemp -d) && mkdir -p "$site" && ln -sfn /tmp/site/warp "$site/warp"
  for i in $(seq "$n"); do cat "$parts/wheels.tar.$i-of-$n"; done | tar xf - -C "$tmp"
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target "$site" "$tmp"/*.whl 2>&1 \
    | grep -vi warning || true
  rm -rf "$tmp"
  PYTHONPATH=$site python3 -c "import mujoco_warp, rsl_rl, torch, warp, importlib.metadata as m
print('mjlab site:', *(f'{d} {m.version(d)}' for d in ('mjlab', 'mujoco-warp', 'rsl-rl-lib')), 'warp', warp.__version__,
      'cuda', torch.cuda.is_available())" ;;
*) echo "usage: bash benchmarks/mjlab_env.sh stage|install" >&2; exit 2 ;;
esac
