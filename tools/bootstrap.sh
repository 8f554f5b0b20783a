#!/usr/bin/env bash
# Make this checkout runnable on a fresh Debian machine with Python 3.11:
#   1. the Debian packages in tools/apt-packages.txt (Mesa EGL/llvmpipe, X client libs),
#   2. a virtual environment .venv with the pins of requirements.txt.
#   3. the runtime wheels of the extension zips in build/wheels (tools/build_extension.py --fetch-only).
# Idempotent and quick when nothing changed (a stamp holds the requirements' hash).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

say() { printf '[bootstrap] %s\n' "$*" >&2; }

# --- Debian packages -------------------------------------------------------
mapfile -t apt_pkgs < <(grep -v '^\s*#' tools/apt-packages.txt | awk 'NF {print $1}')
missing=()
for p in "${apt_pkgs[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
        missing+=("$p")
    fi
done
if ((${#missing[@]})); then
    say "installing Debian packages: ${missing[*]}"
    if [[ $(id -u) -eq 0 ]]; then sudo_cmd=(); elif command -v sudo >/dev/null; then sudo_cmd=(sudo); else
        say "ERROR: need root or sudo to install: ${missing[*]}"; exit 1; fi
    export DEBIAN_FRONTEND=noninteractive
    "${sudo_cmd[@]}" apt-get update -qq
    "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# --- Python virtual environment --------------------------------------------
py="${PRTT_PYTHON:-}"
if [[ -z "$py" ]]; then
    for cand in python3.11 python3; do
        if command -v "$cand" >/dev/null && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
            py="$cand"; break
        fi
    done
fi
if [[ -z "$py" ]]; then
    say "ERROR: Python 3.11 not found (bpy 5.0.1 needs exactly 3.11); set PRTT_PYTHON=/path/to/python3.11"
    exit 1
fi
want="$(sha256sum requirements.txt | cut -d' ' -f1)"
stamp=".venv/.requirements.sha256"
if [[ ! -x .venv/bin/python ]] || [[ "$(cat "$stamp" 2>/dev/null)" != "$want" ]]; then
    say "creating .venv with $("$py" --version) and requirements.txt (bpy is ~370 MB, first time only)"
    "$py" -m venv .venv
    .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
    .venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.txt
    echo "$want" > "$stamp"
fi

# --- independent readers (npm) ------------------------------------------------
# tools/js/package-lock.json pins the JavaScript PRTT uses: ktx-parse (the
# tests' independent KTX2 reader, and the web viewer's) and three.js (viewer/).
# Installed again when the lock changes.
js_want="$(sha256sum tools/js/package-lock.json | cut -d' ' -f1)"
js_stamp="tools/js/node_modules/.lock.sha256"
if [[ "$(cat "$js_stamp" 2>/dev/null)" != "$js_want" ]]; then
    if command -v npm >/dev/null; then
        say "installing tools/js (npm ci: ktx-parse, three)"
        npm ci --prefix tools/js --no-audit --no-fund --loglevel=error >/dev/null
        echo "$js_want" > "$js_stamp"
    else
        say "WARNING: npm not found: tests/test_ktx2.py needs Node.js 20 and npm (ktx-parse)"
    fi
fi

# --- extension wheels --------------------------------------------------------
# The runtime wheels of every platform's extension zip, fetched now so that
# building the zip (and the tests that do) never needs the network. Cached in
# build/wheels: nothing is downloaded when they are there.
.venv/bin/python tools/build_extension.py --fetch-only >/dev/null
