#!/usr/bin/env bash
# PRTT developer entry point. Sets the machine up (tools/bootstrap.sh) and then:
#   ./prtt.sh demo [args]   the main job (see README)
#   ./prtt.sh test [args]   the whole test suite (pytest on PRTT_TEST_WORKERS processes, default 2:
#                           about 12 min on 2 cores against 20.5 in one; extra args are passed on, -n 0 for one)
#   ./prtt.sh slow [args]   the slow, large benchmark-style tests only
#   ./prtt.sh fuzz [args]   fuzz every reader of outside data (docs/fuzzing.md; --help)
#   ./prtt.sh compat [VERSION ...]  the installed extension zip in each Blender it claims (docs/addon.md)
#   ./prtt.sh py ARGS...    run the project's Python (e.g. ./prtt.sh py -m prtt_addon.dev.bench bake)
# demo and py run in the folder you call them from, so relative paths you give
# (--out textures, job.npz, scene.blend) are yours; test and slow run in the
# repository (pytest's configuration and test paths are there).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
"$root/tools/bootstrap.sh"              # cds into the repository itself, in its own process
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
py="$root/.venv/bin/python"
cmd="${1:-}"; shift || true
case "$cmd" in
    demo) exec "$py" -m prtt_addon.dev.demo "$@" ;;
    test) cd "$root" && exec "$py" -m pytest -m "not slow" -n "${PRTT_TEST_WORKERS:-2}" "$@" ;;
    slow) cd "$root" && exec "$py" -m pytest -m slow "$@" ;;
    fuzz) cd "$root" && exec "$py" -m prtt_addon.dev.fuzz "$@" ;;
    compat) cd "$root" && exec "$py" tools/compat.py "$@" ;;
    py)   exec "$py" "$@" ;;
    *) echo "usage: ./prtt.sh demo|test|slow|fuzz|compat|py ..." >&2; exit 2 ;;
esac
